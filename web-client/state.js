// The page's shared state: what the other modules read and change, in two explicit objects,
// and the page URL's parameters. No module keeps a copy of either; each imports them from here.
//
// - `vx`: everything tests (and curious people in the console) may look at; app.js publishes
//   it as `window.voxlight`. Its few functions are filled in by the module that owns them.
// - `local`: this page's copy of the editable session state (what it shows and last sent).
// - `params`: the page URL's query (?session, ?dataset, ?technique, ?iterations, ?ws, ?token);
//   session.js removes the token from it and from the address bar before anything else runs.

import * as Cam from './camera.js';

/** @typedef {import('./camera.js').Camera} Camera */
/** @typedef {import('./connection.js').Connection} Connection */
/** @typedef {import('./connection.js').FrameMeta} FrameMeta */

export const $ = (/** @type {string} */ id) => /** @type {any} */ (document.getElementById(id));
export const params = new URLSearchParams(location.search);

/** Everything tests (and curious people in the console) may look at: `window.voxlight`. */
export const vx = {
  connected: false,
  session: /** @type {string|null} */ (null),
  welcome: /** @type {any} */ (null),
  /** This connection as the other viewers see it ({id, name}). */
  viewer: /** @type {{id: number, name: string}|null} */ (null),
  /** Everyone viewing the session, this viewer included. */
  viewers: /** @type {{id: number, name: string}[]} */ ([]),
  /** Did the last welcome join an existing session? */
  joined: false,
  /** Our display name (sent in hello; session.js loads it from localStorage). */
  name: '',
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
  /** The link that opens this session (no token in it); set by session.js. */
  shareLink: () => '',
  dataset: /** @type {any} */ (null),
  techniques: /** @type {{name: string, description: string}[]} */ ([]),
  /** A dataset arriving from a PACS: {dataset, done, total} from the last `loading` message. */
  loading: /** @type {{dataset: string, done: number, total: number}|null} */ (null),
  framesReceived: 0,
  framesShown: 0,
  framesDropped: 0,
  lastMeta: /** @type {FrameMeta|null} */ (null),
  lastShownMeta: /** @type {FrameMeta|null} */ (null),
  /** The last SHOWN_LOG (frames.js) frames shown, for tests: {seq, version, preview, scale,
   * width, height, lossless, converged, drawn: the canvas rectangle the picture was scaled to}. */
  shownLog: /** @type {any[]} */ ([]),
  lastStats: /** @type {any} */ (null),
  lastLatencyMs: /** @type {number|null} */ (null),
  sent: /** @type {Record<string, number>} */ ({}),
  lastSent: /** @type {Record<string, any>} */ ({}),
  errors: /** @type {{code: string, message: string}[]} */ ([]),
  camera: /** @type {Camera} */ (Cam.cloneCamera(Cam.DEFAULT_CAMERA)),
  viewport: { width: 512, height: 512 },
  /** The TF editor's points (what this page shows); set by controls.js. */
  tfPoints: () => /** @type {any[]} */ ([]),
  /** Small grayscale thumbnail of the displayed picture, for tests: {w, h, data: number[]};
   * set by frames.js. */
  sample: (/** @type {number} */ _n) => /** @type {{w: number, h: number, data: number[]}|null} */ (null),
  connection: /** @type {Connection|null} */ (null),
};

/** Local copy of the editable session state (what we show and what we last sent). */
export const local = {
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
