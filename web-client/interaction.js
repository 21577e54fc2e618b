// Pointer, wheel and keyboard input on the view, turned into `camera` edits (and window/level
// into `tf` edits). The camera moves locally at once; the message goes out with the next
// animation frame (session.js's outbox), so a fast drag sends at most one per frame.
//
// - mouse: drag orbits, right/middle/shift-drag pans, ctrl/cmd/alt-drag does window/level
// - touch: one finger orbits, two pinch-zoom and pan
// - wheel zooms; double-click, `r` or Home go back to the home camera; arrows orbit, +/- zoom

import * as Cam from './camera.js';
import { vx, local } from './state.js';
import { canvas, cssSize } from './frames.js';
import { queue } from './session.js';
import { tfEditor, markPreset, queueTf } from './controls.js';
import { clipTf } from './presets.js';

/** Active pointers on the viewer: id → last position. */
const pointers = /** @type {Map<number, {x: number, y: number}>} */ (new Map());
/** @type {null | {mode: 'orbit'|'pan'|'wl'|'touch', startX: number, startY: number, base?: any}} */
let gesture = null;
let pinchPrev = /** @type {{d: number, cx: number, cy: number} | null} */ (null);

function queueCamera() {
  queue('camera', () => {
    const m = Cam.toMessage(vx.camera);
    const { type: _t, ...body } = m;
    return body;
  });
}

function pinchInfo() {
  const [a, b] = [...pointers.values()];
  return { d: Math.hypot(a.x - b.x, a.y - b.y), cx: (a.x + b.x) / 2, cy: (a.y + b.y) / 2 };
}

export function initInteraction() {
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
}

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

/**
 * Window/level in the 3D view: horizontal drag shifts the whole TF along the value axis (level),
 * vertical drag narrows (up) or widens (down) it around its centre (window).
 * @param {any[]} base points when the drag started
 * @param {number} dx
 * @param {number} dy
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
