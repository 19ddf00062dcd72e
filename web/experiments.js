// SafeDICE dashboard, the experiments pages: a grid of algorithms × seeds queued as jobs
// (/v1/experiments), its progress, the paper's metrics per algorithm as mean ± standard error
// over the seeds (with each seed's value, job and policy), the training curves of the grid and a
// cost-vs-return scatter with error bars. Loaded after models.js (its confirmation dialog) and
// before app.js, whose route table names these pages.
'use strict';

const EXPERIMENT_POLL_MS = 1500;
/** Points per job and metric the curves ask for (the server picks them by LTTB). */
const CURVE_POINTS = 300;
/** The paper's metrics as an experiment reports them (`eval/` stripped), in the paper's order,
 *  then DSRL's normalized cost: the server's vocabulary ({key, label, ...}). */
const EXPERIMENT_METRICS = [...PAPER_METRIC_INFO,
  ...VOCABULARY.evaluation_metrics.filter((m) => m.kind === 'dsrl')];
// The job statuses in the server's lifecycle order: those a job leaves (queued, running) and
// its endings other than the success (SUCCESS, lib.js).
const UNFINISHED = JOB_STATUSES.filter((s) => !s.final).map((s) => s.name);
const OTHER_ENDINGS = JOB_STATUSES.filter((s) => s.final && !s.success).map((s) => s.name);

const unfinishedCount = (p) => UNFINISHED.reduce((sum, s) => sum + p[s], 0);
/** Jobs of a grid that ended, whatever the end. */
const finishedCount = (p) => p.total - unfinishedCount(p);

const experimentHref = (id) => `#/experiments/${id}`;
const experimentTitle = (e) => e.name || shortId(e.id);
const gridActive = (e) => unfinishedCount(e.progress) > 0;

/** Where a grid stands, from its progress counts: [word, status class for the pill]: the
 *  latest stage any job is still in (with how many are done, unless none has started), then
 *  finished, or how many ended otherwise (failed, discarded, cancelled). */
function gridStatus(p) {
  const finished = finishedCount(p);
  for (const stage of [...UNFINISHED].reverse()) {
    if (!p[stage]) continue;
    const bare = stage === UNFINISHED[0] && !finished;
    return [bare ? stage : `${stage} (${finished} of ${p.total} done)`, stage];
  }
  for (const end of OTHER_ENDINGS) {
    if (p[end]) return [`${p[end]} ${end}`, end];
  }
  return ['finished', SUCCESS];
}

/** "12.34 ± 0.56": the mean to 4 significant digits, its standard error to 2; the mean alone
 *  when there is no standard error (one seed). */
function meanSeText(summary) {
  if (!summary) return '—';
  if (summary.se === null || summary.se === undefined) return fmt(summary.mean, 4);
  return `${fmt(summary.mean, 4)} ± ${fmt(summary.se, 2)}`;
}

/** A colour per arm: the algorithm's accent for its first arm, a palette colour for another arm
 *  of the same algorithm. */
function armColors(experiment) {
  const seen = new Set();
  return new Map(experiment.algorithms.map((arm, i) => {
    const label = arm.label || arm.algorithm;
    const color = seen.has(arm.algorithm) ? PALETTE[i % PALETTE.length] : algoColor(arm.algorithm);
    seen.add(arm.algorithm);
    return [label, color];
  }));
}

// ---------- the list and the form ----------

function experimentsTable(items) {
  if (!items.length) {
    return h('div', { class: 'empty' }, 'No experiments yet. Create one above: every algorithm × every seed is queued as a job.');
  }
  return tableWrap(h('table', { id: 'experiments-table' },
    h('thead', {}, h('tr', {}, h('th', {}, 'Experiment'), h('th', {}, 'Status'), h('th', {}, 'Algorithms'), h('th', { class: 'num' }, 'Seeds'), h('th', {}, 'Created'))),
    h('tbody', {}, items.map((e) => h('tr', { 'data-id': e.id, 'data-status': gridStatus(e.progress)[1] },
      h('td', {}, h('a', { href: experimentHref(e.id), class: e.name ? 'experiment-name' : 'mono experiment-name' }, experimentTitle(e)),
        h('div', { class: 'muted mono' }, shortId(e.id))),
      h('td', { class: 'experiment-status', title: progressText(e.progress) },
        h('span', { class: `status status-${gridStatus(e.progress)[1]}` }, gridStatus(e.progress)[0])),
      h('td', { class: 'algorithms' }, e.algorithms.map((label) => (ALGORITHMS[label] ? algoBadge(label) : h('span', { class: 'tag' }, label)))),
      h('td', { class: 'num' }, String(e.seeds.length)),
      h('td', {}, fmtTime(e.created_at)))))));
}

/** The create form: datasets by role, algorithm checkboxes (the server's table), seeds, the
 *  knobs every job shares, an optional in-training evaluation. Empty fields are not sent. */
function experimentForm(datasets, envs, onCreated) {
  const option = (d) => h('option', { value: d.id }, `${d.name} (${fmt(d.transitions)} transitions)`);
  const name = h('input', { id: 'exp-name', placeholder: 'e.g. six-rooms grid', autocomplete: 'off' });
  const unlabeled = h('select', { id: 'exp-unlabeled' }, datasetChoices(datasets, 'unlabeled').map(option));
  const nonPreferred = h('select', { id: 'exp-non-preferred' }, h('option', { value: '' }, '— none —'),
    datasetChoices(datasets, 'non_preferred').map(option));
  const firstNonPreferred = datasets.find((d) => d.role === 'non_preferred');
  if (firstNonPreferred) nonPreferred.value = firstNonPreferred.id;
  const algorithms = h('div', { class: 'checks', id: 'exp-algorithms' }, Object.keys(ALGORITHMS).map((value) =>
    h('label', {}, h('input', { type: 'checkbox', value, checked: value === 'safedice' || value === 'bc' }), algoBadge(value))));
  const seeds = h('input', { id: 'exp-seeds', inputmode: 'numeric', placeholder: '3' });
  const iterations = h('input', { id: 'exp-iterations', inputmode: 'numeric', placeholder: 'preset' });
  const hidden = h('input', { id: 'exp-hidden-sizes', placeholder: 'preset, e.g. 64,64' });
  const batch = h('input', { id: 'exp-batch-size', inputmode: 'numeric', placeholder: 'preset' });
  const evalEnv = h('select', { id: 'exp-eval-env' });
  const every = h('input', { id: 'exp-eval-every', inputmode: 'numeric', placeholder: 'at the end' });
  const episodes = h('input', { id: 'exp-eval-episodes', inputmode: 'numeric', placeholder: 'server default' });
  const tags = h('input', { id: 'exp-tags', placeholder: 'comma-separated' });
  const submit = h('button', { type: 'submit', id: 'exp-submit' }, 'Queue experiment');
  const result = h('div', { id: 'exp-form-result' });
  const fillEnvs = () => {
    const dataset = datasets.find((d) => d.id === unlabeled.value);
    const fitting = dataset ? envs.filter((e) => envFits(e, dataset.obs_dim, dataset.action_space)) : [];
    evalEnv.replaceChildren(h('option', { value: '' }, 'no evaluation'), ...fitting.map((e) => h('option', { value: e.name }, e.name)));
    if (fitting.length) evalEnv.value = fitting[0].name;
  };
  unlabeled.addEventListener('change', fillEnvs);
  fillEnvs();
  const form = h('form', { id: 'experiment-form', class: 'card', autocomplete: 'off' }, h('h2', {}, 'New experiment'),
    h('div', { class: 'form-grid' },
      h('label', {}, 'Name', name),
      h('label', {}, 'Unlabeled dataset Dᵁ', unlabeled),
      h('label', {}, 'Non-preferred dataset Dᴺ', nonPreferred),
      h('label', {}, 'Tags', tags),
      h('div', { class: 'algo-field' }, h('span', {}, 'Algorithms'), algorithms),
      h('label', {}, 'Seeds (0 … n−1)', seeds),
      h('label', {}, 'Iterations', iterations),
      h('label', {}, 'Hidden sizes', hidden),
      h('label', {}, 'Batch size', batch),
      h('label', {}, 'Evaluate on', evalEnv),
      h('label', {}, 'Evaluate every (policy steps)', every),
      h('label', {}, 'Evaluation episodes', episodes)),
    h('p', { class: 'hint' }, 'Every checked algorithm is trained once per seed on the same datasets (BC never reads Dᴺ). Empty fields take each algorithm’s preset. With an environment, each job evaluates itself at the end of training (and every N policy steps if “Evaluate every” is set); the results are the paper’s metrics per algorithm as mean ± standard error over the seeds.'),
    h('div', { class: 'form-actions' }, submit), result);
  form.addEventListener('submit', async (event) => {
    event.preventDefault();
    result.replaceChildren();
    const num = (input) => Number(input.value.trim());
    const body = {
      unlabeled_dataset: unlabeled.value,
      algorithms: [...algorithms.querySelectorAll('input:checked')].map((box) => box.value),
      seed_count: seeds.value.trim() ? num(seeds) : 3,
      tags: parseTags(tags.value),
    };
    if (name.value.trim()) body.name = name.value.trim();
    if (nonPreferred.value) body.non_preferred_dataset = nonPreferred.value;
    const config = {};
    if (iterations.value.trim()) config.iterations = num(iterations);
    if (hidden.value.trim()) config.hidden_sizes = hidden.value.split(/[\s,]+/).filter(Boolean).map(Number);
    if (batch.value.trim()) config.batch_size = num(batch);
    if (Object.keys(config).length) body.config = config;
    if (evalEnv.value) {
      body.eval = { env: evalEnv.value };
      if (every.value.trim()) body.eval.every = num(every);
      if (episodes.value.trim()) body.eval.episodes = num(episodes);
    }
    submit.disabled = true;
    try {
      const experiment = await api('/v1/experiments', { method: 'POST', json: body });
      result.replaceChildren(h('div', { class: 'notice', id: 'experiment-created' }, 'Queued ',
        h('a', { href: experimentHref(experiment.id) }, experimentTitle(experiment)),
        `: ${experiment.progress.total} jobs (${experiment.algorithms.length} algorithms × ${experiment.seeds.length} seeds).`));
      onCreated(experiment);
    } catch (err) {
      result.replaceChildren(errorBox(err, 'experiment-form-error'));
    } finally {
      submit.disabled = false;
    }
  });
  return form;
}

function experimentsPage(view) {
  const formSlot = h('div', {}, h('div', { class: 'card muted' }, 'Loading the datasets…'));
  const list = h('div', { id: 'experiments-list' });
  const pages = pagedList({ path: '/v1/experiments', size: PAGE_SIZE, id: 'experiments-pager',
    render: (items) => list.replaceChildren(experimentsTable(items)) });
  const reload = () => pages.reload().catch((err) => list.replaceChildren(errorBox(err)));
  view.append(h('h1', {}, 'Experiments'), formSlot, h('div', { class: 'card' }, h('h2', {}, 'Experiments'), list, pages.nav));
  Promise.all([api('/v1/datasets?limit=100'), api('/v1/envs')]).then(([datasets, envs]) => {
    formSlot.replaceChildren(datasets.items.length
      ? experimentForm(datasets.items, envs.items, reload)
      : h('div', { class: 'card empty' }, 'Upload an unlabeled dataset first, on the ', h('a', { href: '#/datasets' }, 'Datasets'), ' page.'));
  }).catch((err) => formSlot.replaceChildren(errorBox(err)));
  reload();
}

// ---------- one experiment ----------

function progressText(p) {
  const parts = [SUCCESS, ...[...UNFINISHED].reverse()].map((s) => `${p[s]} ${s}`);
  for (const end of OTHER_ENDINGS) {
    if (p[end]) parts.push(`${p[end]} ${end}`);
  }
  return `${finishedCount(p)} of ${p.total} jobs finished: ${parts.join(', ')}`;
}

function experimentSummary(e, actions) {
  const p = e.progress;
  const fraction = p.total ? finishedCount(p) / p.total : 0;
  const csvPath = `/v1/experiments/${e.id}/results.csv`;
  const csv = h('a', { href: csvPath, id: 'experiment-csv', class: 'secondary button-link',
    onclick: (event) => { event.preventDefault(); actions.csv(csvPath); } }, 'Results (CSV)');
  return [h('h2', {}, 'Progress'),
    h('div', { class: 'grid-progress' }, progressBar({ algorithm: 'grid', progress: { fraction } }, true),
      h('span', { id: 'experiment-progress', 'data-active': String(gridActive(e)) }, progressText(p))),
    h('dl', { class: 'kv' },
      h('dt', {}, 'algorithms'), h('dd', {}, e.algorithms.map((a) => (a.label && a.label !== a.algorithm
        ? h('span', { class: 'tag' }, `${a.label} (${algoLabel(a.algorithm)})`) : algoBadge(a.algorithm)))),
      h('dt', {}, 'seeds'), h('dd', {}, e.seeds.join(', ')),
      h('dt', {}, 'datasets'), h('dd', { class: 'mono' }, `Dᵁ ${shortId(e.unlabeled_dataset)}`, e.non_preferred_dataset ? `, Dᴺ ${shortId(e.non_preferred_dataset)}` : ''),
      h('dt', {}, 'config'), h('dd', { class: 'mono wrap-any' }, e.config ? JSON.stringify(e.config) : 'presets'),
      h('dt', {}, 'evaluation'), h('dd', { class: 'mono wrap-any' }, e.eval ? JSON.stringify(e.eval) : 'none in training'),
      e.tags.length ? [h('dt', {}, 'tags'), h('dd', {}, tagChips(e.tags))] : null,
      h('dt', {}, 'created'), h('dd', {}, fmtTime(e.created_at))),
    h('div', { class: 'form-actions wrap' },
      h('button', { type: 'button', class: 'secondary', id: 'experiment-cancel', disabled: !gridActive(e), onclick: actions.cancel }, 'Cancel'),
      h('button', { type: 'button', class: 'danger', id: 'experiment-delete', onclick: actions.remove }, 'Delete'),
      csv),
    h('p', { class: 'hint' }, `The jobs are tagged experiment=${e.id} (`, h('a', { href: '#/jobs' }, 'Jobs'),
      ' page, tag filter). Delete removes the jobs, their metrics and policies, once none is queued or running.')];
}

/** Which evaluation protocol the results are under, and the others the jobs have results under
 *  (a select when there are several: means are taken within one protocol, never across). */
function protocolLine(e, onProtocol) {
  if (!e.protocol) return null;
  const withResults = e.jobs.filter((j) => j.protocols.length).length;
  if (e.protocols.length === 1) {
    return h('p', { class: 'hint', id: 'experiment-protocol-line' }, 'Evaluation protocol: ',
      h('span', { id: 'experiment-protocol', 'data-key': e.protocol.key }, e.protocol.label), '.');
  }
  const select = h('select', { id: 'experiment-protocol', 'aria-label': 'Evaluation protocol',
    onchange: () => onProtocol(select.value) },
  e.protocols.map((p) => h('option', { value: p.protocol.key, selected: p.protocol.key === e.protocol.key },
    `${p.protocol.label} (${p.jobs} of ${withResults} jobs)`)));
  const why = e.protocol_choice === 'most_jobs'
    ? ' No protocol is shared by every job; shown: the one most jobs have, and the means leave out the jobs without it.'
    : '';
  return h('div', { class: 'notice warn', id: 'experiment-mixed' },
    h('p', {}, `The jobs were evaluated under ${e.protocols.length} protocols (environment, episodes, seed, deterministic or sampled actions, runtime). Means are over one protocol, never across them.${why}`),
    h('label', { class: 'protocol-pick' }, 'Show results under ', select));
}

/** The results table: per arm the paper's metrics as mean ± SE and the seeds they are over; a
 *  toggle shows each seed's values with its job and policy. */
function resultsTable(e, expanded, onToggle, onProtocol) {
  const shown = EXPERIMENT_METRICS.filter((m) => m.key !== 'normalized_cost'
    || e.results.some((r) => r.metrics[m.key]));
  const jobsOf = (label) => e.jobs.filter((j) => j.arm === label).sort((a, b) => e.seeds.indexOf(a.seed) - e.seeds.indexOf(b.seed));
  const rows = e.results.map((r) => {
    const counts = shown.map((m) => (r.metrics[m.key] ? r.metrics[m.key].n : 0));
    const n = Math.max(0, ...counts);
    const open = expanded.has(r.label);
    const toggle = h('button', { type: 'button', class: 'secondary seeds-toggle', 'aria-expanded': open ? 'true' : 'false',
      onclick: () => onToggle(r.label) }, open ? '▾ seeds' : '▸ seeds');
    const armRow = h('tr', { class: 'arm-row', 'data-label': r.label, 'data-algorithm': r.algorithm },
      // The seeds' toggle beside the arm's name, in view however wide the table is.
      h('td', { class: 'arm' }, algoBadge(r.algorithm), r.label !== r.algorithm ? h('span', { class: 'arm-label' }, ` ${r.label}`) : null, ' ', toggle),
      h('td', { class: 'num n-seeds', title: `${r.succeeded} of ${r.jobs} jobs succeeded` }, `${n} seed${n === 1 ? '' : 's'}`,
        r.jobs !== n ? h('span', { class: 'muted' }, ` of ${r.jobs}`) : null),
      shown.map((m) => {
        const summary = r.metrics[m.key];
        return h('td', { class: 'num mean-se', 'data-metric': m.key, title: summary ? `n = ${summary.n}` : null },
          meanSeText(summary), summary && summary.n !== n ? h('span', { class: 'muted' }, ` (n=${summary.n})`) : null);
      }),
      h('td', {}));
    const seedRows = jobsOf(r.label).map((j) => h('tr', { class: 'seed-row', 'data-arm': r.label, 'data-seed': j.seed, hidden: !open },
      h('td', {}, `seed ${j.seed} `, h('a', { href: `#/jobs/${j.job_id}`, class: 'job-link mono', title: 'the job' }, shortId(j.job_id)),
        j.policy_id ? [' · ', h('a', { href: `#/policies/${j.policy_id}`, class: 'policy-link', title: 'the policy' }, 'policy')] : null),
      h('td', {}, statusPill(j.status)),
      shown.map((m) => h('td', { class: 'num seed-value', 'data-metric': m.key }, fmt(j.metrics[m.key], 4))),
      h('td', { class: 'muted' }, j.metrics_from
        || (j.protocols.length ? 'no evaluation under this protocol' : 'no metrics yet'))));
    return [armRow, seedRows];
  });
  const anyMetrics = e.jobs.some((j) => Object.keys(j.metrics).length);
  return [h('h2', {}, 'Results per algorithm'), protocolLine(e, onProtocol),
    tableWrap(h('table', { id: 'experiment-results-table' },
      h('thead', {}, h('tr', {}, h('th', {}, 'Algorithm'), h('th', { class: 'num' }, 'Seeds'),
        shown.map((m) => h('th', { class: 'num', 'data-metric': m.key }, m.label)), h('th', {}, 'Metrics from'))),
      h('tbody', {}, rows))),
    h('p', { class: 'hint' }, anyMetrics
      ? 'Mean ± standard error over the seeds (sample standard deviation / √n). Each seed’s metrics come from its policy’s newest evaluation under the protocol shown, else from the job’s last in-training evaluation.'
      : 'No job has metrics yet: they come from each policy’s newest evaluation, or from the jobs’ in-training evaluation (the eval block).')];
}

/** Value of a series of [step, value] (sorted) at `x` by linear interpolation; null outside it. */
function valueAt(points, x) {
  if (!points.length || x < points[0][0] || x > points.at(-1)[0]) return null;
  const hi = points.findIndex((p) => p[0] >= x);
  if (points[hi][0] === x) return points[hi][1];
  const [x0, y0] = points[hi - 1];
  const [x1, y1] = points[hi];
  return y0 + ((y1 - y0) * (x - x0)) / (x1 - x0);
}

/** The curves chart's spec: per arm the mean over its seeds with a ±SE band (seeds are matched
 *  at each recorded step, interpolating between a seed's points), or one thin line per seed. */
function curveSpec(e, metric, perJob, mode) {
  const colors = armColors(e);
  const series = [];
  const bands = [];
  for (const [label, color] of colors) {
    const mine = perJob.filter((r) => r.job.arm === label && r.points.length);
    if (!mine.length) continue;
    if (mode === 'seeds') {
      for (const r of mine) series.push({ name: `${label} · seed ${r.job.seed}`, points: r.points, color, width: 1, thin: true });
      continue;
    }
    const steps = [...new Set(mine.flatMap((r) => r.points.map((p) => p[0])))].sort((a, b) => a - b);
    const mean = []; const upper = []; const lower = [];
    for (const x of steps) {
      const values = mine.map((r) => valueAt(r.points, x)).filter((v) => v !== null && Number.isFinite(v));
      if (!values.length) continue;
      const m = values.reduce((a, b) => a + b, 0) / values.length;
      mean.push([x, m]);
      if (values.length > 1) {
        const se = Math.sqrt(values.reduce((a, v) => a + (v - m) ** 2, 0) / (values.length - 1) / values.length);
        upper.push([x, m + se]);
        lower.push([x, m - se]);
      }
    }
    series.push({ name: label, points: mean, color, width: 2 });
    if (upper.length) {
      series.push({ name: `${label} +SE`, points: upper, color, width: 0.5, thin: true, band: true });
      series.push({ name: `${label} −SE`, points: lower, color, width: 0.5, thin: true, band: true });
      bands.push({ series: [series.length - 1, series.length], fill: `${color}33` });
    }
  }
  // Steps are policy iterations (each job's pretraining subtracted), so arms line up whatever
  // their pretraining; a metric of the pretraining phase sits at 0 and below.
  const beforePolicy = series.some((sr) => sr.points.some((p) => p[0] <= 0));
  return { key: 'experiment-curves', title: mode === 'seeds' ? `${metric}, each seed` : `${metric}, mean ± SE over seeds`,
    xLabel: beforePolicy ? 'policy iteration (≤ 0: pretraining)' : 'policy iteration', yLabel: metric,
    series, bands: bands.length ? bands : undefined };
}

/** The metric the curves open on: one every algorithm of the grid has recorded (a
 *  SafeDICE-only diagnostic would leave the others out), the paper's first. */
function defaultCurveMetric(names, shared) {
  const pick = (list) => ['eval/normalized_return', 'eval/average_cost'].find((n) => list.includes(n))
    || list.find((n) => n.endsWith('_loss')) || list[0];
  return pick(shared) || pick(names) || '';
}

/** The curves card: a metric picker (by default one every algorithm has: defaultCurveMetric,
 *  until the user picks one), mean ± SE or per-seed lines, over policy iterations;
 *  `refresh(experiment)` reads the histories again. */
function curvesCard() {
  const metric = h('select', { id: 'curve-metric' });
  const mode = h('select', { id: 'curve-mode' }, h('option', { value: 'mean' }, 'mean ± SE'), h('option', { value: 'seeds' }, 'each seed'));
  const note = h('div', { class: 'muted', id: 'curves-note' }, 'Loading metrics…');
  const slot = h('div', { id: 'experiment-curves' });
  const element = h('div', { class: 'card', id: 'experiment-curves-card' }, h('h2', {}, 'Training curves'),
    h('div', { class: 'axis-pick' }, 'metric', metric, mode), note, slot);
  let experiment = null;
  let names = [];
  let listed = ''; // the names (and those every algorithm has) the picker offers
  let picked = false; // the user chose the metric: keep it
  let box = null;
  let drawn = '';
  const pretraining = new Map(); // job id → its pretraining steps (GET /v1/jobs/{id})
  const pretrainingOf = async (id) => {
    if (!pretraining.has(id)) pretraining.set(id, (await api(`/v1/jobs/${id}`)).pretraining_steps || 0);
    return pretraining.get(id);
  };
  const draw = async () => {
    if (!experiment || !metric.value) return;
    const started = experiment.jobs.filter((j) => j.status !== UNFINISHED[0]);
    const perJob = await Promise.all(started.map(async (job) => {
      const [m, before] = await Promise.all([api(withParams(`/v1/jobs/${job.job_id}/metrics`,
        { names: metric.value, max_points: CURVE_POINTS })), pretrainingOf(job.job_id)]);
      return { job, points: m.rows.map((r) => [r.step - before, r.value]) };
    }));
    const spec = curveSpec(experiment, metric.value, perJob, mode.value);
    note.textContent = spec.series.length ? '' : `No job has recorded ${metric.value} yet.`;
    const key = `${metric.value}|${mode.value}`;
    if (box && drawn === key) { box.update(spec); return; }
    box = lineChart(spec);
    box.dataset.metric = metric.value;
    drawn = key;
    slot.replaceChildren(box);
  };
  const redraw = () => draw().catch((err) => { note.replaceChildren(errorBox(err)); });
  metric.addEventListener('change', () => { picked = true; redraw(); });
  mode.addEventListener('change', redraw);
  const refresh = async (e) => {
    experiment = e;
    const started = e.jobs.filter((j) => j.status !== UNFINISHED[0]);
    const lists = await Promise.all(started.map((j) => api(`/v1/jobs/${j.job_id}/metrics/names`)));
    const found = [...new Set(lists.flat().map((m) => m.name))].sort((a, b) => (a.startsWith('eval/') === b.startsWith('eval/') ? a.localeCompare(b) : a.startsWith('eval/') ? -1 : 1));
    // The metrics every algorithm of the grid has recorded (in one of its jobs at least).
    const perArm = new Map();
    started.forEach((j, i) => perArm.set(j.arm, new Set([...(perArm.get(j.arm) || []), ...lists[i].map((m) => m.name)])));
    const shared = found.filter((n) => [...perArm.values()].every((set) => set.has(n)));
    const key = `${found.join()}|${shared.join()}`;
    if (key !== listed) {
      names = found;
      listed = key;
      const chosen = metric.value;
      metric.replaceChildren(...names.map((n) => h('option', { value: n },
        shared.includes(n) || perArm.size < 2 ? n : `${n} (not every algorithm)`)));
      metric.value = picked && names.includes(chosen) ? chosen : defaultCurveMetric(names, shared);
    }
    if (!names.length) { note.textContent = 'No metrics recorded yet.'; return; }
    await draw();
  };
  return { element, refresh };
}

/** Average cost against normalized return, one point per arm at its means, error bars ± SE. */
function experimentScatter(e) {
  const colors = armColors(e);
  const points = e.results.filter((r) => r.metrics.average_cost && r.metrics.normalized_return).map((r) => ({
    label: r.label, group: r.label, color: colors.get(r.label),
    x: r.metrics.average_cost.mean, xErr: r.metrics.average_cost.se ?? null,
    y: r.metrics.normalized_return.mean, yErr: r.metrics.normalized_return.se ?? null,
  }));
  return scatterChart({ key: 'experiment-scatter', title: 'Cost vs return (mean ± SE over seeds)',
    xLabel: 'average cost', yLabel: 'normalized return', points, fromZero: true });
}

function experimentPage(view, id) {
  const title = h('span', { id: 'experiment-title' }, shortId(id));
  const notice = h('div', { id: 'experiment-notice' });
  const slot = h('div', {}, h('div', { class: 'card muted' }, 'Loading the experiment…'));
  const dialog = actionDialog();
  view.append(h('h1', {}, 'Experiment ', title), notice, slot, dialog.element);
  const mine = generation;
  const expanded = new Set();
  const summary = h('div', { class: 'card', id: 'experiment-summary' });
  const results = h('div', { class: 'card', id: 'experiment-results' });
  const scatter = h('div', { class: 'card', id: 'experiment-scatter' });
  const curves = curvesCard();
  let experiment = null;
  let built = false;
  let polling = false;
  let protocol = null; // the key the user picked; null: the server's default

  const drawResults = () => results.replaceChildren(...resultsTable(experiment, expanded, (label) => {
    if (expanded.has(label)) expanded.delete(label); else expanded.add(label);
    drawResults();
  }, (key) => {
    protocol = key;
    load().catch((err) => notice.replaceChildren(errorBox(err)));
  }));
  const actions = {
    csv: (path) => download(path, `experiment-${id}.csv`).catch((err) => notice.replaceChildren(errorBox(err))),
    cancel: () => dialog.show({
      title: `Cancel ${experimentTitle(experiment)}`,
      fields: [h('p', { class: 'hint' }, 'Queued jobs are cancelled, running ones stopped; finished jobs and their results stay.')],
      question: `Cancel the ${unfinishedCount(experiment.progress)} unfinished jobs?`,
      confirmLabel: 'Cancel jobs',
      action: async () => {
        experiment = await api(`/v1/experiments/${id}/cancel`, { method: 'POST' });
        notice.replaceChildren(h('div', { class: 'notice', id: 'experiment-cancelled' }, 'The experiment was cancelled.'));
        poll();
      },
    }),
    remove: () => dialog.show({
      title: `Delete ${experimentTitle(experiment)}`,
      fields: [h('p', { class: 'hint' }, `Its ${experiment.progress.total} jobs, their metrics, logs and policies are deleted too.`)],
      question: 'Delete the experiment and its jobs?',
      confirmLabel: 'Delete',
      action: async () => {
        await api(`/v1/experiments/${id}`, { method: 'DELETE' });
        location.hash = '#/experiments';
      },
    }),
  };

  const fetchExperiment = async () => {
    try {
      return await api(protocol ? withParams(`/v1/experiments/${id}`, { protocol }) : `/v1/experiments/${id}`);
    } catch (err) {
      // The picked protocol's evaluations were deleted: back to the default.
      if (err.status !== 404 || !protocol) throw err;
      protocol = null;
      return api(`/v1/experiments/${id}`);
    }
  };
  const load = async () => {
    const e = await fetchExperiment();
    if (mine !== generation) return false;
    experiment = e;
    if (!built) {
      slot.replaceChildren(summary, results, h('div', { class: 'grid2' }, curves.element, scatter));
      built = true;
    }
    title.textContent = experimentTitle(e);
    summary.replaceChildren(...experimentSummary(e, actions));
    drawResults();
    scatter.replaceChildren(h('h2', {}, 'Cost vs return'), experimentScatter(e));
    await curves.refresh(e);
    return gridActive(e);
  };
  // Polls while jobs are queued or running, then stops (a cancel starts it once more).
  const poll = () => {
    if (polling) return;
    polling = true;
    every(EXPERIMENT_POLL_MS, async () => {
      const more = await load();
      polling = more !== false;
      return more;
    }, (err) => {
      if (err.status === 404) {
        polling = false;
        slot.replaceChildren(notFound('experiment', id, '#/experiments', 'experiments list'));
        return false;
      }
      notice.replaceChildren(errorBox(err));
      return true;
    });
  };
  poll();
}
