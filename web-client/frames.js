// Frames: the server's binary frames decoded and drawn on the view's 2D canvas, acknowledged
// for flow control, and the canvas size that sets the session's viewport.
//
// - one frame decodes at a time; newer ones wait in a single slot (newest wins, the one it
//   replaces is acknowledged so the server's window keeps moving)
// - every frame shown or undecodable is acknowledged (`ack`): the server keeps at most
//   MAX_IN_FLIGHT unacknowledged; a watchdog repeats the newest ack when the stream stalls
// - a picture is letterboxed into the canvas: a reduced-resolution preview fills the same
//   rectangle as the full-resolution still
// - edit→frame latency: from an own camera/TF edit to the first frame that shows it

import { $, vx } from './state.js';
import { conn, send } from './session.js';
import { renderStatus } from './status.js';

/** @typedef {import('./connection.js').FrameMeta} FrameMeta */
/** @typedef {{meta: FrameMeta, image: Uint8Array, receivedAt: number, welcomeNo: number}} Frame */

/** Frames the server may send before we acknowledge them: one on screen, one decoding. */
export const MAX_IN_FLIGHT = 2;
/** Frames kept in `voxlight.shownLog`. */
const SHOWN_LOG = 200;
/** Longest edge the server accepts (protocol MAX_VIEWPORT_EDGE). */
const MAX_VIEWPORT_EDGE = 4096;
/** Streamed images are capped to about this many pixels (1024²). */
const MAX_VIEWPORT_PIXELS = 1024 * 1024;
const MIN_VIEWPORT_EDGE = 64;
/** Frames should be coming but none came for this long: repeat the newest ack. */
const REACK_AFTER_MS = 3000;

export const canvas = /** @type {HTMLCanvasElement} */ ($('viewer'));
const ctx = /** @type {CanvasRenderingContext2D} */ (canvas.getContext('2d', { alpha: false }));

/** @type {Frame | null} */
let pendingFrame = null;
/**
 * Counts welcomes. A frame remembers the connection it came on: one still decoding when the
 * connection changed must not be acknowledged on the new one (a new session numbers its frames
 * from the start again, so its old, large seq would acknowledge frames not yet sent).
 */
let welcomeNo = 0;
/** When the last frame arrived, and when the watchdog last repeated an ack (performance.now). */
let lastFrameAt = 0;
let lastReackAt = 0;
let decoding = false;
/** @type {ImageBitmap | null} */
let shownBitmap = null;
/** Display times of the last second's frames, for fps. */
const shownTimes = /** @type {number[]} */ ([]);
/**
 * The oldest own edit not yet seen in a frame: {at, baseVersion, kind, target}. `target` is
 * the version its echo announced; until the echo arrives any newer scene_version counts (others'
 * edits can make that early, but the echo normally comes before the first frame showing it).
 */
let pendingEdit = /** @type {{at: number, baseVersion: number, kind: string, target: number|null} | null} */ (null);
let maxSceneVersion = -1;

export function initFrames() {
  vx.sample = (n) => sampleCanvas(n || 32);
  conn.addEventListener('frame', (/** @type {any} */ e) => onFrame(e.detail));
  setInterval(ackWatchdog, 1000);
  new ResizeObserver(resizeCanvas).observe(canvas);
  vx.viewport = computeViewport();
}

/** A new connection (welcome): forget the last one's frames and the edit being timed. */
export function resetFrameTracking() {
  welcomeNo++;
  pendingEdit = null;
  maxSceneVersion = -1;
  pendingFrame = null;
  vx.acked = -1;
}

/**
 * An own camera or TF edit went out: time it to its first frame unless one is being timed.
 * @param {string} kind
 */
export function editSent(kind) {
  if (!pendingEdit) pendingEdit = { at: performance.now(), baseVersion: maxSceneVersion, kind, target: null };
}

/**
 * The echo (`edited`) of an own edit announced its scene version: the edit being timed, if of
 * this kind, is shown by the first frame of at least that version.
 * @param {string} kind
 * @param {number} version
 */
export function editEchoed(kind, version) {
  if (pendingEdit && pendingEdit.target == null && pendingEdit.kind === kind && Number.isFinite(version)) pendingEdit.target = version;
}

/** Frames displayed in the last second. */
export function framesLastSecond() {
  const now = performance.now();
  while (shownTimes.length && now - shownTimes[0] > 1000) shownTimes.shift();
  return shownTimes.length;
}

/** @param {{meta: FrameMeta, image: Uint8Array, receivedAt: number}} detail */
function onFrame(detail) {
  const f = { ...detail, welcomeNo };
  lastFrameAt = performance.now();
  vx.framesReceived++;
  vx.lastMeta = f.meta;
  const sv = Number(f.meta.scene_version);
  if (Number.isFinite(sv)) {
    if (pendingEdit && (pendingEdit.target != null ? sv >= pendingEdit.target : sv > pendingEdit.baseVersion)) {
      vx.lastLatencyMs = f.receivedAt - pendingEdit.at;
      pendingEdit = null;
    }
    maxSceneVersion = Math.max(maxSceneVersion, sv);
  }
  if (decoding) {
    if (pendingFrame) {
      // Newest wins; the dropped one is acknowledged so the server's window keeps moving.
      vx.framesDropped++;
      ackFrame(pendingFrame);
    }
    pendingFrame = f;
    return;
  }
  void decodeAndShow(f);
}

/**
 * Acknowledges every frame up to this one (flow control, hello.max_in_flight): the server
 * sends the next frame only when fewer than MAX_IN_FLIGHT are unacknowledged.
 * @param {Frame} f
 */
function ackFrame(f) {
  const seq = Number(f.meta && f.meta.seq);
  if (f.welcomeNo !== welcomeNo || !Number.isSafeInteger(seq) || seq <= vx.acked) return;
  if (send('ack', { seq })) vx.acked = seq;
}

/**
 * Repeats the newest ack when the picture should be changing (not converged yet, or an edit
 * newer than the last frame) but no frame came for a while: an ack the server dropped (its rate
 * limit counts acks too) would otherwise leave the window full and the stream stalled for good.
 * The server ignores an ack that is not newer than the last one it took, so this is harmless.
 */
function ackWatchdog() {
  const m = vx.lastMeta;
  if (!conn.ready || !m || vx.acked < 0 || decoding) return;
  const expecting = !m.converged || vx.version > Number(m.scene_version);
  const now = performance.now();
  if (expecting && now - lastFrameAt > REACK_AFTER_MS && now - lastReackAt > REACK_AFTER_MS) {
    lastReackAt = now;
    send('ack', { seq: vx.acked });
  }
}

/** @param {Frame} f */
async function decodeAndShow(f) {
  decoding = true;
  try {
    const type = f.meta.format === 'png' ? 'image/png' : 'image/jpeg';
    const bmp = await createImageBitmap(new Blob([f.image], { type }));
    if (shownBitmap) shownBitmap.close();
    shownBitmap = bmp;
    const drawn = drawShown();
    vx.framesShown++;
    vx.lastShownMeta = f.meta;
    vx.shownLog.push({
      seq: f.meta.seq,
      version: f.meta.scene_version,
      preview: !!f.meta.preview,
      scale: Number(f.meta.resolution_scale ?? 1),
      width: f.meta.width,
      height: f.meta.height,
      lossless: !!f.meta.lossless,
      converged: !!f.meta.converged,
      drawn,
    });
    if (vx.shownLog.length > SHOWN_LOG) vx.shownLog.shift();
    const now = performance.now();
    shownTimes.push(now);
    while (shownTimes.length && now - shownTimes[0] > 1000) shownTimes.shift();
    renderStatus();
  } catch (err) {
    console.warn('voxlight: could not decode frame', f.meta && f.meta.seq, err);
  } finally {
    // Shown (or undecodable): either way the server may send the next one.
    ackFrame(f);
    decoding = false;
    const next = pendingFrame;
    pendingFrame = null;
    if (next) void decodeAndShow(next);
  }
}

/**
 * Draws the current bitmap scaled to fit the canvas (letterboxed, aspect kept): a reduced
 * preview is scaled up to the same rectangle as a full-resolution frame.
 * @returns {{x: number, y: number, w: number, h: number}|null} where it was drawn
 */
function drawShown() {
  ctx.fillStyle = '#000';
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  const b = shownBitmap;
  if (!b) return null;
  const s = Math.min(canvas.width / b.width, canvas.height / b.height);
  const w = b.width * s;
  const h = b.height * s;
  ctx.imageSmoothingEnabled = true;
  ctx.imageSmoothingQuality = 'high';
  const rect = { x: (canvas.width - w) / 2, y: (canvas.height - h) / 2, w, h };
  ctx.drawImage(b, rect.x, rect.y, w, h);
  return rect;
}

function sampleCanvas(n = 32) {
  const c = document.createElement('canvas');
  c.width = n;
  c.height = n;
  const g = /** @type {CanvasRenderingContext2D} */ (c.getContext('2d'));
  g.drawImage(canvas, 0, 0, n, n);
  const d = g.getImageData(0, 0, n, n).data;
  const out = new Array(n * n);
  for (let i = 0; i < n * n; i++) out[i] = Math.round((d[4 * i] + d[4 * i + 1] + d[4 * i + 2]) / 3);
  return { w: n, h: n, data: out };
}

// ---- canvas size and viewport --------------------------------------------------------------

/** The view's size in CSS pixels. */
export function cssSize() {
  const r = canvas.getBoundingClientRect();
  return { w: Math.max(1, r.width), h: Math.max(1, r.height) };
}

/** CSS size × devicePixelRatio, capped to ~1024² pixels and MAX_VIEWPORT_EDGE, at least 64. */
export function computeViewport() {
  const { w, h } = cssSize();
  const dpr = window.devicePixelRatio || 1;
  const s = Math.min(dpr, Math.sqrt(MAX_VIEWPORT_PIXELS / (w * h)));
  const clampEdge = (x) => Math.max(MIN_VIEWPORT_EDGE, Math.min(MAX_VIEWPORT_EDGE, Math.round(x)));
  return { width: clampEdge(w * s), height: clampEdge(h * s) };
}

let viewportTimer = 0;
/** Sends our viewport after `delay` ms of no resizing, when it differs from the session's. */
export function scheduleViewport(delay = 150) {
  clearTimeout(viewportTimer);
  viewportTimer = setTimeout(() => {
    const vp = computeViewport();
    if (vp.width !== vx.viewport.width || vp.height !== vx.viewport.height) {
      if (send('viewport', vp)) vx.viewport = vp;
    }
  }, delay);
}

function resizeCanvas() {
  const { w, h } = cssSize();
  const dpr = Math.min(2, window.devicePixelRatio || 1);
  const bw = Math.max(1, Math.round(w * dpr));
  const bh = Math.max(1, Math.round(h * dpr));
  if (canvas.width !== bw || canvas.height !== bh) {
    canvas.width = bw;
    canvas.height = bh;
  }
  drawShown();
  scheduleViewport();
}
