// ceiling: one ordered session against one server and one browser: the later pages (policy, models, experiments, Compare) use the datasets, trained job and policy that the earlier tests made, so a split would train them again per file
// Browser tests of the dashboard: headless Chromium (Debian's `chromium`, driven by
// playwright-core) against the real `safedice serve` binary on a free loopback port with a
// fresh data dir. The tests run in order and share one server: upload, submit, watch, chart,
// act, compare. Run: `npm ci && npm test` here, after `cargo build` (see README, Dashboard).
//
// Environment: SAFEDICE_BIN (default ../../target/debug/safedice), CHROMIUM (default: chromium
// on PATH), SCREENSHOT_DIR (when set, PNGs of the main pages are written there).

import { test, before, after } from 'node:test';
import assert from 'node:assert/strict';
import { spawn, execFileSync } from 'node:child_process';
import { mkdtempSync, readFileSync, rmSync, mkdirSync, writeFileSync } from 'node:fs';
import { tmpdir } from 'node:os';
import { join, resolve, dirname } from 'node:path';
import { fileURLToPath } from 'node:url';
import net from 'node:net';
import { chromium } from 'playwright-core';

const here = dirname(fileURLToPath(import.meta.url));
const BIN = resolve(process.env.SAFEDICE_BIN || join(here, '../../target/debug/safedice'));
const CHROMIUM = process.env.CHROMIUM || execFileSync('sh', ['-c', 'command -v chromium || command -v chromium-browser']).toString().trim();
const SCREENSHOT_DIR = process.env.SCREENSHOT_DIR ? resolve(process.env.SCREENSHOT_DIR) : null;
// A tiny SafeDICE run: small networks so CI trains it in seconds, long enough to be watched.
const ITERATIONS = Number(process.env.BROWSER_TEST_ITERATIONS || 6000);
const TOKEN = 'browser-test-token';

let work; // temp dir: data dirs, generated datasets, the browser profile
let servers = [];
let context;
let page;
let base;
const state = {}; // what earlier tests created, for later ones

function freePort() {
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

async function startServer(name, extraArgs = []) {
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

async function api(path, options = {}) {
  const response = await fetch(`${base}${path}`, options);
  const body = await response.json();
  return { status: response.status, body };
}

const post = (path, body) => api(path, {
  method: 'POST', headers: { 'content-type': 'application/json' }, body: JSON.stringify(body),
});

/** Waits for a job to finish through the API; returns it. */
async function finished(id) {
  for (let i = 0; i < 900; i += 1) {
    const job = (await api(`/v1/jobs/${id}`)).body;
    if (['succeeded', 'failed', 'cancelled'].includes(job.status)) return job;
    await new Promise((r) => setTimeout(r, 200));
  }
  throw new Error(`job ${id} did not finish`);
}

/** Clicks what `trigger` clicks and returns the downloaded file's bytes and name. */
async function downloaded(trigger) {
  const [file] = await Promise.all([page.waitForEvent('download'), trigger()]);
  const path = await file.path();
  return { name: file.suggestedFilename(), bytes: readFileSync(path) };
}

/** Problems of the current page's layout: anything wider than the window; inputs whose
 *  placeholder does not fit (measured in the input's own font); controls (buttons, fields,
 *  links styled as buttons) not wholly in view without scrolling sideways, or covered by
 *  something else; table cells lying under a sticky actions cell; anything cut by a box that
 *  hides its overflow (not one that scrolls). */
async function layoutProblems() {
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
async function labelProblems(selector) {
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

async function screenshot(name) {
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

test('the vendored chart library is the npm package, byte for byte', () => {
  for (const file of ['uPlot.iife.min.js', 'uPlot.min.css']) {
    const vendored = readFileSync(join(here, '../../web/vendor', file));
    assert.ok(vendored.equals(readFileSync(join(here, 'node_modules/uplot/dist', file))), file);
  }
});

test('a bad upload dropped on the datasets page shows the server’s validation error verbatim', async () => {
  // Line 2 has a 3-wide observation after a 2-wide one: a ragged dataset.
  const bad = '{"episode": 0, "obs": [0, 0], "action": [0.1]}\n{"episode": 0, "obs": [0, 0, 1], "action": [0.2]}\n';
  const form = new FormData();
  form.append('file', new Blob([bad]), 'ragged.jsonl');
  const direct = await api('/v1/datasets', { method: 'POST', body: form });
  assert.equal(direct.status, 422);
  const serverMessage = direct.body.error.message;

  await page.goto(`${base}/#/datasets`);
  await page.waitForSelector('#datasets-list .empty');
  const dataTransfer = await page.evaluateHandle((text) => {
    const dt = new DataTransfer();
    dt.items.add(new File([text], 'ragged.jsonl', { type: 'application/x-ndjson' }));
    return dt;
  }, bad);
  await page.dispatchEvent('#dropzone', 'drop', { dataTransfer });
  const shown = await page.waitForSelector('.upload-error .error-message');
  assert.equal(await shown.textContent(), serverMessage);
  assert.equal(await page.textContent('.upload-error .error-code'), direct.body.error.code);
  // Nothing was stored, and the page says what to do about the empty list.
  assert.equal((await api('/v1/datasets')).body.total, 0);
  assert.match(await page.textContent('#datasets-list'), /No datasets yet/);
});

test('datasets are uploaded with their role and listed with it and their statistics', async () => {
  await page.goto(`${base}/#/datasets`);
  for (const [file, name, role] of [['unlabeled.jsonl', 'six-rooms unlabeled', 'unlabeled'], ['non_preferred.jsonl', 'six-rooms non-preferred', 'non_preferred']]) {
    await page.fill('#upload-name', name);
    await page.selectOption('#upload-role', role);
    await page.setInputFiles('#upload-file', join(work, 'demo', file));
    await page.waitForSelector(`#upload-ok:has-text("${name}")`);
  }
  await page.waitForFunction(() => document.querySelectorAll('#datasets-table tbody tr').length === 2);
  const { body } = await api('/v1/datasets');
  assert.equal(body.total, 2);
  for (const dataset of body.items) {
    const row = page.locator(`#datasets-table tr[data-id="${dataset.id}"]`);
    const cells = await row.locator('td').allTextContents();
    assert.match(cells[0], new RegExp(dataset.name));
    assert.match(cells[1], dataset.role === 'unlabeled' ? /^unlabeled/ : /^non-preferred/);
    assert.equal(cells[3], dataset.transitions.toLocaleString('en-US'));
    assert.equal(cells[4], dataset.episodes.toLocaleString('en-US'));
    if (dataset.stats.episode_return) assert.match(cells[7], /±/);
  }
  state.unlabeled = body.items.find((d) => d.name === 'six-rooms unlabeled');
  state.nonPreferred = body.items.find((d) => d.name === 'six-rooms non-preferred');
  assert.equal(state.unlabeled.role, 'unlabeled');
  assert.equal(state.nonPreferred.role, 'non_preferred');
  await screenshot('datasets');
});

test('a dataset can be previewed, downloaded and deleted from its row', async () => {
  await page.goto(`${base}/#/datasets`);
  const row = `#datasets-table tr[data-id="${state.unlabeled.id}"]`;
  await page.click(`${row} button.preview`);
  await page.waitForSelector('#preview-episodes');
  const preview = (await api(`/v1/datasets/${state.unlabeled.id}/preview?rows=20&episodes=20`)).body;
  const episodeRows = await page.$$eval('#preview-episodes tbody tr', (trs) => trs.map((tr) => [...tr.cells].map((c) => c.textContent)));
  assert.equal(episodeRows.length, preview.episodes.length);
  assert.equal(episodeRows[0][1], String(preview.episodes[0].length));
  assert.equal(await page.$$eval('#preview-transitions tbody tr', (trs) => trs.length), preview.transitions.length);

  const npz = await downloaded(() => page.click(`${row} button.download`));
  const direct = Buffer.from(await (await fetch(`${base}/v1/datasets/${state.unlabeled.id}/download`)).arrayBuffer());
  assert.ok(npz.bytes.equals(direct), 'the page saves what the API serves');
  assert.match(npz.name, /\.npz$/);

  // A third upload, deleted with the two-step button; nothing of it is left.
  await page.selectOption('#upload-role', '');
  await page.fill('#upload-name', 'scratch');
  const scratchFile = join(work, 'scratch.jsonl');
  writeFileSync(scratchFile, '{"episode": 0, "obs": [0, 0], "action": [0.1]}\n{"episode": 0, "obs": [0, 1], "action": [0.2], "terminal": true}\n');
  await page.setInputFiles('#upload-file', scratchFile);
  await page.waitForSelector('#upload-ok:has-text("scratch")');
  const scratch = (await api('/v1/datasets')).body.items.find((d) => d.name === 'scratch');
  assert.equal(scratch.role ?? null, null);
  const scratchRow = `#datasets-table tr[data-id="${scratch.id}"]`;
  await page.waitForSelector(scratchRow);
  assert.equal(await page.textContent(`${scratchRow} td.role`), 'not given');
  await page.click(`${scratchRow} button.delete`);
  assert.match(await page.textContent(`${scratchRow} button.delete`), /Really/);
  await page.click(`${scratchRow} button.delete`);
  await page.waitForSelector('#dataset-deleted');
  await page.waitForSelector(scratchRow, { state: 'detached' });
  assert.equal((await api(`/v1/datasets/${scratch.id}`)).status, 404);
});

test('the job form defaults the datasets by role, estimates the run and creates the job with its labels', async () => {
  await page.goto(`${base}/#/jobs`);
  await page.waitForSelector('#job-form');
  // The newest upload is the non-preferred set; the unlabeled select still defaults to Dᵁ and
  // does not offer the non-preferred set at all.
  assert.equal(await page.inputValue('#job-unlabeled'), state.unlabeled.id);
  assert.equal(await page.inputValue('#job-non-preferred'), state.nonPreferred.id);
  const unlabeledChoices = await page.$$eval('#job-unlabeled option', (os) => os.map((o) => o.value));
  assert.ok(!unlabeledChoices.includes(state.nonPreferred.id));
  // BC reads no Dᴺ: its select is disabled while BC is chosen (nothing of it is sent).
  await page.selectOption('#job-algorithm', 'bc');
  assert.equal(await page.isDisabled('#job-non-preferred'), true);
  // Empty iterations: the preset's run, said in steps before anything is queued.
  await page.selectOption('#job-algorithm', 'safedice');
  assert.equal(await page.isDisabled('#job-non-preferred'), false);
  // The service preset trains SafeDICE's discriminator for as many steps as the iterations.
  assert.match(await page.textContent('#job-estimate'), /^200,000 steps = 100,000 discriminator pretraining \+ 100,000 policy iterations: no finished job/);
  assert.equal(await page.getAttribute('#job-discriminator_iterations', 'placeholder'), 'iterations');
  await page.fill('#job-name', 'six-rooms safedice small');
  await page.fill('#job-tags', 'browser, six-rooms');
  await page.fill('#job-notes', 'queued from the dashboard test');
  await page.fill('#job-iterations', String(ITERATIONS));
  assert.match(await page.textContent('#job-estimate'), new RegExp(`^${(ITERATIONS * 2).toLocaleString('en-US')} steps = ${ITERATIONS.toLocaleString('en-US')} discriminator pretraining`));
  await page.fill('#job-seed', '7');
  await page.fill('#job-hidden_sizes', '32, 32');
  await page.fill('#job-batch_size', '64');
  await page.fill('#job-log_every', '25');
  // The six-rooms data fit the six-rooms environment, which the form offers for evaluation.
  assert.equal(await page.inputValue('#job-eval-env'), 'six-rooms');
  await page.fill('#job-eval-every', String(ITERATIONS / 4));
  await page.fill('#job-eval-episodes', '100');
  await page.click('#job-submit');
  await page.waitForSelector('#job-created');

  const { body } = await api('/v1/jobs');
  assert.equal(body.total, 1);
  const job = body.items[0];
  assert.equal(job.name, 'six-rooms safedice small');
  assert.deepEqual(job.tags, ['browser', 'six-rooms']);
  assert.equal(job.notes, 'queued from the dashboard test');
  assert.equal(job.algorithm, 'safedice');
  assert.equal(job.unlabeled_dataset, state.unlabeled.id);
  assert.equal(job.non_preferred_dataset, state.nonPreferred.id);
  assert.equal(job.config.iterations, ITERATIONS);
  assert.equal(job.config.seed, 7);
  assert.deepEqual(job.config.hidden_sizes, [32, 32]);
  assert.equal(job.config.batch_size, 64);
  assert.equal(job.runner.log_every, 25);
  assert.deepEqual(job.eval, { env: 'six-rooms', every: ITERATIONS / 4, episodes: 100, seed: 0, deterministic: false });
  // The notice names the job and explains its step count with the server's total.
  assert.ok(await page.isVisible(`#job-created a[href="#/jobs/${job.id}"]:has-text("six-rooms safedice small")`));
  assert.match(await page.textContent('#job-created'), new RegExp(`${job.progress.total.toLocaleString('en-US')} steps = ${(job.progress.total - ITERATIONS).toLocaleString('en-US')} discriminator pretraining \\+ ${ITERATIONS.toLocaleString('en-US')} policy iterations`));
  state.job = job;
});

test('the job list follows jobs while they train, without reloading the page', async () => {
  // Still on the jobs page the form left us on. A marker on window survives only without a reload.
  await page.evaluate(() => { window.__sameDocument = true; });
  // The submitted job's row follows it to the end.
  const row = `#jobs-table tr[data-id="${state.job.id}"]`;
  await page.waitForSelector(`${row}:is([data-status="succeeded"], [data-status="failed"], [data-status="cancelled"])`, { timeout: 180_000 });
  assert.equal(await page.getAttribute(row, 'data-status'), 'succeeded');
  const total = state.job.progress.total;
  assert.equal(await page.textContent(`${row} .step`), `${total.toLocaleString('en-US')} / ${total.toLocaleString('en-US')}`);
  assert.equal(await page.getAttribute(`${row} .progress`, 'aria-valuenow'), '100');
  assert.equal(await page.textContent(`${row} .job-name`), 'six-rooms safedice small');
  assert.deepEqual(await page.$$eval(`${row} .tag`, (ts) => ts.map((t) => t.textContent)), ['browser', 'six-rooms']);

  // A finished job of this shape now times the form's estimate.
  await page.reload();
  await page.waitForSelector('#job-form');
  await page.evaluate(() => { window.__sameDocument = true; });
  await page.selectOption('#job-algorithm', 'safedice');
  await page.fill('#job-hidden_sizes', '32, 32');
  await page.fill('#job-batch_size', '64');
  assert.match(await page.textContent('#job-estimate'), /: about .+ at the pace of “six-rooms safedice small”/);

  // Whether that job was ever seen running depends on the machine's speed (a fast build trains
  // it between two refreshes), so the running rows are watched on a job of the API's maximum
  // length, which no machine finishes while the test watches; its Cancel button then stops it.
  const created = await post('/v1/jobs', { algorithm: 'bc', unlabeled_dataset: state.unlabeled.id,
    config: { iterations: 100_000_000, hidden_sizes: [32, 32], batch_size: 64, seed: 2 } });
  assert.equal(created.status, 201);
  const endless = `#jobs-table tr[data-id="${created.body.id}"]`;
  const seenRunningSteps = new Set();
  const deadline = Date.now() + 120_000;
  while (seenRunningSteps.size < 2 && Date.now() < deadline) {
    const status = await page.getAttribute(endless, 'data-status').catch(() => null);
    if (status === 'running') seenRunningSteps.add(await page.textContent(`${endless} .step`));
    else assert.ok(status === null || status === 'queued', `endless job ${status}`);
    await page.waitForTimeout(150);
  }
  assert.ok(seenRunningSteps.size >= 2, `saw the running job at steps ${[...seenRunningSteps]}`);
  await screenshot('jobs');

  // While it runs, its dataset cannot be deleted: the datasets page shows the server's 409.
  await page.goto(`${base}/#/datasets`);
  const datasetRow = `#datasets-table tr[data-id="${state.unlabeled.id}"]`;
  await page.click(`${datasetRow} button.delete`);
  await page.click(`${datasetRow} button.delete`);
  assert.equal(await (await page.waitForSelector('.dataset-delete-error .error-code')).textContent(), 'dataset_in_use');
  assert.equal((await api(`/v1/datasets/${state.unlabeled.id}`)).status, 200);

  await page.goto(`${base}/#/jobs`);
  await page.click(`${endless} button.cancel`);
  await page.waitForSelector(`${endless}[data-status="cancelled"]`);
  assert.equal((await api(`/v1/jobs/${created.body.id}`)).body.status, 'cancelled');
  state.endless = created.body;
});

test('the job list pages through jobs with stable pages and filters by name, tag and status', async () => {
  // 26 more jobs, cancelled while queued (they never train): 28 jobs in all, two pages.
  for (let i = 0; i < 26; i += 1) {
    const created = await post('/v1/jobs', { algorithm: 'bc', unlabeled_dataset: state.unlabeled.id, name: `filler ${i}`,
      tags: i % 2 ? ['odd'] : ['even'], config: { iterations: 100_000_000, hidden_sizes: [8], seed: i } });
    assert.equal(created.status, 201);
    assert.equal((await post(`/v1/jobs/${created.body.id}/cancel`, {})).status < 300, true);
  }
  for (;;) {
    const { body } = await api('/v1/jobs?status=running');
    if (!body.total) break;
    await new Promise((r) => setTimeout(r, 200));
  }
  await page.goto(`${base}/#/jobs`);
  await page.waitForSelector('#jobs-pager .pager-range:has-text("1–25 of 28")');
  const firstPage = await page.$$eval('#jobs-table tbody tr', (trs) => trs.map((tr) => tr.dataset.id));
  assert.equal(firstPage.length, 25);
  await page.click('#jobs-pager .pager-older');
  await page.waitForSelector('#jobs-pager .pager-range:has-text("26–28 of 28")');
  const secondPage = await page.$$eval('#jobs-table tbody tr', (trs) => trs.map((tr) => tr.dataset.id));
  assert.equal(secondPage.length, 3);
  assert.ok(secondPage.includes(state.job.id) && !firstPage.includes(state.job.id));
  // A job that arrives now goes to page one; page two, refreshed every second, stays the same.
  const newest = await post('/v1/jobs', { algorithm: 'bc', unlabeled_dataset: state.unlabeled.id, config: { iterations: 100_000_000, hidden_sizes: [8] } });
  await post(`/v1/jobs/${newest.body.id}/cancel`, {});
  await page.waitForSelector('#jobs-pager .pager-range:has-text("26–28 of 29")');
  assert.deepEqual(await page.$$eval('#jobs-table tbody tr', (trs) => trs.map((tr) => tr.dataset.id)), secondPage);
  await page.click('#jobs-pager .pager-newer');
  await page.waitForSelector('#jobs-pager .pager-range:has-text("1–25 of 29")');

  // Filters: a tag, a name search, a status; each list is what the API lists for it.
  await page.fill('#jobs-tag', 'odd');
  await page.click('#jobs-filters button');
  await page.waitForSelector('#jobs-pager .pager-range:has-text("1–13 of 13")').catch(() => {});
  await page.waitForFunction(() => document.querySelectorAll('#jobs-table tbody tr').length === 13);
  await page.fill('#jobs-tag', '');
  await page.fill('#jobs-search', 'SMALL');
  await page.click('#jobs-filters button');
  await page.waitForFunction(() => document.querySelectorAll('#jobs-table tbody tr').length === 1);
  assert.equal(await page.getAttribute('#jobs-table tbody tr', 'data-id'), state.job.id);
  await page.fill('#jobs-search', '');
  // The status filter offers the server's statuses (GET /v1/vocabulary), each with its meaning.
  const vocabulary = (await api('/v1/vocabulary')).body;
  const offered = await page.$$eval('#jobs-status option', (os) => os.map((o) => [o.value, o.title]));
  assert.deepEqual(offered, [['', ''], ...vocabulary.job_statuses.map((s) => [s.name, s.meaning])]);
  assert.ok(offered.some(([value]) => value === 'discarded'));
  await page.selectOption('#jobs-status', 'succeeded');
  await page.waitForFunction(() => document.querySelectorAll('#jobs-table tbody tr').length === 1);
  await page.fill('#jobs-search', 'no such job');
  await page.click('#jobs-filters button');
  await page.waitForSelector('#jobs-list .empty');
});

test('the job page charts the training metrics in the browser, with values on hover and a log scale', async () => {
  await page.goto(`${base}/#/jobs/${state.job.id}`);
  await page.waitForSelector('#charts .chart-box[data-chart="losses"] .u-over');
  const metrics = (await api(`/v1/jobs/${state.job.id}/metrics?max_points=1000`)).body.rows;
  const pointsOf = (name) => metrics.filter((r) => r.name === name);
  const charted = await page.$$eval('#charts .chart-box', (boxes) => boxes.map((b) => ({
    key: b.dataset.chart, series: JSON.parse(b.dataset.series),
    // What uPlot draws: per series, the non-empty values.
    drawn: b.uplot.data.slice(1).map((column) => column.filter((v) => v !== null)),
  })));
  assert.ok(charted.length >= 3, JSON.stringify(charted.map((c) => c.key)));
  for (const chart of charted) {
    chart.series.forEach(([name, count], i) => {
      assert.equal(count, pointsOf(name).length, name);
      assert.deepEqual(chart.drawn[i], pointsOf(name).map((r) => r.value), name);
    });
  }
  const losses = charted.find((c) => c.key === 'losses');
  assert.ok(losses.series.length >= 2 && losses.series.every(([, n]) => n > 10), JSON.stringify(losses.series));
  assert.equal(await page.$eval('.chart-box[data-chart="losses"]', (b) => b.uplot.axes[0].label), 'training step (all phases)');

  // Hovering the plot shows the values at the cursor in the legend.
  const over = await page.$('.chart-box[data-chart="losses"] .u-over');
  await over.scrollIntoViewIfNeeded();
  const bounds = await over.boundingBox();
  await page.mouse.move(bounds.x + bounds.width * 0.6, bounds.y + bounds.height / 2, { steps: 5 });
  await page.waitForFunction(() => document.querySelector('.chart-box[data-chart="losses"] .u-legend .u-series .u-value').textContent !== '—');
  const legend = await page.$$eval('.chart-box[data-chart="losses"] .u-legend .u-series .u-value', (vs) => vs.map((v) => v.textContent));
  assert.ok(Number(legend[0].replace(/,/g, '')) > 0, `step under the cursor: ${legend}`);
  assert.ok(legend.slice(1).some((v) => Number.isFinite(Number(v))), `values under the cursor: ${legend}`);

  // A log scale where every value is positive; switched off where one is not.
  const positive = await page.$$eval('#charts .chart-box', (boxes) => boxes.filter((b) => !b.querySelector('.log-scale').disabled).map((b) => b.dataset.chart));
  assert.ok(positive.length >= 1, 'some chart can be drawn on a log scale');
  await page.check(`.chart-box[data-chart="${positive[0]}"] .log-scale`);
  assert.equal(await page.$eval(`.chart-box[data-chart="${positive[0]}"]`, (b) => b.uplot.scales.y.distr), 3);
  for (const chart of charted) {
    const hasNonPositive = chart.drawn.some((values) => values.some((v) => v <= 0));
    if (hasNonPositive) assert.equal(await page.$eval(`.chart-box[data-chart="${chart.key}"] .log-scale`, (c) => c.disabled), true, chart.key);
  }
  // The discriminator's outputs are probabilities, on their own [0, 1] axis; its early-stopping
  // steps are no point on that axis but a sentence (the -1 of "not stopped" in words).
  const discriminator = charted.find((c) => c.key === 'discriminator');
  assert.ok(discriminator, JSON.stringify(charted.map((c) => c.key)));
  assert.ok(discriminator.series.every(([n]) => n.startsWith('discriminator_prob_')), JSON.stringify(discriminator.series));
  assert.deepEqual(await page.$eval('.chart-box[data-chart="discriminator"]', (b) => [b.uplot.scales.y.min, b.uplot.scales.y.max]), [0, 1]);
  const chartedNames = charted.flatMap((c) => c.series.map(([n]) => n));
  assert.ok(!chartedNames.includes('discriminator_best_step') && !chartedNames.includes('discriminator_stopped_at'), JSON.stringify(chartedNames));
  const stoppedAt = pointsOf('discriminator_stopped_at').at(-1).value;
  const bestStep = pointsOf('discriminator_best_step').at(-1).value;
  const stopping = await page.textContent('#discriminator-stopping');
  assert.match(stopping, stoppedAt < 0 ? /did not stop early \(trained all [\d,]+ steps\)/ : new RegExp(`stopped early at discriminator step ${stoppedAt.toLocaleString('en-US')} of`));
  assert.match(stopping, new RegExp(`best at step ${bestStep.toLocaleString('en-US')}, whose weights it kept`));
  assert.doesNotMatch(stopping, /-1/);
  const alpha = charted.find((c) => c.key === 'alpha');
  assert.ok(alpha.series[0][1] >= 1);
  assert.match(await page.textContent('#job-config'), new RegExp(`iterations\\s*${ITERATIONS}`));
  assert.match(await page.textContent('#step-plan'), /discriminator pretraining \+ [\d,]+ policy iterations/);

  // The evaluation section: the paper's metrics at policy steps ITERATIONS/4, /2, 3/4 and the end.
  await page.waitForSelector('#eval-charts .chart-box[data-chart="eval-cost"] .u-over');
  const evalSeries = await page.$$eval('#eval-charts .chart-box', (boxes) => boxes.flatMap((b) => JSON.parse(b.dataset.series)));
  assert.equal(pointsOf('eval/average_cost').length, 4);
  assert.deepEqual(evalSeries.map(([n]) => n).sort(), ['CVaR 10%', 'CVaR 20%', 'CVaR 50%', 'CVaR 5%', 'eval/average_cost',
    'eval/cost_violation_ratio', 'eval/normalized_return'].sort());
  assert.ok(evalSeries.every(([, n]) => n === 4), JSON.stringify(evalSeries));
  const lastCost = pointsOf('eval/average_cost').at(-1).value;
  const latestCost = page.locator('#eval-latest tr', { hasText: 'eval/average_cost' }).locator('td.num');
  assert.equal(Number(await latestCost.textContent()), Number(lastCost.toPrecision(4)));

  // The worker's log, and every metric as CSV (the API's file).
  await page.waitForSelector('#job-log .log-line');
  const log = (await api(`/v1/jobs/${state.job.id}/logs`)).body;
  assert.deepEqual(await page.$$eval('#job-log .log-line', (ls) => ls.map((l) => Number(l.dataset.seq))), log.map((l) => l.seq));
  assert.match(await page.textContent('#job-log'), /claimed by worker/);
  const csv = await downloaded(() => page.click('#metrics-csv'));
  const direct = await (await fetch(`${base}/v1/jobs/${state.job.id}/metrics.csv`)).text();
  assert.equal(csv.bytes.toString(), direct);
  assert.match(await page.textContent('#job-worker'), /-/);
  assert.equal(await page.textContent('#job-attempts'), '1 of 3');
  assert.equal(await page.locator('#lease-expired, #retry-at').count(), 0);
  await screenshot('job');
});

test('a job is renamed, retagged and deleted from its page', async () => {
  await page.goto(`${base}/#/jobs/${state.job.id}`);
  await page.waitForSelector('#edit-form');
  await page.fill('#edit-name', 'renamed in the browser');
  await page.fill('#edit-tags', 'browser, kept');
  await page.click('#edit-save');
  await page.waitForSelector('#edit-ok');
  const job = (await api(`/v1/jobs/${state.job.id}`)).body;
  assert.equal(job.name, 'renamed in the browser');
  assert.deepEqual(job.tags, ['browser', 'kept']);
  assert.equal(await page.textContent('h1 span'), 'renamed in the browser');
  // A bad label is refused with the server's message, and nothing changes.
  await page.fill('#edit-tags', 'has space');
  await page.click('#edit-save');
  assert.equal(await (await page.waitForSelector('.edit-error .error-code')).textContent(), 'invalid_labels');
  assert.deepEqual((await api(`/v1/jobs/${state.job.id}`)).body.tags, ['browser', 'kept']);
  state.job = job;

  // The cancelled endless job is deleted with the two-step button; the page goes to the list.
  await page.goto(`${base}/#/jobs/${state.endless.id}`);
  await page.waitForSelector('#job-delete');
  // A job without an eval block shows no stray "null" anywhere.
  await page.waitForSelector('#job-config');
  assert.doesNotMatch(await page.innerText('main'), /\bnull\b/);
  await page.click('#job-delete');
  await page.click('#job-delete');
  await page.waitForFunction(() => location.hash === '#/jobs');
  assert.equal((await api(`/v1/jobs/${state.endless.id}`)).status, 404);
});

test('a job page for an unknown or deleted job says so instead of loading forever', async () => {
  await page.goto(`${base}/#/jobs/${state.endless.id}`);
  const message = await page.waitForSelector('.not-found .error-message');
  assert.match(await message.textContent(), new RegExp(`no job with id ${state.endless.id}`));
  assert.equal(await page.isVisible('text=Loading metrics'), false);
  await page.goto(`${base}/#/policies/00000000-0000-0000-0000-000000000000`);
  assert.match(await (await page.waitForSelector('.not-found .error-message')).textContent(), /no policy with id/);
});

test('a job page opened while the job runs shows when it finished, once it has', async () => {
  const created = await post('/v1/jobs', { algorithm: 'bc', unlabeled_dataset: state.unlabeled.id, name: 'watched to the end',
    config: { iterations: 4000, hidden_sizes: [32, 32], batch_size: 64, seed: 3 }, runner: { log_every: 50 } });
  assert.equal(created.status, 201);
  await page.goto(`${base}/#/jobs/${created.body.id}`);
  await page.waitForSelector('#job-finished');
  const finishedJob = await finished(created.body.id);
  assert.equal(finishedJob.status, 'succeeded');
  await page.waitForFunction(() => document.querySelector('#job-finished').textContent !== '—');
  assert.equal(await page.textContent('#job-finished'), await page.evaluate((iso) => new Date(iso).toLocaleString(), finishedJob.finished_at));
  assert.equal(await page.textContent('#job-summary .status'), 'succeeded');
  state.bcJob = finishedJob;
});

test('the policy page turns pasted observations into the same actions as the API', async () => {
  const job = (await api(`/v1/jobs/${state.job.id}`)).body;
  assert.ok(job.policy_id);
  state.policy = job.policy_id;
  // The policies list names each policy by its job's name.
  await page.goto(`${base}/#/policies`);
  const listed = page.locator(`#policies-table tr[data-id="${job.policy_id}"] .policy-name`);
  assert.equal(await listed.textContent(), job.name);
  await page.goto(`${base}/#/policies/${job.policy_id}`);
  await page.waitForSelector('#act-form');
  // Its title names it by its job; its final metrics say the early-stopping codes in words.
  assert.equal(await page.textContent('#policy-title'), `${job.name} ${job.policy_id.slice(0, 8)}`);
  const policy = (await api(`/v1/policies/${job.policy_id}`)).body;
  const stoppedAt = policy.final_metrics.discriminator_stopped_at;
  assert.equal(typeof stoppedAt, 'number', JSON.stringify(policy.final_metrics));
  assert.equal(await page.textContent('#final-metrics tr[data-metric="discriminator_stopped_at"] td.num'),
    stoppedAt < 0 ? 'did not stop early' : `stopped early at step ${stoppedAt.toLocaleString('en-US')}`);
  assert.equal(await page.textContent('#final-metrics tr[data-metric="discriminator_best_step"] td.num'),
    `step ${policy.final_metrics.discriminator_best_step.toLocaleString('en-US')}`);
  const obsDim = state.unlabeled.obs_dim;
  const observations = [Array.from({ length: obsDim }, (_, i) => (i % 3) * 0.1), Array(obsDim).fill(0.5)];
  await page.fill('#act-input', observations.map((o) => o.join(', ')).join('\n'));
  await page.click('#act-submit');
  const shown = JSON.parse((await page.textContent('#act-result')).replace(/\n/g, ''));
  const direct = await post(`/v1/policies/${job.policy_id}/act`, { observations, deterministic: true });
  assert.equal(direct.status, 200);
  assert.deepEqual(shown, direct.body.actions);
  // A SafeDICE policy also answers its safety scores, one row per observation, as the API does.
  await page.check('#act-safety');
  await page.click('#act-submit');
  await page.waitForSelector('#act-safety tbody tr[data-row="1"]');
  const scored = await post(`/v1/policies/${job.policy_id}/act`, { observations, deterministic: true, safety_score: true });
  for (const [column, score] of [[2, 'non_preferred_log_ratio'], [3, 'out_of_support']]) {
    const cells = await page.$$eval(`#act-safety tbody td:nth-child(${column})`, (tds) => tds.map((td) => td.textContent));
    cells.forEach((text, i) => assert.ok(closeToShown(text, scored.body.safety[score][i], 4), `${score} row ${i}: ${text}`));
  }
  await page.uncheck('#act-safety');
  assert.match(await page.textContent('#snippet-curl'), new RegExp(`/v1/policies/${job.policy_id}/act`));
  assert.match(await page.textContent('#snippet-oip'), new RegExp(`/v2/models/${job.policy_id}/infer`));
  // A wrong width is answered with the server's message.
  await page.fill('#act-input', '1, 2');
  await page.click('#act-submit');
  assert.ok((await page.textContent('.act-error .error-message')).length > 0);
  await page.fill('#act-input', observations.map((o) => o.join(', ')).join('\n'));
  await page.click('#act-submit');
  await page.waitForSelector('#act-result');
  // The ONNX model downloads as the export endpoint serves it.
  const onnx = await downloaded(() => page.click('#onnx-download'));
  const exported = Buffer.from(await (await fetch(`${base}/v1/policies/${job.policy_id}/export?format=onnx`)).arrayBuffer());
  assert.ok(onnx.bytes.equals(exported));

  // Evaluate it in the background: the table fills in with the API's metrics.
  await page.fill('#eval-episodes', '200');
  await page.fill('#eval-seed', '3');
  await page.click('#eval-submit');
  // Two succeeded rows: this one and the job's own at the end of training.
  await page.waitForFunction(() => document.querySelectorAll('#evaluations-table tr[data-status="succeeded"]').length === 2, null, { timeout: 60_000 });
  const evaluations = (await api(`/v1/evaluations?policy_id=${job.policy_id}`)).body.items;
  // The one just run, and the job's own at the end of training (its eval block), marked so.
  assert.equal(evaluations.length, 2);
  const [evaluation, atEnd] = evaluations;
  assert.equal(atEnd.training_step, job.progress.total);
  await page.waitForSelector(`#evaluations-table tr[data-id="${atEnd.id}"] .source-training`);
  assert.equal(evaluation.training_step, null);
  assert.deepEqual([evaluation.env, evaluation.episodes, evaluation.seed, evaluation.deterministic], ['six-rooms', 200, 3, false]);
  const row = page.locator(`#evaluations-table tr[data-id="${evaluation.id}"]`);
  assert.equal(Number(await row.locator('.eval-cost').textContent()), Number(evaluation.metrics.average_cost.toPrecision(4)));
  assert.equal(Number(await row.locator('.eval-return').textContent()), Number(evaluation.metrics.normalized_return.toPrecision(4)));
  // An evaluation run in the user's own simulator shows beside it, marked external.
  const recorded = await post(`/v1/policies/${job.policy_id}/evaluations`, { env: 'sim/walk', returns: [1, 2], costs: [0, 1],
    reference: { preferred_return: 2, preferred_cost: 0.5, non_preferred_return: 2, non_preferred_cost: 1.5 } });
  assert.equal(recorded.status, 201);
  await page.reload();
  const external = page.locator(`#evaluations-table tr[data-id="${recorded.body.id}"]`);
  await external.waitFor();
  assert.equal(await external.locator('.source-external').textContent(), 'external');
  assert.equal(Number(await external.locator('.eval-return').textContent()), 75);
  await screenshot('policy');
});

test('compare shows the paper’s metrics side by side, exports them, and plots them from zero', async () => {
  // A quick BC job beside the SafeDICE one.
  const created = await post('/v1/jobs', { algorithm: 'bc', unlabeled_dataset: state.unlabeled.id, name: 'bc baseline',
    config: { iterations: 300, hidden_sizes: [32, 32], batch_size: 64, seed: 1 }, runner: { log_every: 25 },
    eval: { env: 'six-rooms', every: 100, episodes: 100 } });
  assert.equal(created.status, 201);
  assert.equal((await finished(created.body.id)).status, 'succeeded');
  await page.goto(`${base}/#/compare`);
  await page.waitForSelector('#compare-jobs input');
  // Tick exactly the SafeDICE job and the BC baseline.
  for (const box of await page.$$('#compare-jobs input')) {
    const id = await box.getAttribute('value');
    if ([state.job.id, created.body.id].includes(id)) await box.check(); else await box.uncheck();
  }
  await page.waitForFunction(() => document.querySelectorAll('#compare-table thead th').length === 3);
  const headers = await page.$$eval('#compare-table thead th', (ths) => ths.map((t) => t.textContent));
  assert.ok(headers.some((t) => t.includes('renamed in the browser')) && headers.some((t) => t.includes('bc baseline')), JSON.stringify(headers));
  // The table's metric rows are the paper's; the diagnostics are folded away below it.
  const rows = await page.$$eval('#compare-table tr[data-metric]', (trs) => trs.map((tr) => tr.dataset.metric));
  assert.deepEqual(rows, ['eval/normalized_return', 'eval/average_cost', 'eval/cost_violation_ratio',
    'eval/cvar_cost_50', 'eval/cvar_cost_20', 'eval/cvar_cost_10', 'eval/cvar_cost_5']);
  assert.equal(await page.isVisible('#compare-diagnostics tr[data-metric="alpha_hat"]'), false);
  assert.ok(await page.$('#compare-diagnostics tr[data-metric="alpha_hat"]'));
  // The axes offer the paper's metrics only, until diagnostics are asked for.
  assert.deepEqual(await page.$$eval('#scatter-x option', (os) => os.map((o) => o.value)), rows);
  assert.equal(await page.inputValue('#scatter-x'), 'eval/average_cost');
  assert.equal(await page.inputValue('#scatter-y'), 'eval/normalized_return');
  await page.check('#scatter-diagnostics');
  assert.ok((await page.$$eval('#scatter-x option', (os) => os.map((o) => o.value))).includes('alpha_hat'));
  assert.equal(await page.inputValue('#scatter-x'), 'eval/average_cost');

  // Points at the jobs' last evaluation, named; both axes from zero by default.
  const points = await page.$$eval('.chart-box[data-chart="scatter"] g.point', (gs) => gs.map((g) => ({ label: g.dataset.label, x: Number(g.dataset.x), y: Number(g.dataset.y) })));
  const last = async (id, name) => (await api(`/v1/jobs/${id}/metrics?names=${name}&max_points=2`)).body.rows.at(-1).value;
  assert.deepEqual(points.map((p) => p.label).sort(), ['bc baseline', 'renamed in the browser']);
  const bcPoint = points.find((p) => p.label === 'bc baseline');
  assert.equal(bcPoint.x, await last(created.body.id, 'eval/average_cost'));
  assert.equal(bcPoint.y, await last(created.body.id, 'eval/normalized_return'));
  const ticks = await page.$$eval('.chart-box[data-chart="scatter"] text.tick', (ts) => ts.map((t) => t.textContent));
  assert.ok(ticks.filter((t) => t === '0').length >= 2, `both axes start at 0: ${ticks}`);
  assert.match(await page.textContent('.chart-box[data-chart="scatter"] svg'), /Cost vs return/);
  await screenshot('compare');

  // The side-by-side table as CSV, every metric included.
  const file = await downloaded(() => page.click('#compare-csv'));
  const lines = file.bytes.toString().trim().split('\n');
  assert.equal(file.name, 'compare.csv');
  const columns = lines[0].split(',');
  assert.equal(columns[0], 'metric');
  const bcColumn = columns.findIndex((c) => c === `bc baseline (${created.body.id})`);
  assert.ok(bcColumn > 0 && columns.includes(`renamed in the browser (${state.job.id})`), lines[0]);
  const costLine = lines.find((l) => l.startsWith('eval/average_cost,'));
  assert.equal(Number(costLine.split(',')[bcColumn]), await last(created.body.id, 'eval/average_cost'));
  assert.ok(lines.some((l) => l.startsWith('alpha_hat,')));
  const shared = 'runtime=builtin;actions=sampled;episodes=100;seed=0;env=six-rooms';
  assert.deepEqual(lines.find((l) => l.startsWith('protocol,')).split(',').slice(1), [shared, shared]);

  // The SafeDICE policy was also evaluated on 200 episodes and in a simulator (the policy test):
  // the numbers above are under the protocol both jobs share, and the others are offered.
  const options = await page.$$eval('#compare-protocol option', (os) => os.map((o) => [o.value, o.selected]));
  assert.equal(options.length, 3, JSON.stringify(options));
  assert.deepEqual(options.find(([, selected]) => selected), [shared, true]);
  assert.match(await page.textContent('#compare-mixed'), /3 protocols/);
  const wider = options.map(([key]) => key).find((key) => key.includes('episodes=200'));
  await page.selectOption('#compare-protocol', wider);
  await page.waitForSelector('#compare-other-protocol');
  assert.match(await page.textContent('#compare-other-protocol'), /bc baseline/);
  const under = await page.$$eval('.chart-box[data-chart="scatter"] g.point', (gs) => gs.map((g) => g.dataset.label));
  assert.deepEqual(under, ['renamed in the browser']);
  for (const width of [1400, 500]) {
    await page.setViewportSize({ width, height: 900 });
    await page.waitForTimeout(200);
    assert.deepEqual(await layoutProblems(), [], `compare with a protocol picked at ${width}px`);
  }
  await page.setViewportSize({ width: 1360, height: 900 });
});

test('a model is created on the Models page, and a name that breaks the rule shows the server’s rule', async () => {
  await page.goto(`${base}/#/models`);
  await page.waitForSelector('#models-list .empty');
  assert.equal(await page.getAttribute('nav a[data-nav="models"]', 'class'), 'active');
  // The page states the rule before anything is sent.
  assert.match(await page.textContent('#model-name-rule'), /1-64 characters from ASCII letters, digits and - _ \./);
  assert.match(await page.textContent('#model-name-rule'), /starting with a letter or a digit/);

  // A name starting with a dash is refused; the page shows the server's 422 as it comes.
  const direct = await post('/v1/models', { name: '-pilot', description: '', tags: [] });
  assert.equal(direct.status, 422);
  assert.equal(direct.body.error.code, 'invalid_name');
  await page.fill('#model-name', '-pilot');
  await page.click('#model-submit');
  const shown = await page.waitForSelector('.model-form-error .error-message');
  assert.equal(await shown.textContent(), direct.body.error.message);
  assert.match(await shown.textContent(), /starting with a letter or a digit/);
  assert.equal(await page.textContent('.model-form-error .error-code'), 'invalid_name');
  assert.equal((await api('/v1/models')).body.total, 0);

  await page.fill('#model-name', 'pilot');
  await page.fill('#model-description', 'six-rooms navigator');
  await page.fill('#model-tags', 'browser, six-rooms');
  await page.click('#model-submit');
  await page.waitForSelector('#model-created a[href="#/models/pilot"]');
  const row = '#models-table tr[data-name="pilot"]';
  await page.waitForSelector(row);
  const model = (await api('/v1/models/pilot')).body;
  assert.equal(model.description, 'six-rooms navigator');
  assert.deepEqual(model.tags, ['browser', 'six-rooms']);
  assert.equal(model.latest_version ?? null, null);
  assert.equal(await page.textContent(`${row} .latest`), '—');
  assert.equal(await page.textContent(`${row} .aliases`), 'none');
  assert.equal(await page.inputValue('#model-name'), '', 'the form is cleared after a create');
});

test('versions are promoted through the dialog and rolled back; the model page and the API agree', async () => {
  // Two trained policies as versions 1 and 2 (the SafeDICE job's and the BC job's).
  const v1 = await post('/v1/models/pilot/versions', { policy_id: state.policy, description: 'safedice small' });
  assert.equal(v1.status, 201);
  assert.equal(v1.body.version, 1);
  const v2 = await post('/v1/models/pilot/versions', { policy_id: state.bcJob.policy_id });
  assert.equal(v2.status, 201);
  assert.equal(v2.body.version, 2);

  await page.goto(`${base}/#/models/pilot`);
  await page.waitForSelector('#versions-table tr[data-version="2"]');
  assert.match(await page.textContent('#model-description-text'), /six-rooms navigator/);
  assert.deepEqual(await page.$$eval('#model-tags-list .tag', (ts) => ts.map((t) => t.textContent)), ['browser', 'six-rooms']);
  assert.deepEqual(await page.$$eval('#versions-table tbody tr', (trs) => trs.map((tr) => tr.dataset.version)), ['2', '1']);
  // Each version links to its policy and its job (the paper's metrics are one click away).
  const first = '#versions-table tr[data-version="1"]';
  assert.equal(await page.getAttribute(`${first} .policy-link`, 'href'), `#/policies/${state.policy}`);
  assert.equal(await page.getAttribute(`${first} .job-link`, 'href'), `#/jobs/${state.job.id}`);
  assert.equal(await page.textContent(`${first} .source`), 'api');
  assert.ok(await page.isVisible('#aliases-empty'));

  // v1 to a new alias, production: the dialog asks first.
  await page.click(`${first} button.promote`);
  await page.waitForSelector('#model-dialog[open]');
  await page.fill('#promote-new-alias', 'production');
  assert.equal(await page.textContent('#dialog-question'), 'Point the new alias production at v1?');
  await page.click('#dialog-confirm');
  await page.waitForSelector('#model-dialog', { state: 'hidden' });
  await page.waitForSelector('#aliases-table tr[data-alias="production"] .version:has-text("v1")');

  // Cancelling the dialog moves nothing.
  const second = '#versions-table tr[data-version="2"]';
  await page.click(`${second} button.promote`);
  await page.waitForSelector('#model-dialog[open]');
  assert.equal(await page.inputValue('#promote-alias'), 'production');
  assert.equal(await page.textContent('#dialog-question'), 'Point production from v1 to v2?');
  await page.click('#dialog-cancel');
  await page.waitForSelector('#model-dialog', { state: 'hidden' });
  assert.equal((await api('/v1/models/pilot/history')).body.items.length, 1);

  // v2 to production, this time confirmed.
  await page.click(`${second} button.promote`);
  await page.waitForSelector('#model-dialog[open]');
  assert.equal(await page.textContent('#dialog-question'), 'Point production from v1 to v2?');
  await page.click('#dialog-confirm');
  await page.waitForSelector('#aliases-table tr[data-alias="production"] .version:has-text("v2")');
  assert.equal(await page.textContent('#model-moved'), 'production now points at v2 (was v1).');
  assert.equal((await api('/v1/models/pilot')).body.aliases[0].version, 2);

  // Roll back: production goes where it pointed before its latest move.
  await page.click('#aliases-table tr[data-alias="production"] button.rollback');
  await page.waitForSelector('#model-dialog[open]');
  assert.equal(await page.textContent('#dialog-question'), 'Roll production back from v2 to v1?');
  await page.click('#dialog-confirm');
  await page.waitForSelector('#aliases-table tr[data-alias="production"] .version:has-text("v1")');

  // The API says what the page says.
  const model = (await api('/v1/models/pilot')).body;
  assert.equal(model.latest_version, 2);
  assert.equal(model.version_count, 2);
  assert.deepEqual(model.aliases.map((a) => [a.alias, a.version, a.canary ?? null]), [['production', 1, null]]);
  const history = (await api('/v1/models/pilot/history')).body.items;
  assert.deepEqual(history.map((m) => [m.alias, m.from_version ?? null, m.to_version, m.actor]),
    [['production', 2, 1, 'dashboard'], ['production', 1, 2, 'dashboard'], ['production', null, 1, 'dashboard']]);
  const rows = await page.$$eval('#history-table tbody tr', (trs) => trs.map((tr) => ({ seq: tr.dataset.seq,
    alias: tr.querySelector('.alias').textContent, move: tr.querySelector('.move').textContent, actor: tr.querySelector('.actor').textContent })));
  assert.deepEqual(rows, history.map((m, i) => ({ seq: String(m.seq), alias: 'production', move: ['v2 → v1', 'v1 → v2', 'created at v1'][i], actor: 'dashboard' })));
  assert.deepEqual(await page.$$eval(`${first} .alias-tag`, (ts) => ts.map((t) => t.textContent)), ['production']);
  assert.equal(await page.$$eval(`${second} .alias-tag`, (ts) => ts.length), 0);
  await screenshot('model');

  // While production points at a version, the model cannot be deleted: the server's 409 shows.
  await page.click('#model-delete');
  await page.click('#model-delete');
  assert.equal(await (await page.waitForSelector('.model-delete-error .error-code')).textContent(), 'model_in_use');
  assert.equal((await api('/v1/models/pilot')).status, 200);

  // The list shows where the alias points now.
  await page.click('nav a[data-nav="models"]');
  await page.waitForSelector('#models-table tr[data-name="pilot"] .alias-chip');
  assert.equal(await page.textContent('#models-table tr[data-name="pilot"] .aliases'), 'production → v1');
  assert.equal(await page.textContent('#models-table tr[data-name="pilot"] .latest'), 'v2');

  // A version's policy link opens the policy page.
  await page.goto(`${base}/#/models/pilot`);
  await page.click(`${second} .policy-link`);
  await page.waitForSelector('#policy-meta');
  assert.equal(await page.evaluate(() => location.hash), `#/policies/${state.bcJob.policy_id}`);
});

test('the job form registers the job’s policy as the next version of a model, with an alias', async () => {
  await page.goto(`${base}/#/jobs`);
  await page.waitForSelector('#job-form');
  assert.deepEqual(await page.$$eval('#job-register-model option', (os) => os.map((o) => o.value)), ['', 'pilot']);
  assert.equal(await page.isDisabled('#job-register-alias'), true);
  await page.selectOption('#job-algorithm', 'bc');
  await page.fill('#job-name', 'registered bc');
  await page.fill('#job-iterations', '300');
  await page.fill('#job-hidden_sizes', '32, 32');
  await page.fill('#job-batch_size', '64');
  // "Evaluate every" left at its placeholder: one evaluation, at the end of training.
  assert.equal(await page.getAttribute('#job-eval-every', 'placeholder'), 'at the end');
  await page.selectOption('#job-eval-env', 'six-rooms');
  await page.fill('#job-eval-every', '');
  await page.fill('#job-eval-episodes', '20');
  await page.selectOption('#job-register-model', 'pilot');
  await page.fill('#job-register-alias', 'staging');
  await page.click('#job-submit');
  const link = await page.waitForSelector('#job-created a');
  const id = (await link.getAttribute('href')).replace('#/jobs/', '');
  const job = (await api(`/v1/jobs/${id}`)).body;
  assert.equal(job.name, 'registered bc');
  assert.deepEqual(job.register, { model: 'pilot', alias: 'staging' });
  assert.deepEqual(job.eval, { env: 'six-rooms', episodes: 20, seed: 0, deterministic: false });
  const done = await finished(id);
  assert.equal(done.status, 'succeeded');
  const evaluated = (await api(`/v1/jobs/${id}/metrics?names=eval/average_cost`)).body.rows;
  assert.deepEqual(evaluated.map((r) => r.step), [done.progress.total]);

  const model = (await api('/v1/models/pilot')).body;
  assert.equal(model.latest_version, 3);
  assert.deepEqual(model.aliases.map((a) => [a.alias, a.version]).sort(), [['production', 1], ['staging', 3]]);
  const v3 = (await api('/v1/models/pilot/versions/3')).body;
  assert.equal(v3.policy_id, done.policy_id);
  assert.equal(v3.job_id, id);
  await page.goto(`${base}/#/models/pilot`);
  const row = '#versions-table tr[data-version="3"]';
  await page.waitForSelector(row);
  assert.equal(await page.textContent(`${row} .source`), `job ${id.slice(0, 8)}`);
  assert.equal(await page.getAttribute(`${row} .source`, 'title'), v3.source);
  assert.equal(v3.source, `job ${id}`);
  assert.equal(await page.getAttribute(`${row} .job-link`, 'href'), `#/jobs/${id}`);
  assert.equal(await page.textContent('#aliases-table tr[data-alias="staging"] .version'), 'v3');

  // staging is removed through the dialog; the history keeps the move.
  await page.click('#aliases-table tr[data-alias="staging"] button.remove-alias');
  await page.waitForSelector('#model-dialog[open]');
  assert.equal(await page.textContent('#dialog-question'), 'Remove the alias staging (now at v3)?');
  await page.click('#dialog-confirm');
  await page.waitForSelector('#aliases-table tr[data-alias="staging"]', { state: 'detached' });
  assert.deepEqual((await api('/v1/models/pilot')).body.aliases.map((a) => a.alias), ['production']);
  const [removal] = (await api('/v1/models/pilot/history?alias=staging')).body.items;
  assert.deepEqual([removal.from_version, removal.to_version ?? null, removal.actor], [3, null, 'dashboard']);
  assert.equal(await page.textContent(`#history-table tr[data-seq="${removal.seq}"] .move`), 'v3 → deleted');

  // A move confirmed on a page that is out of date is refused instead of undoing someone else's.
  await page.click('#versions-table tr[data-version="3"] button.promote');
  await page.waitForSelector('#model-dialog[open]');
  assert.equal(await page.textContent('#dialog-question'), 'Point production from v1 to v3?');
  const meanwhile = await api('/v1/models/pilot/aliases/production', { method: 'PUT', headers: { 'content-type': 'application/json' },
    body: JSON.stringify({ version: 2, actor: 'someone else' }) });
  assert.equal(meanwhile.status, 200);
  await page.click('#dialog-confirm');
  assert.match(await (await page.waitForSelector('.dialog-error .error-message')).textContent(), /^production points at v2 now, not v1 as this page showed/);
  assert.equal((await api('/v1/models/pilot')).body.aliases.find((a) => a.alias === 'production').version, 2);
  assert.equal((await api('/v1/models/pilot/history?alias=production')).body.items[0].actor, 'someone else');
  await page.waitForSelector('#aliases-table tr[data-alias="production"] .version:has-text("v2")');
  await page.click('#dialog-cancel');
  await page.waitForSelector('#model-dialog', { state: 'hidden' });
});

test('the policy page registers its policy as a version; the model page shows each version’s numbers and safety scores and sets and ends a canary, each move with its reason', async () => {
  await page.setViewportSize({ width: 1400, height: 900 });
  await page.goto(`${base}/#/policies/${state.policy}`);
  await page.waitForSelector('#register-form');
  assert.deepEqual(await page.$$eval('#register-model option', (os) => os.map((o) => o.value)), ['pilot']);
  await page.fill('#register-description', 'safedice again, from its page');
  await page.fill('#register-alias', 'candidate');
  await page.click('#register-submit');
  assert.equal(await (await page.waitForSelector('#register-ok')).textContent(), 'Registered as v4 of pilot; candidate points at it.');
  const model = (await api('/v1/models/pilot')).body;
  assert.equal(model.latest_version, 4);
  const v4 = (await api('/v1/models/pilot/versions/4')).body;
  assert.deepEqual([v4.policy_id, v4.description], [state.policy, 'safedice again, from its page']);
  assert.deepEqual(model.aliases.map((a) => [a.alias, a.version]).sort(), [['candidate', 4], ['production', 2]]);
  assert.equal((await api('/v1/models/pilot/history?alias=candidate')).body.items[0].actor, 'dashboard');

  // Beside each version, its job's return and cost as /v1/results gives them (Compare's rule).
  await page.click('#register-ok a');
  await page.waitForSelector('#versions-table tr[data-version="4"]');
  const versions = (await api('/v1/models/pilot/versions')).body.items;
  const results = (await api(`/v1/results?jobs=${[...new Set(versions.map((v) => v.job_id))].join(',')}`)).body;
  assert.equal(await page.textContent('#versions-protocol .protocol-label'), results.protocol.label);
  let withNumbers = 0;
  for (const v of versions) {
    const { metrics } = results.jobs.find((j) => j.job_id === v.job_id);
    for (const key of ['normalized_return', 'average_cost']) {
      const shown = await page.textContent(`#versions-table tr[data-version="${v.version}"] td.metric-${key}`);
      if (metrics[key] === undefined) assert.equal(shown, '—', `v${v.version} ${key}`);
      else assert.ok(closeToShown(shown, metrics[key], 4), `v${v.version} ${key}: shown ${shown}, API ${metrics[key]}`);
    }
    if (metrics.normalized_return !== undefined) withNumbers += 1;
  }
  assert.ok(withNumbers >= 1, JSON.stringify(results.jobs));

  // A canary on production: v4 takes 10 % of its requests, with the reason typed.
  const production = '#aliases-table tr[data-alias="production"]';
  await page.click(`${production} button.canary-set`);
  await page.waitForSelector('#model-dialog[open]');
  await page.selectOption('#canary-version', '4');
  await page.fill('#canary-share', '10');
  assert.equal(await page.textContent('#dialog-question'), 'Send 10% of production’s requests to v4 (v2 answers the rest)?');
  await page.fill('#dialog-reason', 'ten percent trial of v4');
  await page.click('#dialog-confirm');
  await page.waitForSelector(`${production} .canary-text:has-text("v4 takes 10%")`);
  const productionNow = async () => (await api('/v1/models/pilot')).body.aliases.find((a) => a.alias === 'production');
  const lastMove = async () => (await api('/v1/models/pilot/history?alias=production')).body.items[0];
  const withCanary = await productionNow();
  assert.deepEqual([withCanary.version, withCanary.canary], [2, { version: 4, weight: 0.1 }]);
  assert.equal(await page.textContent('#model-moved'), 'production stays at v2, with v4 taking 10% of its requests.');
  let move = await lastMove();
  assert.deepEqual([move.to_version, move.canary, move.actor, move.reason], [2, { version: 4, weight: 0.1 }, 'dashboard', 'ten percent trial of v4']);
  await page.waitForSelector(`#history-table tr[data-seq="${move.seq}"]`);
  assert.equal(await page.textContent(`#history-table tr[data-seq="${move.seq}"] .reason`), 'ten percent trial of v4');
  // With the canary's buttons too, nothing is cut or overlaps, at both widths.
  for (const width of [1400, 500]) {
    await page.setViewportSize({ width, height: 900 });
    await page.waitForTimeout(200);
    assert.deepEqual(await layoutProblems(), [], `model page with a canary at ${width}px`);
    await screenshot(`model-canary-${width}`);
  }
  await page.setViewportSize({ width: 1400, height: 900 });

  // Ended without a reason typed: the move says what it did.
  await page.click(`${production} button.canary-clear`);
  await page.waitForSelector('#model-dialog[open]');
  assert.equal(await page.textContent('#dialog-question'), 'End the canary of production (v4 takes 10%)? v2 answers every request.');
  await page.click('#dialog-confirm');
  await page.waitForSelector(`${production} .canary-text:has-text("none")`);
  assert.equal((await productionNow()).canary ?? null, null);
  move = await lastMove();
  assert.deepEqual([move.to_version, move.canary ?? null, move.reason], [2, null, 'canary v4 ended']);

  // A promotion with its reason.
  await page.click('#versions-table tr[data-version="4"] button.promote');
  await page.waitForSelector('#model-dialog[open]');
  await page.selectOption('#promote-alias', 'production');
  await page.fill('#dialog-reason', 'v4 passed review');
  await page.click('#dialog-confirm');
  await page.waitForSelector(`${production} .version:has-text("v4")`);
  move = await lastMove();
  assert.deepEqual([move.from_version, move.to_version, move.reason], [2, 4, 'v4 passed review']);

  // Safety scores asked of production (v4, a SafeDICE policy) show on the model page, bin by
  // bin as this node's statistics count them.
  const { obs_dim: obsDim } = (await api(`/v1/policies/${state.policy}`)).body;
  const observations = Array.from({ length: 5 }, (_, i) => Array.from({ length: obsDim }, (_, j) => ((i + j) % 3) - 1));
  const scored = await post('/v1/models/pilot@production/act', { observations, safety_score: true });
  assert.equal(scored.status, 200, JSON.stringify(scored.body));
  assert.equal(scored.body.safety.out_of_support.length, 5);
  await page.reload();
  const v4Scores = '#safety-card .safety-version[data-version="4"]';
  await page.waitForSelector(v4Scores);
  const served = (await api('/v2/models/pilot/stats')).body.model_stats.find((s) => s.version === '4').safety_scores;
  for (const score of ['non_preferred_log_ratio', 'out_of_support']) {
    const shown = await page.$$eval(`${v4Scores} [data-score="${score}"] .safety-count`,
      (els) => els.map((e) => Number(e.textContent.split(' ')[0].replace(/,/g, ''))));
    assert.deepEqual(shown, served[score].counts, score);
    assert.equal(served[score].counts.reduce((a, b) => a + b, 0), 5, score);
  }
  for (const width of [1400, 500]) {
    await page.setViewportSize({ width, height: 900 });
    await page.waitForTimeout(200);
    assert.deepEqual(await layoutProblems(), [], `model page with safety scores at ${width}px`);
    await (await page.$('#safety-card')).scrollIntoViewIfNeeded();
    await screenshot(`model-safety-${width}`);
  }
  await page.setViewportSize({ width: 1400, height: 900 });
});

test('a shadow is set on an alias from the model page, its comparison shows as the API reports it, and it is promoted', async () => {
  await page.setViewportSize({ width: 1400, height: 900 });
  await page.goto(`${base}/#/models/pilot`);
  const production = '#aliases-table tr[data-alias="production"]';
  await page.waitForSelector(`${production} button.shadow-set`);
  assert.equal(await page.textContent(`${production} .version`), 'v4');
  await page.click(`${production} button.shadow-set`);
  await page.waitForSelector('#model-dialog[open]');
  await page.selectOption('#shadow-version', '2');
  await page.fill('#shadow-share', '100');
  assert.equal(await page.textContent('#dialog-question'), 'Run v2 beside v4 on 100% of production’s requests and compare? Its actions are never returned.');
  await page.click('#dialog-confirm');
  await page.waitForSelector(`${production} .shadow-text:has-text("v2 on 100%")`);
  assert.equal(await page.textContent('#model-moved'), 'production stays at v4, with no canary, shadowed by v2 on 100%.');
  const alias = (await api('/v1/models/pilot')).body.aliases.find((a) => a.alias === 'production');
  assert.deepEqual([alias.version, alias.shadow], [4, { version: 2, sample: 1 }]);
  const move = (await api('/v1/models/pilot/history?alias=production')).body.items[0];
  assert.deepEqual([move.shadow, move.reason], [{ version: 2, sample: 1 }, 'shadow v2 on 100%']);

  // Agents' requests: every one answered by v4, and compared with v2 off the response path.
  const { obs_dim: obsDim } = (await api(`/v1/policies/${state.policy}`)).body;
  const observations = Array.from({ length: 5 }, (_, i) => Array.from({ length: obsDim }, (_, j) => ((i + 2 * j) % 3) - 1));
  for (let i = 0; i < 8; i += 1) {
    const acted = await post('/v1/models/pilot@production/act', { observations });
    assert.equal(acted.status, 200, JSON.stringify(acted.body));
  }
  const report = (await api('/v1/models/pilot/shadow')).body;
  const compared = report.series.find((s) => s.alias === 'production' && s.production_version === 4 && s.shadow_version === 2);
  assert.ok(compared, JSON.stringify(report));
  assert.deepEqual([compared.actions, compared.total.requests, compared.total.observations], ['discrete', 8, 40]);
  await page.reload();
  const series = '#shadow-card .shadow-series[data-alias="production"][data-production="4"][data-shadow="2"]';
  await page.waitForSelector(`${series} .chart-box[data-chart="production-4-2-diff"] .u-over`);
  const rate = `${Number((compared.total.disagreement_rate * 100).toPrecision(4))}%`;
  const summary = await page.textContent(`${series} .shadow-summary`);
  assert.ok(summary.startsWith(`8 requests shadowed (0 skipped, 0 failed), 40 observations: disagreement ${rate}`), summary);
  // v4 is a SafeDICE policy: its log-ratios are charted beside the comparison.
  assert.ok(compared.total.production_mean_log_ratio !== null, JSON.stringify(compared.total));
  await page.waitForSelector(`${series} .chart-box[data-chart="production-4-2-safety"]`);
  assert.equal(await page.textContent(`#history-table tr[data-seq="${move.seq}"] .shadow`), 'v2 on 100%');
  for (const width of [1400, 500]) {
    await page.setViewportSize({ width, height: 900 });
    await page.waitForTimeout(200);
    assert.deepEqual(await layoutProblems(), [], `model page with a shadow at ${width}px`);
    await (await page.$('#shadow-card')).scrollIntoViewIfNeeded();
    await screenshot(`model-shadow-${width}`);
  }
  await page.setViewportSize({ width: 1400, height: 900 });

  // Promoted from the comparison: the alias moves to the shadow's version, and the shadow ends.
  await page.click(`${series} button.shadow-promote`);
  await page.waitForSelector('#model-dialog[open]');
  assert.equal(await page.textContent('#dialog-question'), 'Point production from v4 to its shadow v2? The shadow ends: v2 answers every request.');
  await page.click('#dialog-confirm');
  await page.waitForSelector(`${production} .version:has-text("v2")`);
  const promoted = (await api('/v1/models/pilot')).body.aliases.find((a) => a.alias === 'production');
  assert.deepEqual([promoted.version, promoted.shadow ?? null], [2, null]);
  const last = (await api('/v1/models/pilot/history?alias=production')).body.items[0];
  assert.deepEqual([last.from_version, last.to_version, last.from_shadow, last.reason], [4, 2, { version: 2, sample: 1 }, 'promoted shadow v2 from the dashboard']);
  await page.waitForSelector(`${series} h3:has-text("(ended)")`);
});

/** Rows of `table` whose last cell (Cancel, Delete, Promote…) is not wholly inside the window. */
async function actionsOutOfView(table) {
  return page.$$eval(`${table} tbody tr`, (rows) => rows.map((row) => row.lastElementChild.getBoundingClientRect())
    .filter((r) => r.width > 0 && (r.left < -0.5 || r.right > window.innerWidth + 0.5))
    .map((r) => `${Math.round(r.left)}-${Math.round(r.right)} in ${window.innerWidth}`));
}

test('in a narrow window no page is wider than the window and no placeholder is cut off', async () => {
  for (const width of [500, 420]) {
    await page.setViewportSize({ width, height: 900 });
    for (const [hash, table] of [['#/jobs', '#jobs-table'], ['#/datasets', '#datasets-table'], ['#/models/pilot', '#versions-table']]) {
      await page.goto(`${base}/${hash}`);
      await page.waitForSelector(table);
      assert.deepEqual(await actionsOutOfView(table), [], `${table}'s actions at ${width}px`);
    }
    await page.goto(`${base}/#/jobs`);
    await page.waitForSelector('#jobs-table');
    await screenshot(`jobs-${width}`);
  }
  for (const width of [1360, 420]) {
    await page.setViewportSize({ width, height: 900 });
    for (const [hash, ready] of [['#/datasets', '#datasets-table'], ['#/jobs', '#jobs-table'],
      [`#/jobs/${state.job.id}`, '#charts .u-over'], ['#/compare', '#compare-table'], [`#/policies/${state.policy}`, '#act-form'],
      ['#/models', '#models-table'], ['#/models/pilot', '#history-table']]) {
      await page.goto(`${base}/${hash}`);
      await page.waitForSelector(ready);
      await page.waitForTimeout(200); // charts take their width on the next frame
      assert.deepEqual(await layoutProblems(), [], `${hash} at ${width}px`);
    }
  }
  await screenshot('narrow-job');
  await page.setViewportSize({ width: 1360, height: 900 });
});

// ---------- experiments ----------

/** A number as a page shows it ("12.34", "1,234", "1.20e-4") and the tolerance its shown
 *  precision allows against `exact`: half a unit of the last shown digit, or of the `sig`-th
 *  significant digit where the page rounds to significant digits. */
function closeToShown(text, exact, sig) {
  const t = text.replace(/,/g, '').trim();
  const [mantissa, exponent] = t.split('e');
  const decimals = (mantissa.split('.')[1] || '').length;
  const byDecimals = 0.5 * 10 ** (Number(exponent || 0) - decimals);
  const bySignificant = exact === 0 ? 0 : 0.5 * 10 ** (Math.floor(Math.log10(Math.abs(exact))) - (sig - 1));
  const tolerance = Math.max(byDecimals, bySignificant) * (1 + 1e-9) + 1e-12;
  return Math.abs(Number(t) - exact) <= tolerance;
}

/** Mean and standard error (sample standard deviation / √n; null for one value). */
function meanSe(values) {
  const n = values.length;
  const mean = values.reduce((a, b) => a + b, 0) / n;
  const se = n > 1 ? Math.sqrt(values.reduce((a, v) => a + (v - mean) ** 2, 0) / (n - 1) / n) : null;
  return { mean, se, n };
}

test('an experiment of 2 algorithms × 3 seeds is queued from the form and its page shows mean ± SE, curves and the scatter', async () => {
  await page.setViewportSize({ width: 1400, height: 900 });
  await page.goto(`${base}/#/experiments`);
  await page.waitForSelector('#experiment-form');
  assert.ok(await page.isVisible('nav a[data-nav="experiments"].active'));
  // A refusal shows the server's message as it comes.
  const refused = await post('/v1/experiments', { unlabeled_dataset: state.unlabeled.id, algorithms: ['bc'], seed_count: 0 });
  assert.equal(refused.status, 422);
  await page.fill('#exp-seeds', '0');
  await page.click('#exp-submit');
  assert.equal(await (await page.waitForSelector('.experiment-form-error .error-message')).textContent(), refused.body.error.message);

  // The datasets default by role; SafeDICE and BC are checked; small networks, a short run.
  assert.equal(await page.inputValue('#exp-unlabeled'), state.unlabeled.id);
  assert.equal(await page.inputValue('#exp-non-preferred'), state.nonPreferred.id);
  const checked = await page.$$eval('#exp-algorithms input:checked', (bs) => bs.map((b) => b.value));
  assert.deepEqual(checked.sort(), ['bc', 'safedice']);
  await page.fill('#exp-name', 'browser grid');
  await page.fill('#exp-seeds', '3');
  await page.fill('#exp-iterations', '300');
  await page.fill('#exp-hidden-sizes', '32, 32');
  await page.fill('#exp-batch-size', '64');
  assert.equal(await page.inputValue('#exp-eval-env'), 'six-rooms');
  // "Evaluate every" left at its placeholder: each job evaluates once, at the end.
  assert.equal(await page.getAttribute('#exp-eval-every', 'placeholder'), 'at the end');
  await page.fill('#exp-eval-episodes', '50');
  await page.click('#exp-submit');
  await page.waitForSelector('#experiment-created');
  const listed = (await api('/v1/experiments')).body;
  assert.equal(listed.total, 1);
  const id = listed.items[0].id;
  const created = (await api(`/v1/experiments/${id}`)).body;
  assert.equal(created.name, 'browser grid');
  assert.deepEqual(created.seeds, [0, 1, 2]);
  assert.deepEqual(created.algorithms.map((a) => a.algorithm).sort(), ['bc', 'safedice']);
  assert.deepEqual(created.config, { iterations: 300, hidden_sizes: [32, 32], batch_size: 64 });
  assert.deepEqual(created.eval, { env: 'six-rooms', episodes: 50 });
  assert.equal(created.progress.total, 6);
  await page.waitForSelector(`#experiments-table tr[data-id="${id}"]`);
  // The list says where each grid stands, from its progress counts.
  assert.match(await page.textContent(`#experiments-table tr[data-id="${id}"] .experiment-status`), /^(queued|running \(\d of 6 done\))$/);

  // Its page follows the grid to the end.
  await page.click(`#experiment-created a[href="#/experiments/${id}"]`);
  await page.waitForSelector('#experiment-progress');
  await page.waitForSelector('#experiment-progress[data-active="false"]', { timeout: 600000 });
  const experiment = (await api(`/v1/experiments/${id}`)).body;
  assert.equal(experiment.progress.succeeded, 6, JSON.stringify(experiment.progress));
  assert.match(await page.textContent('#experiment-progress'), /^6 of 6 jobs finished: 6 succeeded/);
  assert.equal(await page.isDisabled('#experiment-cancel'), true);

  // Each arm's mean ± SE, computed here from the jobs' per-seed metrics.
  const labels = experiment.algorithms.map((a) => a.label || a.algorithm);
  await page.waitForFunction((n) => document.querySelectorAll('#experiment-results-table tr.arm-row').length === n, labels.length);
  const metrics = await page.$$eval('#experiment-results-table thead th[data-metric]', (ths) => ths.map((t) => t.dataset.metric));
  assert.deepEqual(metrics.slice(0, 7), ['normalized_return', 'average_cost', 'cost_violation_ratio', 'cvar_cost_50', 'cvar_cost_20', 'cvar_cost_10', 'cvar_cost_5']);
  for (const label of labels) {
    const jobs = experiment.jobs.filter((j) => j.arm === label);
    assert.equal(jobs.length, 3);
    const row = `#experiment-results-table tr.arm-row[data-label="${label}"]`;
    assert.equal((await page.textContent(`${row} td.n-seeds`)).trim(), '3 seeds');
    for (const metric of metrics) {
      const expected = meanSe(jobs.map((j) => j.metrics[metric]));
      const text = (await page.textContent(`${row} td.mean-se[data-metric="${metric}"]`)).trim();
      const [mean, se] = text.split(' ± ');
      assert.ok(closeToShown(mean, expected.mean, 4), `${label} ${metric}: shown ${text}, computed mean ${expected.mean}`);
      assert.ok(se !== undefined && closeToShown(se, expected.se, 2), `${label} ${metric}: shown ${text}, computed se ${expected.se}`);
    }
    // Per seed: the values, the job and the policy, once expanded.
    const seedRows = `#experiment-results-table tr.seed-row[data-arm="${label}"]`;
    assert.equal(await page.isVisible(seedRows), false);
    await page.click(`${row} button.seeds-toggle`);
    await page.waitForSelector(seedRows, { state: 'visible' });
    for (const job of jobs) {
      const seedRow = `${seedRows}[data-seed="${job.seed}"]`;
      assert.ok(await page.$(`${seedRow} a.job-link[href="#/jobs/${job.job_id}"]`), `${label} seed ${job.seed} links its job`);
      assert.ok(await page.$(`${seedRow} a.policy-link[href="#/policies/${job.policy_id}"]`), `${label} seed ${job.seed} links its policy`);
      const shown = await page.textContent(`${seedRow} td.seed-value[data-metric="normalized_return"]`);
      assert.ok(closeToShown(shown, job.metrics.normalized_return, 4), `${label} seed ${job.seed}: ${shown}`);
    }
  }

  // Each job evaluated once, after its last step (SafeDICE's comes after its discriminator's).
  for (const job of experiment.jobs) {
    const [resource, rows] = await Promise.all([api(`/v1/jobs/${job.job_id}`), api(`/v1/jobs/${job.job_id}/metrics?names=eval/normalized_return`)]);
    assert.deepEqual(rows.body.rows.map((r) => r.step), [resource.body.progress.total]);
    assert.equal(resource.body.progress.total, resource.body.pretraining_steps + 300);
  }

  // The curves: eval/normalized_return by default (a metric every algorithm has), one mean line
  // per algorithm (with its band), over policy iterations: both algorithms' evaluations at 300,
  // though SafeDICE's were recorded at step 600 of its run (its discriminator came first).
  await page.waitForSelector('.chart-box[data-chart="experiment-curves"] .u-over');
  assert.equal(await page.inputValue('#curve-metric'), 'eval/normalized_return');
  const curves = '.chart-box[data-chart="experiment-curves"]';
  const curveNames = JSON.parse(await page.getAttribute(curves, 'data-series')).map(([name]) => name);
  assert.deepEqual(curveNames.filter((n) => !/SE$/.test(n)).sort(), [...labels].sort());
  assert.deepEqual(await page.$eval(curves, (b) => [...b.uplot.data[0]]), [300]);
  assert.equal(await page.$eval(curves, (b) => b.uplot.axes[0].label), 'policy iteration');
  /** Pixels of each colour the curves' canvas has drawn (what the user sees, not the options). */
  const drawn = (colors) => page.$eval(`${curves} canvas`, (canvas, hexes) => {
    const { data } = canvas.getContext('2d').getImageData(0, 0, canvas.width, canvas.height);
    const rgb = hexes.map((hx) => [1, 3, 5].map((i) => parseInt(hx.slice(i, i + 2), 16)));
    const counts = hexes.map(() => 0);
    for (let i = 0; i < data.length; i += 4) {
      rgb.forEach((c, k) => { if (data[i + 3] > 200 && c.every((v, j) => Math.abs(v - data[i + j]) <= 10)) counts[k] += 1; });
    }
    return counts;
  }, colors);
  const algorithmColors = Object.fromEntries((await api('/v1/algorithms')).body.items.map((a) => [a.name, a.color]));
  const armColors = experiment.algorithms.map((a) => algorithmColors[a.algorithm]);
  assert.ok((await drawn(armColors)).every((n) => n > 0), `mean curves drawn: ${await drawn(armColors)}`);
  await page.selectOption('#curve-mode', 'seeds');
  await page.waitForFunction(() => {
    const box = document.querySelector('.chart-box[data-chart="experiment-curves"]');
    return box && box.dataset.series && JSON.parse(box.dataset.series).length === 6;
  });
  await page.waitForTimeout(200);
  // One point per seed: each is drawn as a marker, not an empty chart of one-point lines.
  assert.ok((await drawn(armColors)).every((n) => n > 0), `each seed drawn: ${await drawn(armColors)}`);
  await page.selectOption('#curve-mode', 'mean');
  await page.waitForFunction(() => {
    const box = document.querySelector('.chart-box[data-chart="experiment-curves"]');
    return box && box.dataset.series && !JSON.parse(box.dataset.series).some(([n]) => / · seed /.test(n));
  });

  // The scatter: one point per algorithm at its means, error bars where the seeds differ.
  const points = await page.$$eval('.chart-box[data-chart="experiment-scatter"] g.point', (gs) => gs.map((g) => ({ label: g.dataset.label, x: Number(g.dataset.x), y: Number(g.dataset.y) })));
  assert.deepEqual(points.map((p) => p.label).sort(), [...labels].sort());
  for (const p of points) {
    const result = experiment.results.find((r) => r.label === p.label);
    assert.equal(p.x, result.metrics.average_cost.mean);
    assert.equal(p.y, result.metrics.normalized_return.mean);
  }
  const anySpread = experiment.results.some((r) => r.metrics.normalized_return.se > 0 || r.metrics.average_cost.se > 0);
  if (anySpread) assert.ok(await page.$('.chart-box[data-chart="experiment-scatter"] line.error-bar'));

  // One seed evaluated once more, deterministically: the page says the results are mixed, keeps
  // the means under the protocol every seed has, and offers the other.
  assert.equal(await page.textContent('#experiment-protocol'), 'six-rooms · 50 episodes · seed 0 · sampled · built-in');
  const queued = await post(`/v1/policies/${experiment.jobs[0].policy_id}/evaluate`, { env: 'six-rooms', episodes: 50, deterministic: true });
  assert.equal(queued.status, 202);
  for (let i = 0; i < 600 && (await api(`/v1/evaluations/${queued.body.id}`)).body.status !== 'succeeded'; i++) await page.waitForTimeout(100);
  await page.reload();
  await page.waitForSelector('#experiment-mixed select#experiment-protocol');
  assert.deepEqual((await api(`/v1/experiments/${id}`)).body.results, experiment.results);
  const offered = await page.$$eval('#experiment-protocol option', (os) => os.map((o) => o.textContent));
  assert.deepEqual(offered, ['six-rooms · 50 episodes · seed 0 · sampled · built-in (6 of 6 jobs)',
    'six-rooms · 50 episodes · seed 0 · deterministic · built-in (1 of 6 jobs)']);
  for (const width of [1400, 500]) {
    await page.setViewportSize({ width, height: 900 });
    await page.waitForTimeout(200);
    assert.deepEqual(await layoutProblems(), [], `experiment with mixed protocols at ${width}px`);
  }
  await page.setViewportSize({ width: 1360, height: 900 });

  // The CSV of the results, one line per job and metric.
  const file = await downloaded(() => page.click('#experiment-csv'));
  const lines = file.bytes.toString().trim().split('\n');
  assert.equal(lines[0], 'arm,algorithm,protocol,stat,seed,job_id,metric,value');
  const bcSeed0 = experiment.jobs.find((j) => j.arm === 'bc' && j.seed === 0);
  assert.ok(lines.some((l) => l.startsWith(`bc,bc,${bcSeed0.protocol},value,0,${bcSeed0.job_id},normalized_return,`)));

  for (const width of [1400, 500]) {
    await page.setViewportSize({ width, height: 900 });
    await page.waitForTimeout(300); // charts take their width on the next frame
    assert.deepEqual(await layoutProblems(), [], `experiment page at ${width}px`);
    assert.deepEqual(await labelProblems('.chart-box[data-chart="experiment-scatter"] svg'), [], `experiment scatter at ${width}px`);
    await screenshot(`experiment-${width}`);
  }
  await page.goto(`${base}/#/experiments`);
  await page.waitForSelector('#experiments-table');
  assert.equal(await page.textContent(`#experiments-table tr[data-id="${id}"] .experiment-status`), 'finished');
  assert.deepEqual(await layoutProblems(), [], 'experiments list at 500px');
  await screenshot('experiments-500');
  await page.setViewportSize({ width: 1360, height: 900 });
  state.experiment = id;
});

test('an experiment is cancelled and deleted through the page’s dialog; deleting an active one shows the server’s refusal', async () => {
  const created = await post('/v1/experiments', { name: 'to cancel', unlabeled_dataset: state.unlabeled.id, algorithms: ['bc'],
    seed_count: 1, config: { iterations: 200000, hidden_sizes: [32, 32], batch_size: 64 } });
  assert.equal(created.status, 201);
  const id = created.body.id;
  await page.goto(`${base}/#/experiments/${id}`);
  await page.waitForSelector('#experiment-progress[data-active="true"]');
  await page.click('#experiment-delete');
  await page.waitForSelector('#model-dialog[open]');
  await page.click('#dialog-confirm');
  assert.equal(await (await page.waitForSelector('#model-dialog .dialog-error .error-code')).textContent(), 'experiment_active');
  await page.click('#dialog-cancel');
  await page.click('#experiment-cancel');
  await page.waitForSelector('#model-dialog[open]');
  await page.click('#dialog-confirm');
  await page.waitForSelector('#experiment-cancelled');
  await page.waitForSelector('#experiment-progress[data-active="false"]');
  assert.match(await page.textContent('#experiment-progress'), /1 cancelled/);
  await page.goto(`${base}/#/experiments`);
  assert.equal(await (await page.waitForSelector(`#experiments-table tr[data-id="${id}"] .experiment-status`)).textContent(), '1 cancelled');
  await page.goto(`${base}/#/experiments/${id}`);
  await page.waitForSelector('#experiment-delete');
  await page.click('#experiment-delete');
  await page.click('#dialog-confirm');
  await page.waitForFunction(() => location.hash === '#/experiments');
  assert.equal((await api(`/v1/experiments/${id}`)).status, 404);
  await page.waitForSelector(`#experiments-table tr[data-id="${state.experiment}"]`);
  assert.equal(await page.$(`#experiments-table tr[data-id="${id}"]`), null);
});

test('Compare with four jobs keeps every column within reach and its scatter labels told apart, at 1400 and 500 px', async () => {
  for (const width of [1400, 500]) {
    await page.setViewportSize({ width, height: 900 });
    await page.goto(`${base}/#/compare`);
    // The four newest finished jobs are ticked: the experiment's, "browser grid · <arm> · seed <s>".
    await page.waitForFunction(() => document.querySelectorAll('#compare-table thead th').length === 5);
    const headers = await page.$$eval('#compare-table thead th.num', (ths) => ths.map((t) => t.textContent));
    assert.ok(headers.every((t) => t.includes('browser grid · ')), JSON.stringify(headers));
    await page.waitForTimeout(300);
    assert.deepEqual(await layoutProblems(), [], `compare with 4 jobs at ${width}px`);
    // Every column can be brought into view: scrolled to its end, the table shows its last
    // column whole (a table cut by its card would not).
    const beyond = await page.$eval('#compare-table', (table) => {
      const wrap = table.closest('.table-wrap');
      wrap.scrollLeft = wrap.scrollWidth;
      const frame = wrap.getBoundingClientRect();
      const out = [...table.querySelectorAll('thead th')].filter((c) => c.getBoundingClientRect().right > Math.min(frame.right, window.innerWidth) + 0.5)
        .map((c) => c.textContent);
      wrap.scrollLeft = 0;
      return out;
    });
    assert.deepEqual(beyond, [], `columns out of reach at ${width}px`);
    // In a wide window the four columns are all in view, none behind a sideways scroll.
    if (width === 1400) assert.ok(await page.$eval('#compare-table', (t) => t.closest('.table-wrap').scrollWidth <= t.closest('.table-wrap').clientWidth + 1), 'the table fits at 1400px');
    const labels = await page.$$eval('.chart-box[data-chart="scatter"] text.point-label', (ts) => ts.map((t) => t.textContent));
    assert.equal(labels.length, 4);
    assert.equal(new Set(labels).size, 4, JSON.stringify(labels));
    assert.deepEqual(await labelProblems('.chart-box[data-chart="scatter"] svg'), [], `compare's scatter at ${width}px`);
    await screenshot(`compare-4-${width}`);
  }
  await page.setViewportSize({ width: 1360, height: 900 });
});

test('every page, the model and experiment pages included, keeps its layout and its chart labels at 1400 and 500 px', async () => {
  // A dataset named as D4RL and DSRL name theirs, long and without spaces.
  const form = new FormData();
  form.append('file', new Blob([readFileSync(join(work, 'demo', 'unlabeled.jsonl'))]), 'unlabeled.jsonl');
  form.append('name', 'OfflinePointGoal1Gymnasium-v0-medium-replay-from-dsrl');
  assert.equal((await api('/v1/datasets', { method: 'POST', body: form })).status, 201);
  const pages = [['#/datasets', '#datasets-table'], ['#/jobs', '#jobs-table'], [`#/jobs/${state.job.id}`, '#charts .u-over'],
    ['#/compare', '#compare-table'], ['#/experiments', '#experiments-table'],
    [`#/experiments/${state.experiment}`, '.chart-box[data-chart="experiment-curves"] .u-over'], ['#/policies', '#policies-table'],
    [`#/policies/${state.policy}`, '#act-form'], ['#/models', '#models-table'], ['#/models/pilot', '#history-table']];
  for (const width of [1400, 500]) {
    await page.setViewportSize({ width, height: 900 });
    for (const [hash, ready] of pages) {
      await page.goto(`${base}/${hash}`);
      await page.waitForSelector(ready);
      await page.waitForTimeout(300); // charts take their width on the next frame
      assert.deepEqual(await layoutProblems(), [], `${hash} at ${width}px`);
      assert.deepEqual(await labelProblems('svg.scatter'), [], `${hash}'s chart labels at ${width}px`);
    }
    await page.goto(`${base}/#/models/pilot`);
    await page.waitForSelector('#history-table');
    await screenshot(`model-${width}`);
  }
  await page.setViewportSize({ width: 1360, height: 900 });
});

test('with an API token the pages say so once, then work once the token is saved', async () => {
  const secured = await startServer('token', ['--api-token', TOKEN]);
  await page.goto(`${secured}/#/jobs`);
  await page.waitForSelector('#token-banner', { state: 'visible' });
  await page.waitForTimeout(1500); // every request of the page has been refused by now
  const saying = await page.$$eval('body *', (els) => els.filter((e) => e.children.length === 0
    && e.offsetParent !== null && /requires an API token/.test(e.textContent)).length);
  assert.equal(saying, 1);
  assert.equal(await page.$$eval('.error-box', (boxes) => boxes.length), 0);
  await page.fill('#token', TOKEN);
  await page.click('#token-form button');
  await page.waitForSelector('#token-banner', { state: 'hidden' });
  await page.waitForSelector('#job-form .empty, #jobs-list .empty');
  assert.equal(await page.evaluate(() => sessionStorage.getItem('safedice.token')), TOKEN);
  await page.evaluate(() => sessionStorage.clear());
});

// ---------- after the demo ----------

/** `safedice demo --serve` on a free port with its own data dir (short runs: the test is about
 *  what the pages show, not how well the policies do); resolves once both of the demo's
 *  evaluations have succeeded, with the server's address. */
async function startDemo() {
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

test('after demo --serve, Compare shows both policies’ paper metrics and a cost-return point for each', async () => {
  const demo = await startDemo();
  const get = async (path) => (await fetch(`${demo}${path}`)).json();
  const jobs = (await get('/v1/jobs')).items;
  assert.deepEqual(jobs.map((j) => j.algorithm).sort(), ['bc', 'safedice']);
  await page.setViewportSize({ width: 1400, height: 900 });
  await page.goto(`${demo}/#/compare`);
  await page.waitForFunction(() => document.querySelectorAll('#compare-table thead th').length === 3);
  // The paper's metrics for both, from the demo's evaluations (POST …/evaluate).
  const rows = await page.$$eval('#compare-table tr[data-metric]', (trs) => trs.map((tr) => tr.dataset.metric));
  assert.deepEqual(rows, ['eval/normalized_return', 'eval/average_cost', 'eval/cost_violation_ratio',
    'eval/cvar_cost_50', 'eval/cvar_cost_20', 'eval/cvar_cost_10', 'eval/cvar_cost_5']);
  assert.equal(await page.$('#compare-unevaluated'), null);
  assert.equal(await page.textContent('#compare-protocol'), 'six-rooms · 50 episodes · seed 0 · sampled · built-in');
  assert.equal(await page.inputValue('#scatter-x'), 'eval/average_cost');
  assert.equal(await page.inputValue('#scatter-y'), 'eval/normalized_return');
  const points = await page.$$eval('.chart-box[data-chart="scatter"] g.point', (gs) => gs.map((g) => ({ label: g.dataset.label, x: Number(g.dataset.x), y: Number(g.dataset.y) })));
  assert.equal(points.length, 2);
  const headers = await page.$$eval('#compare-table thead th.num', (ths) => ths.map((t) => t.textContent));
  for (const job of jobs) {
    const [evaluation] = (await get(`/v1/evaluations?policy_id=${job.policy_id}`)).items;
    const point = points.find((p) => headers.some((hd) => hd.includes(p.label)) && p.x === evaluation.metrics.average_cost);
    assert.ok(point, `a point at ${job.algorithm}'s evaluation: ${JSON.stringify(points)}`);
    assert.equal(point.y, evaluation.metrics.normalized_return);
  }
  assert.deepEqual(await labelProblems('.chart-box[data-chart="scatter"] svg'), []);
  await screenshot('compare-after-demo');
  await page.setViewportSize({ width: 500, height: 900 });
  await page.waitForTimeout(200);
  assert.deepEqual(await labelProblems('.chart-box[data-chart="scatter"] svg'), []);
  assert.deepEqual(await layoutProblems(), []);
  await screenshot('compare-after-demo-500');
  await page.setViewportSize({ width: 1360, height: 900 });
});

test('no uncaught errors in the pages', () => {
  assert.deepEqual(state.pageErrors || [], []);
});
