// The dashboard's browser tests, part 3: layout in narrow windows, experiments, Compare with
// four jobs, the API token, the pages after `demo --serve`, and no uncaught page errors.

import { test } from 'node:test';
import assert from 'node:assert/strict';
import { readFileSync } from 'node:fs';
import { join } from 'node:path';
import { here, TOKEN, work, page, base, state, startServer, api, post, finished, downloaded, layoutProblems, labelProblems, screenshot, actionsOutOfView, startDemo, closeToShown, meanSe } from './session.mjs';

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
