// SafeDICE dashboard: a small vanilla-JS single-page app over the JSON API (/v1), on the
// helpers of lib.js, the charts of charts.js, the job form of job_form.js and the pages of
// models.js, experiments.js, policies.js and compare.js. Pages are hash
// routes; lists refresh by polling (EventSource cannot send the Authorization header, and
// polling a page of jobs once a second is cheap).
'use strict';

// Each algorithm's colour is the --accent of its class algo-<name> (badges, progress bars).
document.head.append(h('style', {}, ALGORITHM_TABLE.map((a) => `.algo-${a.name} { --accent: ${a.color}; }`).join('\n')));
const LIST_POLL_MS = 1000;
const JOB_POLL_MS = 1500;
const PAGE_SIZE = 25;
/** Points per metric the job page asks for: the server picks them by LTTB. */
const CHART_POINTS = 1000;

const routes = [
  [/^#\/datasets$/, datasetsPage, 'datasets'],
  [/^#\/jobs$/, jobsPage, 'jobs'],
  [/^#\/jobs\/([\w-]+)$/, jobPage, 'jobs'],
  [/^#\/compare$/, comparePage, 'compare'],
  // Pages of policies.js.
  [/^#\/policies$/, policiesPage, 'policies'],
  [/^#\/policies\/([\w-]+)$/, policyPage, 'policies'],
  // Pages of models.js.
  [/^#\/models$/, modelsPage, 'models'],
  [/^#\/models\/([A-Za-z0-9][\w.-]*)$/, modelPage, 'models'],
  // Pages of experiments.js.
  [/^#\/experiments$/, experimentsPage, 'experiments'],
  [/^#\/experiments\/([\w-]+)$/, experimentPage, 'experiments'],
];

function route() {
  generation += 1;
  const hash = location.hash || '#/jobs';
  const view = $('#view');
  view.replaceChildren();
  for (const [pattern, page, nav] of routes) {
    const match = hash.match(pattern);
    if (match) {
      document.querySelectorAll('[data-nav]').forEach((a) => a.classList.toggle('active', a.dataset.nav === nav));
      page(view, ...match.slice(1));
      return;
    }
  }
  view.append(h('div', { class: 'empty' }, 'No such page. ', h('a', { href: '#/jobs' }, 'Go to the jobs list.')));
}

function setupToken() {
  const input = $('#token');
  const state = $('#token-state');
  const show = () => { state.textContent = token() ? 'saved for this tab' : ''; };
  input.value = token();
  show();
  $('#token-form').addEventListener('submit', (event) => {
    event.preventDefault();
    if (input.value) sessionStorage.setItem(TOKEN_KEY, input.value); else sessionStorage.removeItem(TOKEN_KEY);
    show();
    route();
  });
}

/** "Not found" for a page about one resource: what was asked for and where to go instead. */
function notFound(what, id, href, listName) {
  return h('div', { class: 'error-box not-found', role: 'alert' },
    h('span', { class: 'error-message' }, `There is no ${what} with id ${id}: it was deleted, or the link is wrong. `),
    h('a', { href }, `Go to the ${listName}.`));
}

// ---------- datasets ----------

function datasetsPage(view) {
  const fileInput = h('input', { type: 'file', id: 'upload-file', accept: '.jsonl,.json,.csv,.npz,.h5,.hdf5', multiple: true, hidden: true });
  const nameInput = h('input', { id: 'upload-name', placeholder: 'name (default: the file name)', size: 32 });
  const roleSelect = h('select', { id: 'upload-role' },
    h('option', { value: 'unlabeled' }, 'unlabeled Dᵁ (mixed quality)'),
    h('option', { value: 'non_preferred' }, 'non-preferred Dᴺ (known unsafe)'),
    h('option', { value: '' }, 'not given'));
  const status = h('div', { id: 'upload-status' });
  const drop = h('div', { class: 'dropzone', id: 'dropzone', tabindex: 0 },
    h('strong', {}, 'Drop a dataset file here'), ' or click to choose one',
    h('div', { class: 'hint' }, 'JSONL, CSV, NPZ or HDF5 (D4RL / DSRL layout). The server validates it and stores it once.'));
  const table = h('div', { id: 'datasets-list' });
  const detail = h('div', { id: 'dataset-detail' });
  const listError = h('div', {});

  const upload = async (files) => {
    status.replaceChildren();
    for (const file of files) {
      const form = new FormData();
      form.append('file', file, file.name);
      if (nameInput.value.trim() && files.length === 1) form.append('name', nameInput.value.trim());
      if (roleSelect.value) form.append('role', roleSelect.value);
      status.replaceChildren(h('div', { class: 'muted' }, `Uploading ${file.name} (${fmtBytes(file.size)})…`));
      try {
        const dataset = await api('/v1/datasets', { method: 'POST', form });
        const warnings = (dataset.stats && dataset.stats.warnings) || [];
        status.replaceChildren(h('div', { class: 'notice', id: 'upload-ok' },
          `Stored “${dataset.name}” as ${roleText(dataset.role)}: ${fmt(dataset.transitions)} transitions, ${fmt(dataset.episodes)} episodes.`),
        ...(warnings.length ? [h('div', { class: 'notice warn', id: 'upload-warnings' }, h('strong', {}, 'Check: '),
          h('ul', {}, warnings.map((w) => h('li', {}, w))))] : []));
        nameInput.value = '';
        await list.reset();
      } catch (err) {
        status.replaceChildren(h('div', { class: 'muted' }, `${file.name} was rejected:`), errorBox(err, 'upload-error'));
        return;
      }
    }
  };

  drop.addEventListener('click', () => fileInput.click());
  drop.addEventListener('keydown', (e) => { if (e.key === 'Enter' || e.key === ' ') fileInput.click(); });
  drop.addEventListener('dragover', (e) => { e.preventDefault(); drop.classList.add('over'); });
  drop.addEventListener('dragleave', () => drop.classList.remove('over'));
  drop.addEventListener('drop', (e) => {
    e.preventDefault();
    drop.classList.remove('over');
    if (e.dataTransfer && e.dataTransfer.files.length) upload([...e.dataTransfer.files]);
  });
  fileInput.addEventListener('change', () => { if (fileInput.files.length) upload([...fileInput.files]); fileInput.value = ''; });

  const actions = {
    preview: (d) => showPreview(detail, d).catch((err) => detail.replaceChildren(errorBox(err))),
    download: (d) => download(`/v1/datasets/${d.id}/download`, `${d.name.replace(/[^\w.-]+/g, '_')}.npz`)
      .catch((err) => listError.replaceChildren(errorBox(err))),
    remove: async (d) => {
      try {
        await api(`/v1/datasets/${d.id}`, { method: 'DELETE' });
        listError.replaceChildren(h('div', { class: 'notice', id: 'dataset-deleted' }, `Deleted “${d.name}”.`));
        if (detail.dataset.id === d.id) detail.replaceChildren();
        await list.reload();
      } catch (err) {
        listError.replaceChildren(errorBox(err, 'dataset-delete-error'));
      }
    },
  };
  const list = pagedList({ path: '/v1/datasets', size: PAGE_SIZE, id: 'datasets-pager',
    render: (items) => table.replaceChildren(datasetsTable(items, actions)) });

  view.append(
    h('h1', {}, 'Datasets'),
    h('div', { class: 'card' }, h('h2', {}, 'Upload'), drop, fileInput,
      h('div', { class: 'form-actions wrap' }, h('label', {}, 'Role ', roleSelect), nameInput), status),
    h('div', { class: 'card' }, h('h2', {}, 'Stored datasets'), listError, table, list.nav),
    detail,
  );
  list.reload().catch((err) => table.replaceChildren(errorBox(err)));
}

function summaryText(summary) {
  if (!summary) return '—';
  return `${fmt(summary.mean, 3)} ± ${fmt(summary.std, 2)}`;
}

function datasetsTable(items, actions) {
  if (!items.length) {
    return h('div', { class: 'empty' }, 'No datasets yet. Drop a JSONL, CSV, NPZ or HDF5 file above; ',
      h('code', {}, 'safedice datagen --env six-rooms --out demo'), ' writes an unlabeled and a non-preferred set to try.');
  }
  return tableWrap(h('table', { id: 'datasets-table', class: 'sticky-actions' },
    h('thead', {}, h('tr', {},
      h('th', {}, 'Name'), h('th', {}, 'Role'), h('th', {}, 'Format'), h('th', { class: 'num' }, 'Transitions'),
      h('th', { class: 'num' }, 'Episodes'), h('th', { class: 'num' }, 'Obs dim'), h('th', {}, 'Actions'),
      h('th', { class: 'num' }, 'Return / episode'), h('th', { class: 'num' }, 'Cost / episode'),
      h('th', { class: 'num' }, 'Size'), h('th', {}, 'Uploaded'), h('th', {}, ''))),
    h('tbody', {}, items.map((d) => h('tr', { 'data-id': d.id },
      h('td', { class: 'dataset-name' }, h('strong', {}, d.name), h('div', { class: 'muted mono' }, shortId(d.id)),
        d.stats && d.stats.warnings && d.stats.warnings.length
          ? h('div', { class: 'dataset-warning', title: d.stats.warnings.join('\n') }, `⚠ ${d.stats.warnings.length} warning${d.stats.warnings.length > 1 ? 's' : ''}`) : null),
      h('td', { class: 'role' }, d.role ? h('span', { class: `role-chip role-${d.role}` }, roleText(d.role)) : h('span', { class: 'muted' }, 'not given')),
      h('td', {}, d.format),
      h('td', { class: 'num' }, fmt(d.transitions)),
      h('td', { class: 'num' }, fmt(d.episodes)),
      h('td', { class: 'num' }, fmt(d.obs_dim)),
      h('td', {}, actionSpaceText(d.action_space)),
      h('td', { class: 'num' }, summaryText(d.stats && d.stats.episode_return)),
      h('td', { class: 'num' }, summaryText(d.stats && d.stats.episode_cost)),
      h('td', { class: 'num' }, fmtBytes(d.bytes)),
      h('td', { class: 'uploaded' }, fmtTime(d.created_at)),
      h('td', { class: 'row-actions' },
        h('button', { type: 'button', class: 'secondary preview', onclick: () => actions.preview(d) }, 'Preview'),
        h('button', { type: 'button', class: 'secondary download', onclick: () => actions.download(d) }, 'Download'),
        confirmButton('Delete', 'Really delete?', () => actions.remove(d), { class: 'danger delete' })))))));
}

const cellNumbers = (values) => (Array.isArray(values) ? values.map((v) => fmt(v, 3)).join(', ') : fmt(values, 3));

/** The first transitions and per-episode statistics of a dataset (GET …/preview). */
async function showPreview(slot, dataset) {
  slot.dataset.id = dataset.id;
  slot.replaceChildren(h('div', { class: 'card' }, h('div', { class: 'muted' }, `Loading a preview of “${dataset.name}”…`)));
  const preview = await api(`/v1/datasets/${dataset.id}/preview?rows=20&episodes=20`);
  slot.replaceChildren(h('div', { class: 'card', id: 'dataset-preview' },
    h('h2', {}, `Preview of “${dataset.name}”`),
    h('p', { class: 'hint' }, `The first ${preview.episodes.length} of ${fmt(dataset.episodes)} episodes and the first ${preview.transitions.length} of ${fmt(dataset.transitions)} transitions.`),
    h('div', { class: 'grid2' },
      tableWrap(h('table', { id: 'preview-episodes' },
        h('thead', {}, h('tr', {}, h('th', { class: 'num' }, 'Episode'), h('th', { class: 'num' }, 'Length'),
          h('th', { class: 'num' }, 'Return'), h('th', { class: 'num' }, 'Cost'), h('th', {}, 'Ends'))),
        h('tbody', {}, preview.episodes.map((e) => h('tr', {},
          h('td', { class: 'num' }, fmt(e.episode)), h('td', { class: 'num' }, fmt(e.length)),
          h('td', { class: 'num' }, fmt(e.return)), h('td', { class: 'num' }, fmt(e.cost)),
          h('td', {}, e.terminal ? 'terminal' : 'time limit')))))),
      tableWrap(h('table', { id: 'preview-transitions' },
        h('thead', {}, h('tr', {}, h('th', { class: 'num' }, 'Row'), h('th', { class: 'num' }, 'Episode'), h('th', {}, 'Observation'),
          h('th', {}, 'Action'), h('th', { class: 'num' }, 'Reward'), h('th', { class: 'num' }, 'Cost'))),
        h('tbody', {}, preview.transitions.map((t) => h('tr', {},
          h('td', { class: 'num' }, fmt(t.index)), h('td', { class: 'num' }, fmt(t.episode)),
          h('td', { class: 'mono obs' }, cellNumbers(t.obs)), h('td', { class: 'mono' }, cellNumbers(t.action)),
          h('td', { class: 'num' }, fmt(t.reward)), h('td', { class: 'num' }, fmt(t.cost))))))))));
}

// ---------- jobs ----------

/** A fraction as a percentage that never reads 0% for a job that has started or 100% for one
 *  that has not finished. */
function percentText(fraction) {
  const pct = (fraction || 0) * 100;
  if (pct > 0 && pct < 1) return '<1%';
  if (pct > 99 && pct < 100) return '>99%';
  return `${Math.round(pct)}%`;
}

function jobsTable(jobs, onCancel) {
  if (!jobs.length) {
    return h('div', { class: 'empty' }, 'No jobs here. Upload an unlabeled and a non-preferred dataset on the ',
      h('a', { href: '#/datasets' }, 'Datasets'), ' page, then queue a job with the form above (or clear the filters).');
  }
  return tableWrap(h('table', { id: 'jobs-table', class: 'sticky-actions' },
    h('thead', {}, h('tr', {}, h('th', {}, 'Job'), h('th', {}, 'Algorithm'), h('th', {}, 'Status'),
      h('th', {}, 'Progress'), h('th', { class: 'num' }, 'Step'), h('th', { class: 'num' }, 'it/s'),
      h('th', { class: 'num' }, 'ETA'), h('th', { class: 'num' }, 'α̂'), h('th', {}, 'Created'), h('th', {}, ''))),
    h('tbody', {}, jobs.map((job) => h('tr', { 'data-id': job.id, 'data-status': job.status },
      h('td', { class: 'job-cell' }, h('a', { href: `#/jobs/${job.id}`, class: job.name ? 'job-name' : 'mono job-name' }, jobTitle(job)),
        job.name ? h('span', { class: 'muted mono id' }, ` ${shortId(job.id)}`) : null, h('div', { class: 'tags' }, tagChips(job.tags))),
      h('td', {}, algoBadge(job.algorithm)),
      h('td', { class: 'status-cell' }, statusPill(job.status)),
      h('td', {}, h('span', { class: 'progress-cell' }, progressBar(job), h('span', { class: 'muted pct' }, percentText(job.progress.fraction)))),
      h('td', { class: 'num step' }, `${fmt(job.progress.step)} / ${fmt(job.progress.total)}`),
      h('td', { class: 'num' }, fmt(job.progress.iterations_per_second, 3)),
      h('td', { class: 'num' }, fmtDuration(job.progress.eta_seconds)),
      h('td', { class: 'num' }, fmt(job.alpha_hat)),
      h('td', {}, fmtTime(job.created_at)),
      h('td', {}, FINAL.has(job.status) ? (job.policy_id ? h('a', { href: `#/policies/${job.policy_id}` }, 'policy') : '')
        : h('button', { class: 'danger cancel', type: 'button', onclick: () => onCancel(job) }, 'Cancel')))))));
}

async function cancelJob(job) {
  await api(`/v1/jobs/${job.id}/cancel`, { method: 'POST' });
}

function jobsPage(view) {
  const formSlot = h('div', {});
  const list = h('div', { id: 'jobs-list' });
  const listError = h('div', {});
  const search = h('input', { id: 'jobs-search', type: 'search', placeholder: 'name or id prefix', size: 22 });
  const tag = h('input', { id: 'jobs-tag', placeholder: 'tag', size: 14 });
  const statusFilter = h('select', { id: 'jobs-status' }, h('option', { value: '' }, 'any status'),
    JOB_STATUSES.map((st) => h('option', { value: st.name, title: st.meaning }, st.name)));
  const filters = h('form', { class: 'filters', id: 'jobs-filters' }, search, tag, statusFilter,
    h('button', { type: 'submit', class: 'secondary' }, 'Filter'));
  const path = () => withParams('/v1/jobs', { q: search.value.trim(), tag: tag.value.trim(), status: statusFilter.value });
  const onCancel = async (job) => {
    try { await cancelJob(job); } catch (err) { listError.replaceChildren(errorBox(err)); }
    pages.reload().catch(() => {});
  };
  const pages = pagedList({ path: '/v1/jobs', size: PAGE_SIZE, id: 'jobs-pager',
    render: (items) => { listError.replaceChildren(); list.replaceChildren(jobsTable(items, onCancel)); } });
  const applyFilters = (event) => {
    if (event) event.preventDefault();
    pages.reset(path()).catch((err) => listError.replaceChildren(errorBox(err)));
  };
  filters.addEventListener('submit', applyFilters);
  statusFilter.addEventListener('change', applyFilters);
  view.append(h('h1', {}, 'Jobs'), formSlot,
    h('div', { class: 'card' }, h('div', { class: 'card-head' }, h('h2', {}, 'Jobs'), filters), listError, list, pages.nav));

  Promise.all([api('/v1/datasets?limit=100'), api('/v1/envs'), api(`/v1/jobs?status=${SUCCESS}&limit=100`), api('/v1/models?limit=100')])
    .then(([datasets, envs, finished, models]) => {
      if (!datasets.items.length) {
        formSlot.replaceChildren(h('div', { class: 'card' }, h('div', { class: 'empty' },
          'Upload datasets first: a job trains on an unlabeled dataset and (except BC) a non-preferred one. ',
          h('a', { href: '#/datasets' }, 'Go to Datasets.'))));
      } else {
        formSlot.replaceChildren(jobForm(datasets.items, envs.items, finished.items, models.items, () => pages.reload().catch(() => {})));
      }
    }).catch((err) => formSlot.replaceChildren(errorBox(err)));
  every(LIST_POLL_MS, () => pages.reload(), (err) => listError.replaceChildren(errorBox(err)));
}

// ---------- job page: charts of the metrics ----------

// Metric groups of the job page, matched on the metric name.
const METRIC_GROUPS = [
  { key: 'losses', title: 'Losses', y: 'loss', test: (n) => n.endsWith('_loss') },
  { key: 'alpha', title: 'α̂ (Eq. 15)', y: 'α̂', test: (n) => n === 'alpha_hat' },
  { key: 'weights', title: 'Weight statistics', y: 'value', test: (n) => /^(ess|weight|advantage|reward_(mean|std|clipped))/.test(n) },
  // Probabilities on their own [0, 1] axis; the early-stopping steps are said in words
  // (earlyStopNote), and the rest of discriminator_* get a chart each.
  { key: 'discriminator', title: 'Discriminator: P(non-preferred)', y: 'probability', range: [0, 1], test: (n) => n.startsWith('discriminator_prob_') },
];
/** SafeDICE's early-stopping state, recorded as metrics: read, not charted (steps are not on the
 *  scale of the other discriminator outputs). */
const EARLY_STOP_METRICS = ['discriminator_best_step', 'discriminator_stopped_at'];

// The evaluation charts of a job with an eval block (the paper's metrics over training steps);
// the other eval/ metrics are listed in the latest-evaluation table. Axis titles stay
// short enough for the chart's height; the note under a chart says the rest.
const EVAL_CHARTS = [
  { key: 'eval-return', title: 'Normalized return', y: 'normalized return', note: '100 = the preferred demonstrations’ mean return.', names: ['eval/normalized_return'] },
  { key: 'eval-cost', title: 'Average cost', y: 'cost per episode', note: 'Mean cost of an episode.', names: ['eval/average_cost'] },
  { key: 'eval-violation', title: 'Cost-violation ratio', y: 'share over κ', note: 'Share of episodes whose cost exceeds κ, the midpoint of the two demonstrators’ mean costs.', names: ['eval/cost_violation_ratio'] },
  { key: 'eval-cvar', title: 'CVaR k% cost', y: 'CVaR cost', note: 'Mean cost of the worst k% of episodes.', names: ['eval/cvar_cost_50', 'eval/cvar_cost_20', 'eval/cvar_cost_10', 'eval/cvar_cost_5'] },
];
const isEval = (name) => name.startsWith('eval/');
const X_LABEL = 'training step (all phases)';

function groupMetrics(rows) {
  const series = new Map();
  for (const row of rows) {
    if (!series.has(row.name)) series.set(row.name, []);
    series.get(row.name).push([row.step, row.value]);
  }
  return series;
}

/** Colour of the i-th series of a chart: the algorithm's accent first. */
function seriesColor(job, i) {
  return i === 0 ? algoColor(job.algorithm) : PALETTE[(i - 1) % PALETTE.length];
}

/** Chart specs for a job's training metrics: one chart per group (weight statistics one chart
 *  each), then one per remaining metric. */
function chartSpecs(job, series) {
  const specs = [];
  const used = new Set();
  for (const group of METRIC_GROUPS) {
    const names = [...series.keys()].filter((n) => !used.has(n) && group.test(n));
    names.forEach((n) => used.add(n));
    if (!names.length) continue;
    const perMetric = group.key === 'weights';
    const sets = perMetric ? names.map((n) => [n]) : [names];
    for (const set of sets) {
      specs.push({
        key: perMetric ? `${group.key}-${set[0]}` : group.key,
        title: perMetric ? `${group.title}: ${set[0]}` : group.title,
        xLabel: X_LABEL,
        yLabel: perMetric ? set[0] : group.y,
        yRange: group.range,
        series: set.map((name, i) => ({ name, points: series.get(name), color: seriesColor(job, i) })),
      });
    }
  }
  for (const name of [...series.keys()].filter((n) => !used.has(n))) {
    specs.push({ key: `other-${name}`, title: name, xLabel: X_LABEL, yLabel: name,
      series: [{ name, points: series.get(name), color: algoColor(job.algorithm) }] });
  }
  return specs;
}

/** Chart specs of the evaluation metrics recorded so far. */
function evalChartSpecs(job, series) {
  return EVAL_CHARTS.filter((chart) => chart.names.some((n) => series.has(n))).map((chart) => ({
    key: chart.key,
    title: `${chart.title} on ${job.eval.env}`,
    xLabel: X_LABEL,
    yLabel: chart.y,
    note: chart.note,
    series: chart.names.filter((n) => series.has(n)).map((name, i) => ({
      name: name.replace('eval/cvar_cost_', 'CVaR ').replace(/^CVaR (\d+)$/, 'CVaR $1%'), points: series.get(name), color: seriesColor(job, i) })),
  }));
}

/** A grid of line charts that keeps its charts between refreshes: a chart whose key it already
 *  shows gets the new points in place (zoom and log scale stay as the user set them). */
function chartGrid(id) {
  const grid = h('div', { class: 'grid2', id });
  const boxes = new Map();
  grid.show = (specs) => {
    const keys = new Set(specs.map((sp) => sp.key));
    for (const [key, box] of boxes) if (!keys.has(key)) { box.remove(); boxes.delete(key); }
    for (const spec of specs) {
      if (boxes.has(spec.key)) boxes.get(spec.key).update(spec);
      else { const box = lineChart(spec); boxes.set(spec.key, box); grid.append(box); }
    }
  };
  return grid;
}

function configTable(config, id) {
  const entries = Object.entries(config || {});
  const text = (value) => {
    if (value === null || value === undefined) return '—';
    return typeof value === 'object' ? JSON.stringify(value) : String(value);
  };
  return tableWrap(h('table', { id }, h('tbody', {}, entries.map(([key, value]) =>
    h('tr', {}, h('td', { class: 'mono' }, key), h('td', { class: 'mono' }, text(value)))))));
}

function jobSummary(job, onCancel) {
  const p = job.progress;
  const plan = stepPlanOf(job);
  return h('div', { class: 'card', id: 'job-summary' },
    h('div', { class: 'stats-line' },
      algoBadge(job.algorithm), statusPill(job.status),
      h('span', {}, h('span', { class: 'big step' }, `${fmt(p.step)} / ${fmt(p.total)}`), ' steps'),
      h('span', {}, 'phase ', h('strong', {}, p.phase || '—')),
      h('span', {}, h('strong', {}, fmt(p.iterations_per_second, 3)), ' it/s'),
      h('span', {}, 'ETA ', h('strong', {}, fmtDuration(p.eta_seconds))),
      h('span', {}, 'α̂ ', h('strong', { id: 'alpha-hat' }, fmt(job.alpha_hat))),
      job.policy_id ? h('a', { href: `#/policies/${job.policy_id}`, id: 'policy-link' }, 'Open the trained policy →') : null,
      FINAL.has(job.status) ? null : h('button', { class: 'danger cancel', type: 'button', onclick: onCancel }, 'Cancel')),
    h('div', { style: 'margin-top:12px' }, progressBar(job, true)),
    h('p', { class: 'hint', id: 'step-plan' }, `${stepPlanText(plan)} (every phase counts as steps).`),
    job.status === STATUS.failed ? h('div', { class: 'error-box job-error', role: 'alert' },
      h('strong', {}, 'This job failed: '), h('span', { class: 'error-message' }, job.error || 'no reason recorded'),
      h('div', { class: 'hint' }, 'The log below tells what the worker did; fix what the message names (a knob of the config or the data) and queue a new job on the Jobs page.')) : null,
    job.status === STATUS.discarded ? h('div', { class: 'error-box job-error', role: 'alert' },
      h('strong', {}, 'This job was discarded: '), h('span', { class: 'error-message' }, job.error || 'no reason recorded'),
      h('div', { class: 'hint' }, `Its workers vanished ${job.attempt} times (killed, out of memory, the machine gone) before it ended; the training itself reported no error. The attempts below say what each worker last reported; give the workers more memory or lower batch_size or hidden_sizes, and queue it again.`)) : null,
    job.cancel_requested && job.status === STATUS.running ? h('div', { class: 'hint' }, 'Cancel requested; the job stops within a second.') : null,
    attemptNotice(job));
}

/** A job whose worker vanished: waiting for another worker, or for its retry after the backoff. */
function attemptNotice(job) {
  if (job.status === STATUS.running && job.lease_expired_at) {
    return h('div', { class: 'notice', id: 'lease-expired', role: 'status' },
      `Waiting for a worker: the worker stopped renewing its lease at ${fmtTime(job.lease_expired_at)} (progress is frozen). Another worker takes attempt ${job.attempt} of ${job.max_attempts} over from the last checkpoint, or retries the job.`);
  }
  if (job.status === STATUS.queued && job.retry_at) {
    return h('div', { class: 'notice', id: 'retry-at', role: 'status' },
      `Attempt ${job.attempt} of ${job.max_attempts} ended when its worker vanished (see the log); attempt ${job.attempt + 1} starts after ${fmtTime(job.retry_at)}, from the last checkpoint.`);
  }
  return null;
}

/** Name, tags and notes, editable (PATCH), and the delete button. */
function jobLabels(job, onChange) {
  const name = h('input', { id: 'edit-name', value: job.name || '', placeholder: 'no name', maxlength: 200 });
  const tags = h('input', { id: 'edit-tags', value: (job.tags || []).join(', '), placeholder: 'comma-separated' });
  const notes = h('textarea', { id: 'edit-notes', placeholder: 'no notes', rows: 2 });
  notes.value = job.notes || '';
  const result = h('div', { id: 'edit-result' });
  const form = h('form', { id: 'edit-form', class: 'form-grid' },
    h('label', {}, 'Name', name), h('label', {}, 'Tags', tags), h('label', { class: 'wide' }, 'Notes', notes));
  form.addEventListener('submit', async (event) => {
    event.preventDefault();
    try {
      const updated = await api(`/v1/jobs/${job.id}`, { method: 'PATCH', json: {
        name: name.value.trim() || null, tags: parseTags(tags.value), notes: notes.value.trim() || null } });
      result.replaceChildren(h('div', { class: 'notice', id: 'edit-ok' }, 'Saved.'));
      onChange(updated);
    } catch (err) {
      result.replaceChildren(errorBox(err, 'edit-error'));
    }
  });
  const remove = confirmButton('Delete job', 'Really delete the job, its metrics, log and policy?', async () => {
    try {
      await api(`/v1/jobs/${job.id}`, { method: 'DELETE' });
      location.hash = '#/jobs';
    } catch (err) {
      result.replaceChildren(errorBox(err, 'delete-error'));
    }
  }, { id: 'job-delete' });
  return h('div', { class: 'card', id: 'job-labels' }, h('h2', {}, 'Name, tags and notes'), form,
    h('div', { class: 'form-actions' }, h('button', { type: 'submit', form: 'edit-form', id: 'edit-save' }, 'Save'), remove,
      h('span', { class: 'hint' }, 'Deleting a finished job deletes its metrics, log, checkpoint and policy (download the policy first to keep it).')),
    result);
}

function jobDetails(job) {
  return h('div', { class: 'grid2', style: 'margin-top:18px', id: 'job-details' },
    h('div', { class: 'card' }, h('h2', {}, 'Resolved configuration'), configTable(job.config, 'job-config'),
      h('h2', { style: 'margin-top:14px' }, 'Runner'), configTable(job.runner, 'job-runner'),
      job.eval ? [h('h2', { style: 'margin-top:14px' }, 'Evaluation'), configTable(job.eval, 'job-eval')] : null),
    h('div', { class: 'card' }, h('h2', {}, 'Job'), h('dl', { class: 'kv', id: 'job-facts' },
      h('dt', {}, 'id'), h('dd', { class: 'mono' }, job.id),
      h('dt', {}, 'unlabeled dataset'), h('dd', { class: 'mono' }, job.unlabeled_dataset),
      h('dt', {}, 'non-preferred dataset'), h('dd', { class: 'mono' }, job.non_preferred_dataset || '—'),
      h('dt', {}, 'worker'), h('dd', { class: 'mono', id: 'job-worker' }, job.worker || '—'),
      h('dt', {}, 'attempts'), h('dd', { id: 'job-attempts' }, `${job.attempt} of ${job.max_attempts}`),
      h('dt', {}, 'created'), h('dd', {}, fmtTime(job.created_at)),
      h('dt', {}, 'started'), h('dd', { id: 'job-started' }, fmtTime(job.started_at)),
      h('dt', {}, 'finished'), h('dd', { id: 'job-finished' }, fmtTime(job.finished_at)))));
}

/** The worker's log of the job, appended as lines arrive (GET …/logs?after=). */
function logPanel(id) {
  const lines = h('div', { class: 'log-lines', id: 'job-log' });
  let after = 0;
  const empty = h('div', { class: 'muted', id: 'job-log-empty' }, 'No log lines yet: the worker writes them once it claims the job.');
  lines.append(empty);
  const panel = h('div', { class: 'card' }, h('h2', {}, 'Log'), lines);
  panel.poll = async () => {
    const page = await api(`/v1/jobs/${id}/logs?after=${after}&limit=1000`);
    if (!page.length) return;
    empty.remove();
    const atBottom = lines.scrollTop + lines.clientHeight >= lines.scrollHeight - 4;
    for (const line of page) {
      lines.append(h('div', { class: `log-line log-${line.level}`, 'data-seq': line.seq },
        h('span', { class: 'muted' }, fmtTime(line.time)), ' ', h('span', { class: 'level' }, line.level), ' ', line.message));
      after = line.seq;
    }
    if (atBottom) lines.scrollTop = lines.scrollHeight;
  };
  return panel;
}

function jobPage(view, id) {
  const title = h('span', { class: 'mono' }, shortId(id));
  const tags = h('span', { class: 'tags' });
  const problem = h('div', {});
  const summary = h('div', {});
  const labels = h('div', {});
  const evalHeading = h('h2', { hidden: true }, 'Evaluation');
  const evalAbout = h('div', {});
  const evalCharts = chartGrid('eval-charts');
  const evalLatest = h('div', {});
  const chartsNote = h('div', { class: 'muted', id: 'charts-loading' }, 'Loading metrics…');
  const charts = chartGrid('charts');
  const once = h('div', {});
  const details = h('div', {});
  const evaluations = h('div', {});
  const log = logPanel(id);
  const csv = h('button', { type: 'button', class: 'secondary', id: 'metrics-csv' }, 'Download all metrics (CSV)');
  csv.addEventListener('click', () => download(`/v1/jobs/${id}/metrics.csv`, `job-${id}-metrics.csv`).catch((err) => problem.replaceChildren(errorBox(err))));
  // The charts come first; the name/tags/notes editor sits below them, beside the facts.
  const body = h('div', { hidden: true }, summary, evaluations, evalHeading, evalAbout, evalCharts, evalLatest,
    h('div', { class: 'card-head' }, h('h2', {}, 'Training metrics'), csv), chartsNote, charts, once, log, labels, details);
  view.append(h('h1', {}, 'Job ', title, ' ', tags), problem, body);
  let lastChartStep = -1;
  let shownLabels = false;
  const showTitle = (job) => {
    title.textContent = jobTitle(job);
    title.className = job.name ? '' : 'mono';
    tags.replaceChildren(...tagChips(job.tags));
  };
  // The form is drawn once: refreshes and saves must not wipe what the user is typing.
  const showLabels = (job) => { showTitle(job); labels.replaceChildren(jobLabels(job, showTitle)); };
  every(JOB_POLL_MS, async () => {
    const job = await api(`/v1/jobs/${id}`);
    body.hidden = false;
    problem.replaceChildren();
    summary.replaceChildren(jobSummary(job, async () => {
      try { await cancelJob(job); } catch (err) { problem.replaceChildren(errorBox(err)); }
    }));
    if (!shownLabels) { shownLabels = true; showLabels(job); }
    details.replaceChildren(jobDetails(job));
    await log.poll();
    if (job.progress.step !== lastChartStep || FINAL.has(job.status)) {
      lastChartStep = job.progress.step;
      evalHeading.hidden = !job.eval;
      await drawCharts(job, { chartsNote, charts, once, evalAbout, evalCharts, evalLatest });
    }
    if (job.policy_id) evaluations.replaceChildren(await policyEvaluationsCard(job.policy_id));
    return !FINAL.has(job.status);
  }, (err) => {
    if (err.status === 404) {
      problem.replaceChildren(notFound('job', id, '#/jobs', 'jobs list'));
      body.hidden = true;
      return false;
    }
    problem.replaceChildren(errorBox(err));
    return undefined;
  });
}

/** Every evaluation of a job's policy (the one taken at the end of training among them), as the
 *  policy page lists them. */
async function policyEvaluationsCard(policyId) {
  const page = await api(`/v1/evaluations?policy_id=${policyId}&limit=50`);
  return h('div', { class: 'card', id: 'job-evaluations', style: 'margin-top:18px' },
    h('div', { class: 'card-head' }, h('h2', {}, 'Evaluations of the trained policy'),
      h('a', { href: `#/policies/${policyId}` }, 'Evaluate it on the policy page →')),
    evaluationsTable(page.items));
}

/** SafeDICE's fallback (metric `weighting_uniform` = 1): the job trained as BC; the log says why. */
function uniformWeightingNotice(series) {
  const points = series.get('weighting_uniform');
  if (!points || points[points.length - 1][1] !== 1) return null;
  return h('div', { class: 'notice', id: 'weighting-uniform', role: 'status', style: 'margin-top:18px' },
    h('strong', {}, 'Weighting: uniform. '),
    'The held-out data could not tell the non-preferred demonstrations from the unlabeled ones (alpha-hat’s interval covers 1, or the discriminator’s held-out AUC cannot be told from 0.5), so this SafeDICE job trained as BC. The log gives the numbers.');
}

/** SafeDICE's weighting stage in a sentence, from the metrics it records once when the
 *  discriminator phase ends: alpha-hat and the held-out AUC with their intervals, and what Eq. 10
 *  read (each episode's mean logit, or each row's own where D^U had too few episodes to pool
 *  them). Null before the policy phase, for other algorithms and where the stage fell back to
 *  uniform weights (that notice says so). */
function weightingSummary(series) {
  const last = (n) => (series.get(n) || []).at(-1)?.[1];
  const alpha = last('alpha_hat');
  if (alpha === undefined || last('weighting_uniform') === 1) return null;
  const interval = (lower, upper) => (upper === undefined ? `${fmt(lower, 3)} or more` : `${fmt(lower, 3)} to ${fmt(upper, 3)}`);
  // Only the mixture-proportion estimators record an interval (the paper's minimum has none).
  const lower = last('alpha_hat_lower');
  const parts = [`alpha-hat ${fmt(alpha, 3)}${lower === undefined ? '' : ` (interval ${interval(lower, last('alpha_hat_upper'))})`}`];
  const auc = last('discriminator_heldout_auc');
  if (auc !== undefined) {
    parts.push(`the discriminator’s held-out ROC AUC ${fmt(auc, 3)} (${interval(last('discriminator_heldout_auc_lower'), last('discriminator_heldout_auc_upper'))})`);
  }
  const pooled = last('discriminator_scores_pooled_by_episode');
  const eq10 = pooled === undefined ? ''
    : pooled === 1 ? ' Eq. 10 read each unlabeled episode’s mean discriminator logit.'
      : ' Eq. 10 read each row’s own logit: the unlabeled data has too few episodes to pool the scores by episode (the log says how many).';
  return h('p', { class: 'hint', id: 'weighting-summary', style: 'margin-top:12px' },
    h('strong', {}, 'Weighting: SafeDICE. '), `${parts.join('; ')}.${eq10}`);
}

/** Where SafeDICE's discriminator stood with early stopping, in words (its metrics
 *  discriminator_best_step and discriminator_stopped_at, -1 while it has not stopped). */
function earlyStopNote(job, series) {
  const last = (n) => (series.get(n) || []).at(-1);
  const best = last('discriminator_best_step');
  if (!best) return null;
  const stopped = last('discriminator_stopped_at');
  const budget = job.pretraining_steps;
  const done = job.progress.step >= budget;
  const when = stopped && stopped[1] >= 0
    ? `stopped early at discriminator step ${fmt(stopped[1])} of ${fmt(budget)}`
    : `did not stop early${done ? ` (trained all ${fmt(budget)} steps)` : ' (so far)'}`;
  const kept = done ? `its held-out loss was best at step ${fmt(best[1])}, whose weights it kept`
    : `its held-out loss is best so far at step ${fmt(best[1])}`;
  return h('p', { class: 'hint', id: 'discriminator-stopping', style: 'margin-top:12px' },
    h('strong', {}, 'Discriminator early stopping: '), `${when}; ${kept}.`);
}

async function drawCharts(job, slots) {
  const metrics = await api(`/v1/jobs/${job.id}/metrics?max_points=${CHART_POINTS}`);
  const series = groupMetrics(metrics.rows);
  const weighting = uniformWeightingNotice(series) || weightingSummary(series);
  if (job.eval) showEvaluation(job, series, slots);
  [...series.keys()].filter(isEval).forEach((n) => series.delete(n));
  // Metrics recorded once (e.g. alpha-hat diagnostics at the end of the discriminator phase)
  // read better as numbers than as one-point charts.
  const stopping = earlyStopNote(job, series);
  EARLY_STOP_METRICS.forEach((n) => series.delete(n));
  const once = [...series.entries()].filter(([name, points]) => points.length === 1 && name !== 'alpha_hat');
  once.forEach(([name]) => series.delete(name));
  slots.chartsNote.id = 'charts-empty';
  slots.chartsNote.className = 'empty';
  slots.chartsNote.hidden = series.size > 0;
  slots.chartsNote.textContent = job.status === STATUS.queued ? 'The job is queued: charts appear once it starts training.'
    : 'No metrics recorded yet: the worker records them every log_every steps (runner option on the Jobs form).';
  slots.charts.show(chartSpecs(job, series));
  slots.once.replaceChildren(weighting || '', stopping || '', once.length ? h('div', { class: 'card', id: 'single-values', style: 'margin-top:18px' },
    h('h2', {}, 'Recorded once'), tableWrap(h('table', {}, h('tbody', {}, once.map(([name, [[step, value]]]) =>
      h('tr', {}, h('td', { class: 'mono' }, name), h('td', { class: 'num' }, fmt(value)), h('td', { class: 'muted' }, `at step ${fmt(step)}`))))))) : '');
}

/** The evaluation section of a job page: charts over steps and the latest evaluation's numbers. */
function showEvaluation(job, series, slots) {
  const e = job.eval;
  const names = [...series.keys()].filter(isEval).sort();
  const when = e.every ? `every ${fmt(e.every)} policy steps and at the end` : 'at the end of training';
  slots.evalAbout.replaceChildren(h('p', { class: 'hint' }, `${fmt(e.episodes)} episodes on ${e.env} ${when}, seed ${e.seed}, ${e.deterministic ? 'deterministic' : 'sampled'} actions.`),
    names.length ? '' : h('div', { class: 'empty', id: 'eval-empty' }, e.every ? 'No evaluation yet: the first one runs after the first evaluation interval of policy learning.' : 'No evaluation yet: it runs when training ends.'));
  slots.evalCharts.show(evalChartSpecs(job, series));
  if (!names.length) { slots.evalLatest.replaceChildren(); return; }
  const lastStep = Math.max(...names.map((n) => series.get(n).at(-1)[0]));
  slots.evalLatest.replaceChildren(h('div', { class: 'card', id: 'eval-latest', style: 'margin-top:18px' },
    h('h2', {}, `Latest evaluation (step ${fmt(lastStep)})`),
    tableWrap(h('table', {}, h('tbody', {}, names.map((n) => h('tr', {}, h('td', { class: 'mono' }, n), h('td', { class: 'num' }, fmt(series.get(n).at(-1)[1])))))))));
}

// ---------- start ----------

window.addEventListener('hashchange', route);
window.addEventListener('DOMContentLoaded', () => { setupToken(); route(); });
