// The panel: dataset and technique pickers, technique options, render-parameter, light and
// streaming sliders, the transfer-function editor and its presets. Input here becomes edits
// (`dataset`, `technique`, `params`, `lights`, `quality`, `tf`); the setters show the session's
// state and others' edits and never send, so an edit is not echoed back and forth.
//
// - sliders, lights and the TF editor queue their message for the next animation frame
//   (session.js's outbox: the latest value per type); pickers and technique options send at once
// - `quality` carries only the fields that changed: `jpeg_quality` is this viewer's own,
//   `iterations` edits the shared session
// - lights on the wire are direction/irradiance vectors; the panel shows the first directional
//   light as azimuth, elevation and intensity, the environment as one brightness
// - pushAll() sends this page's whole state into a fresh session after ours expired

import * as Cam from './camera.js';
import { TfEditor } from './tf-editor.js';
import { PRESETS, presetToTf } from './presets.js';
import { $, vx, local, params } from './state.js';
import { conn, send, queue, accessToken, TOKEN_KEY } from './session.js';
import { toast, fmtNum } from './status.js';

/** @typedef {[number, number, number]} Vec3 */
/** @typedef {{set: (v: number) => void}} Slider */

export const tfEditor = new TfEditor($('tf'), { colorInput: $('tf-color'), readout: $('tf-readout') });

export function initControls() {
  vx.tfPoints = () => tfEditor.points;
  bindTfEditor();
  bindSliders();
  bindPickers();
  // What the panel shows until the welcome brings the session's state.
  sDensity.set(local.params.density_scale);
  sExposure.set(local.params.exposure);
  sG.set(local.params.g);
  lightsToControls([
    { kind: 'directional', direction: [0.35, 0.75, -0.55], irradiance: [3.2, 3.1, 2.9] },
    { kind: 'environment', radiance: [0.1, 0.11, 0.13] },
  ]);
  sJpeg.set(local.jpeg_quality);
  sIters.set(local.iterations);
}

// ---- TF editor + presets -------------------------------------------------------------------

/** @param {any[]} points */
export function queueTf(points) {
  queue('tf', () => ({ points }));
}

function bindTfEditor() {
  tfEditor.addEventListener('change', (/** @type {any} */ e) => {
    markPreset(null);
    queueTf(e.detail);
  });

  $('tf-sqrt').addEventListener('click', () => {
    const on = $('tf-sqrt').getAttribute('aria-pressed') !== 'true';
    $('tf-sqrt').setAttribute('aria-pressed', String(on));
    tfEditor.setSqrtY(on);
  });

  for (const p of PRESETS) {
    const b = document.createElement('button');
    b.type = 'button';
    b.textContent = p.label;
    b.title = p.description;
    b.dataset.preset = p.id;
    b.addEventListener('click', () => applyPreset(p.id));
    $('presets').appendChild(b);
  }
}

/** @param {string} id */
function applyPreset(id) {
  const p = PRESETS.find((q) => q.id === id);
  if (!p) return;
  const d = vx.dataset?.details;
  const min = d && Number.isFinite(d.value_min) ? d.value_min : 0;
  const max = d && Number.isFinite(d.value_max) ? d.value_max : 1;
  if (p.space === 'HU' && d && d.units !== 'HU') {
    toast('info', 'preset', `${p.label} assumes CT data in HU; this dataset's units are “${d.units || 'unknown'}”`);
  }
  const points = presetToTf(p, min, max);
  tfEditor.setPoints(points);
  markPreset(id);
  queueTf(tfEditor.points);
}

/** @param {string|null} id */
export function markPreset(id) {
  for (const b of $('presets').querySelectorAll('button')) b.classList.toggle('active', b.dataset.preset === id);
}
// ---- sliders -------------------------------------------------------------------------------

/** Maps a 0..1000 slider to [lo, hi] logarithmically. */
const logMap = (lo, hi) => ({
  toValue: (/** @type {number} */ s) => lo * Math.pow(hi / lo, s / 1000),
  toSlider: (/** @type {number} */ v) => Math.round((1000 * Math.log(Math.max(lo, Math.min(hi, v)) / lo)) / Math.log(hi / lo)),
});
const densityMap = logMap(0.5, 2000);
const exposureMap = logMap(0.05, 20);
const intensityMap = logMap(0.05, 50);
const envMap = { toValue: (s) => (s / 1000) * 2, toSlider: (v) => Math.round((Math.max(0, Math.min(2, v)) / 2) * 1000) };
const itersMap = logMap(1, 4096);

/**
 * Binds a slider: on input, updates its output text and calls onChange(value).
 * @param {string} id
 * @param {{toValue: (s: number) => number, toSlider: (v: number) => number}} map
 * @param {(v: number) => string} fmt
 * @param {(v: number) => void} onChange
 * @returns {Slider}
 */
function bindSlider(id, map, fmt, onChange) {
  const input = $(id);
  const out = $(id + '-out');
  input.addEventListener('input', () => {
    const v = +map.toValue(Number(input.value)).toPrecision(4);
    out.textContent = fmt(v);
    onChange(v);
  });
  return {
    /** @param {number} v */
    set(v) {
      input.value = String(map.toSlider(v));
      out.textContent = fmt(v);
    },
  };
}

const fmt2 = (v) => (v >= 100 ? v.toFixed(0) : v >= 10 ? v.toFixed(1) : v.toFixed(2));
const identity = { toValue: (s) => s, toSlider: (v) => Math.round(v) };

/** The key (first directional) light and the environment as the light sliders show them. */
const key = { az: -34, el: 44, intensity: 2.5, tint: /** @type {Vec3} */ ([1, 0.96, 0.88]) };
const env = { brightness: 0.25, tint: /** @type {Vec3} */ ([1, 1.08, 1.2]) };

// The sliders, bound by bindSliders() (initControls).
/** @type {Slider} */ let sDensity;
/** @type {Slider} */ let sExposure;
/** @type {Slider} */ let sG;
/** @type {Slider} */ let sAz;
/** @type {Slider} */ let sEl;
/** @type {Slider} */ let sInt;
/** @type {Slider} */ let sEnv;
/** @type {Slider} */ let sJpeg;
/** @type {Slider} */ let sIters;

function bindSliders() {
  sDensity = bindSlider('density', densityMap, fmt2, (v) => {
    local.params.density_scale = v;
    queueParams();
  });
  sExposure = bindSlider('exposure', exposureMap, fmt2, (v) => {
    local.params.exposure = v;
    queueParams();
  });
  sG = bindSlider('g', { toValue: (s) => s / 100, toSlider: (v) => Math.round(v * 100) }, (v) => v.toFixed(2), (v) => {
    local.params.g = v;
    queueParams();
  });

  sAz = bindSlider('light-az', identity, (v) => `${Math.round(v)}°`, (v) => {
    key.az = v;
    queueLights();
  });
  sEl = bindSlider('light-el', identity, (v) => `${Math.round(v)}°`, (v) => {
    key.el = v;
    queueLights();
  });
  sInt = bindSlider('light-int', intensityMap, fmt2, (v) => {
    key.intensity = v;
    queueLights();
  });
  sEnv = bindSlider('light-env', envMap, fmt2, (v) => {
    env.brightness = v;
    queueLights();
  });

  sJpeg = bindSlider('jpeg-q', identity, (v) => String(Math.round(v)), (v) => {
    local.jpeg_quality = Math.round(v);
    queueQuality('jpeg_quality');
  });
  sIters = bindSlider('iters', itersMap, (v) => String(Math.round(v)), (v) => {
    local.iterations = Math.max(1, Math.round(v));
    queueQuality('iterations');
  });
}

function queueParams() {
  queue('params', () => ({ ...local.params }));
}

/**
 * Fields of the next `quality` message. Only what changed is sent: `jpeg_quality` is this
 * viewer's own, while `iterations` edits the shared session (everyone sees an `edited`).
 */
const qualityDirty = new Set();
/** @param {'jpeg_quality'|'iterations'} field */
function queueQuality(field) {
  qualityDirty.add(field);
  queue('quality', () => {
    /** @type {Record<string, number>} */
    const body = {};
    if (qualityDirty.has('jpeg_quality')) body.jpeg_quality = local.jpeg_quality;
    if (qualityDirty.has('iterations')) body.iterations = local.iterations;
    qualityDirty.clear();
    return body;
  });
}

/** Is an `iterations` change waiting for the next animation frame (a shared-session edit)? */
export function iterationsQueued() {
  return qualityDirty.has('iterations');
}

/** ?iterations=N in the page URL: a convergence target for a new session (demos, tests). */
export function applyUrlIterations() {
  const wanted = Number(params.get('iterations'));
  if (Number.isInteger(wanted) && wanted >= 1 && wanted !== local.iterations) {
    local.iterations = wanted;
    sIters.set(wanted);
    send('quality', { jpeg_quality: local.jpeg_quality, iterations: wanted });
  }
}

/**
 * Key-light direction from azimuth (degrees, 0 = from the front (−y), positive toward +x) and
 * elevation (degrees above the xy plane). `direction` on the wire is the way the light travels,
 * i.e. from the light into the scene, so it is minus the vector toward the light.
 */
function keyDirection(az, el) {
  const a = (az * Math.PI) / 180;
  const e = (el * Math.PI) / 180;
  const toLight = [Math.cos(e) * Math.sin(a), -Math.cos(e) * Math.cos(a), Math.sin(e)];
  return toLight.map((x) => round5(-x));
}

const round5 = (x) => Math.round(x * 1e5) / 1e5;
const maxc = (/** @type {number[]} */ v) => Math.max(1e-6, v[0], v[1], v[2]);

function buildLights() {
  const lights = [];
  let haveKey = false;
  let haveEnv = false;
  for (const l of local.lights) {
    if (l.kind === 'directional' && !haveKey) {
      haveKey = true;
      lights.push({ kind: 'directional', direction: keyDirection(key.az, key.el), irradiance: key.tint.map((t) => round5(t * key.intensity)) });
    } else if (l.kind === 'environment' && !haveEnv) {
      haveEnv = true;
      lights.push({ kind: 'environment', radiance: env.tint.map((t) => round5(t * env.brightness)) });
    } else {
      lights.push(l);
    }
  }
  if (!haveKey) lights.unshift({ kind: 'directional', direction: keyDirection(key.az, key.el), irradiance: key.tint.map((t) => round5(t * key.intensity)) });
  if (!haveEnv) lights.push({ kind: 'environment', radiance: env.tint.map((t) => round5(t * env.brightness)) });
  return lights.slice(0, 16);
}

function queueLights() {
  local.lights = buildLights();
  queue('lights', () => ({ lights: local.lights }));
}

/** Reads the first directional and environment light into the light controls. */
function lightsToControls(lights) {
  local.lights = Array.isArray(lights) ? lights.map((l) => ({ ...l })) : [];
  const k = local.lights.find((l) => l.kind === 'directional');
  if (k && Array.isArray(k.direction) && Array.isArray(k.irradiance)) {
    const d = Cam.normalize(/** @type {Vec3} */ (k.direction.map((x) => -x)));
    key.el = (Math.asin(Math.max(-1, Math.min(1, d[2]))) * 180) / Math.PI;
    key.az = (Math.atan2(d[0], -d[1]) * 180) / Math.PI;
    key.intensity = maxc(k.irradiance);
    key.tint = /** @type {Vec3} */ (k.irradiance.map((x) => x / key.intensity));
  }
  const en = local.lights.find((l) => l.kind === 'environment');
  if (en && Array.isArray(en.radiance)) {
    env.brightness = maxc(en.radiance);
    env.tint = /** @type {Vec3} */ (en.radiance.map((x) => x / env.brightness));
  }
  sAz.set(key.az);
  sEl.set(key.el);
  sInt.set(key.intensity);
  sEnv.set(env.brightness);
}

// ---- dataset + technique pickers -----------------------------------------------------------

function bindPickers() {
  $('dataset').addEventListener('change', () => {
    const name = $('dataset').value;
    if (!name || name === vx.dataset?.name) return;
    if (send('dataset', { name })) {
      local.dataset = name;
      $('dataset').disabled = true;
      $('dataset-info').textContent = `loading ${name}…`;
    }
  });

  $('technique').addEventListener('change', () => {
    const name = $('technique').value;
    if (send('technique', { name })) {
      local.technique = name;
      showTechniqueDesc();
      renderTechniqueOptions();
    }
  });
}

export async function loadDatasetList() {
  try {
    /** @type {Record<string, string>} */
    const headers = { accept: 'application/json' };
    if (accessToken()) headers.authorization = `Bearer ${accessToken()}`;
    const res = await fetch('./api/datasets', { headers });
    if (res.status === 401) {
      // The server wants a token: ask once, then reconnect with it.
      const token = window.prompt('This voxlight server needs an access token:');
      if (token) {
        sessionStorage.setItem(TOKEN_KEY, token.trim());
        conn.connect();
        return loadDatasetList();
      }
    }
    if (!res.ok) throw new Error(`HTTP ${res.status}`);
    const body = await res.json();
    const list = Array.isArray(body.datasets) ? body.datasets : [];
    const sel = $('dataset');
    const current = vx.dataset?.name || local.dataset || body.default;
    sel.textContent = '';
    for (const d of list) {
      const o = document.createElement('option');
      o.value = d.name;
      o.textContent = d.kind && !String(d.name).startsWith(d.kind) ? `${d.name}  (${d.kind})` : d.name;
      sel.appendChild(o);
    }
    ensureDatasetOption(current);
  } catch (err) {
    console.warn('voxlight: could not list datasets', err);
    if (vx.dataset) ensureDatasetOption(vx.dataset.name);
  }
}

function ensureDatasetOption(name) {
  if (!name) return;
  const sel = $('dataset');
  if (![...sel.options].some((o) => o.value === name)) {
    const o = document.createElement('option');
    o.value = name;
    o.textContent = name;
    sel.appendChild(o);
  }
  sel.value = name;
}

export function fillTechniques(list) {
  const sel = $('technique');
  sel.textContent = '';
  for (const t of list) {
    const o = document.createElement('option');
    o.value = t.name;
    o.textContent = t.name;
    o.title = t.description || '';
    sel.appendChild(o);
  }
}

function showTechniqueDesc() {
  const t = vx.techniques.find((x) => x.name === $('technique').value);
  $('technique-desc').textContent = t ? t.description : '';
}

/** @param {any} info DatasetInfo */
export function applyDatasetInfo(info) {
  if (!info) return;
  vx.dataset = info;
  local.dataset = info.name;
  ensureDatasetOption(info.name);
  $('dataset').disabled = false;
  const d = info.details;
  $('hud-dataset').textContent = info.name;
  if (d) {
    tfEditor.setDataset(d);
    const units = d.units ? ` ${d.units}` : '';
    const sp = (d.spacing || []).map((x) => +Number(x).toFixed(3)).join(' × ');
    $('dataset-info').textContent = `${(d.dims || []).join(' × ')} voxels · spacing ${sp} · ${fmtNum(d.value_min)}…${fmtNum(d.value_max)}${units}` + (d.modality ? ` · ${d.modality}` : '') + (d.format ? ` · ${d.format}` : '')
      + (d.downsampled ? ` · shown at 1/${d.downsampled.factor} per axis (loaded ${(d.downsampled.original_dims || []).join(' × ')}: ${d.downsampled.reason})` : '');
    $('hud-sub').textContent = [d.modality, d.dims ? d.dims.join('×') : ''].filter(Boolean).join(' · ');
    for (const w of d.warnings || []) toast('info', 'dataset', String(w));
    const isCt = d.units === 'HU';
    for (const b of $('presets').querySelectorAll('button')) {
      const p = PRESETS.find((q) => q.id === b.dataset.preset);
      b.classList.toggle('not-ct', !!p && p.space === 'HU' && !isCt);
    }
  } else {
    tfEditor.setDataset({});
    $('dataset-info').textContent = info.kind || '';
  }
}

// The setters below change what the UI shows and never send anything: they apply the server's
// state and others' edits, so sending from them would echo edits back and forth.

/**
 * Shows someone else's edit in the UI. Returns whether it was understood.
 * @param {any} edit a client message as the server applied it
 */
export function applyEdit(edit) {
  switch (edit.type) {
    case 'camera':
      return setCamera(edit);
    case 'tf':
      return setTf(edit.points);
    case 'lights':
      if (!Array.isArray(edit.lights)) return false;
      lightsToControls(edit.lights);
      return true;
    case 'params':
      return setParams(edit);
    case 'technique':
      if (edit.options) overlayOptions(edit.options);
      return setTechnique(edit.name);
    case 'quality':
      return setIterations(edit.iterations);
    case 'viewport':
      // The session has one viewport: someone else's window size is now the picture's size.
      if (!Number.isFinite(edit.width) || !Number.isFinite(edit.height)) return false;
      vx.viewport = { width: edit.width, height: edit.height };
      return true;
    default:
      return false; // newer servers may edit more
  }
}

/**
 * Applies a whole SessionState (welcome, dataset_loaded, state).
 * @param {any} s SessionState
 * @param {(kind: string) => boolean} [keep] kinds to leave as they are (newer local input)
 */
export function applyState(s, keep = () => false) {
  if (!keep('camera')) setCamera(s.camera);
  if (s.tf && !keep('tf')) setTf(s.tf.points);
  if (!keep('params')) setParams(s.params);
  if (Array.isArray(s.lights) && !keep('lights')) lightsToControls(s.lights);
  if (!keep('technique')) {
    local.techniqueOptions = structuredClone(s.technique_options || {});
    setTechnique(s.technique);
  }
  if (Number.isFinite(s.jpeg_quality)) local.jpeg_quality = s.jpeg_quality;
  sJpeg.set(local.jpeg_quality);
  if (!keep('quality')) setIterations(s.iterations);
  if (typeof s.dataset === 'string') ensureDatasetOption(s.dataset);
}

/** @param {any} c Camera */
function setCamera(c) {
  if (!c || !Cam.isValidCamera(c)) return false;
  vx.camera = Cam.cloneCamera(c);
  return true;
}

/** @param {any} points TfPoint[] */
function setTf(points) {
  if (!Array.isArray(points)) return false;
  tfEditor.setPoints(points);
  markPreset(null);
  return true;
}

/** @param {any} p RenderParams (absent fields keep their value) */
function setParams(p) {
  if (p) for (const k of ['density_scale', 'g', 'exposure']) if (Number.isFinite(p[k])) local.params[k] = p[k];
  sDensity.set(local.params.density_scale);
  sExposure.set(local.params.exposure);
  sG.set(local.params.g);
  return !!p;
}

/** @param {any} name */
export function setTechnique(name) {
  if (typeof name === 'string') {
    local.technique = name;
    $('technique').value = name;
  }
  showTechniqueDesc();
  renderTechniqueOptions();
  return typeof name === 'string';
}

/** `base` with every option `edit` sets taken from `edit` (as the server overlays them). */
export function overlaid(/** @type {any} */ base, /** @type {any} */ edit) {
  const out = structuredClone(base || {});
  for (const [group, fields] of Object.entries(edit || {})) {
    if (fields && typeof fields === 'object') out[group] = { ...(out[group] || {}), ...fields };
  }
  return out;
}

function overlayOptions(/** @type {any} */ edit) {
  local.techniqueOptions = overlaid(local.techniqueOptions, edit);
}

/**
 * The options the panel offers per technique (the server's `default_options` give the
 * defaults; any value the session holds is shown even when not in the list).
 * @type {Record<string, {key: string, label: string, title: string, values: any[]}[]>}
 */
const OPTION_CONTROLS = {
  photon: [
    { key: 'photons_per_pass', label: 'Photons/pass', title: 'Photon paths traced per progressive pass', values: [4096, 16384, 65536] },
    { key: 'bounces', label: 'Bounces', title: 'Most scattering events per photon path (1: single scattering; Russian roulette ends most paths earlier)', values: [1, 2, 4, 8, 16, 64, 256, 1024] },
    { key: 'segments', label: 'Segments', title: 'View-ray segments per pixel (Vn)', values: [4, 8, 16] },
    { key: 'invalidation', label: 'TF-edit test', title: 'How a TF edit finds the view-ray segments to gather again', values: ['dirty_cells', 'spatial3x64', 'any_photon'] },
  ],
  manylight: [
    { key: 'virtual_lights', label: 'Virtual lights', title: 'Virtual spherical lights stored', values: [64, 256, 1000, 2000] },
    { key: 'transmittance', label: 'Transmittance', title: 'From each virtual light: shadow-map lookup (point or interpolated) or a ray marched', values: ['avsm_trilinear', 'avsm_point', 'ray_marched'] },
    { key: 'face_res', label: 'Shadow maps', title: 'Shadow-map texels per cube-face edge', values: [4, 8, 16, 24, 48] },
    { key: 'vsl_radius', label: 'Light radius', title: 'Radius of a virtual spherical light (world units; the volume is 1 across)', values: [0.01, 0.02, 0.025, 0.05] },
    { key: 'iterations_per_set', label: 'New lights every', title: 'Iterations rendered with one set of virtual lights before a new, independent set is averaged in (0: one set, as in the paper)', values: [0, 1, 4, 16] },
  ],
  irradiance: [
    { key: 'cache', label: 'Cache', title: 'Use the irradiance cache (off: plain Monte Carlo)', values: [true, false] },
    { key: 'locking', label: 'Locking', title: 'Locks while an entry is created: octree node (object) or image block (screen)', values: ['object', 'screen'] },
    { key: 'priorities', label: 'Priorities', title: 'Render image blocks by expected gain instead of in turn', values: [true, false] },
    { key: 'max_radius_voxels', label: 'Zone radius', title: 'Largest cache-zone radius in voxels', values: [1, 2, 4, 8, 16] },
    { key: 'cached_light', label: 'Cached light', title: 'What cache entries hold: the indirect light (lights traced with shadow rays) or all of it (the paper)', values: ['indirect', 'all'] },
  ],
};

function optionText(/** @type {any} */ v) {
  if (v === true) return 'on';
  if (v === false) return 'off';
  return String(v).replaceAll('_', ' ');
}

/** Shows the current technique's options as drop-downs; a change is sent at once. */
function renderTechniqueOptions() {
  const box = $('technique-options');
  box.textContent = '';
  const name = local.technique;
  const controls = OPTION_CONTROLS[name];
  if (!controls) return;
  const info = /** @type {any} */ (vx.techniques.find((t) => t.name === name));
  const defaults = info?.default_options?.[name] || {};
  const set = local.techniqueOptions[name] || {};
  for (const c of controls) {
    const current = c.key in set ? set[c.key] : defaults[c.key];
    const values = [...c.values];
    if (current !== undefined && !values.includes(current)) values.push(current);
    const row = document.createElement('label');
    row.className = 'row';
    row.title = c.title;
    const span = document.createElement('span');
    span.textContent = c.label;
    const sel = document.createElement('select');
    sel.dataset.option = c.key;
    sel.setAttribute('aria-label', `${name} ${c.label}`);
    values.forEach((v, i) => {
      const o = document.createElement('option');
      o.value = String(i);
      o.textContent = optionText(v) + (v === defaults[c.key] ? ' (default)' : '');
      sel.appendChild(o);
    });
    sel.value = String(Math.max(0, values.indexOf(current)));
    sel.addEventListener('change', () => {
      const value = values[Number(sel.value)];
      const options = { [name]: { [c.key]: value } };
      if (send('technique', { name, options })) overlayOptions(options);
    });
    row.append(span, sel);
    box.appendChild(row);
  }
}

/** @param {any} n */
function setIterations(n) {
  if (Number.isFinite(n) && n >= 1) local.iterations = n;
  sIters.set(local.iterations);
  return Number.isFinite(n);
}

/** Into a fresh session after ours expired: send this page's whole state. */
export function pushAll() {
  send('camera', Cam.toMessage(vx.camera));
  send('tf', { points: tfEditor.points });
  send('lights', { lights: buildLights() });
  send('params', { ...local.params });
  const options = local.techniqueOptions;
  const hasOptions = Object.values(options).some((group) => group && Object.keys(group).length > 0);
  if (local.technique && (vx.welcome?.state?.technique !== local.technique || hasOptions)) {
    send('technique', hasOptions ? { name: local.technique, options } : { name: local.technique });
  }
  if (vx.welcome?.state?.iterations !== local.iterations) send('quality', { jpeg_quality: local.jpeg_quality, iterations: local.iterations });
  $('technique').value = local.technique;
  showTechniqueDesc();
}

