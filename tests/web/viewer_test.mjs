#!/usr/bin/env node
// End-to-end test of the voxlight web viewer against a running server, in headless Chromium
// with the GPU (and so WebGL) disabled: the client must work on a plain 2D canvas.
//
//   cd tests/web && npm ci && node viewer_test.mjs http://127.0.0.1:8080/
//
// The server URL comes from argv[2] or VOXLIGHT_URL (default http://127.0.0.1:8080/).
// Screenshots go to VOXLIGHT_SCREENSHOTS (default /tmp). The browser is CHROMIUM_PATH
// (default /usr/bin/chromium). VOXLIGHT_TIMEOUT_S scales every wait (default 60 s per step).
// Prints one line per check and ends with `viewer: N passed, M failed`; exits 1 when a
// check failed and 2 when the test could not run at all (no browser, server unreachable).

import fs from 'node:fs';
import path from 'node:path';
import { chromium } from 'playwright-core';

const URL_ = process.argv[2] || process.env.VOXLIGHT_URL || 'http://127.0.0.1:8080/';
// A software renderer converges slowly at full page size: ask for fewer iterations.
const ITERATIONS = process.env.VOXLIGHT_ITERATIONS || '12';
/** The page URL with ?iterations=N unless the URL already names it. */
function withIterations(url) {
  const u = new URL(url);
  if (!u.searchParams.has('iterations') && ITERATIONS !== '0') u.searchParams.set('iterations', ITERATIONS);
  return u.toString();
}
const SHOTS = process.env.VOXLIGHT_SCREENSHOTS || '/tmp';
const CHROMIUM = process.env.CHROMIUM_PATH || '/usr/bin/chromium';
const STEP_MS = 1000 * Number(process.env.VOXLIGHT_TIMEOUT_S || 60);
// Soft tissue first: it differs most from the server's bone-weighted default CT TF.
const CT_PRESETS = ['soft', 'lung', 'vessels', 'bone'];

const results = /** @type {{name: string, ok: boolean, detail: string}[]} */ ([]);
const consoleErrors = /** @type {string[]} */ ([]);

function record(name, ok, detail = '') {
  results.push({ name, ok, detail });
  console.log(`${ok ? 'ok  ' : 'FAIL'} ${name}${detail ? ' — ' + detail : ''}`);
}

/** Mean absolute difference of two grayscale thumbnails (0..255). */
function meanAbsDiff(a, b) {
  if (!a || !b || a.data.length !== b.data.length) return Infinity;
  let s = 0;
  for (let i = 0; i < a.data.length; i++) s += Math.abs(a.data[i] - b.data[i]);
  return s / a.data.length;
}

function spread(a) {
  let min = 255;
  let max = 0;
  let sum = 0;
  for (const x of a.data) {
    min = Math.min(min, x);
    max = Math.max(max, x);
    sum += x;
  }
  const mean = sum / a.data.length;
  let v = 0;
  for (const x of a.data) v += (x - mean) ** 2;
  return { min, max, mean, std: Math.sqrt(v / a.data.length) };
}

async function main() {
  fs.mkdirSync(SHOTS, { recursive: true });
  if (!fs.existsSync(CHROMIUM)) {
    console.error(`web viewer: cannot run: no Chromium at ${CHROMIUM} (set CHROMIUM_PATH or apt-get install chromium)`);
    return 2;
  }
  // Fail early and clearly when the server is not there.
  try {
    const health = await fetch(new URL('/healthz', URL_));
    console.log(`server ${URL_} /healthz: ${health.status} ${(await health.text()).slice(0, 200)}`);
  } catch (err) {
    console.error(`web viewer: cannot run: server ${URL_} unreachable (${err.cause?.code || err.message}); start it with \`voxlight serve\` or pass its URL`);
    return 2;
  }

  const browser = await chromium.launch({
    executablePath: CHROMIUM,
    args: ['--headless', '--no-sandbox', '--disable-gpu', '--disable-webgl', '--disable-3d-apis', '--disable-quic', '--no-first-run', '--disable-background-networking', '--disable-component-update', '--disable-sync'],
  });
  try {
    const page = await browser.newPage({ viewport: { width: 960, height: 600 } });
    page.on('console', (m) => {
      if (m.type() === 'error') consoleErrors.push(m.text());
    });
    page.on('pageerror', (e) => consoleErrors.push(`uncaught: ${e.message}`));
    page.setDefaultTimeout(STEP_MS);
    const shot = async (name) => {
      const file = path.join(SHOTS, `voxlight-${name}.png`);
      await page.screenshot({ path: file }).catch(() => {});
      return file;
    };
    const sample = () => page.evaluate(() => window.voxlight.sample(64));
    const shownVersion = () => page.evaluate(() => window.voxlight.lastShownMeta?.scene_version ?? -1);
    const receivedVersion = () => page.evaluate(() => window.voxlight.lastMeta?.scene_version ?? -1);
    // The newest frame shown before the orbit drag of step 4 (step 6 looks at what came after).
    let dragFromSeq = -1;

    /**
     * Waits for a displayed frame with scene_version > v whose picture differs from `before` by
     * more than `minDiff` (mean abs difference of 64×64 thumbnails); returns the last diff seen.
     */
    async function waitChangedFrame(v, before, minDiff) {
      const deadline = Date.now() + STEP_MS;
      let diff = 0;
      let newer = false;
      while (Date.now() < deadline) {
        newer = (await shownVersion()) > v;
        if (newer) {
          diff = meanAbsDiff(before, await sample());
          if (diff > minDiff) return { ok: true, diff, newer };
        }
        await page.waitForTimeout(150);
      }
      return { ok: false, diff, newer };
    }

    // 1. Page loads, connects, gets a welcome.
    try {
      await page.goto(withIterations(URL_), { waitUntil: 'load' });
      await page.waitForFunction(() => window.voxlight && window.voxlight.connected && window.voxlight.welcome);
      const w = await page.evaluate(() => ({ s: window.voxlight.session, d: window.voxlight.dataset?.name, t: window.voxlight.welcome.state?.technique, n: window.voxlight.techniques.length }));
      record('connects and receives welcome', true, `session ${w.s}, dataset ${w.d}, technique ${w.t}, ${w.n} techniques`);
    } catch (err) {
      await shot('failure-connect');
      record('connects and receives welcome', false, String(err.message || err).split('\n')[0]);
      return 1;
    }

    // 2. A frame is drawn and the canvas is not a flat colour.
    let first;
    try {
      await page.waitForFunction(() => window.voxlight.framesShown > 0);
      // Give progressive refinement a moment, then look at the pixels.
      await page.waitForFunction(() => window.voxlight.framesShown >= 3 || window.voxlight.lastShownMeta?.converged, null, { timeout: STEP_MS }).catch(() => {});
      first = await sample();
      const s = spread(first);
      const file = await shot('01-first-frame');
      const meta = await page.evaluate(() => window.voxlight.lastShownMeta);
      const ok = s.max - s.min > 12 && s.std > 2;
      record('first frame drawn, not flat', ok, `${meta.width}×${meta.height} ${meta.format} it ${meta.iteration}/${meta.target_iterations}, gray min ${s.min} max ${s.max} std ${s.std.toFixed(1)}; ${file}`);
    } catch (err) {
      await shot('failure-first-frame');
      record('first frame drawn, not flat', false, String(err.message || err).split('\n')[0]);
      return 1;
    }

    // 3. A CT preset (clicked in the UI) changes the picture.
    try {
      const before = await sample();
      const v0 = await receivedVersion();
      const tf0 = await page.evaluate(() => window.voxlight.sent.tf || 0);
      const current = JSON.stringify(await page.evaluate(() => window.voxlight.welcome.state?.tf?.points || []));
      let chosen = '';
      let res = { ok: false, diff: 0, newer: false };
      for (const id of CT_PRESETS) {
        await page.click(`#presets button[data-preset="${id}"]`);
        await page.waitForFunction((n) => (window.voxlight.sent.tf || 0) > n, tf0, { timeout: 5000 });
        const sent = JSON.stringify(await page.evaluate(() => window.voxlight.lastSent.tf.points));
        if (sent === current) continue; // identical to the server's TF: try the next one
        chosen = id;
        res = await waitChangedFrame(v0, before, 1.5);
        break;
      }
      const file = await shot('02-preset');
      record('CT preset changes the picture', res.ok, `preset ${chosen || '(none differed)'}, newer frame ${res.newer}, mean |Δ| ${res.diff.toFixed(2)}; ${file}`);
    } catch (err) {
      await shot('failure-preset');
      record('CT preset changes the picture', false, String(err.message || err).split('\n')[0]);
    }

    // 4. Orbiting by dragging sends camera messages and brings a new frame.
    try {
      // A CT preset on non-CT data may leave nothing visible; put the generic ramp back first so
      // that an orbit has something to change.
      const units = await page.evaluate(() => window.voxlight.dataset?.details?.units || '');
      if (units !== 'HU') {
        const v = await receivedVersion();
        const b = await sample();
        await page.click('#presets button[data-preset="ramp"]');
        await waitChangedFrame(v, b, 0);
        console.log(`     (dataset units “${units}”, not HU: applied the generic ramp preset before orbiting)`);
      }
      const before = await sample();
      const v0 = await receivedVersion();
      dragFromSeq = await page.evaluate(() => window.voxlight.lastShownMeta?.seq ?? -1);
      const cam0 = await page.evaluate(() => window.voxlight.sent.camera || 0);
      const box = await page.locator('#viewer').boundingBox();
      const cx = box.x + box.width / 2;
      const cy = box.y + box.height / 2;
      await page.mouse.move(cx, cy);
      await page.mouse.down();
      for (let i = 1; i <= 12; i++) {
        await page.mouse.move(cx + i * 12, cy + i * 3);
        await page.waitForTimeout(20);
      }
      await page.mouse.up();
      await page.waitForFunction((n) => (window.voxlight.sent.camera || 0) > n, cam0, { timeout: 5000 });
      const cam = await page.evaluate(() => ({ n: window.voxlight.sent.camera, last: window.voxlight.lastSent.camera }));
      const res = await waitChangedFrame(v0, before, 0.5);
      const file = await shot('03-orbit');
      const lat = await page.evaluate(() => window.voxlight.lastLatencyMs);
      // A flat picture (nothing visible) cannot change when orbiting: then a newer frame suffices.
      const flat = spread(before).std < 1;
      record('orbit drag sends camera and updates the view', res.newer && (res.ok || flat), `${cam.n - cam0} camera messages, eye ${JSON.stringify(cam.last.eye)}, newer frame ${res.newer}, mean |Δ| ${res.diff.toFixed(2)}, edit→frame ${lat == null ? '?' : Math.round(lat) + ' ms'}; ${file}`);
    } catch (err) {
      await shot('failure-orbit');
      record('orbit drag sends camera and updates the view', false, String(err.message || err).split('\n')[0]);
    }

    // 5. Once input stops the picture converges to a lossless frame of the latest edit.
    try {
      const v = await receivedVersion();
      await page.waitForFunction((sv) => {
        const m = window.voxlight.lastShownMeta;
        return m && m.converged && m.scene_version >= sv;
      }, v, { timeout: STEP_MS * 2 });
      const m = await page.evaluate(() => window.voxlight.lastShownMeta);
      const status = await page.locator('#status').innerText();
      const file = await shot('04-converged');
      const ok = m.lossless === true && m.format === 'png' && /converged/.test(status);
      record('converges to a lossless frame', ok, `${m.format} lossless=${m.lossless} it ${m.iteration}/${m.target_iterations} v${m.scene_version}; status “${status.replace(/\s+/g, ' ').slice(0, 120)}”; ${file}`);
    } catch (err) {
      await shot('failure-converge');
      record('converges to a lossless frame', false, String(err.message || err).split('\n')[0]);
    }

    // 6. The interaction mode as the viewer shows it (issue 20): the orbit drag of step 4 was
    //    shown by previews at a reduced resolution (the server's default 60 ms target on a
    //    software adapter), each the viewport divided by its scale and drawn scaled up to the
    //    rectangle the full-resolution still fills; then came the lossless still of the viewport.
    try {
      const log = await page.evaluate((from) => window.voxlight.shownLog.filter((e) => e.seq > from), dragFromSeq);
      const vp = await page.evaluate(() => window.voxlight.viewport);
      const previews = log.filter((e) => e.preview);
      const reduced = previews.filter((e) => e.scale < 1);
      const still = log.filter((e) => e.converged && e.lossless).pop();
      const problems = [];
      if (reduced.length === 0) problems.push(`no reduced preview among ${previews.length} previews (scales ${[...new Set(previews.map((e) => e.scale))]})`);
      for (const e of reduced) {
        const want = [Math.ceil(vp.width * e.scale), Math.ceil(vp.height * e.scale)];
        if (e.width !== want[0] || e.height !== want[1]) problems.push(`preview at ${e.scale} is ${e.width}×${e.height}, not ${want.join('×')}`);
      }
      if (!still) problems.push('no lossless still after the drag');
      else {
        if (still.preview || still.scale !== 1 || still.width !== vp.width || still.height !== vp.height) problems.push(`the still is ${still.width}×${still.height} at scale ${still.scale} (preview ${still.preview}), viewport ${vp.width}×${vp.height}`);
        // Scaled up to the still's rectangle, give or take the rounding of its size.
        for (const e of reduced) {
          const off = Math.max(Math.abs(e.drawn.w - still.drawn.w), Math.abs(e.drawn.h - still.drawn.h));
          if (off > 0.02 * Math.max(still.drawn.w, still.drawn.h)) problems.push(`preview at ${e.scale} drawn ${Math.round(e.drawn.w)}×${Math.round(e.drawn.h)}, the still ${Math.round(still.drawn.w)}×${Math.round(still.drawn.h)}`);
        }
        if (log.indexOf(still) < Math.max(...reduced.map((e) => log.indexOf(e)))) problems.push('a preview came after the still');
      }
      const scales = reduced.map((e) => e.scale).join(',');
      record('drag shows reduced previews scaled to the canvas, then the lossless still', problems.length === 0, problems.length ? problems.slice(0, 4).join('; ') : `${reduced.length} reduced previews (scales ${scales}) of ${log.length} frames, then the ${still.width}×${still.height} PNG`);
    } catch (err) {
      record('drag shows reduced previews scaled to the canvas, then the lossless still', false, String(err.message || err).split('\n')[0]);
    }

    // 7. Technique options: the panel shows the chosen technique's options with the server's
    //    defaults; a change goes to the server as a `technique` message and the session keeps it.
    try {
      await page.selectOption('#technique', 'irradiance');
      const locking = page.locator('#technique-options select[data-option="locking"]');
      await locking.waitFor();
      const shown = await page.$$eval('#technique-options select', (els) => els.map((e) => `${e.dataset.option}=${e.selectedOptions[0]?.textContent}`));
      const screen = await locking.evaluate((el) => [...el.options].findIndex((o) => o.textContent.startsWith('screen')));
      await locking.selectOption(String(screen));
      await page.waitForFunction(() => window.voxlight.state?.technique_options?.irradiance?.locking === 'screen');
      await page.waitForFunction(() => window.voxlight.lastShownMeta?.technique === 'irradiance');
      const sent = await page.evaluate(() => window.voxlight.lastSent.technique);
      const file = await shot('05-technique-options');
      const ok = shown.includes('locking=object (default)') && sent?.name === 'irradiance' && sent?.options?.irradiance?.locking === 'screen';
      record('technique options shown, sent and kept', ok, `${shown.join(', ')}; sent ${JSON.stringify(sent)}; ${file}`);
    } catch (err) {
      await shot('failure-options');
      record('technique options shown, sent and kept', false, String(err.message || err).split('\n')[0]);
    }

    // 8. No console errors, no uncaught exceptions, no `error` messages from the server.
    const serverErrors = await page.evaluate(() => window.voxlight.errors);
    record(
      'no console errors or server error messages',
      consoleErrors.length === 0 && serverErrors.length === 0,
      consoleErrors.length || serverErrors.length
        ? `console: ${JSON.stringify(consoleErrors.slice(0, 5))}; server: ${JSON.stringify(serverErrors.slice(0, 5))}`
        : `${await page.evaluate(() => window.voxlight.framesShown)} frames shown, ${await page.evaluate(() => window.voxlight.framesDropped)} dropped before decode`,
    );
  } finally {
    await browser.close();
  }
  return results.every((r) => r.ok) ? 0 : 1;
}

let code;
try {
  code = await main();
} catch (err) {
  console.error(`web viewer: cannot run: ${err && err.message ? err.message : err}`);
  code = 2;
}
const passed = results.filter((r) => r.ok).length;
const failed = results.length - passed;
if (code !== 0) for (const r of results.filter((x) => !x.ok)) console.error(`failed: ${r.name}: ${r.detail}`);
console.log(`viewer: ${passed} passed, ${failed} failed`);
process.exit(code === 0 && failed === 0 ? 0 : code || 1);
