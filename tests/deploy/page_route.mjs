#!/usr/bin/env node
// The web viewer behind a router (tests/deploy/routing_test.py drives it): opens the
// deployment's root in headless Chromium and reports, as one JSON line per event on stdout,
// where the page ended up. Commands on stdin, one per line:
//   `moved`  waits until the page is in another session and showing its frames (after its
//            server process drained), then reports it;
//   `quit`   closes the browser.
//
//   node tests/deploy/page_route.mjs http://127.0.0.1:8080/
//
// Needs playwright-core from tests/web (npm ci there) and Chromium at CHROMIUM_PATH
// (default /usr/bin/chromium).

import { createRequire } from 'node:module';
import readline from 'node:readline';

const require = createRequire(new URL('../web/package.json', import.meta.url));
const { chromium } = require('playwright-core');

const URL_ = process.argv[2];
const CHROMIUM = process.env.CHROMIUM_PATH || '/usr/bin/chromium';
const STEP_MS = 1000 * Number(process.env.VOXLIGHT_TIMEOUT_S || 90);

const firstLine = (err) => String((err && err.message) || err).split('\n')[0];
const say = (event) => console.log(JSON.stringify(event));

/** Where the page is: its path, session, share link, and whether frames are on screen. */
const where = (page) =>
  page.evaluate(() => ({
    path: location.pathname,
    session: window.voxlight.session,
    share: window.voxlight.shareLink(),
    connected: window.voxlight.connected,
    framesShown: window.voxlight.framesShown,
  }));

async function main() {
  const browser = await chromium.launch({
    executablePath: CHROMIUM,
    args: ['--headless', '--no-sandbox', '--disable-gpu', '--disable-webgl', '--disable-3d-apis', '--disable-quic', '--no-first-run', '--disable-background-networking', '--disable-component-update', '--disable-sync'],
  });
  try {
    const page = await browser.newPage({ viewport: { width: 320, height: 240 } });
    const errors = [];
    page.on('pageerror', (e) => errors.push(String(e)));
    await page.goto(`${URL_}?iterations=4`);
    // Welcomed by some process: the page moves under that process's route with its session.
    await page.waitForFunction(
      () => /\/p\/\d+\/$/.test(location.pathname) && window.voxlight.connected && window.voxlight.framesShown > 0,
      null,
      { timeout: STEP_MS },
    );
    let last = await where(page);
    say({ event: 'routed', ...last, errors });
    const lines = readline.createInterface({ input: process.stdin });
    for await (const line of lines) {
      if (line.trim() === 'quit') break;
      if (line.trim() === 'moved') {
        // A new session, and a frame shown after the move was asked for.
        const before = { session: last.session, frames: (await where(page)).framesShown };
        try {
          await page.waitForFunction(
            (old) => window.voxlight.connected && window.voxlight.session !== old.session && window.voxlight.framesShown > old.frames,
            before,
            { timeout: STEP_MS },
          );
        } catch (err) {
          const now = await where(page).catch(() => ({}));
          const overlay = await page.evaluate(() => document.getElementById('overlay-text')?.textContent || '').catch(() => '');
          throw new Error(`did not move: ${firstLine(err)}; page ${JSON.stringify(now)}; overlay “${overlay}”; errors ${errors.join(' | ')}`);
        }
        last = await where(page);
        say({ event: 'moved', ...last, errors });
      }
    }
  } finally {
    await browser.close();
  }
}

main().catch((err) => {
  say({ event: 'failed', error: firstLine(err) });
  process.exit(1);
});
