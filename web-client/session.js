// The session: the connection and its hello, what the welcome and the other server messages
// do, the shared-session edits of the other viewers, the viewer list and names, the share
// link, and following the route of the server process that holds the session.
//
// - every (re)connection's hello names the session to join: the share link's at first, then
//   the one we were welcomed into, so a dropped connection resumes it (none: a new session)
// - a session that ended while we were away: the welcome starts a new one and pushAll() puts
//   back what this page showed
// - send() counts what went out (`voxlight.sent`); queue() sends input once per animation
//   frame, the latest per message type
// - own edits come back as `edited` (ignored); others' are shown unless an own edit of the
//   same kind is still on its way (see "shared session" below)
// - behind a router (`welcome.route`), the page, its share link and reconnects move under the
//   prefix of the process holding the session; when that process drains or is gone, the view
//   reopens at the deployment's root

import { Connection, PROTOCOL_VERSION, routeFolders, wsUrlFor } from './connection.js';
import { $, vx, local, params } from './state.js';
import { MAX_IN_FLIGHT, computeViewport, scheduleViewport, resetFrameTracking, editSent, editEchoed } from './frames.js';
import { applyDatasetInfo, applyEdit, applyState, applyUrlIterations, fillTechniques, iterationsQueued, overlaid, pushAll, setTechnique } from './controls.js';
import { toast, showOverlay, hideOverlay, setConnDot, showAdapter, showLoading, showOffline, renderStatus } from './status.js';

// Access token: taken once from ?token= and then removed from the address bar and history
// (initSession); kept for this tab only. It travels as a WebSocket subprotocol and a bearer
// header, never in a URL the server logs.
export const TOKEN_KEY = 'voxlight.token';
export const accessToken = () => sessionStorage.getItem(TOKEN_KEY) || '';

/** Longest display name (protocol MAX_NAME_CHARS). */
const MAX_NAME_CHARS = 64;
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
 * The WebSocket URL from ?ws=, used as given: it turns the routing off (see followRoute: behind
 * a router, the page and the connection follow the route prefix of the process holding our
 * session).
 */
const explicitWs = params.get('ws');
/** The server process told us it drains: at its `bye` we reopen the view at the root. */
let serverDraining = false;

export const conn = new Connection(explicitWs || wsUrlFor(location), () => {
  vx.viewport = computeViewport();
  /** @type {any} */
  const hello = { type: 'hello', protocol: PROTOCOL_VERSION, viewport: vx.viewport, name: vx.name, max_in_flight: MAX_IN_FLIGHT };
  if (local.dataset) hello.dataset = local.dataset;
  if (local.technique) hello.technique = local.technique;
  if (joinSession) hello.session = joinSession;
  return hello;
}, () => (accessToken() ? ['voxlight', `voxlight.token.${accessToken()}`] : ['voxlight']));

/** @param {string} type @param {object} body */
export function send(type, body = {}) {
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

/** Call first: the token leaves the address bar before anything reads or rewrites the URL. */
export function initSession() {
  if (params.get('token')) {
    sessionStorage.setItem(TOKEN_KEY, params.get('token') || '');
    params.delete('token');
    const query = params.toString();
    history.replaceState(null, '', location.pathname + (query ? `?${query}` : '') + location.hash);
  }
  vx.name = loadName();
  vx.connection = conn;
  vx.shareLink = () => shareLink();
  conn.addEventListener('connecting', onConnecting);
  conn.addEventListener('welcome', onWelcome);
  conn.addEventListener('message', onMessage);
  conn.addEventListener('close', onClose);
  $('overlay-retry').addEventListener('click', () => conn.retryNow());
  bindShare();
  bindName();
}

function onConnecting(/** @type {any} */ e) {
  setConnDot('wait');
  if (vx.welcome) showOverlay('Connection lost', `reconnecting (attempt ${e.detail.attempt})…`, true);
  else showOverlay('Connecting…', `to ${location.host || 'server'}${e.detail.attempt > 1 ? ` (attempt ${e.detail.attempt})` : ''}`, e.detail.attempt > 1);
}

function onWelcome(/** @type {any} */ e) {
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
  showAdapter(w);
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
}

function onMessage(/** @type {any} */ e) {
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
    case 'loading':
      showLoading(m, conn.ready);
      break;
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
}

function onClose(/** @type {any} */ e) {
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
  showOffline();
}

// ---- messages out, one per type and animation frame ----------------------------------------

/** Messages waiting for the next animation frame, one per type (latest wins). */
const outbox = /** @type {Map<string, () => object>} */ (new Map());
let outboxRaf = 0;

/** @param {string} type @param {() => object} build */
export function queue(type, build) {
  outbox.set(type, build);
  if (!outboxRaf) outboxRaf = requestAnimationFrame(flushOutbox);
}

function flushOutbox() {
  outboxRaf = 0;
  for (const [type, build] of outbox) {
    const body = build();
    // Camera and TF edits are timed to the first frame showing them (edit→frame latency).
    if (send(type, body) && (type === 'camera' || type === 'tf')) editSent(type);
  }
  outbox.clear();
}

// ---- shared session --------------------------------------------------------------------------
//
// Every viewer may edit; the server applies edits in arrival order and sends each one to every
// viewer as `edited`, the editor included. We apply others' edits to the UI through controls.js's
// setters (which never send), and ignore our own echoes. One subtlety: an `edited` from someone
// else that arrives while an own edit of the same kind is still on its way (sent, echo not yet
// back, or queued for the next animation frame) was applied BEFORE ours, so ours overwrites it
// on the server; applying it here would leave our UI showing a state the session no longer has.

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
  return type === 'quality' ? iterationsQueued() : outbox.has(type);
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
    editEchoed(edit.type, version);
  } else if (!ownEditPending(edit.type)) {
    applied = applyEdit(edit);
    if (applied) noteOthersEdit(m.by, edit.type);
  }
  vx.editLog.push({ by: m.by, version, kind: edit.type, own, applied });
  if (vx.editLog.length > 100) vx.editLog.shift();
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

function bindShare() {
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
}

function bindName() {
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
}
