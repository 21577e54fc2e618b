// Transfer-function presets. CT presets are written in Hounsfield units and converted to the
// protocol's normalized value with the dataset's value range; the generic ones are normalized.
//
// Opacity is an extinction multiplier: the server uses sigma_t = density_scale · opacity per
// world unit (density_scale defaults to 60, the volume's longest side is 1 world unit). So 0.05 is
// already a clearly visible soft material over a few centimetres; 1 is an opaque surface.
// Colours are albedo, given here as sRGB hex for readability and converted to linear RGB.

import { hexToLinear } from './color.js';

/** @typedef {{value: number, color: [number, number, number], opacity: number}} TfPoint */
/** @typedef {{hu?: number, v?: number, color: string, opacity: number}} PresetPoint */
/**
 * @typedef {object} Preset
 * @property {string} id
 * @property {string} label
 * @property {string} description
 * @property {'HU'|'normalized'} space
 * @property {PresetPoint[]} points
 * @property {{density_scale?: number}} [params]  suggested render parameters (applied too)
 */

/** @type {Preset[]} */
export const PRESETS = [
  {
    id: 'bone',
    label: 'Bone',
    description: 'Cortical and trabecular bone; soft tissue hidden (opacity from 200 HU, opaque at 1000 HU)',
    space: 'HU',
    points: [
      { hu: 180, color: '#c8a078', opacity: 0 },
      { hu: 300, color: '#d9bc94', opacity: 0.12 },
      { hu: 600, color: '#eedfc4', opacity: 0.55 },
      { hu: 1000, color: '#fbf5e6', opacity: 1 },
    ],
  },
  {
    id: 'soft',
    label: 'Soft tissue',
    description: 'Skin, fat (≈ −100 HU) and muscle (≈ 40 HU) in warm tones, bone faint ivory',
    space: 'HU',
    points: [
      { hu: -400, color: '#b06040', opacity: 0 },
      { hu: -150, color: '#e8c080', opacity: 0.004 },
      { hu: -90, color: '#f0cc8a', opacity: 0.012 },
      { hu: -30, color: '#c86a58', opacity: 0.006 },
      { hu: 40, color: '#b8443a', opacity: 0.05 },
      { hu: 120, color: '#d07060', opacity: 0.08 },
      { hu: 300, color: '#f0e0c8', opacity: 0.25 },
      { hu: 1000, color: '#fff8ec', opacity: 0.6 },
    ],
  },
  {
    id: 'vessels',
    label: 'Vessels / contrast',
    description: 'Contrast-filled vessels (150–400 HU) in red, bone above 500 HU faint',
    space: 'HU',
    points: [
      { hu: 100, color: '#a01818', opacity: 0 },
      { hu: 160, color: '#c02820', opacity: 0.3 },
      { hu: 280, color: '#e04030', opacity: 0.7 },
      { hu: 420, color: '#f07050', opacity: 0.7 },
      { hu: 550, color: '#eee0c8', opacity: 0.1 },
      { hu: 1200, color: '#fff8ec', opacity: 0.2 },
    ],
  },
  {
    id: 'lung',
    label: 'Lung',
    description: 'Airways and parenchyma (−900…−500 HU) visible, everything else faint',
    space: 'HU',
    points: [
      { hu: -980, color: '#6080c0', opacity: 0 },
      { hu: -900, color: '#80a0e0', opacity: 0.05 },
      { hu: -750, color: '#e8a0a0', opacity: 0.12 },
      { hu: -500, color: '#f0b8a8', opacity: 0.06 },
      { hu: -350, color: '#c08070', opacity: 0 },
      { hu: 0, color: '#c08070', opacity: 0.002 },
      { hu: 300, color: '#f0e6d6', opacity: 0.02 },
      { hu: 1200, color: '#fff8ec', opacity: 0.05 },
    ],
  },
  {
    id: 'ramp',
    label: 'Ramp',
    description: 'Generic linear ramp over the normalized value, for non-CT data',
    space: 'normalized',
    points: [
      { v: 0.1, color: '#c06030', opacity: 0 },
      { v: 0.5, color: '#e0b070', opacity: 0.3 },
      { v: 1.0, color: '#fffaf0', opacity: 1 },
    ],
  },
];

/** @param {string} id */
export function presetById(id) {
  return PRESETS.find((p) => p.id === id) || null;
}

/**
 * Converts a preset to protocol TF points for a dataset with the given value range. The preset
 * is a piecewise-linear function of the value; it is clipped to [0, 1] (points interpolated at
 * the cut) so that a range narrower than the preset keeps the right opacity at the edges.
 * @param {Preset} preset
 * @param {number} valueMin
 * @param {number} valueMax
 * @returns {TfPoint[]}
 */
export function presetToTf(preset, valueMin, valueMax) {
  const span = valueMax - valueMin;
  /** @type {TfPoint[]} */
  const raw = preset.points.map((p) => ({
    value:
      preset.space === 'HU'
        ? Math.abs(span) > 0 && Number.isFinite(span)
          ? ((p.hu ?? 0) - valueMin) / span
          : 0.5
        : p.v ?? 0,
    color: hexToLinear(p.color),
    opacity: p.opacity,
  }));
  raw.sort((a, b) => a.value - b.value);
  return clipTf(raw).map(roundPoint);
}

/**
 * Clips a sorted piecewise-linear TF (constant beyond its ends) to values in [0, 1].
 * @param {TfPoint[]} pts
 * @returns {TfPoint[]}
 */
export function clipTf(pts) {
  if (pts.length === 0) return [];
  const inside = pts.filter((p) => p.value >= 0 && p.value <= 1);
  /** @type {TfPoint[]} */
  const out = [];
  if (pts[0].value < 0) out.push({ ...evalTf(pts, 0), value: 0 });
  out.push(...inside);
  if (pts[pts.length - 1].value > 1) out.push({ ...evalTf(pts, 1), value: 1 });
  // Deduplicate equal values (keep the last, which is what a piecewise function would show).
  return out.filter((p, i) => i === out.length - 1 || out[i + 1].value > p.value + 1e-7);
}

/**
 * Evaluates a sorted TF at normalized value v (piecewise linear, constant beyond the ends).
 * @param {TfPoint[]} pts
 * @param {number} v
 * @returns {TfPoint}
 */
export function evalTf(pts, v) {
  if (pts.length === 0) return { value: v, color: [0, 0, 0], opacity: 0 };
  if (v <= pts[0].value) return { value: v, color: [...pts[0].color], opacity: pts[0].opacity };
  const last = pts[pts.length - 1];
  if (v >= last.value) return { value: v, color: [...last.color], opacity: last.opacity };
  for (let i = 1; i < pts.length; i++) {
    const a = pts[i - 1];
    const b = pts[i];
    if (v <= b.value) {
      const t = b.value > a.value ? (v - a.value) / (b.value - a.value) : 1;
      return {
        value: v,
        color: [0, 1, 2].map((k) => a.color[k] + (b.color[k] - a.color[k]) * t),
        opacity: a.opacity + (b.opacity - a.opacity) * t,
      };
    }
  }
  return { value: v, color: [...last.color], opacity: last.opacity };
}

/** @param {TfPoint} p */
function roundPoint(p) {
  const r = (x) => Math.round(Math.min(1, Math.max(0, x)) * 1e6) / 1e6;
  return { value: r(p.value), color: /** @type {[number,number,number]} */ (p.color.map(r)), opacity: r(p.opacity) };
}
