// The dashboard's browser tests, part 2: models, versions, aliases, canaries and shadows,
// on the job and policy part 1 trained.

import { test } from 'node:test';
import assert from 'node:assert/strict';
import { page, base, state, api, post, finished, layoutProblems, screenshot, closeToShown } from './session.mjs';

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
