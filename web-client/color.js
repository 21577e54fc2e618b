// Colour helpers. The wire carries albedo as *linear* RGB in [0, 1]; everything a person picks
// or sees (CSS, <input type=color>) is sRGB. Convert at the boundary, never in between.

/** @typedef {[number, number, number]} Vec3 */

/** sRGB-encoded component (0..1) → linear (0..1). */
export function srgbToLinear(c) {
  c = clamp01(c);
  return c <= 0.04045 ? c / 12.92 : Math.pow((c + 0.055) / 1.055, 2.4);
}

/** Linear component (0..1) → sRGB-encoded (0..1). */
export function linearToSrgb(c) {
  c = clamp01(c);
  return c <= 0.0031308 ? c * 12.92 : 1.055 * Math.pow(c, 1 / 2.4) - 0.055;
}

export function clamp01(x) {
  return Number.isFinite(x) ? Math.min(1, Math.max(0, x)) : 0;
}

/**
 * "#rrggbb" (sRGB) → linear RGB.
 * @param {string} hex
 * @returns {Vec3}
 */
export function hexToLinear(hex) {
  const m = /^#?([0-9a-f]{2})([0-9a-f]{2})([0-9a-f]{2})$/i.exec(hex.trim());
  if (!m) return [1, 1, 1];
  return /** @type {Vec3} */ ([m[1], m[2], m[3]].map((h) => srgbToLinear(parseInt(h, 16) / 255)));
}

/**
 * Linear RGB → "#rrggbb" (sRGB).
 * @param {ArrayLike<number>} rgb
 */
export function linearToHex(rgb) {
  let s = '#';
  for (let i = 0; i < 3; i++) {
    s += Math.round(linearToSrgb(rgb[i]) * 255).toString(16).padStart(2, '0');
  }
  return s;
}

/**
 * Linear RGB → CSS colour string, optional alpha.
 * @param {ArrayLike<number>} rgb
 * @param {number} [alpha]
 */
export function linearToCss(rgb, alpha = 1) {
  const r = Math.round(linearToSrgb(rgb[0]) * 255);
  const g = Math.round(linearToSrgb(rgb[1]) * 255);
  const b = Math.round(linearToSrgb(rgb[2]) * 255);
  return alpha >= 1 ? `rgb(${r},${g},${b})` : `rgba(${r},${g},${b},${alpha.toFixed(3)})`;
}
