// node browser.mjs JOB.json: opens pages in headless Chromium (Debian's, through playwright-core;
// no browser download) and writes what the tests look at. JOB: {"chromium": path, "pages": [{
//   "url", "width", "height", "scale" (device pixel ratio), "wait": "viewer" | "load",
//   "actions": [{"drag": [dx, dy]} | {"click": selector} | {"wheel": dy}],
//   "screenshot": PNG path, "element": CSS selector to screenshot (default: the page)}]}
// Prints [{ "console": [...], "errors": [...], "attributes": {<html>'s, "viewers": [each viewer element's]},
//   "url": final URL }] as JSON.
import { chromium } from 'playwright-core';
import fs from 'fs';

const job = JSON.parse(fs.readFileSync(process.argv[2], 'utf8'));
const browser = await chromium.launch({
  executablePath: job.chromium,
  args: ['--no-sandbox', '--disable-gpu', '--use-angle=swiftshader', '--enable-unsafe-swiftshader', '--disable-quic',
         '--no-first-run', '--disable-background-networking', '--disable-component-update', '--disable-sync'],
});
const results = [];
try {
  for (const spec of job.pages) {
    const page = await browser.newPage({ viewport: { width: spec.width, height: spec.height },
                                         deviceScaleFactor: spec.scale || 1 });
    const consoleMessages = [], errors = [];
    page.on('console', (m) => consoleMessages.push({ type: m.type(), text: m.text() }));
    page.on('pageerror', (e) => errors.push(String(e && e.message || e)));
    await page.goto(spec.url, { waitUntil: 'load' });
    const selector = spec.wait === 'load' ? null : '[data-viewer]';
    if (selector) {
      await page.waitForFunction(() => {
        const all = [document.documentElement, ...document.querySelectorAll('[data-viewer]')];
        const states = all.map((e) => e.getAttribute('data-viewer')).filter((s) => s !== null);
        return states.length && states.every((s) => s === 'ready' || s === 'error' || s === 'absent');
      }, null, { timeout: 150000 });
    }
    for (const action of spec.actions || []) {
      const box = await page.locator('canvas').first().boundingBox();
      const cx = box.x + box.width / 2, cy = box.y + box.height / 2;
      if (action.drag) {
        await page.mouse.move(cx, cy);
        await page.mouse.down();
        await page.mouse.move(cx + action.drag[0], cy + action.drag[1], { steps: 8 });
        await page.mouse.up();
      } else if (action.wheel) {
        await page.mouse.move(cx, cy);
        await page.mouse.wheel(0, action.wheel);
      } else if (action.click) {
        await page.click(action.click);
      }
      await page.waitForTimeout(400);  // the page writes its address 300 ms after a change
    }
    if (spec.screenshot) {
      const target = spec.element ? page.locator(spec.element).first() : page;
      await target.screenshot({ path: spec.screenshot, fullPage: !spec.element && !!spec.fullPage });
    }
    const attributes = await page.evaluate(() => {
      const out = {};
      for (const a of document.documentElement.attributes) out[a.name] = a.value;
      out.viewers = [...document.querySelectorAll('body [data-viewer]')].map((e) => {
        const v = {};
        for (const a of e.attributes) v[a.name] = a.value;
        return v;
      });
      return out;
    });
    results.push({ console: consoleMessages, errors, attributes, url: page.url() });
    await page.close();
  }
} finally {
  await browser.close();
}
process.stdout.write(JSON.stringify(results));
