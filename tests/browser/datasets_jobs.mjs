// The dashboard's browser tests, part 1: datasets, the job form and list, the job page, the
// policy page and Compare, on the session of session.mjs.

import { test } from 'node:test';
import assert from 'node:assert/strict';
import { readFileSync, writeFileSync } from 'node:fs';
import { join } from 'node:path';
import { here, ITERATIONS, work, page, base, state, api, post, finished, downloaded, layoutProblems, screenshot, closeToShown } from './session.mjs';

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

/** Waits for the job form's estimate (the server's plan of the typed knobs) to match `pattern`. */
async function estimateMatches(pattern) {
  await page.waitForFunction(([source, flags]) => new RegExp(source, flags).test(document.querySelector('#job-estimate')?.textContent || ''),
    [pattern.source, pattern.flags], { timeout: 10_000 }).catch(async () => {
    assert.match(await page.textContent('#job-estimate'), pattern);
  });
}

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
  await estimateMatches(/^200,000 steps = 100,000 discriminator pretraining \+ 100,000 policy iterations: no finished job/);
  assert.equal(await page.getAttribute('#job-discriminator_iterations', 'placeholder'), 'iterations');
  await page.fill('#job-name', 'six-rooms safedice small');
  await page.fill('#job-tags', 'browser, six-rooms');
  await page.fill('#job-notes', 'queued from the dashboard test');
  // A knob the server would refuse says why before anything is queued.
  await page.fill('#job-iterations', '0');
  await estimateMatches(/^Not a configuration a job accepts: config\.iterations/);
  assert.equal(await page.getAttribute('#job-estimate', 'class'), 'estimate invalid');
  await page.fill('#job-iterations', String(ITERATIONS));
  await estimateMatches(new RegExp(`^${(ITERATIONS * 2).toLocaleString('en-US')} steps = ${ITERATIONS.toLocaleString('en-US')} discriminator pretraining`));
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
  await estimateMatches(/: about .+ at the pace of “six-rooms safedice small”/);

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
  // The weighting stage in words, with the numbers the metrics hold (the service preset pools
  // the discriminator's scores by episode; this D^U has 80 episodes, enough to).
  const lastOf = (name) => pointsOf(name).at(-1)?.value;
  const three = (v) => String(Number(v.toPrecision(3)));
  assert.equal(lastOf('weighting_uniform'), 0);
  assert.equal(lastOf('discriminator_scores_pooled_by_episode'), 1);
  assert.equal(await page.locator('#weighting-uniform').count(), 0);
  const weighting = await page.textContent('#weighting-summary');
  assert.ok(weighting.startsWith('Weighting: SafeDICE. alpha-hat ' + three(lastOf('alpha_hat'))
    + ` (interval ${three(lastOf('alpha_hat_lower'))} `), weighting);
  assert.ok(weighting.includes(`held-out ROC AUC ${three(lastOf('discriminator_heldout_auc'))} `
    + `(${three(lastOf('discriminator_heldout_auc_lower'))} to ${three(lastOf('discriminator_heldout_auc_upper'))})`), weighting);
  assert.match(weighting, /Eq\. 10 read each unlabeled episode’s mean discriminator logit\.$/);
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
