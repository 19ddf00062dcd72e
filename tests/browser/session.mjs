// The shared session of the dashboard's browser tests: one `safedice serve` on a free loopback
// port with a fresh data dir, one headless Chromium, the API helpers, the layout and label
// checks, and `state`, where earlier tests leave what later ones use. Imported by every part
// of dashboard.test.mjs; the hooks below open and close the session once for all of them.
import { before, after } from 'node:test';
import { spawn, execFileSync } from 'node:child_process';
import { mkdtempSync, readFileSync, rmSync, mkdirSync } from 'node:fs';
import { tmpdir } from 'node:os';
import { join, resolve, dirname } from 'node:path';
import { fileURLToPath } from 'node:url';
import net from 'node:net';
import { chromium } from 'playwright-core';

export const here = dirname(fileURLToPath(import.meta.url));
export const BIN = resolve(process.env.SAFEDICE_BIN || join(here, '../../target/debug/safedice'));
export const CHROMIUM = process.env.CHROMIUM || execFileSync('sh', ['-c', 'command -v chromium || command -v chromium-browser']).toString().trim();
export const SCREENSHOT_DIR = process.env.SCREENSHOT_DIR ? resolve(process.env.SCREENSHOT_DIR) : null;
// A tiny SafeDICE run: small networks so CI trains it in seconds, long enough to be watched.
export const ITERATIONS = Number(process.env.BROWSER_TEST_ITERATIONS || 6000);
export const TOKEN = 'browser-test-token';

export let work; // temp dir: data dirs, generated datasets, the browser profile
export let servers = [];
export let context;
export let page;
export let base;
export const state = {}; // what earlier tests created, for later ones

export function freePort() {
  return new Promise((resolvePort, reject) => {
    const srv = net.createServer();
    srv.unref();
    srv.on('error', reject);
    srv.listen(0, '127.0.0.1', () => {
      const { port } = srv.address();
      srv.close(() => resolvePort(port));
    });
  });
}

export async function startServer(name, extraArgs = []) {
  const port = await freePort();
  const dataDir = join(work, `data-${name}`);
  const child = spawn(BIN, ['serve', '--bind', `127.0.0.1:${port}`, '--data-dir', dataDir, '--log-format', 'json', ...extraArgs],
    { stdio: ['ignore', 'ignore', 'pipe'], env: { ...process.env, RUST_LOG: 'warn' } });
  let stderr = '';
  child.stderr.on('data', (chunk) => { stderr += chunk; });
  servers.push(child);
  const url = `http://127.0.0.1:${port}`;
  for (let i = 0; i < 300; i += 1) {
    if (child.exitCode !== null) throw new Error(`safedice serve exited with ${child.exitCode}: ${stderr}`);
    try {
      if ((await fetch(`${url}/readyz`)).ok) return url;
    } catch (_) { /* not listening yet */ }
    await new Promise((r) => setTimeout(r, 100));
  }
  throw new Error(`safedice serve did not become ready: ${stderr}`);
}

export async function api(path, options = {}) {
  const response = await fetch(`${base}${path}`, options);
  const body = await response.json();
  return { status: response.status, body };
}

export const post = (path, body) => api(path, {
  method: 'POST', headers: { 'content-type': 'application/json' }, body: JSON.stringify(body),
});

/** Waits for a job to reach a final status (the server's vocabulary says which are) through the
 *  API; returns it. */
export async function finished(id) {
  const { job_statuses: statuses } = (await api('/v1/vocabulary')).body;
  const final = new Set(statuses.filter((s) => s.final).map((s) => s.name));
  for (let i = 0; i < 900; i += 1) {
    const job = (await api(`/v1/jobs/${id}`)).body;
    if (final.has(job.status)) return job;
    await new Promise((r) => setTimeout(r, 200));
  }
  throw new Error(`job ${id} did not finish`);
}

/** Clicks what `trigger` clicks and returns the downloaded file's bytes and name. */
export async function downloaded(trigger) {
  const [file] = await Promise.all([page.waitForEvent('download'), trigger()]);
  const path = await file.path();
  return { name: file.suggestedFilename(), bytes: readFileSync(path) };
}

/** Problems of the current page's layout: anything wider than the window; inputs whose
 *  placeholder does not fit (measured in the input's own font); controls (buttons, fields,
 *  links styled as buttons) not wholly in view without scrolling sideways, or covered by
 *  something else; table cells lying under a sticky actions cell; anything cut by a box that
 *  hides its overflow (not one that scrolls). */
export async function layoutProblems() {
  return page.evaluate(() => {
    const problems = [];
    const root = document.documentElement;
    if (root.scrollWidth > window.innerWidth + 1) problems.push(`page ${root.scrollWidth}px wide in a ${window.innerWidth}px window`);
    const name = (el) => `${el.tagName.toLowerCase()}${el.id ? `#${el.id}` : ''}${el.className && typeof el.className === 'string' ? `.${el.className.trim().split(/\s+/).join('.')}` : ''} “${(el.textContent || el.value || el.placeholder || '').trim().slice(0, 30)}”`;
    const clippers = (el) => {
      const boxes = [];
      for (let a = el.parentElement; a && a !== document.body; a = a.parentElement) {
        const style = getComputedStyle(a);
        if (style.overflowX !== 'visible' || style.overflowY !== 'visible') boxes.push({ el: a, r: a.getBoundingClientRect(), scrolls: /auto|scroll/.test(style.overflowX) });
      }
      return boxes;
    };
    const x0 = window.scrollX; const y0 = window.scrollY;
    for (const el of document.querySelectorAll('button, select, input:not([type="hidden"]), textarea, a.button-link')) {
      if (!el.offsetParent || el.closest('dialog:not([open])')) continue;
      let r = el.getBoundingClientRect();
      if (!r.width) continue;
      const clips = clippers(el);
      if (r.left < -0.5 || r.right > window.innerWidth + 0.5 || clips.some((c) => r.left < c.r.left - 0.5 || r.right > c.r.right + 0.5)) {
        problems.push(`${name(el)} is cut or out of view sideways (${Math.round(r.left)}-${Math.round(r.right)} in ${window.innerWidth}px)`);
        continue;
      }
      // In a box that scrolls vertically and out of its view: nothing to see on the page now.
      if (clips.some((c) => r.top < c.r.top - 0.5 || r.bottom > c.r.bottom + 0.5)) continue;
      window.scrollTo(x0, Math.max(0, window.scrollY + r.top - window.innerHeight / 2));
      r = el.getBoundingClientRect();
      const hit = document.elementFromPoint(r.left + r.width / 2, r.top + r.height / 2);
      if (hit && hit !== el && !el.contains(hit) && !hit.contains(el) && hit.control !== el) problems.push(`${name(el)} is covered by ${name(hit)}`);
    }
    window.scrollTo(x0, y0);
    for (const cell of document.querySelectorAll('td, th')) {
      if (!cell.offsetParent || getComputedStyle(cell).position !== 'sticky') continue;
      const s = cell.getBoundingClientRect();
      const under = [...cell.parentElement.children].filter((other) => {
        const r = other.getBoundingClientRect();
        return other !== cell && r.width > 0 && r.right > s.left + 0.5 && r.left < s.right - 0.5;
      });
      if (under.length) problems.push(`${name(under[0])} lies under the sticky cell ${name(cell)} in #${cell.closest('table').id}`);
    }
    for (const el of document.querySelectorAll('th, td, label, p, h1, h2, dd, dt, a, strong, span')) {
      if (!el.offsetParent || el.closest('svg, .u-wrap, .u-legend, dialog:not([open])')) continue;
      const r = el.getBoundingClientRect();
      if (!r.width) continue;
      const cut = clippers(el).find((c) => !c.scrolls && (r.left < c.r.left - 1 || r.right > c.r.right + 1));
      if (cut) problems.push(`${name(el)} is cut by ${name(cut.el)} (overflow hidden)`);
    }
    const ctx = document.createElement('canvas').getContext('2d');
    for (const input of document.querySelectorAll('input[placeholder], textarea[placeholder]')) {
      if (!input.offsetParent || input.tagName === 'TEXTAREA') continue;
      const style = getComputedStyle(input);
      ctx.font = `${style.fontWeight} ${style.fontSize} ${style.fontFamily}`;
      const room = input.clientWidth - parseFloat(style.paddingLeft) - parseFloat(style.paddingRight);
      const need = ctx.measureText(input.placeholder).width;
      if (need > room + 0.5) problems.push(`#${input.id} placeholder “${input.placeholder}” needs ${need.toFixed(0)}px, has ${room.toFixed(0)}px`);
    }
    return problems;
  });
}

/** Texts of an SVG chart that collide: point labels overlapping each other or a point other than
 *  their own, and any text sticking out of the SVG (as the page draws them, in page pixels). */
export async function labelProblems(selector) {
  return page.evaluate((sel) => {
    const problems = [];
    for (const svg of document.querySelectorAll(sel)) {
      const frame = svg.getBoundingClientRect();
      const boxes = [...svg.querySelectorAll('text')].map((t) => ({ text: t.textContent, label: t.classList.contains('point-label'),
        own: t.closest('g.point')?.dataset.label, r: t.getBoundingClientRect() }));
      const dots = [...svg.querySelectorAll('g.point')].map((g) => ({ label: g.dataset.label, r: g.querySelector('circle').getBoundingClientRect() }));
      const meet = (a, b) => a.left < b.right - 0.5 && b.left < a.right - 0.5 && a.top < b.bottom - 0.5 && b.top < a.bottom - 0.5;
      for (const b of boxes) {
        if (b.r.left < frame.left - 0.5 || b.r.right > frame.right + 0.5 || b.r.top < frame.top - 0.5 || b.r.bottom > frame.bottom + 0.5) problems.push(`“${b.text}” sticks out of the chart`);
      }
      const labels = boxes.filter((b) => b.label);
      labels.forEach((a, i) => labels.slice(i + 1).forEach((b) => { if (meet(a.r, b.r)) problems.push(`“${a.text}” overlaps “${b.text}”`); }));
      for (const l of labels) for (const d of dots) if (d.label !== l.own && meet(l.r, d.r)) problems.push(`“${l.text}” covers the point of ${d.label}`);
      // Shortened labels stay told apart, and each is made of pieces of its own point's name.
      const texts = labels.map((l) => l.text);
      if (new Set(texts).size !== new Set(labels.map((l) => l.own)).size) problems.push(`labels not told apart: ${JSON.stringify(texts)}`);
      for (const l of labels) {
        let at = 0;
        for (const piece of l.text.split('…').map((p) => p.trim()).filter(Boolean)) {
          const found = l.own.indexOf(piece, at);
          if (found < 0) { problems.push(`“${l.text}” is not a shortening of “${l.own}”`); break; }
          at = found + piece.length;
        }
      }
    }
    return problems;
  }, selector);
}

export async function screenshot(name) {
  if (!SCREENSHOT_DIR) return;
  mkdirSync(SCREENSHOT_DIR, { recursive: true });
  await page.screenshot({ path: join(SCREENSHOT_DIR, `${name}.png`), fullPage: true });
}

before(async () => {
  work = mkdtempSync(join(tmpdir(), 'safedice-browser-'));
  execFileSync(BIN, ['datagen', '--env', 'six-rooms', '--preferred', '40', '--non-preferred', '40', '--labeled', '15',
    '--format', 'jsonl', '--out', join(work, 'demo')]);
  base = await startServer('main');
  context = await chromium.launchPersistentContext(join(work, 'profile'), {
    executablePath: CHROMIUM,
    headless: true,
    chromiumSandbox: false, // --no-sandbox: CI runs as root in a container
    args: ['--disable-gpu', '--disable-quic', '--no-first-run', '--disable-background-networking',
      '--disable-component-update', '--disable-sync'],
    viewport: { width: 1360, height: 900 },
  });
  page = context.pages()[0] || await context.newPage();
  page.on('pageerror', (e) => { state.pageErrors = [...(state.pageErrors || []), String(e)]; });
});

after(async () => {
  if (context) await context.close();
  for (const child of servers) {
    if (child.exitCode === null) {
      child.kill('SIGTERM');
      await new Promise((r) => { child.once('exit', r); setTimeout(r, 5000); });
    }
  }
  if (work) rmSync(work, { recursive: true, force: true });
});


/** Rows of `table` whose last cell (Cancel, Delete, Promote…) is not wholly inside the window. */
export async function actionsOutOfView(table) {
  return page.$$eval(`${table} tbody tr`, (rows) => rows.map((row) => row.lastElementChild.getBoundingClientRect())
    .filter((r) => r.width > 0 && (r.left < -0.5 || r.right > window.innerWidth + 0.5))
    .map((r) => `${Math.round(r.left)}-${Math.round(r.right)} in ${window.innerWidth}`));
}

/** `safedice demo --serve` on a free port with its own data dir (short runs: the test is about
 *  what the pages show, not how well the policies do); resolves once both of the demo's
 *  evaluations have succeeded, with the server's address. */
export async function startDemo() {
  const port = await freePort();
  const child = spawn(BIN, ['demo', '--serve', '--bind', `127.0.0.1:${port}`, '--data-dir', join(work, 'data-demo'),
    '--iterations', '300', '--episodes', '50'], { stdio: ['ignore', 'ignore', 'pipe'], env: { ...process.env, RUST_LOG: 'warn' } });
  let stderr = '';
  child.stderr.on('data', (chunk) => { stderr += chunk; });
  servers.push(child);
  const url = `http://127.0.0.1:${port}`;
  for (let i = 0; i < 1800; i += 1) {
    if (child.exitCode !== null) throw new Error(`safedice demo --serve exited with ${child.exitCode}: ${stderr}`);
    try {
      const evaluations = await (await fetch(`${url}/v1/evaluations`)).json();
      if (evaluations.items.filter((e) => e.status === 'succeeded').length === 2) return url;
    } catch (_) { /* not listening yet */ }
    await new Promise((r) => setTimeout(r, 200));
  }
  throw new Error(`the demo did not finish: ${stderr}`);
}

/** A number as a page shows it ("12.34", "1,234", "1.20e-4") and the tolerance its shown
 *  precision allows against `exact`: half a unit of the last shown digit, or of the `sig`-th
 *  significant digit where the page rounds to significant digits. */
export function closeToShown(text, exact, sig) {
  const t = text.replace(/,/g, '').trim();
  const [mantissa, exponent] = t.split('e');
  const decimals = (mantissa.split('.')[1] || '').length;
  const byDecimals = 0.5 * 10 ** (Number(exponent || 0) - decimals);
  const bySignificant = exact === 0 ? 0 : 0.5 * 10 ** (Math.floor(Math.log10(Math.abs(exact))) - (sig - 1));
  const tolerance = Math.max(byDecimals, bySignificant) * (1 + 1e-9) + 1e-12;
  return Math.abs(Number(t) - exact) <= tolerance;
}

/** Mean and standard error (sample standard deviation / √n; null for one value). */
export function meanSe(values) {
  const n = values.length;
  const mean = values.reduce((a, b) => a + b, 0) / n;
  const se = n > 1 ? Math.sqrt(values.reduce((a, v) => a + (v - mean) ** 2, 0) / (n - 1) / n) : null;
  return { mean, se, n };
}
