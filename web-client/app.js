// voxlight browser client: shows the server's progressively refined frames and sends camera,
// transfer-function, light, technique and parameter edits. Plain ES modules, no dependencies,
// 2D canvas only (works with GPU and WebGL disabled). Protocol: docs/protocol.md.
//
// Sessions are shared: the page URL carries `?session=ID` (the share link), every viewer may
// edit (last writer wins, the server tells everyone who edited with `edited`), and a dropped
// connection rejoins the same session.

import { Connection, PROTOCOL_VERSION, routeFolders, wsUrlFor } from './connection.js';
import * as Cam from './camera.js';
import { TfEditor } from './tf-editor.js';
import { PRESETS, presetToTf, clipTf } from './presets.js';

/** @typedef {import('./camera.js').Camera} Camera */
/** @typedef {import('./connection.js').FrameMeta} FrameMeta */
/** @typedef {[number, number, number]} Vec3 */

const $ = (/** @type {string} */ id) => /** @type {any} */ (document.getElementById(id));
const params = new URLSearchParams(location.search);

// Access token: taken once from ?token= and then removed from the address bar and history;
// kept for this tab only. It travels as a WebSocket subprotocol and a bearer header, never in
// a URL the server logs.
const TOKEN_KEY = 'voxlight.token';
if (params.get('token')) {
  sessionStorage.setItem(TOKEN_KEY, params.get('token') || '');
  params.delete('token');
  const query = params.toString();
  history.replaceState(null, '', location.pathname + (query ? `?${query}` : '') + location.hash);
}
const accessToken = () => sessionStorage.getItem(TOKEN_KEY) || '';

/** Longest edge the server accepts (protocol MAX_VIEWPORT_EDGE). */
const MAX_VIEWPORT_EDGE = 4096;
/** Streamed images are capped to about this many pixels (1024²). */
const MAX_VIEWPORT_PIXELS = 1024 * 1024;
const MIN_VIEWPORT_EDGE = 64;
/** Longest display name (protocol MAX_NAME_CHARS). */
const MAX_NAME_CHARS = 64;
/** Frames the server may send before we acknowledge them: one on screen, one decoding. */
const MAX_IN_FLIGHT = 2;
/** Frames kept in `voxlight.shownLog`. */
const SHOWN_LOG = 200;
/**
 * How long an own edit counts as on its way to the server. Its echo normally comes back within
 * a round trip (a technique switch waits for a rebuild); this only bounds how long a lost echo
 * can hide others' edits of the same kind.
 */
const OWN_ECHO_TIMEOUT_MS = 10000;
/** Message types that edit the shared session; the server echoes each one as `edited`. */
const EDIT_TYPES = new Set(['camera', 'tf', 'lights', 'technique', 'params', 'quality']);

// Display name: chosen once per browser, editable in the panel, shown to the other viewers.
const NAME_KEY = 'voxlight.name';
/** @param {string} name */
const cleanName = (name) => String(name || '').replace(/[\u0000-\u001f\u007f]/g, '').trim().slice(0, MAX_NAME_CHARS);
function loadName() {
  let name = '';
  try {
    name = cleanName(localStorage.getItem(NAME_KEY) || '');
  } catch {
    /* storage disabled: a name for this page only */
  }
  if (!name) {
    name = `viewer-${1000 + Math.floor(Math.random() * 9000)}`;
    saveName(name);
  }
  return name;
}
/** @param {string} name */
function saveName(name) {
  try {
    localStorage.setItem(NAME_KEY, name);
  } catch {
    /* storage disabled */
  }
}

// ---- state ---------------------------------------------------------------------------------

/** Everything tests (and curious people in the console) may look at. */
const vx = {
  connected: false,
  session: /** @type {string|null} */ (null),
  welcome: /** @type {any} */ (null),
  /** This connection as the other viewers see it ({id, name}). */
  viewer: /** @type {{id: number, name: string}|null} */ (null),
  /** Everyone viewing the session, this viewer included. */
  viewers: /** @type {{id: number, name: string}[]} */ ([]),
  /** Did the last welcome join an existing session? */
  joined: false,
  /** Our display name (sent in hello). */
  name: loadName(),
  /** The session state as the server has it: welcome/state/dataset_loaded plus every edit. */
  state: /** @type {any} */ (null),
  /** Newest scene version announced by `edited` or `state`. */
  version: 0,
  /** Who last changed the session, when it was someone else: {id, name, kind, at}. */
  lastEditBy: /** @type {any} */ (null),
  /** Recent `edited` messages: {by, version, kind, own, applied}. */
  editLog: /** @type {any[]} */ ([]),
  /** Newest frame seq acknowledged. */
  acked: -1,
  /** The link that opens this session (no token in it). */
  shareLink: () => shareLink(),
  dataset: /** @type {any} */ (null),
  techniques: /** @type {{name: string, description: string}[]} */ ([]),
  framesReceived: 0,
  framesShown: 0,
  framesDropped: 0,
  lastMeta: /** @type {FrameMeta|null} */ (null),
  lastShownMeta: /** @type {FrameMeta|null} */ (null),
  /** The last SHOWN_LOG frames shown, for tests: {seq, version, preview, scale, width, height,
   * lossless, converged, drawn: the canvas rectangle the picture was scaled to}. */
  shownLog: /** @type {any[]} */ ([]),
  lastStats: /** @type {any} */ (null),
  lastLatencyMs: /** @type {number|null} */ (null),
  sent: /** @type {Record<string, number>} */ ({}),
  lastSent: /** @type {Record<string, any>} */ ({}),
  errors: /** @type {{code: string, message: string}[]} */ ([]),
  camera: /** @type {Camera} */ (Cam.cloneCamera(Cam.DEFAULT_CAMERA)),
  viewport: { width: 512, height: 512 },
  /** The TF editor's points (what this page shows). */
  tfPoints: () => tfEditor.points,
  /** Small grayscale thumbnail of the displayed picture, for tests: {w, h, data: number[]}. */
  sample: (/** @type {number} */ n) => sampleCanvas(n || 32),
  connection: /** @type {Connection|null} */ (null),
};
// @ts-ignore
window.voxlight = vx;

/** Local copy of the editable session state (what we show and what we last sent). */
const local = {
  dataset: params.get('dataset') || '',
  technique: params.get('technique') || '',
  params: { density_scale: 60, g: 0, exposure: 1 },
  /** @type {any[]} */
  lights: [],
  jpeg_quality: 80,
  iterations: 64,
  /** Technique options as set in the session, one group per technique (absent: default). */
  techniqueOptions: /** @type {Record<string, Record<string, any>>} */ ({}),
  /** The home camera for double-click reset. */
  home: Cam.cloneCamera(Cam.DEFAULT_CAMERA),
};

// ---- elements ------------------------------------------------------------------------------

const canvas = /** @type {HTMLCanvasElement} */ ($('viewer'));
const ctx = /** @type {CanvasRenderingContext2D} */ (canvas.getContext('2d', { alpha: false }));
const tfEditor = new TfEditor($('tf'), { colorInput: $('tf-color'), readout: $('tf-readout') });

// ---- connection ----------------------------------------------------------------------------

/**
 * The session the next hello joins: the share link's at first, then the one we were welcomed
 * into (so a dropped connection resumes it); null starts a new session.
 */
let joinSession = params.get('session') || null;
/** The last hello named a session that no longer exists: the next welcome is a fresh one. */
let sessionLost = false;
/** Why the server refused the last hello (shown while reconnecting); '' once welcomed. */
let helloError = '';
/** Viewer ids this page has had (its earlier connections), so their leaving is not announced. */
const ownIds = new Set();

/**
 * Behind a router that spreads sessions over several server processes, the route prefix of
 * the one holding our session (from `welcome`); viewers, the share link and reconnects use it.
 * An explicit ?ws= URL turns the routing off.
 */
const explicitWs = params.get('ws');
/** The server process told us it drains: at its `bye` we reopen the view at the root. */
let serverDraining = false;

const conn = new Connection(explicitWs || wsUrlFor(location), () => {
  /** @type {any} */
  vx.viewport = computeViewport();
  const hello = { type: 'hello', protocol: PROTOCOL_VERSION, viewport: vx.viewport, name: vx.name, max_in_flight: MAX_IN_FLIGHT };
  if (local.dataset) hello.dataset = local.dataset;
  if (local.technique) hello.technique = local.technique;
  if (joinSession) hello.session = joinSession;
  return hello;
}, () => (accessToken() ? ['voxlight', `voxlight.token.${accessToken()}`] : ['voxlight']));
vx.connection = conn;

/** @param {string} type @param {object} body */
function send(type, body = {}) {
  const msg = { type, ...body };
  const ok = conn.send(msg);
  if (ok) {
    vx.sent[type] = (vx.sent[type] || 0) + 1;
    vx.lastSent[type] = msg;
    // A quality message without iterations changes only this viewer: no echo comes.
    if (EDIT_TYPES.has(type) && !(type === 'quality' && msg.iterations == null)) ownEditSent(type);
  }
  return ok;
}

conn.addEventListener('connecting', (/** @type {any} */ e) => {
  setConnDot('wait');
  if (vx.welcome) showOverlay('Connection lost', `reconnecting (attempt ${e.detail.attempt})…`, true);
  else showOverlay('Connecting…', `to ${location.host || 'server'}${e.detail.attempt > 1 ? ` (attempt ${e.detail.attempt})` : ''}`, e.detail.attempt > 1);
});

conn.addEventListener('welcome', (/** @type {any} */ e) => {
  const w = e.detail.msg;
  const hadSession = !!vx.welcome; // this page was in a session before: a reconnect
  const lost = sessionLost;
  sessionLost = false;
  helloError = '';
  vx.welcome = w;
  vx.connected = true;
  vx.session = w.session;
  joinSession = w.session;
  vx.joined = !!w.joined;
  vx.version = 0; // welcome carries no version; a new session counts from 0 again
  vx.viewer = w.viewer && Number.isFinite(w.viewer.id) ? { id: w.viewer.id, name: String(w.viewer.name || '') } : null;
  if (vx.viewer) ownIds.add(vx.viewer.id);
  vx.techniques = Array.isArray(w.techniques) ? w.techniques : [];
  resetFrameTracking();
  resetOwnEdits();
  hideOverlay();
  setConnDot('on');
  // The software flag first: the status bar cuts long adapter names short.
  $('st-adapter').textContent = `${w.software_renderer ? 'software, no GPU: ' : ''}${w.adapter || '?'} · server ${w.server_version || '?'} · session ${String(w.session || '').slice(0, 8)}`;
  fillTechniques(vx.techniques);
  setViewers(w.viewers, false);
  serverDraining = false;
  followRoute(w.route);
  setSessionInUrl(w.session);
  // A fresh session although this page had one: ours expired while we were away. Put back what
  // this page showed (its own and others' edits alike).
  const restore = !w.joined && hadSession && w.dataset && w.dataset.name === local.dataset;
  applyDatasetInfo(w.dataset);
  vx.state = w.state ? structuredClone(w.state) : null;
  if (restore) {
    toast('info', 'reconnected', 'the shared session had ended; started a new one with your view and settings');
    pushAll();
  } else {
    // A joined session's state wins over ours (and over the page URL's).
    applyState(w.state || {});
    if (!w.joined) applyUrlIterations();
    if (w.joined && hadSession) toast('info', 'reconnected', 'back in the shared session');
    else if (w.joined) toast('info', 'joined', `shared session with ${namesOfOthers() || 'nobody else (yet)'}`);
    else if (lost) toast('info', 'new session', 'the shared session has ended; this is a new one');
  }
  // The session's viewport (a joined session may have another); send ours if it differs.
  const svp = w.state && w.state.viewport;
  if (svp && Number.isFinite(svp.width) && Number.isFinite(svp.height)) vx.viewport = { width: svp.width, height: svp.height };
  scheduleViewport(0);
});

/** ?iterations=N in the page URL: a convergence target for a new session (demos, tests). */
function applyUrlIterations() {
  const wanted = Number(params.get('iterations'));
  if (Number.isInteger(wanted) && wanted >= 1 && wanted !== local.iterations) {
    local.iterations = wanted;
    sIters.set(wanted);
    send('quality', { jpeg_quality: local.jpeg_quality, iterations: wanted });
  }
}

conn.addEventListener('message', (/** @type {any} */ e) => {
  const m = e.detail.msg;
  switch (m.type) {
    case 'dataset_loaded': {
      $('dataset').disabled = false;
      applyDatasetInfo(m.dataset);
      applyState(m.state || {});
      if (m.state) vx.state = structuredClone(m.state);
      const name = m.dataset?.name || 'dataset';
      if (isOthers(m.by)) {
        noteOthersEdit(m.by, 'dataset');
        toast('info', 'dataset', `${m.by.name} opened ${name}`);
      } else {
        toast('info', 'dataset', `${name} loaded`);
      }
      break;
    }
    case 'edited':
      onEdited(m);
      break;
    case 'state':
      onStateResync(m);
      break;
    case 'viewers':
      setViewers(m.viewers, true);
      break;
    case 'stats':
      vx.lastStats = m;
      renderStatus();
      break;
    case 'error': {
      const err = { code: String(m.code || 'error'), message: String(m.message || '') };
      vx.errors.push(err);
      if (vx.errors.length > 50) vx.errors.shift();
      if (err.code === 'unknown_dataset' || err.code === 'load_failed') $('dataset').disabled = false;
      if (!conn.ready) helloError = err.message || err.code;
      if (!conn.ready && err.code === 'unknown_session') {
        // Our session expired (grace period over) or the link is stale: start a new one at
        // once; the server closes this socket.
        sessionLost = true;
        joinSession = null;
        conn.reconnectSoon(0);
        toast('info', 'session ended', 'starting a new session');
        break;
      }
      if (!conn.ready && err.code === 'session_full') {
        // Keep trying with backoff: someone may leave.
        toast('error', err.code, `${err.message}; retrying`);
        break;
      }
      if (!conn.ready && (err.code === 'at_capacity' || err.code === 'draining')) {
        // This server process takes no new session. Behind a router, the root finds one that
        // does (at once); otherwise keep trying with backoff.
        if (toDeploymentRoot()) conn.reconnectSoon(0);
        else learnRoute();
        toast('error', err.code, `${err.message}; retrying`);
        break;
      }
      // The failed edit will not be echoed: stop waiting for our own echoes, and show the
      // technique and options the session kept (a refused switch or option changes nothing).
      if (conn.ready) {
        resetOwnEdits();
        if (vx.state) {
          local.techniqueOptions = structuredClone(vx.state.technique_options || {});
          setTechnique(vx.state.technique);
        }
      }
      toast('error', err.code, err.message);
      break;
    }
    case 'loading': {
      // A dataset arriving from a PACS: parts (instances) fetched so far.
      const what = `${m.dataset}: ${m.done} of ${m.total} images received`;
      if (!conn.ready) showOverlay('Loading the dataset…', what, false);
      else $('dataset-info').textContent = `loading ${what}`;
      vx.loading = { dataset: String(m.dataset), done: Number(m.done), total: Number(m.total) };
      break;
    }
    case 'draining':
      serverDraining = true;
      toast('info', 'server restarting', String(m.message || `this session ends in ${m.seconds_left} s`));
      break;
    case 'bye':
      if (serverDraining && toDeploymentRoot()) {
        // The router's root gives us another process; the welcome there restores our view.
        conn.reconnectSoon(0);
        showOverlay('Moving to another server', String(m.reason || ''), false);
      } else {
        showOverlay('Server is shutting down', String(m.reason || ''), false);
      }
      break;
    default:
      break; // newer servers may send more; ignore what we do not know
  }
});

conn.addEventListener('close', (/** @type {any} */ e) => {
  const d = e.detail;
  vx.connected = false;
  setConnDot('off');
  if (d.retryInMs < 0) {
    showOverlay('Disconnected', '', true);
    return;
  }
  if (!d.everConnected && serverRoute) checkServerGone();
  const why = helloError || (d.reason ? `“${d.reason}”` : d.everConnected ? `connection lost (code ${d.code})` : 'server unreachable');
  showOverlay('Connection lost', `${why} — reconnecting in ${(d.retryInMs / 1000).toFixed(1)} s`, true);
  $('badge').className = 'badge badge-wait';
  $('badge').textContent = 'offline';
});

conn.addEventListener('frame', (/** @type {any} */ e) => onFrame(e.detail));

$('overlay-retry').addEventListener('click', () => conn.retryNow());

// ---- shared session --------------------------------------------------------------------------
//
// Every viewer may edit; the server applies edits in arrival order and sends each one to every
// viewer as `edited`, the editor included. We apply others' edits to the UI through the setters
// (which never send), and ignore our own echoes. One subtlety: an `edited` from someone else
// that arrives while an own edit of the same kind is still on its way (sent, echo not yet back,
// or queued for the next animation frame) was applied BEFORE ours, so ours overwrites it on the
// server; applying it here would leave our UI showing a state the session no longer has.

/** Own edits sent and not yet echoed, per message type: {n, at}. */
const ownInFlight = /** @type {Map<string, {n: number, at: number}>} */ (new Map());

/** @param {string} type */
function ownEditSent(type) {
  const e = ownInFlight.get(type) || { n: 0, at: 0 };
  e.n++;
  e.at = performance.now();
  ownInFlight.set(type, e);
}

function resetOwnEdits() {
  ownInFlight.clear();
}

/** Is local input of this kind waiting for the next animation frame to be sent? */
function queuedLocally(/** @type {string} */ type) {
  return type === 'quality' ? qualityDirty.has('iterations') : outbox.has(type);
}

/** Will an own edit of this kind reach the server after one that arrives now? */
function ownEditPending(/** @type {string} */ type) {
  if (queuedLocally(type)) return true;
  const e = ownInFlight.get(type);
  return !!e && e.n > 0 && performance.now() - e.at < OWN_ECHO_TIMEOUT_MS;
}

/** @param {any} by ViewerInfo */
function isOthers(by) {
  return !!by && Number.isFinite(by.id) && (!vx.viewer || by.id !== vx.viewer.id);
}

/** @param {any} m {by, version, edit} */
function onEdited(m) {
  const edit = m.edit;
  if (!edit || typeof edit.type !== 'string') return;
  const version = Number(m.version);
  if (Number.isFinite(version)) vx.version = Math.max(vx.version, version);
  mirrorEdit(edit);
  const own = !isOthers(m.by);
  let applied = false;
  if (own) {
    const e = ownInFlight.get(edit.type);
    if (e && e.n > 0) e.n--;
    if (pendingEdit && pendingEdit.target == null && pendingEdit.kind === edit.type && Number.isFinite(version)) pendingEdit.target = version;
  } else if (!ownEditPending(edit.type)) {
    applied = applyEdit(edit);
    if (applied) noteOthersEdit(m.by, edit.type);
  }
  vx.editLog.push({ by: m.by, version, kind: edit.type, own, applied });
  if (vx.editLog.length > 100) vx.editLog.shift();
}

/**
 * Shows someone else's edit in the UI. Returns whether it was understood.
 * @param {any} edit a client message as the server applied it
 */
function applyEdit(edit) {
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

/** Keeps vx.state equal to the server's state (own edits included). @param {any} edit */
function mirrorEdit(edit) {
  const st = vx.state;
  if (!st) return;
  const { type, ...body } = edit;
  if (type === 'camera') st.camera = body;
  else if (type === 'tf') st.tf = body;
  else if (type === 'lights') st.lights = body.lights;
  else if (type === 'params') st.params = { ...st.params, ...body };
  else if (type === 'technique') {
    st.technique = body.name;
    if (body.options) st.technique_options = overlaid(st.technique_options || {}, body.options);
  }
  else if (type === 'viewport') st.viewport = body;
  else if (type === 'quality' && Number.isFinite(body.iterations)) st.iterations = body.iterations;
}

/** `state`: we fell behind on edits; the whole state replaces what we missed. @param {any} m */
function onStateResync(m) {
  if (!m.state) return;
  if (Number.isFinite(m.version)) vx.version = Math.max(vx.version, m.version);
  vx.state = structuredClone(m.state);
  // The echoes of our edits were among the missed messages: stop waiting for them. Input queued
  // for the next animation frame is newer than this state, so it stays.
  resetOwnEdits();
  applyState(m.state, queuedLocally);
  const svp = m.state.viewport;
  if (svp && Number.isFinite(svp.width) && Number.isFinite(svp.height)) vx.viewport = { width: svp.width, height: svp.height };
  if (typeof m.state.dataset === 'string' && m.state.dataset !== vx.dataset?.name) {
    // We also missed a dataset switch; state carries only its name.
    local.dataset = m.state.dataset;
    $('hud-dataset').textContent = m.state.dataset;
  }
}

/**
 * "last edit: NAME" in the status line and next to the name in the viewer list.
 * @param {any} by ViewerInfo
 * @param {string} kind
 */
function noteOthersEdit(by, kind) {
  vx.lastEditBy = { id: by.id, name: String(by.name || ''), kind, at: Date.now() };
  const el = $('st-edit');
  el.textContent = `last edit: ${vx.lastEditBy.name}`;
  el.title = `${vx.lastEditBy.name} changed the ${kind} at ${new Date().toLocaleTimeString()}`;
  el.classList.remove('flash');
  void el.offsetWidth; // restart the highlight animation
  el.classList.add('flash');
  renderViewers();
}

/**
 * @param {any} list ViewerInfo[]
 * @param {boolean} announce toast who joined and left
 */
function setViewers(list, announce) {
  const next = (Array.isArray(list) ? list : []).filter((v) => v && Number.isFinite(v.id)).map((v) => ({ id: v.id, name: String(v.name || '') }));
  if (announce) {
    const before = new Map(vx.viewers.map((v) => [v.id, v]));
    const after = new Set(next.map((v) => v.id));
    for (const v of next) if (!before.has(v.id) && !ownIds.has(v.id)) toast('info', 'joined', v.name);
    for (const v of vx.viewers) if (!after.has(v.id) && !ownIds.has(v.id)) toast('info', 'left', v.name);
  }
  vx.viewers = next;
  renderViewers();
}

function renderViewers() {
  const ul = $('viewers');
  ul.textContent = '';
  for (const v of vx.viewers) {
    const li = document.createElement('li');
    li.dataset.id = String(v.id);
    const name = document.createElement('span');
    name.className = 'name';
    name.textContent = v.name;
    li.appendChild(name);
    if (vx.viewer && v.id === vx.viewer.id) {
      li.classList.add('you');
      const you = document.createElement('span');
      you.className = 'tag';
      you.textContent = 'you';
      li.appendChild(you);
    } else if (vx.lastEditBy && vx.lastEditBy.id === v.id) {
      const tag = document.createElement('span');
      tag.className = 'tag dim';
      tag.textContent = `edited ${vx.lastEditBy.kind}`;
      li.appendChild(tag);
    }
    ul.appendChild(li);
  }
  const n = vx.viewers.length;
  $('viewer-count').textContent = n ? `${n} viewer${n === 1 ? '' : 's'}` : '';
}

function namesOfOthers() {
  return vx.viewers.filter((v) => !vx.viewer || v.id !== vx.viewer.id).map((v) => v.name).join(', ');
}

/** The route prefix of the process holding our session (`welcome.route`), '' without one. */
let serverRoute = '';

/**
 * Follows `welcome.route`: the page (its URL, share link) and the connection move under the
 * prefix that reaches the process holding our session, so reconnects and joiners land there.
 * @param {unknown} route
 */
function followRoute(route) {
  if (explicitWs || typeof route !== 'string' || !route) return;
  serverRoute = route;
  const { server } = routeFolders(location.pathname, route);
  conn.url = wsUrlFor(location, server);
  const u = new URL(location.href);
  if (u.pathname !== server) history.replaceState(history.state, '', server + u.search + u.hash);
}

/**
 * Points the connection at the deployment's root (any process taking new sessions) and forgets
 * the session, whose process is full or going away. False when there is no router to ask.
 */
function toDeploymentRoot() {
  if (explicitWs || !serverRoute) return false;
  const { root } = routeFolders(location.pathname, serverRoute);
  serverRoute = '';
  conn.url = wsUrlFor(location, root);
  joinSession = null;
  sessionLost = true;
  const u = new URL(location.href);
  u.searchParams.delete('session');
  history.replaceState(history.state, '', root + u.search + u.hash);
  return true;
}

/**
 * Our server process cannot be reached. When the deployment's root answers and the process's
 * own route does not, the process is gone (scaled down, or crashed without `bye`) and our
 * session with it: reopen the view at the root. When neither answers, the network is down and
 * we keep trying the process, whose session may still be there.
 */
async function checkServerGone() {
  const route = serverRoute;
  const { root, server } = routeFolders(location.pathname, route);
  const answers = async (/** @type {string} */ url) => {
    try {
      return (await fetch(url, { cache: 'no-store' })).ok;
    } catch {
      return false;
    }
  };
  const [serverUp, rootUp] = await Promise.all([answers(`${server}healthz`), answers(`${root}healthz`)]);
  if (!serverUp && rootUp && serverRoute === route && !conn.ready && toDeploymentRoot()) {
    conn.retryNow();
    toast('info', 'server gone', 'the server holding this session is gone; reopening the view on another');
  }
}

/**
 * A page opened under a process's prefix (an old share link) that was refused before any
 * welcome: ask that process for its route (`/healthz`), so the next attempt goes to the root.
 */
async function learnRoute() {
  if (explicitWs) return;
  try {
    const res = await fetch('./healthz', { cache: 'no-store' });
    const route = res.ok ? (await res.json()).route : null;
    if (typeof route === 'string' && location.pathname.startsWith(routeFolders(location.pathname, route).server)) {
      serverRoute = route;
      toDeploymentRoot();
    }
  } catch {
    /* no answer: keep retrying here with backoff */
  }
}

/** The page URL for a session: ?session=ID, other parameters kept, never a token. */
function urlForSession(/** @type {string} */ id) {
  const u = new URL(location.href);
  u.searchParams.delete('token');
  u.searchParams.set('session', id);
  return u;
}

/** Puts ?session=ID in the address bar, so reloading (or copying the URL) rejoins. */
function setSessionInUrl(/** @type {string} */ id) {
  if (!id) return;
  const u = urlForSession(id);
  if (u.href !== location.href) history.replaceState(history.state, '', u.pathname + u.search + u.hash);
}

function shareLink() {
  return vx.session ? urlForSession(vx.session).href : '';
}

$('share').addEventListener('click', async () => {
  const link = shareLink();
  if (!link) return;
  const box = $('share-link');
  box.value = link;
  try {
    await navigator.clipboard.writeText(link);
    box.hidden = true;
    toast('info', 'share', 'link copied: whoever opens it views and edits this session with you');
  } catch {
    // No clipboard (insecure origin, permission denied): let people copy it themselves.
    box.hidden = false;
    box.focus();
    box.select();
    toast('info', 'share', 'copy the link shown under the Share button');
  }
});

const nameInput = $('name');
nameInput.value = vx.name;
nameInput.addEventListener('change', () => {
  const name = cleanName(nameInput.value);
  if (!name || name === vx.name) {
    nameInput.value = vx.name;
    return;
  }
  vx.name = name;
  nameInput.value = name;
  saveName(name);
  // The others see it through the `viewers` list; hello carries it on reconnects.
  if (conn.ready) send('name', { name });
});

// ---- frames --------------------------------------------------------------------------------

/** @typedef {{meta: FrameMeta, image: Uint8Array, receivedAt: number, welcomeNo: number}} Frame */

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
/** Frames should be coming but none came for this long: repeat the newest ack. */
const REACK_AFTER_MS = 3000;
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

function resetFrameTracking() {
  welcomeNo++;
  pendingEdit = null;
  maxSceneVersion = -1;
  pendingFrame = null;
  vx.acked = -1;
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
setInterval(ackWatchdog, 1000);

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

function cssSize() {
  const r = canvas.getBoundingClientRect();
  return { w: Math.max(1, r.width), h: Math.max(1, r.height) };
}

/** CSS size × devicePixelRatio, capped to ~1024² pixels and MAX_VIEWPORT_EDGE, at least 64. */
function computeViewport() {
  const { w, h } = cssSize();
  const dpr = window.devicePixelRatio || 1;
  const s = Math.min(dpr, Math.sqrt(MAX_VIEWPORT_PIXELS / (w * h)));
  const clampEdge = (x) => Math.max(MIN_VIEWPORT_EDGE, Math.min(MAX_VIEWPORT_EDGE, Math.round(x)));
  return { width: clampEdge(w * s), height: clampEdge(h * s) };
}

let viewportTimer = 0;
function scheduleViewport(delay = 150) {
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
new ResizeObserver(resizeCanvas).observe(canvas);
vx.viewport = computeViewport();

// ---- per-frame send coalescing ---------------------------------------------------------------

/** Messages waiting for the next animation frame, one per type (latest wins). */
const outbox = /** @type {Map<string, () => object>} */ (new Map());
let outboxRaf = 0;

/** @param {string} type @param {() => object} build */
function queue(type, build) {
  outbox.set(type, build);
  if (!outboxRaf) outboxRaf = requestAnimationFrame(flushOutbox);
}

function flushOutbox() {
  outboxRaf = 0;
  for (const [type, build] of outbox) {
    const body = build();
    if (send(type, body) && (type === 'camera' || type === 'tf') && !pendingEdit) {
      pendingEdit = { at: performance.now(), baseVersion: maxSceneVersion, kind: type, target: null };
    }
  }
  outbox.clear();
}

function queueCamera() {
  queue('camera', () => {
    const m = Cam.toMessage(vx.camera);
    const { type: _t, ...body } = m;
    return body;
  });
}

function queueTf(points) {
  queue('tf', () => ({ points }));
}

// ---- camera interaction --------------------------------------------------------------------

/** Active pointers on the viewer: id → last position. */
const pointers = /** @type {Map<number, {x: number, y: number}>} */ (new Map());
/** @type {null | {mode: 'orbit'|'pan'|'wl'|'touch', startX: number, startY: number, base?: any}} */
let gesture = null;
let pinchPrev = /** @type {{d: number, cx: number, cy: number} | null} */ (null);

function pinchInfo() {
  const [a, b] = [...pointers.values()];
  return { d: Math.hypot(a.x - b.x, a.y - b.y), cx: (a.x + b.x) / 2, cy: (a.y + b.y) / 2 };
}

canvas.addEventListener('contextmenu', (e) => e.preventDefault());

canvas.addEventListener('pointerdown', (e) => {
  canvas.focus({ preventScroll: true });
  try {
    canvas.setPointerCapture(e.pointerId);
  } catch {
    /* ignore */
  }
  pointers.set(e.pointerId, { x: e.clientX, y: e.clientY });
  if (e.pointerType === 'touch') {
    gesture = { mode: 'touch', startX: e.clientX, startY: e.clientY };
    pinchPrev = pointers.size === 2 ? pinchInfo() : null;
  } else if (pointers.size === 1) {
    let mode = /** @type {'orbit'|'pan'|'wl'} */ ('orbit');
    if (e.button === 2 || e.button === 1 || e.shiftKey) mode = 'pan';
    else if (e.ctrlKey || e.metaKey || e.altKey) mode = 'wl';
    gesture = { mode, startX: e.clientX, startY: e.clientY, base: mode === 'wl' ? tfEditor.points : null };
  }
  canvas.classList.add('dragging');
  e.preventDefault();
});

canvas.addEventListener('pointermove', (e) => {
  const prev = pointers.get(e.pointerId);
  if (!prev || !gesture) return;
  const dx = e.clientX - prev.x;
  const dy = e.clientY - prev.y;
  prev.x = e.clientX;
  prev.y = e.clientY;
  const { h } = cssSize();
  const ORBIT = Math.PI / Math.max(200, h); // half a turn per view height
  if (gesture.mode === 'touch') {
    if (pointers.size === 1) {
      vx.camera = Cam.orbit(vx.camera, -dx * ORBIT, dy * ORBIT);
    } else if (pointers.size === 2) {
      const now = pinchInfo();
      if (pinchPrev && now.d > 1 && pinchPrev.d > 1) {
        vx.camera = Cam.zoom(vx.camera, pinchPrev.d / now.d);
        vx.camera = Cam.pan(vx.camera, now.cx - pinchPrev.cx, now.cy - pinchPrev.cy, h);
      }
      pinchPrev = now;
    } else {
      return;
    }
    queueCamera();
  } else if (gesture.mode === 'orbit') {
    vx.camera = Cam.orbit(vx.camera, -dx * ORBIT, dy * ORBIT);
    queueCamera();
  } else if (gesture.mode === 'pan') {
    vx.camera = Cam.pan(vx.camera, dx, dy, h);
    queueCamera();
  } else if (gesture.mode === 'wl') {
    windowLevel(gesture.base, e.clientX - gesture.startX, e.clientY - gesture.startY);
  }
});

function endPointer(/** @type {PointerEvent} */ e) {
  pointers.delete(e.pointerId);
  if (pointers.size === 0) {
    gesture = null;
    pinchPrev = null;
    canvas.classList.remove('dragging');
  } else if (pointers.size === 1 && gesture && gesture.mode === 'touch') {
    pinchPrev = null; // back to one-finger orbit
  } else if (pointers.size === 2) {
    pinchPrev = pinchInfo();
  }
}
canvas.addEventListener('pointerup', endPointer);
canvas.addEventListener('pointercancel', endPointer);

canvas.addEventListener(
  'wheel',
  (e) => {
    e.preventDefault();
    const unit = e.deltaMode === 1 ? 33 : e.deltaMode === 2 ? 400 : 1;
    const delta = Math.max(-400, Math.min(400, e.deltaY * unit));
    vx.camera = Cam.zoom(vx.camera, Math.exp(delta * 0.0015));
    queueCamera();
  },
  { passive: false },
);

canvas.addEventListener('dblclick', (e) => {
  e.preventDefault();
  vx.camera = Cam.cloneCamera(local.home);
  queueCamera();
});

canvas.addEventListener('keydown', (e) => {
  const step = e.shiftKey ? 0.2 : 0.05;
  let handled = true;
  if (e.key === 'ArrowLeft') vx.camera = Cam.orbit(vx.camera, step, 0);
  else if (e.key === 'ArrowRight') vx.camera = Cam.orbit(vx.camera, -step, 0);
  else if (e.key === 'ArrowUp') vx.camera = Cam.orbit(vx.camera, 0, step);
  else if (e.key === 'ArrowDown') vx.camera = Cam.orbit(vx.camera, 0, -step);
  else if (e.key === '+' || e.key === '=') vx.camera = Cam.zoom(vx.camera, 0.9);
  else if (e.key === '-') vx.camera = Cam.zoom(vx.camera, 1 / 0.9);
  else if (e.key === 'r' || e.key === 'Home') vx.camera = Cam.cloneCamera(local.home);
  else handled = false;
  if (handled) {
    e.preventDefault();
    queueCamera();
  }
});

/**
 * Window/level in the 3D view: horizontal drag shifts the whole TF along the value axis (level),
 * vertical drag narrows (up) or widens (down) it around its centre (window).
 * @param {any[]} base points when the drag started
 */
function windowLevel(base, dx, dy) {
  if (!base || base.length === 0) return;
  const { w } = cssSize();
  const shift = dx / Math.max(200, w);
  const widen = Math.exp(dy * 0.004);
  const lo = base[0].value;
  const hi = base[base.length - 1].value;
  const c = (lo + hi) / 2;
  const moved = base.map((p) => ({ ...p, value: c + shift + (p.value - c) * widen }));
  const pts = clipTf(moved);
  tfEditor.setPoints(pts);
  markPreset(null);
  queueTf(tfEditor.points);
}

// ---- TF editor + presets -------------------------------------------------------------------

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
function markPreset(id) {
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

const sDensity = bindSlider('density', densityMap, fmt2, (v) => {
  local.params.density_scale = v;
  queueParams();
});
const sExposure = bindSlider('exposure', exposureMap, fmt2, (v) => {
  local.params.exposure = v;
  queueParams();
});
const sG = bindSlider('g', { toValue: (s) => s / 100, toSlider: (v) => Math.round(v * 100) }, (v) => v.toFixed(2), (v) => {
  local.params.g = v;
  queueParams();
});
function queueParams() {
  queue('params', () => ({ ...local.params }));
}

const key = { az: -34, el: 44, intensity: 2.5, tint: /** @type {Vec3} */ ([1, 0.96, 0.88]) };
const env = { brightness: 0.25, tint: /** @type {Vec3} */ ([1, 1.08, 1.2]) };
const sAz = bindSlider('light-az', identity, (v) => `${Math.round(v)}°`, (v) => {
  key.az = v;
  queueLights();
});
const sEl = bindSlider('light-el', identity, (v) => `${Math.round(v)}°`, (v) => {
  key.el = v;
  queueLights();
});
const sInt = bindSlider('light-int', intensityMap, fmt2, (v) => {
  key.intensity = v;
  queueLights();
});
const sEnv = bindSlider('light-env', envMap, fmt2, (v) => {
  env.brightness = v;
  queueLights();
});

const sJpeg = bindSlider('jpeg-q', identity, (v) => String(Math.round(v)), (v) => {
  local.jpeg_quality = Math.round(v);
  queueQuality('jpeg_quality');
});
const sIters = bindSlider('iters', itersMap, (v) => String(Math.round(v)), (v) => {
  local.iterations = Math.max(1, Math.round(v));
  queueQuality('iterations');
});

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

async function loadDatasetList() {
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

function fillTechniques(list) {
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
function applyDatasetInfo(info) {
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
 * Applies a whole SessionState (welcome, dataset_loaded, state).
 * @param {any} s SessionState
 * @param {(kind: string) => boolean} [keep] kinds to leave as they are (newer local input)
 */
function applyState(s, keep = () => false) {
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
function setTechnique(name) {
  if (typeof name === 'string') {
    local.technique = name;
    $('technique').value = name;
  }
  showTechniqueDesc();
  renderTechniqueOptions();
  return typeof name === 'string';
}

/** `base` with every option `edit` sets taken from `edit` (as the server overlays them). */
function overlaid(/** @type {any} */ base, /** @type {any} */ edit) {
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
    { key: 'bounces', label: 'Bounces', title: 'Scattering events stored per photon path (1: single scattering)', values: [1, 2, 4, 8] },
    { key: 'segments', label: 'Segments', title: 'View-ray segments per pixel (Vn)', values: [4, 8, 16] },
    { key: 'invalidation', label: 'TF-edit test', title: 'How a TF edit finds the view-ray segments to gather again', values: ['dirty_cells', 'spatial3x64', 'any_photon'] },
  ],
  manylight: [
    { key: 'virtual_lights', label: 'Virtual lights', title: 'Virtual spherical lights stored', values: [64, 256, 1000, 2000] },
    { key: 'transmittance', label: 'Transmittance', title: 'From each virtual light: shadow-map lookup (point or interpolated) or a ray marched', values: ['avsm_trilinear', 'avsm_point', 'ray_marched'] },
    { key: 'face_res', label: 'Shadow maps', title: 'Shadow-map texels per cube-face edge', values: [16, 24, 48] },
    { key: 'vsl_radius', label: 'Light radius', title: 'Radius of a virtual spherical light (world units; the volume is 1 across)', values: [0.01, 0.02, 0.05] },
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
function pushAll() {
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

// ---- status line, badge, toasts, overlay ---------------------------------------------------

function renderStatus() {
  const m = vx.lastShownMeta || vx.lastMeta;
  const st = vx.lastStats;
  const now = performance.now();
  while (shownTimes.length && now - shownTimes[0] > 1000) shownTimes.shift();
  $('st-fps').textContent = `${shownTimes.length} fps`;
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
setInterval(renderStatus, 500);

/**
 * @param {'error'|'info'} kind
 * @param {string} code
 * @param {string} text
 */
function toast(kind, code, text) {
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

function showOverlay(title, text, retry) {
  $('overlay').hidden = false;
  $('overlay-title').textContent = title;
  $('overlay-text').textContent = text;
  $('overlay-retry').hidden = !retry;
}
function hideOverlay() {
  $('overlay').hidden = true;
}
function setConnDot(state) {
  const d = $('conn-dot');
  d.className = 'dot' + (state === 'on' ? ' on' : state === 'wait' ? ' wait' : '');
  d.title = state === 'on' ? 'connected' : state === 'wait' ? 'connecting' : 'disconnected';
}

function fmtNum(x) {
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

function fmtBytes(n) {
  if (n >= 1 << 30) return (n / (1 << 30)).toFixed(2) + ' GiB';
  if (n >= 1 << 20) return (n / (1 << 20)).toFixed(1) + ' MiB';
  return (n / 1024).toFixed(0) + ' KiB';
}

// ---- start ---------------------------------------------------------------------------------

sDensity.set(local.params.density_scale);
sExposure.set(local.params.exposure);
sG.set(local.params.g);
lightsToControls([
  { kind: 'directional', direction: [0.35, 0.75, -0.55], irradiance: [3.2, 3.1, 2.9] },
  { kind: 'environment', radiance: [0.1, 0.11, 0.13] },
]);
sJpeg.set(local.jpeg_quality);
sIters.set(local.iterations);
showOverlay('Connecting…', `to ${location.host || 'server'}`, false);
void loadDatasetList();
conn.connect();
