// What the viewer tells the person in front of it besides the picture: the status bar under
// the view, the picture-state badge and progress bar, toasts, the connection overlay and dot.
// Everything here only displays; nothing sends.
//
// - renderStatus() redraws the bar from the last frame's meta and the last `stats` (every
//   frame shown, every `stats`, and twice a second for the fps count)
// - the adapter line puts the software-renderer flag first: the bar cuts long names short
// - `loading` progress of a dataset fetched from a PACS goes to the overlay before the first
//   welcome, to the dataset panel after it

import { $, vx } from './state.js';
import { framesLastSecond } from './frames.js';

export function initStatus() {
  setInterval(renderStatus, 500);
}

export function renderStatus() {
  const m = vx.lastShownMeta || vx.lastMeta;
  const st = vx.lastStats;
  $('st-fps').textContent = `${framesLastSecond()} fps`;
  if (m) {
    $('st-iter').textContent = `it ${m.iteration}/${m.target_iterations}`;
    $('st-tech').textContent = m.technique;
    const conv = $('st-conv');
    conv.textContent = m.converged ? 'converged' : 'converging…';
    conv.className = m.converged ? 'done' : 'conv';
    const codec = m.lossless ? 'lossless PNG' : `${String(m.format).toUpperCase()}${m.quality ? ' q' + m.quality : ''}`;
    // A preview while edits stream in: shown at its resolution scale, upscaled to the canvas.
    const scale = Number(m.resolution_scale ?? 1);
    $('st-codec').textContent = m.preview ? `${codec} · preview ${scale === 1 ? 'full' : '1/' + Math.round(1 / scale)} res` : codec;
    $('st-size').textContent = `${m.width}×${m.height}`;
    const frac = m.target_iterations > 0 ? Math.min(1, m.iteration / m.target_iterations) : m.converged ? 1 : 0;
    $('progress-bar').style.width = `${(m.converged ? 1 : frac) * 100}%`;
    $('progress').classList.toggle('done', !!m.converged);
    const badge = $('badge');
    if (m.converged) {
      badge.className = 'badge badge-done';
      badge.textContent = m.lossless ? 'converged · lossless' : 'converged';
    } else {
      badge.className = 'badge badge-conv';
      badge.textContent = `converging ${m.iteration}/${m.target_iterations}`;
    }
  }
  $('st-lat').textContent = vx.lastLatencyMs == null ? 'edit→frame –' : `edit→frame ${Math.round(vx.lastLatencyMs)} ms`;
  if (st) {
    $('st-gpu').textContent = `gpu ${Number(st.gpu_ms || 0).toFixed(1)} ms · ${fmtBytes(st.memory_bytes || 0)}`;
    $('st-details').textContent = fmtDetails(st.details || {});
    // Flow control and adaptation (what the server chose for this viewer's link).
    $('st-fps').title = `Frames displayed per second (last second). Server: ${Number(st.fps || 0).toFixed(0)} fps sent, ${st.frames_skipped || 0} frames skipped while busy, JPEG quality ${st.jpeg_quality || '?'}`;
  }
}

/**
 * The server's adapter, version and our session at the right of the status bar.
 * @param {any} w welcome
 */
export function showAdapter(w) {
  // The software flag first: the status bar cuts long adapter names short.
  $('st-adapter').textContent = `${w.software_renderer ? 'software, no GPU: ' : ''}${w.adapter || '?'} · server ${w.server_version || '?'} · session ${String(w.session || '').slice(0, 8)}`;
}

/**
 * `loading`: a dataset arriving from a PACS, parts (instances) fetched so far.
 * @param {any} m
 * @param {boolean} welcomed the connection has its welcome (else the overlay is up)
 */
export function showLoading(m, welcomed) {
  const what = `${m.dataset}: ${m.done} of ${m.total} images received`;
  if (!welcomed) showOverlay('Loading the dataset…', what, false);
  else $('dataset-info').textContent = `loading ${what}`;
  vx.loading = { dataset: String(m.dataset), done: Number(m.done), total: Number(m.total) };
}

/** The badge while the connection is down (the last frame's state no longer holds). */
export function showOffline() {
  $('badge').className = 'badge badge-wait';
  $('badge').textContent = 'offline';
}

/**
 * @param {'error'|'info'} kind
 * @param {string} code
 * @param {string} text
 */
export function toast(kind, code, text) {
  const el = document.createElement('div');
  el.className = `toast ${kind === 'info' ? 'info' : ''}`;
  const b = document.createElement('b');
  b.textContent = code;
  el.appendChild(b);
  el.appendChild(document.createTextNode(text));
  const box = $('toasts');
  box.appendChild(el);
  while (box.children.length > 4) box.firstChild.remove();
  setTimeout(() => el.remove(), kind === 'error' ? 6000 : 3500);
}

/** @param {string} title @param {string} text @param {boolean} retry show "Reconnect now" */
export function showOverlay(title, text, retry) {
  $('overlay').hidden = false;
  $('overlay-title').textContent = title;
  $('overlay-text').textContent = text;
  $('overlay-retry').hidden = !retry;
}
export function hideOverlay() {
  $('overlay').hidden = true;
}
/** @param {'on'|'wait'|'off'} state */
export function setConnDot(state) {
  const d = $('conn-dot');
  d.className = 'dot' + (state === 'on' ? ' on' : state === 'wait' ? ' wait' : '');
  d.title = state === 'on' ? 'connected' : state === 'wait' ? 'connecting' : 'disconnected';
}

/** @param {number} x */
export function fmtNum(x) {
  if (!Number.isFinite(x)) return '?';
  return (Math.abs(x) >= 100 ? Math.round(x).toString() : (+x.toPrecision(4)).toString()).replace('-', '−');
}
/**
 * One line of a technique's figures (stats.details; only the fields it reports).
 * @param {Record<string, any>} d
 */
function fmtDetails(d) {
  const pct = (x) => `${Number(x).toFixed(0)}%`;
  const parts = [];
  if (d.cache_active === false) parts.push('cache off (anisotropic phase)');
  if (d.cache_entries != null) parts.push(`cache ${d.cache_entries} entries`);
  if (d.cache_hit_rate != null && d.cache_active !== false) parts.push(`hit ${pct(100 * d.cache_hit_rate)}`);
  if (d.pending_entries) parts.push(`${d.pending_entries} pending`);
  if (d.cache_entries_kept_pct != null) parts.push(`last TF edit kept ${pct(d.cache_entries_kept_pct)}`);
  if (d.photons_in_map != null) parts.push(`${d.photons_in_map} photon paths`);
  if (d.photons_retraced_pct != null) parts.push(`retraced ${pct(d.photons_retraced_pct)}`);
  if (d.virtual_lights != null) parts.push(`${d.virtual_lights} virtual lights`);
  if (d.light_paths_retraced_pct != null) parts.push(`paths retraced ${pct(d.light_paths_retraced_pct)}`);
  return parts.join(' · ');
}

/** @param {number} n */
function fmtBytes(n) {
  if (n >= 1 << 30) return (n / (1 << 30)).toFixed(2) + ' GiB';
  if (n >= 1 << 20) return (n / (1 << 20)).toFixed(1) + ' MiB';
  return (n / 1024).toFixed(0) + ' KiB';
}
