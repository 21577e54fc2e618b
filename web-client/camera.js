// Orbit camera math (turntable around `target`, keeping `up`), matching the protocol's pinhole
// camera: right = normalize(forward × up), image row 0 is the top.

/** @typedef {[number, number, number]} Vec3 */
/** @typedef {{eye: Vec3, target: Vec3, up: Vec3, fov_deg: number}} Camera */

/** The protocol's default camera: from world −y toward the origin, +z up, 30° vertical fov. */
export const DEFAULT_CAMERA = Object.freeze({
  eye: /** @type {Vec3} */ ([0, -2.4, 0]),
  target: /** @type {Vec3} */ ([0, 0, 0]),
  up: /** @type {Vec3} */ ([0, 0, 1]),
  fov_deg: 30,
});

export const MIN_DISTANCE = 0.15;
export const MAX_DISTANCE = 20;

export const add = (a, b) => /** @type {Vec3} */ ([a[0] + b[0], a[1] + b[1], a[2] + b[2]]);
export const sub = (a, b) => /** @type {Vec3} */ ([a[0] - b[0], a[1] - b[1], a[2] - b[2]]);
export const scale = (a, s) => /** @type {Vec3} */ ([a[0] * s, a[1] * s, a[2] * s]);
export const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
export const cross = (a, b) =>
  /** @type {Vec3} */ ([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]);
export const length = (a) => Math.hypot(a[0], a[1], a[2]);
export function normalize(a) {
  const l = length(a);
  return l > 1e-12 ? scale(a, 1 / l) : /** @type {Vec3} */ ([0, 0, 0]);
}

/** Rotates v around unit axis k by angle (radians), Rodrigues' formula. */
export function rotate(v, k, angle) {
  const c = Math.cos(angle);
  const s = Math.sin(angle);
  const kxv = cross(k, v);
  const kdv = dot(k, v);
  return /** @type {Vec3} */ ([
    v[0] * c + kxv[0] * s + k[0] * kdv * (1 - c),
    v[1] * c + kxv[1] * s + k[1] * kdv * (1 - c),
    v[2] * c + kxv[2] * s + k[2] * kdv * (1 - c),
  ]);
}

/** @param {Camera} c */
export function cloneCamera(c) {
  return {
    eye: /** @type {Vec3} */ ([...c.eye]),
    target: /** @type {Vec3} */ ([...c.target]),
    up: /** @type {Vec3} */ ([...c.up]),
    fov_deg: c.fov_deg,
  };
}

/** Camera basis: forward (eye→target), right, true up (orthogonal to forward). */
export function basis(c) {
  const forward = normalize(sub(c.target, c.eye));
  let right = normalize(cross(forward, c.up));
  if (length(right) < 0.5) right = normalize(cross(forward, Math.abs(forward[2]) < 0.9 ? [0, 0, 1] : [0, 1, 0]));
  const up = cross(right, forward);
  return { forward, right, up };
}

/**
 * Turntable orbit: yaw around `up`, pitch around the camera's right axis, never flipping over
 * the pole. Angles in radians; positive yaw moves the eye to the right, positive pitch moves it up.
 * @param {Camera} c
 * @returns {Camera}
 */
export function orbit(c, yaw, pitch) {
  const out = cloneCamera(c);
  const up = normalize(c.up);
  let offset = sub(c.eye, c.target);
  const dist = length(offset);
  if (dist < 1e-9) return out;
  offset = rotate(offset, up, yaw);
  // Keep the angle between offset and up inside [minPolar, π − minPolar].
  const minPolar = 0.02;
  const polar = Math.acos(Math.max(-1, Math.min(1, dot(normalize(offset), up))));
  const newPolar = Math.max(minPolar, Math.min(Math.PI - minPolar, polar - pitch));
  const delta = newPolar - polar;
  if (Math.abs(delta) > 1e-9) {
    let axis = normalize(cross(up, offset));
    if (length(axis) < 0.5) axis = basis(c).right;
    // Rotating offset around (up × offset) by +delta increases the polar angle by delta.
    offset = rotate(offset, axis, delta);
  }
  out.eye = add(c.target, scale(normalize(offset), dist));
  return out;
}

/**
 * Pans eye and target in the view plane. dx, dy in CSS pixels of a view `viewHeight` tall:
 * the point under the cursor (at target depth) stays under the cursor.
 * @param {Camera} c
 */
export function pan(c, dx, dy, viewHeight) {
  const out = cloneCamera(c);
  const { right, up } = basis(c);
  const dist = length(sub(c.eye, c.target));
  const worldPerPixel = (2 * dist * Math.tan((c.fov_deg * Math.PI) / 360)) / Math.max(1, viewHeight);
  const move = add(scale(right, -dx * worldPerPixel), scale(up, dy * worldPerPixel));
  out.eye = add(c.eye, move);
  out.target = add(c.target, move);
  return out;
}

/**
 * Dolly toward the target: factor < 1 moves closer.
 * @param {Camera} c
 */
export function zoom(c, factor) {
  const out = cloneCamera(c);
  const offset = sub(c.eye, c.target);
  const dist = length(offset);
  if (dist < 1e-9 || !Number.isFinite(factor) || factor <= 0) return out;
  const nd = Math.min(MAX_DISTANCE, Math.max(MIN_DISTANCE, dist * factor));
  out.eye = add(c.target, scale(offset, nd / dist));
  return out;
}

/** Is this a usable camera (finite numbers, eye ≠ target, up not parallel to the view)? */
export function isValidCamera(c) {
  if (!c || !Array.isArray(c.eye) || !Array.isArray(c.target) || !Array.isArray(c.up)) return false;
  const nums = [...c.eye, ...c.target, ...c.up, c.fov_deg];
  if (nums.length !== 10 || !nums.every(Number.isFinite)) return false;
  const f = sub(c.target, c.eye);
  return length(f) > 1e-6 && length(cross(normalize(f), normalize(c.up))) > 1e-4;
}

/** Rounds for the wire (keeps messages short and stable). */
export function toMessage(c) {
  const r = (x) => Math.round(x * 1e5) / 1e5;
  return {
    type: 'camera',
    eye: c.eye.map(r),
    target: c.target.map(r),
    up: c.up.map(r),
    fov_deg: r(c.fov_deg),
  };
}
