#!/usr/bin/env node
// End-to-end test of shared sessions in the voxlight web viewer: two people (two browser
// contexts, so two names and no shared storage) in one session, in headless Chromium with the
// GPU disabled, against a running server.
//
//   cd tests/web && npm ci && node shared_test.mjs http://127.0.0.1:8080/
//
// Same conventions as viewer_test.mjs: the server URL comes from argv[2] or VOXLIGHT_URL; the
// browser is CHROMIUM_PATH (default /usr/bin/chromium); VOXLIGHT_TIMEOUT_S scales every wait
// (default 60 s per step); screenshots go to VOXLIGHT_SCREENSHOTS (default /tmp). Prints one
// line per check and ends with `shared: N passed, M failed`; exits 1 when a check failed and 2
// when the test could not run at all (no browser, server unreachable).

import fs from 'node:fs';
import path from 'node:path';
import { chromium } from 'playwright-core';

const URL_ = process.argv[2] || process.env.VOXLIGHT_URL || 'http://127.0.0.1:8080/';
// Small pictures and few iterations: the CI server renders on the CPU.
const ITERATIONS = process.env.VOXLIGHT_ITERATIONS || '8';
const VIEW = { width: 480, height: 360 };
const SHOTS = process.env.VOXLIGHT_SCREENSHOTS || '/tmp';
const CHROMIUM = process.env.CHROMIUM_PATH || '/usr/bin/chromium';
const STEP_MS = 1000 * Number(process.env.VOXLIGHT_TIMEOUT_S || 60);
// Presets to try for the shared TF edit; the first that differs from the session's TF is used.
const PRESETS = ['soft', 'lung', 'vessels', 'bone', 'ramp'];

const results = /** @type {{name: string, ok: boolean, detail: string}[]} */ ([]);
const started = Date.now();

function record(name, ok, detail = '') {
  results.push({ name, ok, detail });
  const t = ((Date.now() - started) / 1000).toFixed(1);
  console.log(`${ok ? 'ok  ' : 'FAIL'} ${name}${detail ? ' — ' + detail : ''} [${t} s]`);
}

/** Largest absolute difference between two TF point lists (Infinity when shapes differ). */
function tfDiff(a, b) {
  if (!Array.isArray(a) || !Array.isArray(b) || a.length !== b.length) return Infinity;
  let d = 0;
  for (let i = 0; i < a.length; i++) {
    d = Math.max(d, Math.abs(a[i].value - b[i].value), Math.abs(a[i].opacity - b[i].opacity));
    for (let k = 0; k < 3; k++) d = Math.max(d, Math.abs(a[i].color[k] - b[i].color[k]));
  }
  return d;
}

const firstLine = (err) => String((err && err.message) || err).split('\n')[0];

async function main() {
  fs.mkdirSync(SHOTS, { recursive: true });
  if (!fs.existsSync(CHROMIUM)) {
    console.error(`shared: cannot run: no Chromium at ${CHROMIUM} (set CHROMIUM_PATH or apt-get install chromium)`);
    return 2;
  }
  try {
    const health = await fetch(new URL('/healthz', URL_));
    console.log(`server ${URL_} /healthz: ${health.status}`);
  } catch (err) {
    console.error(`shared: cannot run: server ${URL_} unreachable (${err.cause?.code || err.message}); start it with \`voxlight serve\` or pass its URL`);
    return 2;
  }

  const browser = await chromium.launch({
    executablePath: CHROMIUM,
    args: ['--headless', '--no-sandbox', '--disable-gpu', '--disable-webgl', '--disable-3d-apis', '--disable-quic', '--no-first-run', '--disable-background-networking', '--disable-component-update', '--disable-sync'],
  });
  /** Console errors and uncaught exceptions, per page label. */
  const consoleErrors = /** @type {string[]} */ ([]);

  /** A page in its own browser context whose stored display name is `name`. */
  async function openPerson(label, name) {
    const context = await browser.newContext({ viewport: VIEW });
    await context.addInitScript((n) => localStorage.setItem('voxlight.name', n), name);
    const page = await context.newPage();
    page.on('console', (m) => {
      if (m.type() === 'error') consoleErrors.push(`${label}: ${m.text()}`);
    });
    page.on('pageerror', (e) => consoleErrors.push(`${label}: uncaught: ${e.message}`));
    page.setDefaultTimeout(STEP_MS);
    return page;
  }
  const shot = async (page, name) => {
    const file = path.join(SHOTS, `voxlight-shared-${name}.png`);
    await page.screenshot({ path: file }).catch(() => {});
    return file;
  };
  const vx = (page, fn, arg) => page.evaluate(fn, arg);

  try {
    const a = await openPerson('A', 'Alice');
    const b = await openPerson('B', 'Bob');
    const start = new URL(URL_);
    start.searchParams.set('iterations', ITERATIONS);

    // 1. A starts a session: the URL names it, frames arrive and are acknowledged.
    let sessionId = '';
    let link = '';
    try {
      await a.goto(start.toString(), { waitUntil: 'load' });
      await a.waitForFunction(() => window.voxlight?.welcome && window.voxlight.framesShown > 0);
      // Acks keep the flow-control window (2 frames) moving: more than 2 frames must arrive.
      await a.waitForFunction(() => window.voxlight.framesReceived > 2 || window.voxlight.lastShownMeta?.converged);
      const s = await vx(a, () => ({ session: window.voxlight.session, joined: window.voxlight.joined, viewer: window.voxlight.viewer, search: location.search, link: window.voxlight.shareLink(), received: window.voxlight.framesReceived, acks: window.voxlight.sent.ack || 0, acked: window.voxlight.acked }));
      sessionId = s.session;
      link = s.link;
      const url = new URLSearchParams(s.search);
      const ok = !!sessionId && !s.joined && s.viewer?.name === 'Alice' && url.get('session') === sessionId && url.get('iterations') === ITERATIONS && !/token/.test(link) && s.acks > 0 && s.acked >= 0;
      record('A starts a session; ?session= in the URL; frames acknowledged', ok, `session ${sessionId}, viewer ${JSON.stringify(s.viewer)}, url ${s.search}, ${s.received} frames, ${s.acks} acks (newest ${s.acked})`);
    } catch (err) {
      await shot(a, 'failure-start');
      record('A starts a session; ?session= in the URL; frames acknowledged', false, firstLine(err));
      return 1;
    }

    // 2. B opens A's share link: same session, both list two viewers, B gets a picture.
    try {
      await b.goto(link, { waitUntil: 'load' });
      await b.waitForFunction(() => window.voxlight?.welcome && window.voxlight.framesShown > 0);
      await a.waitForFunction(() => window.voxlight.viewers.length === 2);
      await b.waitForFunction(() => window.voxlight.viewers.length === 2);
      const bs = await vx(b, () => ({ session: window.voxlight.session, joined: window.voxlight.joined, names: window.voxlight.viewers.map((v) => v.name) }));
      const aList = await a.locator('#viewers li').allInnerTexts();
      const bList = await b.locator('#viewers li').allInnerTexts();
      const ok = bs.session === sessionId && bs.joined && aList.length === 2 && bList.length === 2 && aList.some((t) => t.includes('Bob')) && bList.some((t) => /Bob\s*you/.test(t));
      record('B joins by the share link; both show 2 viewers', ok, `B session ${bs.session} joined ${bs.joined}; A lists ${JSON.stringify(aList)}, B lists ${JSON.stringify(bList)}`);
    } catch (err) {
      await shot(b, 'failure-join');
      record('B joins by the share link; both show 2 viewers', false, firstLine(err));
      return 1;
    }

    // 2b. B renames itself: A's list follows, without B reconnecting.
    try {
      const viewerId = await vx(b, () => window.voxlight.viewer.id);
      await b.fill('#name', 'Robert');
      await b.dispatchEvent('#name', 'change');
      await a.waitForFunction(() => window.voxlight.viewers.some((v) => v.name === 'Robert'));
      const same = await vx(b, () => window.voxlight.viewer.id);
      record('B renames itself; A sees the new name; B stays connected', same === viewerId, `viewer id ${viewerId} → ${same}`);
      await b.fill('#name', 'Bob');
      await b.dispatchEvent('#name', 'change');
      await a.waitForFunction(() => window.voxlight.viewers.some((v) => v.name === 'Bob'));
    } catch (err) {
      record('B renames itself; A sees the new name; B stays connected', false, firstLine(err));
    }

    // 3. A applies a preset: B's TF editor follows, B shows "last edit: Alice" and gets a frame
    //    of that scene version; B sends nothing back (no echo).
    try {
      const current = await vx(b, () => window.voxlight.tfPoints());
      const bSent0 = await vx(b, () => ({ ...window.voxlight.sent }));
      const tf0 = await vx(a, () => window.voxlight.sent.tf || 0);
      let chosen = '';
      let sent = null;
      for (const id of PRESETS) {
        await a.click(`#presets button[data-preset="${id}"]`);
        await a.waitForFunction((n) => (window.voxlight.sent.tf || 0) > n, tf0, { timeout: 5000 });
        sent = await vx(a, () => window.voxlight.lastSent.tf.points);
        if (tfDiff(sent, current) > 1e-3) {
          chosen = id;
          break;
        }
      }
      // A's own echo tells the version the edit produced.
      await a.waitForFunction(() => window.voxlight.editLog.some((e) => e.own && e.kind === 'tf'));
      const version = await vx(a, () => window.voxlight.editLog.filter((e) => e.own && e.kind === 'tf').pop().version);
      await b.waitForFunction((v) => window.voxlight.editLog.some((e) => !e.own && e.kind === 'tf' && e.version >= v && e.applied), version);
      const t0 = Date.now();
      await b.waitForFunction((v) => (window.voxlight.lastShownMeta?.scene_version ?? -1) >= v, version);
      const frameMs = Date.now() - t0;
      const bTf = await vx(b, () => window.voxlight.tfPoints());
      const edit = await b.locator('#st-edit').innerText();
      const bSent1 = await vx(b, () => ({ ...window.voxlight.sent }));
      const echoed = ['tf', 'camera', 'lights', 'params', 'technique', 'quality'].filter((k) => (bSent1[k] || 0) !== (bSent0[k] || 0));
      const diff = tfDiff(bTf, sent);
      const file = await shot(b, 'tf-followed');
      const ok = !!chosen && diff < 1e-4 && /last edit: Alice/.test(edit) && echoed.length === 0;
      record('A’s preset reaches B (TF editor, editor name, frame ≥ edit version), no echo', ok, `preset ${chosen}, version ${version}, B's TF off by ${diff.toExponential(1)}, B status “${edit}”, B's frame after ${frameMs} ms, B re-sent ${JSON.stringify(echoed)}; ${file}`);
    } catch (err) {
      await shot(b, 'failure-tf');
      record('A’s preset reaches B (TF editor, editor name, frame ≥ edit version), no echo', false, firstLine(err));
    }

    // 4. B orbits: A's camera follows and A shows "last edit: Bob"; A sends nothing back.
    try {
      const aSent0 = await vx(a, () => ({ ...window.voxlight.sent }));
      const cam0 = await vx(b, () => window.voxlight.sent.camera || 0);
      const box = await b.locator('#viewer').boundingBox();
      const cx = box.x + box.width / 2;
      const cy = box.y + box.height / 2;
      await b.mouse.move(cx, cy);
      await b.mouse.down();
      for (let i = 1; i <= 8; i++) {
        await b.mouse.move(cx + i * 10, cy + i * 2);
        await b.waitForTimeout(20);
      }
      await b.mouse.up();
      await b.waitForFunction((n) => (window.voxlight.sent.camera || 0) > n, cam0, { timeout: 5000 });
      const bCam = await vx(b, () => window.voxlight.lastSent.camera);
      await a.waitForFunction((c) => {
        const e = window.voxlight.camera.eye;
        return Math.hypot(e[0] - c.eye[0], e[1] - c.eye[1], e[2] - c.eye[2]) < 1e-4;
      }, bCam);
      await a.waitForFunction(() => /last edit: Bob/.test(document.getElementById('st-edit').textContent));
      const aSent1 = await vx(a, () => ({ ...window.voxlight.sent }));
      const echoed = ['tf', 'camera', 'lights', 'params', 'technique', 'quality'].filter((k) => (aSent1[k] || 0) !== (aSent0[k] || 0));
      const list = await a.locator('#viewers li').allInnerTexts();
      const file = await shot(a, 'camera-followed');
      record('B’s orbit reaches A (camera, “last edit: Bob”), no echo', echoed.length === 0, `A's eye ${JSON.stringify(await vx(a, () => window.voxlight.camera.eye))}, A lists ${JSON.stringify(list)}, A re-sent ${JSON.stringify(echoed)}; ${file}`);
    } catch (err) {
      await shot(a, 'failure-camera');
      record('B’s orbit reaches A (camera, “last edit: Bob”), no echo', false, firstLine(err));
    }

    // 5. A's connection drops: A rejoins the same session (URL unchanged) and gets a frame.
    try {
      const before = await vx(a, () => ({ search: location.search, received: window.voxlight.framesReceived, viewer: window.voxlight.viewer.id }));
      const t0 = Date.now();
      await vx(a, () => window.voxlight.connection.ws.close());
      await a.waitForFunction((id) => window.voxlight.connected && window.voxlight.viewer && window.voxlight.viewer.id !== id, before.viewer);
      const reconnectMs = Date.now() - t0;
      const received = await vx(a, () => window.voxlight.framesReceived);
      await a.waitForFunction((n) => window.voxlight.framesReceived > n, received);
      const frameMs = Date.now() - t0;
      const after = await vx(a, () => ({ session: window.voxlight.session, joined: window.voxlight.joined, search: location.search, meta: window.voxlight.lastMeta }));
      await b.waitForFunction(() => window.voxlight.viewers.length === 2);
      const ok = after.session === sessionId && after.joined && after.search === before.search;
      record('A’s dropped connection rejoins the same session and gets a frame', ok, `session ${after.session} joined ${after.joined}, url ${after.search === before.search ? 'unchanged' : after.search}, rejoined after ${reconnectMs} ms, frame (v${after.meta?.scene_version} ${after.meta?.format}) after ${frameMs} ms`);
    } catch (err) {
      await shot(a, 'failure-reconnect');
      record('A’s dropped connection rejoins the same session and gets a frame', false, firstLine(err));
    }

    // 6. A link to a session that no longer exists starts a new session instead.
    try {
      const c = await openPerson('C', 'Carol');
      const stale = new URL(link);
      stale.searchParams.set('session', '0123456789abcdef0123456789abcdef');
      await c.goto(stale.toString(), { waitUntil: 'load' });
      await c.waitForFunction(() => window.voxlight?.welcome && window.voxlight.framesShown > 0);
      const s = await vx(c, () => ({ session: window.voxlight.session, joined: window.voxlight.joined, search: location.search, errors: window.voxlight.errors.map((e) => e.code) }));
      const ok = !!s.session && s.session !== sessionId && !s.joined && new URLSearchParams(s.search).get('session') === s.session && s.errors.join() === 'unknown_session';
      record('a stale session link starts a new session', ok, `session ${s.session} joined ${s.joined}, url ${s.search}, server errors ${JSON.stringify(s.errors)}`);
      await c.context().close();
    } catch (err) {
      record('a stale session link starts a new session', false, firstLine(err));
    }

    // 7. No console errors or uncaught exceptions, no server errors on A and B.
    const serverErrors = [...(await vx(a, () => window.voxlight.errors)), ...(await vx(b, () => window.voxlight.errors))];
    record(
      'no console errors or server error messages',
      consoleErrors.length === 0 && serverErrors.length === 0,
      consoleErrors.length || serverErrors.length ? `console: ${JSON.stringify(consoleErrors.slice(0, 5))}; server: ${JSON.stringify(serverErrors.slice(0, 5))}` : `A showed ${await vx(a, () => window.voxlight.framesShown)} frames, B ${await vx(b, () => window.voxlight.framesShown)}`,
    );
  } finally {
    // Bounded: a browser slow to shut down must not hold the test run (process.exit ends it).
    await Promise.race([browser.close(), new Promise((r) => setTimeout(r, 10000))]);
  }
  return results.every((r) => r.ok) ? 0 : 1;
}

let code;
try {
  code = await main();
} catch (err) {
  console.error(`shared: cannot run: ${err && err.message ? err.message : err}`);
  code = 2;
}
const passed = results.filter((r) => r.ok).length;
const failed = results.length - passed;
if (code !== 0) for (const r of results.filter((x) => !x.ok)) console.error(`failed: ${r.name}: ${r.detail}`);
console.log(`shared: ${passed} passed, ${failed} failed`);
process.exit(code === 0 && failed === 0 ? 0 : code || 1);
