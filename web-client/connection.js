// WebSocket connection to the voxlight server: JSON text messages tagged by "type", binary
// frames (4-byte little-endian length N, N bytes UTF-8 JSON FrameMeta, then the image), and
// reconnection with exponential backoff. See docs/protocol.md.
//
// Which session a reconnect resumes is the caller's business: `makeHello` runs for every
// (re)connection, so it can name the session to rejoin (`hello.session`).

export const PROTOCOL_VERSION = 1;
/** Largest text message the server accepts (protocol crate MAX_MESSAGE_BYTES). */
export const MAX_MESSAGE_BYTES = 64 * 1024;

/**
 * @typedef {object} FrameMeta
 * @property {number} seq
 * @property {'jpeg'|'png'} format
 * @property {number} width
 * @property {number} height
 * @property {string} technique
 * @property {number} iteration
 * @property {number} target_iterations
 * @property {boolean} converged
 * @property {boolean} lossless
 * @property {number} [quality]
 * @property {number} scene_version
 * @property {number} render_ms
 * @property {number} encode_ms
 * @property {boolean} [preview] an interactive preview while edits stream in (absent: false)
 * @property {number} [resolution_scale] image size over the viewport's, per axis (absent: 1)
 */

/**
 * Splits a binary frame message. Returns null when it is malformed.
 * @param {ArrayBuffer} buf
 * @returns {{meta: FrameMeta, image: Uint8Array} | null}
 */
export function splitFrame(buf) {
  if (!(buf instanceof ArrayBuffer) || buf.byteLength < 4) return null;
  const n = new DataView(buf).getUint32(0, true);
  if (4 + n > buf.byteLength) return null;
  try {
    const meta = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 4, n)));
    if (!meta || typeof meta !== 'object') return null;
    return { meta, image: new Uint8Array(buf, 4 + n) };
  } catch {
    return null;
  }
}

/**
 * The WebSocket URL for a page URL: same host, ws: or wss: matching http: or https:, `ws` in
 * the page's folder (so a page under a router's prefix, `/p/3/`, talks to `/p/3/ws`).
 * @param {{protocol: string, host: string, pathname?: string}} loc
 * @param {string} [folder] the folder to use instead of the page's
 */
export function wsUrlFor(loc = window.location, folder) {
  const proto = loc.protocol === 'https:' ? 'wss:' : 'ws:';
  return `${proto}//${loc.host}${folder ?? pageFolder(loc.pathname || '/')}ws`;
}

/** The folder of a page path, with its trailing slash: `/p/3/index.html` → `/p/3/`. */
export function pageFolder(pathname) {
  const folder = pathname.replace(/[^/]*$/, '');
  return folder.startsWith('/') ? folder : `/${folder}`;
}

/**
 * Where a deployment of several server processes is reached, given the page's path and the
 * route prefix the server named in `welcome` (`/p/3/`, stripped by the router): `root` takes
 * new sessions on any process, `server` reaches the one that holds this session. Without a
 * route (one process, no router) both are the page's folder.
 * @param {string} pathname
 * @param {string | null | undefined} route
 * @returns {{root: string, server: string}}
 */
export function routeFolders(pathname, route) {
  const folder = pageFolder(pathname);
  if (!route || !route.startsWith('/') || !route.endsWith('/')) return { root: folder, server: folder };
  const root = folder.endsWith(route) ? `${folder.slice(0, folder.length - route.length)}/` : folder;
  return { root, server: `${root}${route.slice(1)}` };
}

/**
 * Events (CustomEvent detail in brackets):
 *  - `connecting` {attempt}
 *  - `welcome` {msg}           the server's welcome; backoff is reset
 *  - `message` {msg}           every other JSON message (dataset_loaded, stats, error, bye, ...)
 *  - `frame` {meta, image, receivedAt}
 *  - `close` {code, reason, retryInMs, everConnected}
 */
export class Connection extends EventTarget {
  /**
   * @param {string} url WebSocket URL
   * @param {() => object} makeHello builds the hello message for each (re)connection
   * @param {() => string[]} [makeProtocols] WebSocket subprotocols (the access token travels as one)
   */
  constructor(url, makeHello, makeProtocols) {
    super();
    this.url = url;
    this.makeHello = makeHello;
    this.makeProtocols = makeProtocols || (() => ['voxlight']);
    /** @type {WebSocket | null} */
    this.ws = null;
    this.attempt = 0;
    this.ready = false; // welcome received on the current socket
    this.closedByUser = false;
    this._timer = 0;
    this.bytesIn = 0;
    this.lastByeReason = '';
    /** Delay for the next automatic reconnect instead of the backoff (once); null: backoff. */
    this._nextDelayMs = /** @type {number|null} */ (null);
  }

  connect() {
    this.closedByUser = false;
    clearTimeout(this._timer);
    this._timer = 0;
    this.ready = false;
    this.attempt++;
    this._emit('connecting', { attempt: this.attempt });
    let ws;
    try {
      ws = new WebSocket(this.url, this.makeProtocols());
    } catch (err) {
      this._scheduleReconnect(0, String(err));
      return;
    }
    ws.binaryType = 'arraybuffer';
    this.ws = ws;
    let opened = false;
    ws.onopen = () => {
      opened = true;
      this._sendRaw(ws, this.makeHello());
    };
    ws.onmessage = (ev) => {
      if (ws !== this.ws) return;
      if (typeof ev.data === 'string') {
        this.bytesIn += ev.data.length;
        let msg;
        try {
          msg = JSON.parse(ev.data);
        } catch {
          console.warn('voxlight: ignoring non-JSON text message');
          return;
        }
        if (!msg || typeof msg.type !== 'string') return;
        if (msg.type === 'welcome') {
          this.ready = true;
          this.attempt = 0;
          this._emit('welcome', { msg });
        } else {
          if (msg.type === 'bye') this.lastByeReason = String(msg.reason || '');
          this._emit('message', { msg });
        }
      } else if (ev.data instanceof ArrayBuffer) {
        this.bytesIn += ev.data.byteLength;
        const f = splitFrame(ev.data);
        if (!f) {
          console.warn('voxlight: ignoring malformed binary frame');
          return;
        }
        this._emit('frame', { meta: f.meta, image: f.image, receivedAt: performance.now() });
      }
    };
    ws.onerror = () => {
      /* a close event follows; handled there */
    };
    ws.onclose = (ev) => {
      if (ws !== this.ws) return;
      this.ws = null;
      this.ready = false;
      if (this.closedByUser) {
        this._emit('close', { code: ev.code, reason: ev.reason, retryInMs: -1, everConnected: opened });
        return;
      }
      this._scheduleReconnect(ev.code, ev.reason || this.lastByeReason, opened);
    };
  }

  _scheduleReconnect(code, reason, everConnected = false) {
    // 0.5 s, 1 s, 2 s, 4 s, 8 s, then every 10 s, with ±20 % jitter.
    const base = Math.min(10000, 500 * Math.pow(2, Math.max(0, this.attempt - 1)));
    let retryInMs = Math.round(base * (0.8 + 0.4 * Math.random()));
    if (this._nextDelayMs != null) {
      retryInMs = this._nextDelayMs;
      this._nextDelayMs = null;
    }
    this._emit('close', { code, reason, retryInMs, everConnected });
    clearTimeout(this._timer);
    this._timer = setTimeout(() => this.connect(), retryInMs);
  }

  /** Reconnect now (e.g. a "retry" button). */
  retryNow() {
    if (this.ws && this.ws.readyState <= 1) return;
    this.attempt = 0;
    this.connect();
  }

  /**
   * Makes the next automatic reconnect happen after `ms` instead of the backoff delay, e.g.
   * when the server refused the hello for a reason the next hello fixes (`unknown_session`).
   * @param {number} [ms]
   */
  reconnectSoon(ms = 0) {
    this._nextDelayMs = Math.max(0, ms);
  }

  close() {
    this.closedByUser = true;
    clearTimeout(this._timer);
    if (this.ws) this.ws.close(1000, 'client closed');
  }

  /**
   * Sends a JSON message once the session is ready. Returns false when it could not be sent.
   * @param {object} msg
   */
  send(msg) {
    if (!this.ws || !this.ready || this.ws.readyState !== WebSocket.OPEN) return false;
    return this._sendRaw(this.ws, msg);
  }

  /** @param {WebSocket} ws */
  _sendRaw(ws, msg) {
    const text = JSON.stringify(msg);
    if (text.length > MAX_MESSAGE_BYTES) {
      console.warn(`voxlight: not sending ${msg && msg.type} (${text.length} bytes > ${MAX_MESSAGE_BYTES})`);
      return false;
    }
    try {
      ws.send(text);
      return true;
    } catch (err) {
      console.warn('voxlight: send failed', err);
      return false;
    }
  }

  get bufferedAmount() {
    return this.ws ? this.ws.bufferedAmount : 0;
  }

  _emit(type, detail) {
    this.dispatchEvent(new CustomEvent(type, { detail }));
  }
}
