// voxlight browser client: shows the server's progressively refined frames and sends camera,
// transfer-function, light, technique and parameter edits. Plain ES modules, no dependencies,
// 2D canvas only (works with GPU and WebGL disabled). Protocol: docs/protocol.md.
//
// Sessions are shared: the page URL carries `?session=ID` (the share link), every viewer may
// edit (last writer wins, the server tells everyone who edited with `edited`), and a dropped
// connection rejoins the same session. This file only wires the modules together:
//
// - state.js ......... the shared state (`window.voxlight`, the local copy, the URL's params)
// - session.js ....... connection, welcome, server messages, others' edits, share link, routes
// - frames.js ........ binary frames: decode, draw, acknowledge; canvas size and viewport
// - controls.js ...... the panel: dataset, technique and options, sliders, lights, TF editor
// - interaction.js ... pointer, wheel and keys on the view → camera (and window/level) edits
// - status.js ........ status bar, badge, toasts, overlay, connection dot
// - connection.js, camera.js, tf-editor.js, presets.js, color.js: the pieces they build on

import { vx } from './state.js';
import { conn, initSession } from './session.js';
import { initFrames } from './frames.js';
import { initInteraction } from './interaction.js';
import { initControls, loadDatasetList } from './controls.js';
import { initStatus, showOverlay } from './status.js';

initSession(); // first: it takes the access token out of the address bar
initFrames();
initInteraction();
initControls();
initStatus();
// @ts-ignore
window.voxlight = vx;

showOverlay('Connecting…', `to ${location.host || 'server'}`, false);
void loadDatasetList();
conn.connect();
