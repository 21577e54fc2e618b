// Transfer-function editor on a 2D canvas: the dataset's histogram (log-scaled bars) under an
// opacity curve (x = data value, y = opacity) filled with the colour ramp.
//
//   click empty space ........ add a point (and drag it)
//   drag a point ............. move it (value between its neighbours, opacity 0..1)
//   right-click / double-click / Delete ... remove the point
//   arrow keys ............... nudge the selected point (Shift: ×10)
//   colour input ............. the selected point's albedo (sRGB in the UI, linear on the wire)

import { linearToCss, linearToHex, hexToLinear } from './color.js';
import { evalTf } from './presets.js';

/** @typedef {{value: number, color: [number, number, number], opacity: number}} TfPoint */
/** @typedef {{histogram?: number[], value_min?: number, value_max?: number, units?: string}} DatasetRange */

export const MAX_TF_POINTS = 256;
const HIT_RADIUS = 9; // CSS px
const MARGIN = { left: 30, right: 10, top: 8, bottom: 20 };

export class TfEditor extends EventTarget {
  /**
   * @param {HTMLCanvasElement} canvas
   * @param {{colorInput?: HTMLInputElement, readout?: HTMLElement}} [opts]
   */
  constructor(canvas, opts = {}) {
    super();
    this.canvas = canvas;
    this.ctx = /** @type {CanvasRenderingContext2D} */ (canvas.getContext('2d'));
    this.colorInput = opts.colorInput || null;
    this.readout = opts.readout || null;
    /** @type {TfPoint[]} */
    this.pts = [];
    /** @type {number} index of the selected point or -1 */
    this.selected = -1;
    /** @type {number[]} */
    this.histogram = [];
    this.valueMin = 0;
    this.valueMax = 1;
    this.units = '';
    /** Square-root opacity axis: low opacities (soft tissue) get room to be edited. */
    this.sqrtY = true;
    /** @type {{x: number, y: number} | null} */
    this.hover = null;
    /** @type {{pointerId: number, index: number} | null} */
    this.drag = null;
    this.cssW = 300;
    this.cssH = 160;
    this._raf = 0;

    canvas.tabIndex = 0;
    canvas.addEventListener('pointerdown', (e) => this._onDown(e));
    canvas.addEventListener('pointermove', (e) => this._onMove(e));
    canvas.addEventListener('pointerup', (e) => this._onUp(e));
    canvas.addEventListener('pointercancel', (e) => this._onUp(e));
    canvas.addEventListener('pointerleave', () => {
      this.hover = null;
      this._updateReadout();
      this.redraw();
    });
    canvas.addEventListener('contextmenu', (e) => {
      e.preventDefault();
      const i = this._hit(...this._pos(e));
      if (i >= 0) this._remove(i);
    });
    canvas.addEventListener('dblclick', (e) => {
      const i = this._hit(...this._pos(e));
      if (i >= 0) this._remove(i);
    });
    canvas.addEventListener('keydown', (e) => this._onKey(e));
    if (this.colorInput) {
      this.colorInput.addEventListener('input', () => {
        if (this.selected < 0 || !this.colorInput) return;
        this.pts[this.selected].color = hexToLinear(this.colorInput.value);
        this._changed();
      });
    }
    new ResizeObserver(() => this._resize()).observe(canvas);
    this._resize();
  }

  /** @returns {TfPoint[]} a copy of the current points, sorted by value */
  get points() {
    return this.pts.map((p) => ({ value: p.value, color: [...p.color], opacity: p.opacity }));
  }

  /**
   * Replaces the points (e.g. from the server's state or a preset) without emitting `change`.
   * @param {TfPoint[]} points
   */
  setPoints(points) {
    this.pts = (points || [])
      .filter((p) => p && Number.isFinite(p.value) && Number.isFinite(p.opacity) && Array.isArray(p.color))
      .map((p) => ({ value: clamp01(p.value), color: /** @type {[number,number,number]} */ ([0, 1, 2].map((k) => clamp01(p.color[k]))), opacity: clamp01(p.opacity) }))
      .sort((a, b) => a.value - b.value)
      .slice(0, MAX_TF_POINTS);
    this.selected = Math.min(this.selected, this.pts.length - 1);
    if (this.drag) this.drag = null;
    this._syncColor();
    this._updateReadout();
    this.redraw();
  }

  /** @param {DatasetRange} d */
  setDataset(d) {
    this.histogram = Array.isArray(d.histogram) ? d.histogram.slice() : [];
    this.valueMin = Number.isFinite(d.value_min) ? /** @type {number} */ (d.value_min) : 0;
    this.valueMax = Number.isFinite(d.value_max) ? /** @type {number} */ (d.value_max) : 1;
    this.units = d.units || '';
    this.redraw();
  }

  setSqrtY(on) {
    this.sqrtY = !!on;
    this.redraw();
  }

  /** Normalized value → value in the dataset's units. */
  toUnits(v) {
    return this.valueMin + v * (this.valueMax - this.valueMin);
  }

  /** Formats a normalized value in the dataset's units, e.g. "−350 HU". */
  formatValue(v) {
    const x = this.toUnits(v);
    const span = Math.abs(this.valueMax - this.valueMin);
    const s = span >= 50 ? Math.round(x).toString() : span >= 5 ? x.toFixed(1) : x.toPrecision(3);
    return (s.replace('-', '−') + (this.units ? ' ' + this.units : '')).trim();
  }

  // ---- geometry -------------------------------------------------------------------------------

  get plotW() {
    return Math.max(10, this.cssW - MARGIN.left - MARGIN.right);
  }
  get plotH() {
    return Math.max(10, this.cssH - MARGIN.top - MARGIN.bottom);
  }
  vToX(v) {
    return MARGIN.left + v * this.plotW;
  }
  xToV(x) {
    return clamp01((x - MARGIN.left) / this.plotW);
  }
  opToY(a) {
    const f = this.sqrtY ? Math.sqrt(clamp01(a)) : clamp01(a);
    return MARGIN.top + (1 - f) * this.plotH;
  }
  yToOp(y) {
    const f = clamp01(1 - (y - MARGIN.top) / this.plotH);
    return this.sqrtY ? f * f : f;
  }

  /** @param {MouseEvent} e @returns {[number, number]} */
  _pos(e) {
    const r = this.canvas.getBoundingClientRect();
    return [e.clientX - r.left, e.clientY - r.top];
  }

  _hit(x, y) {
    let best = -1;
    let bestD = HIT_RADIUS;
    this.pts.forEach((p, i) => {
      const d = Math.hypot(this.vToX(p.value) - x, this.opToY(p.opacity) - y);
      if (d <= bestD) {
        best = i;
        bestD = d;
      }
    });
    return best;
  }

  // ---- interaction ----------------------------------------------------------------------------

  /** @param {PointerEvent} e */
  _onDown(e) {
    if (e.button !== 0) return;
    this.canvas.focus({ preventScroll: true });
    const [x, y] = this._pos(e);
    let i = this._hit(x, y);
    if (i < 0) {
      if (this.pts.length >= MAX_TF_POINTS) return;
      const v = this.xToV(x);
      const base = evalTf(this.pts, v);
      const color = this.pts.length ? base.color : [1, 1, 1];
      const p = { value: v, color: /** @type {[number,number,number]} */ (color), opacity: this.yToOp(y) };
      i = this.pts.findIndex((q) => q.value > v);
      if (i < 0) i = this.pts.length;
      this.pts.splice(i, 0, p);
      this.selected = i;
      this._changed();
    } else {
      this.selected = i;
      this._syncColor();
    }
    this.drag = { pointerId: e.pointerId, index: i };
    try {
      this.canvas.setPointerCapture(e.pointerId);
    } catch {
      /* pointer already gone */
    }
    e.preventDefault();
    this._updateReadout();
    this.redraw();
  }

  /** @param {PointerEvent} e */
  _onMove(e) {
    const [x, y] = this._pos(e);
    this.hover = { x, y };
    if (this.drag && this.drag.pointerId === e.pointerId) {
      const i = this.drag.index;
      const p = this.pts[i];
      if (p) {
        const lo = i > 0 ? this.pts[i - 1].value + 1e-4 : 0;
        const hi = i < this.pts.length - 1 ? this.pts[i + 1].value - 1e-4 : 1;
        p.value = Math.min(hi, Math.max(lo, this.xToV(x)));
        p.opacity = this.yToOp(y);
        this._changed();
      }
    }
    this.canvas.style.cursor = this.drag ? 'grabbing' : this._hit(x, y) >= 0 ? 'grab' : 'crosshair';
    this._updateReadout();
    this.redraw();
  }

  /** @param {PointerEvent} e */
  _onUp(e) {
    if (this.drag && this.drag.pointerId === e.pointerId) this.drag = null;
  }

  /** @param {KeyboardEvent} e */
  _onKey(e) {
    if (this.selected < 0) return;
    const p = this.pts[this.selected];
    const big = e.shiftKey ? 10 : 1;
    if (e.key === 'Delete' || e.key === 'Backspace') {
      this._remove(this.selected);
    } else if (e.key === 'ArrowLeft' || e.key === 'ArrowRight') {
      const i = this.selected;
      const lo = i > 0 ? this.pts[i - 1].value + 1e-4 : 0;
      const hi = i < this.pts.length - 1 ? this.pts[i + 1].value - 1e-4 : 1;
      const d = ((e.key === 'ArrowLeft' ? -1 : 1) * big) / 256;
      p.value = Math.min(hi, Math.max(lo, p.value + d));
      this._changed();
    } else if (e.key === 'ArrowUp' || e.key === 'ArrowDown') {
      const d = (e.key === 'ArrowDown' ? -1 : 1) * big * 0.005;
      p.opacity = clamp01(p.opacity + d);
      this._changed();
    } else if (e.key === 'Escape') {
      this.selected = -1;
      this._syncColor();
    } else {
      return;
    }
    e.preventDefault();
    this._updateReadout();
    this.redraw();
  }

  _remove(i) {
    // The last point stays: the server refuses an empty transfer function (bad_value); drag
    // its opacity to 0 for a transparent volume.
    if (i < 0 || i >= this.pts.length || this.pts.length <= 1) return;
    this.pts.splice(i, 1);
    this.selected = -1;
    this.drag = null;
    this._syncColor();
    this._changed();
    this._updateReadout();
    this.redraw();
  }

  _changed() {
    this.dispatchEvent(new CustomEvent('change', { detail: this.points }));
  }

  _syncColor() {
    if (!this.colorInput) return;
    const p = this.pts[this.selected];
    this.colorInput.disabled = !p;
    if (p) this.colorInput.value = linearToHex(p.color);
  }

  _updateReadout() {
    if (!this.readout) return;
    const p = this.pts[this.selected];
    let s = '';
    if (this.hover) {
      const v = this.xToV(this.hover.x);
      s = `${this.formatValue(v)} · α ${this.yToOp(this.hover.y).toFixed(3)}`;
    } else if (p) {
      s = `point ${this.selected + 1}/${this.pts.length}: ${this.formatValue(p.value)} · α ${p.opacity.toFixed(3)}`;
    } else {
      s = `${this.pts.length} points · click to add`;
    }
    this.readout.textContent = s;
  }

  // ---- drawing --------------------------------------------------------------------------------

  _resize() {
    const r = this.canvas.getBoundingClientRect();
    this.cssW = Math.max(50, r.width || 300);
    this.cssH = Math.max(50, r.height || 160);
    const dpr = Math.min(3, window.devicePixelRatio || 1);
    const w = Math.round(this.cssW * dpr);
    const h = Math.round(this.cssH * dpr);
    if (this.canvas.width !== w || this.canvas.height !== h) {
      this.canvas.width = w;
      this.canvas.height = h;
    }
    this.redraw();
  }

  /** Schedules a redraw on the next animation frame (coalesced). */
  redraw() {
    if (this._raf) return;
    this._raf = requestAnimationFrame(() => {
      this._raf = 0;
      this._draw();
    });
  }

  _draw() {
    const ctx = this.ctx;
    const dpr = this.canvas.width / this.cssW;
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    const W = this.cssW;
    const H = this.cssH;
    const L = MARGIN.left;
    const T = MARGIN.top;
    const PW = this.plotW;
    const PH = this.plotH;
    ctx.clearRect(0, 0, W, H);
    ctx.fillStyle = '#0b0e12';
    ctx.fillRect(L, T, PW, PH);

    // Histogram, log scale.
    const hist = this.histogram;
    if (hist.length) {
      let maxLog = 0;
      for (const c of hist) maxLog = Math.max(maxLog, Math.log1p(c));
      if (maxLog > 0) {
        ctx.fillStyle = 'rgba(140,150,165,0.35)';
        const bw = PW / hist.length;
        for (let i = 0; i < hist.length; i++) {
          const h = (Math.log1p(hist[i]) / maxLog) * PH;
          if (h > 0) ctx.fillRect(L + i * bw, T + PH - h, Math.max(1, bw - 0.3), h);
        }
      }
    }

    // Grid + axes.
    ctx.strokeStyle = 'rgba(255,255,255,0.07)';
    ctx.lineWidth = 1;
    ctx.font = '10px system-ui, sans-serif';
    ctx.fillStyle = '#7d8794';
    ctx.textAlign = 'right';
    ctx.textBaseline = 'middle';
    for (const a of this.sqrtY ? [0, 0.05, 0.25, 0.5, 1] : [0, 0.25, 0.5, 0.75, 1]) {
      const y = Math.round(this.opToY(a)) + 0.5;
      ctx.beginPath();
      ctx.moveTo(L, y);
      ctx.lineTo(L + PW, y);
      ctx.stroke();
      ctx.fillText(a === 0 || a === 1 ? String(a) : a.toString().replace(/^0/, ''), L - 4, y);
    }
    ctx.textBaseline = 'top';
    for (const t of niceTicks(this.valueMin, this.valueMax, Math.max(2, Math.floor(PW / 55)))) {
      const v = (t - this.valueMin) / (this.valueMax - this.valueMin);
      if (!(v >= 0 && v <= 1)) continue;
      const x = Math.round(this.vToX(v)) + 0.5;
      ctx.beginPath();
      ctx.moveTo(x, T);
      ctx.lineTo(x, T + PH + 3);
      ctx.stroke();
      // Labels at the very ends are aligned inward so they stay inside the canvas.
      ctx.textAlign = v < 0.04 ? 'left' : v > 0.96 ? 'right' : 'center';
      ctx.fillText(formatTick(t), ctx.textAlign === 'left' ? x - 3 : ctx.textAlign === 'right' ? x + 3 : x, T + PH + 5);
    }
    if (this.units) {
      ctx.textAlign = 'right';
      ctx.fillStyle = '#a9b4c0';
      ctx.fillText(this.units, L + PW - 4, T + 3);
    }

    // Colour ramp under the opacity curve, one column per CSS pixel.
    const pts = this.pts;
    if (pts.length) {
      for (let px = 0; px < PW; px++) {
        const v = (px + 0.5) / PW;
        const s = evalTf(pts, v);
        const y = this.opToY(s.opacity);
        ctx.fillStyle = linearToCss(s.color, 0.75);
        ctx.fillRect(L + px, y, 1.01, T + PH - y);
      }
      // Curve, extended flat beyond the ends.
      ctx.strokeStyle = '#e8edf3';
      ctx.lineWidth = 1.5;
      // Sampled per pixel, so that it is the true (piecewise-linear in opacity) function even on
      // the square-root axis, plus the exact point positions.
      ctx.beginPath();
      ctx.moveTo(L, this.opToY(pts[0].opacity));
      let k = 0;
      for (let px = 0; px <= PW; px++) {
        const v = px / PW;
        while (k < pts.length && pts[k].value <= v) {
          ctx.lineTo(this.vToX(pts[k].value), this.opToY(pts[k].opacity));
          k++;
        }
        ctx.lineTo(L + px, this.opToY(evalTf(pts, v).opacity));
      }
      ctx.stroke();
      // Points.
      pts.forEach((p, i) => {
        const x = this.vToX(p.value);
        const y = this.opToY(p.opacity);
        const sel = i === this.selected;
        ctx.beginPath();
        ctx.arc(x, y, sel ? 6 : 4.5, 0, Math.PI * 2);
        ctx.fillStyle = linearToCss(p.color);
        ctx.fill();
        ctx.lineWidth = sel ? 2 : 1.25;
        ctx.strokeStyle = sel ? '#4cc2ff' : '#f4f7fa';
        ctx.stroke();
      });
    }

    // Hover crosshair.
    if (this.hover && !this.drag) {
      const x = Math.min(L + PW, Math.max(L, this.hover.x));
      ctx.strokeStyle = 'rgba(76,194,255,0.45)';
      ctx.lineWidth = 1;
      ctx.beginPath();
      ctx.moveTo(Math.round(x) + 0.5, T);
      ctx.lineTo(Math.round(x) + 0.5, T + PH);
      ctx.stroke();
    }
    ctx.strokeStyle = 'rgba(255,255,255,0.18)';
    ctx.strokeRect(L + 0.5, T + 0.5, PW - 1, PH - 1);
  }
}

function clamp01(x) {
  return Number.isFinite(x) ? Math.min(1, Math.max(0, x)) : 0;
}

/** "Nice" tick values (1, 2, 5 × 10^k) covering [a, b]. */
export function niceTicks(a, b, count) {
  if (!(b > a) || !Number.isFinite(a) || !Number.isFinite(b)) return [];
  const raw = (b - a) / Math.max(1, count);
  const mag = Math.pow(10, Math.floor(Math.log10(raw)));
  const step = [1, 2, 2.5, 5, 10].map((m) => m * mag).find((s) => s >= raw) || 10 * mag;
  const out = [];
  for (let t = Math.ceil(a / step) * step; t <= b + 1e-9 * step; t += step) out.push(Math.round(t / step) * step);
  return out;
}

function formatTick(t) {
  const a = Math.abs(t);
  const s = a >= 1000 || a === 0 ? String(Math.round(t)) : a >= 1 ? String(+t.toFixed(1)) : String(+t.toPrecision(2));
  return s.replace('-', '−');
}
