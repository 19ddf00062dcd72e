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
import { mkdtempSync, readFileSync, rmSync, mkdirSync } from 'node:fs';
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

test('datasets chosen in the upload box are stored and listed with their statistics', async () => {
  await page.goto(`${base}/#/datasets`);
  for (const [file, name] of [['unlabeled.jsonl', 'six-rooms unlabeled'], ['non_preferred.jsonl', 'six-rooms non-preferred']]) {
    await page.fill('#upload-name', name);
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
    assert.equal(cells[2], dataset.transitions.toLocaleString('en-US'));
    assert.equal(cells[3], dataset.episodes.toLocaleString('en-US'));
    if (dataset.stats.episode_return) assert.match(cells[6], /±/);
  }
  state.unlabeled = body.items.find((d) => d.name === 'six-rooms unlabeled');
  state.nonPreferred = body.items.find((d) => d.name === 'six-rooms non-preferred');
  await screenshot('datasets');
});

test('the submit form creates a job with the chosen algorithm, datasets and knobs', async () => {
  await page.goto(`${base}/#/jobs`);
  await page.waitForSelector('#job-form');
  await page.selectOption('#job-algorithm', 'safedice');
  await page.selectOption('#job-unlabeled', state.unlabeled.id);
  await page.selectOption('#job-non-preferred', state.nonPreferred.id);
  await page.fill('#job-iterations', String(ITERATIONS));
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
  assert.equal(job.algorithm, 'safedice');
  assert.equal(job.unlabeled_dataset, state.unlabeled.id);
  assert.equal(job.non_preferred_dataset, state.nonPreferred.id);
  assert.equal(job.config.iterations, ITERATIONS);
  assert.equal(job.config.seed, 7);
  assert.deepEqual(job.config.hidden_sizes, [32, 32]);
  assert.equal(job.config.batch_size, 64);
  assert.equal(job.runner.log_every, 25);
  assert.deepEqual(job.eval, { env: 'six-rooms', every: ITERATIONS / 4, episodes: 100, seed: 0, deterministic: false });
  assert.ok(await page.isVisible(`#job-created a[href="#/jobs/${job.id}"]`));
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

  // Whether that job was ever seen running depends on the machine's speed (a fast build trains
  // it between two refreshes), so the running rows are watched on a job of the API's maximum
  // length, which no machine finishes while the test watches; its Cancel button then stops it.
  const created = await api('/v1/jobs', {
    method: 'POST', headers: { 'content-type': 'application/json' },
    body: JSON.stringify({ algorithm: 'bc', unlabeled_dataset: state.unlabeled.id,
      config: { iterations: 100_000_000, hidden_sizes: [32, 32], batch_size: 64, seed: 2 } }),
  });
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
  await page.click(`${endless} button.cancel`);
  await page.waitForSelector(`${endless}[data-status="cancelled"]`);
  assert.equal((await api(`/v1/jobs/${created.body.id}`)).body.status, 'cancelled');
  assert.equal(await page.evaluate(() => window.__sameDocument), true);
});

test('the job page charts the training metrics with their data points', async () => {
  await page.goto(`${base}/#/jobs/${state.job.id}`);
  await page.waitForSelector('#charts .chart-box[data-chart="losses"] svg polyline.series');
  const metrics = (await api(`/v1/jobs/${state.job.id}/metrics?max_points=300`)).body.rows;
  const pointsOf = (name) => metrics.filter((r) => r.name === name).length;
  const lines = await page.$$eval('#charts polyline.series', (els) => els.map((e) => ({
    name: e.dataset.series, points: Number(e.dataset.points), coordinates: e.getAttribute('points').trim().split(/\s+/).length,
  })));
  assert.ok(lines.length >= 3, `charted series: ${JSON.stringify(lines)}`);
  for (const line of lines) {
    assert.equal(line.points, pointsOf(line.name), line.name);
    assert.equal(line.coordinates, line.points, line.name);
  }
  const losses = lines.filter((l) => l.name.endsWith('_loss'));
  assert.ok(losses.length >= 2 && losses.every((l) => l.points > 10), JSON.stringify(losses));
  // Axis titles and the alpha-hat chart of SafeDICE are there; the resolved config is shown.
  const lossesChart = page.locator('.chart-box[data-chart="losses"] svg');
  assert.equal(await lossesChart.locator('.x-label').textContent(), 'training step (all phases)');
  const alphaPoints = await page.$eval('.chart-box[data-chart="alpha"] svg polyline.series', (e) => Number(e.dataset.points));
  assert.ok(alphaPoints >= 1);
  assert.match(await page.textContent('#job-config'), new RegExp(`iterations\\s*${ITERATIONS}`));

  // The evaluation section: the paper's metrics at policy steps ITERATIONS/4, /2, 3/4 and the end.
  await page.waitForSelector('#eval-charts .chart-box[data-chart="eval-cost"] svg polyline.series');
  const evalLines = await page.$$eval('#eval-charts polyline.series', (els) => els.map((e) => ({
    name: e.dataset.series, points: Number(e.dataset.points) })));
  const evalRows = metrics.filter((r) => r.name.startsWith('eval/'));
  assert.equal(evalRows.filter((r) => r.name === 'eval/average_cost').length, 4);
  const charted = evalLines.map((l) => l.name).sort();
  assert.deepEqual(charted, ['CVaR 10%', 'CVaR 20%', 'CVaR 50%', 'CVaR 5%', 'eval/average_cost',
    'eval/cost_violation_ratio', 'eval/normalized_return'].sort());
  assert.ok(evalLines.every((l) => l.points === 4), JSON.stringify(evalLines));
  const lastCost = evalRows.filter((r) => r.name === 'eval/average_cost').at(-1).value;
  const latestCost = page.locator('#eval-latest tr', { hasText: 'eval/average_cost' }).locator('td.num');
  assert.equal(Number(await latestCost.textContent()), Number(lastCost.toPrecision(4)));
  await screenshot('job');
});

test('the policy page turns pasted observations into the same actions as the API', async () => {
  const job = (await api(`/v1/jobs/${state.job.id}`)).body;
  assert.ok(job.policy_id);
  state.policy = job.policy_id;
  await page.goto(`${base}/#/policies/${job.policy_id}`);
  await page.waitForSelector('#act-form');
  const obsDim = state.unlabeled.obs_dim;
  const observations = [Array.from({ length: obsDim }, (_, i) => (i % 3) * 0.1), Array(obsDim).fill(0.5)];
  await page.fill('#act-input', observations.map((o) => o.join(', ')).join('\n'));
  await page.click('#act-submit');
  const shown = JSON.parse((await page.textContent('#act-result')).replace(/\n/g, ''));
  const direct = await api(`/v1/policies/${job.policy_id}/act`, {
    method: 'POST', headers: { 'content-type': 'application/json' }, body: JSON.stringify({ observations, deterministic: true }),
  });
  assert.equal(direct.status, 200);
  assert.deepEqual(shown, direct.body.actions);
  assert.match(await page.textContent('#snippet-curl'), new RegExp(`/v1/policies/${job.policy_id}/act`));
  assert.match(await page.textContent('#snippet-oip'), new RegExp(`/v2/models/${job.policy_id}/infer`));
  // A wrong width is answered with the server's message.
  await page.fill('#act-input', '1, 2');
  await page.click('#act-submit');
  assert.ok((await page.textContent('.act-error .error-message')).length > 0);
  await page.fill('#act-input', observations.map((o) => o.join(', ')).join('\n'));
  await page.click('#act-submit');
  await page.waitForSelector('#act-result');

  // Evaluate it in the background: the table fills in with the API's metrics.
  await page.fill('#eval-episodes', '200');
  await page.fill('#eval-seed', '3');
  await page.click('#eval-submit');
  await page.waitForSelector('#evaluations-table tr[data-status="succeeded"]', { timeout: 60_000 });
  const evaluations = (await api(`/v1/evaluations?policy_id=${job.policy_id}`)).body.items;
  assert.equal(evaluations.length, 1);
  const [evaluation] = evaluations;
  assert.deepEqual([evaluation.env, evaluation.episodes, evaluation.seed, evaluation.deterministic], ['six-rooms', 200, 3, false]);
  const row = page.locator(`#evaluations-table tr[data-id="${evaluation.id}"]`);
  assert.equal(Number(await row.locator('.eval-cost').textContent()), Number(evaluation.metrics.average_cost.toPrecision(4)));
  assert.equal(Number(await row.locator('.eval-return').textContent()), Number(evaluation.metrics.normalized_return.toPrecision(4)));
  await screenshot('policy');
});

test('compare shows finished jobs side by side and as a scatter', async () => {
  // A quick BC job beside the SafeDICE one.
  const created = await api('/v1/jobs', {
    method: 'POST', headers: { 'content-type': 'application/json' },
    body: JSON.stringify({ algorithm: 'bc', unlabeled_dataset: state.unlabeled.id,
      config: { iterations: 300, hidden_sizes: [32, 32], batch_size: 64, seed: 1 }, runner: { log_every: 25 },
      eval: { env: 'six-rooms', every: 100, episodes: 100 } }),
  });
  assert.equal(created.status, 201);
  for (let i = 0; i < 600; i += 1) {
    const job = (await api(`/v1/jobs/${created.body.id}`)).body;
    if (job.status === 'succeeded') break;
    assert.ok(job.status === 'queued' || job.status === 'running', `bc job ${job.status}: ${job.error}`);
    await new Promise((r) => setTimeout(r, 200));
  }
  await page.goto(`${base}/#/compare`);
  await page.waitForSelector('#compare-table');
  await page.waitForSelector('.chart-box[data-chart="scatter"] svg');
  const headers = await page.$$eval('#compare-table thead th', (ths) => ths.map((t) => t.textContent));
  assert.equal(headers.length, 3);
  assert.ok(headers.some((t) => t.includes('SafeDICE')) && headers.some((t) => t.includes('BC')));
  const points = await page.$$eval('.chart-box[data-chart="scatter"] svg g.point', (gs) => gs.map((g) => g.dataset.label));
  assert.equal(points.length, 2);
  // Both jobs evaluated themselves: the scatter is the paper's cost vs return by default.
  assert.equal(await page.inputValue('#scatter-x'), 'eval/average_cost');
  assert.equal(await page.inputValue('#scatter-y'), 'eval/normalized_return');
  assert.match(await page.textContent('.chart-box[data-chart="scatter"] svg'), /Cost vs return/);
  await screenshot('compare');
});

test('with an API token the pages say so, then work once the token is saved', async () => {
  const secured = await startServer('token', ['--api-token', TOKEN]);
  await page.goto(`${secured}/#/datasets`);
  const message = await page.waitForSelector('#datasets-list .error-box .error-message');
  assert.match(await message.textContent(), /requires an API token/);
  await page.fill('#token', TOKEN);
  await page.click('#token-form button');
  await page.waitForSelector('#datasets-list .empty');
  assert.equal(await page.evaluate(() => sessionStorage.getItem('safedice.token')), TOKEN);
  await page.evaluate(() => sessionStorage.clear());
});

test('no uncaught errors in the pages', () => {
  assert.deepEqual(state.pageErrors || [], []);
});
