// SafeDICE dashboard: a small vanilla-JS single-page app over the JSON API (/v1). Pages are
// hash routes; lists refresh by polling (EventSource cannot send the Authorization header, and
// polling a page of jobs once a second is cheap). Charts are SVG rendered by the server
// (POST /ui/charts/*) from the metrics this page fetched.
'use strict';

// One accent colour per algorithm; the same values are the --algo-* variables of style.css.
const ALGORITHMS = {
  safedice: { label: 'SafeDICE', color: '#2563eb' },
  bc: { label: 'BC', color: '#6b7280' },
  dwbc: { label: 'DWBC', color: '#d97706' },
  ppl: { label: 'PPL', color: '#059669' },
  dexperts: { label: 'DExperts', color: '#7c3aed' },
};
const PALETTE = ['#d97706', '#059669', '#7c3aed', '#dc2626', '#0891b2', '#65a30d', '#db2777'];
const FINAL = new Set(['succeeded', 'failed', 'cancelled']);
const TOKEN_KEY = 'safedice.token';
const LIST_POLL_MS = 1000;
const JOB_POLL_MS = 1500;

// ---------- small helpers ----------

/** Builds an element; attributes starting with "on" are listeners; strings become text nodes. */
function h(tag, attrs, ...children) {
  const el = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs || {})) {
    if (value === null || value === undefined || value === false) continue;
    if (key.startsWith('on')) el.addEventListener(key.slice(2), value);
    else if (key === 'class') el.className = value;
    else el.setAttribute(key, value === true ? '' : value);
  }
  for (const child of children.flat()) {
    if (child === null || child === undefined || child === false) continue;
    el.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
  return el;
}

const $ = (selector, root = document) => root.querySelector(selector);

function fmt(value, digits = 4) {
  if (value === null || value === undefined) return '—';
  if (typeof value !== 'number') return String(value);
  if (Number.isInteger(value)) return value.toLocaleString('en-US');
  const abs = Math.abs(value);
  if (abs !== 0 && (abs < 1e-3 || abs >= 1e6)) return value.toExponential(2);
  return Number(value.toPrecision(digits)).toString();
}

function fmtBytes(bytes) {
  const units = ['B', 'KiB', 'MiB', 'GiB'];
  let i = 0;
  while (bytes >= 1024 && i < units.length - 1) { bytes /= 1024; i += 1; }
  return `${i === 0 ? bytes : bytes.toFixed(1)} ${units[i]}`;
}

function fmtDuration(seconds) {
  if (seconds === null || seconds === undefined) return '—';
  const s = Math.round(seconds);
  if (s < 60) return `${s} s`;
  if (s < 3600) return `${Math.floor(s / 60)} min ${s % 60} s`;
  return `${Math.floor(s / 3600)} h ${Math.floor((s % 3600) / 60)} min`;
}

function fmtTime(iso) {
  if (!iso) return '—';
  const d = new Date(iso);
  return Number.isNaN(d.getTime()) ? iso : d.toLocaleString();
}

const shortId = (id) => (id ? id.slice(0, 8) : '—');
const algoColor = (algorithm) => (ALGORITHMS[algorithm] || { color: '#6b7280' }).color;
const algoBadge = (algorithm) =>
  h('span', { class: `badge algo-${algorithm}` }, (ALGORITHMS[algorithm] || { label: algorithm }).label);
const statusPill = (status) => h('span', { class: `status status-${status}` }, status);

function progressBar(job, wide = false) {
  const pct = Math.round((job.progress.fraction || 0) * 1000) / 10;
  return h('span', {
    class: `progress algo-${job.algorithm}${wide ? ' wide' : ''}`,
    role: 'progressbar', 'aria-valuemin': 0, 'aria-valuemax': 100, 'aria-valuenow': pct,
  }, h('span', { class: 'fill', style: `width:${pct}%; display:block` }));
}

function actionSpaceText(space) {
  if (!space) return '—';
  if (space.type === 'discrete') return `discrete, ${space.n} actions`;
  return `continuous, ${space.dim}-dim`;
}

// ---------- API ----------

class ApiError extends Error {
  constructor(status, code, message) {
    super(message);
    this.status = status;
    this.code = code;
  }
}

const token = () => sessionStorage.getItem(TOKEN_KEY) || '';

/** Calls the API with the session's token; throws ApiError with the server's code and message. */
async function api(path, { method = 'GET', json, form, raw = false } = {}) {
  const headers = {};
  if (token()) headers.Authorization = `Bearer ${token()}`;
  let body;
  if (json !== undefined) { headers['Content-Type'] = 'application/json'; body = JSON.stringify(json); }
  if (form !== undefined) body = form;
  let response;
  try {
    response = await fetch(path, { method, headers, body });
  } catch (e) {
    throw new ApiError(0, 'network', `Cannot reach the server (${e.message}). Is safedice serve still running?`);
  }
  if (!response.ok) {
    let code = `http_${response.status}`;
    let message = `${response.status} ${response.statusText}`;
    try {
      const payload = await response.json();
      if (payload && payload.error) ({ code, message } = payload.error);
    } catch (_) { /* not JSON: keep the status line */ }
    throw new ApiError(response.status, code, message);
  }
  if (raw) return response;
  if (response.status === 204) return null;
  return response.json();
}

/** Asks the server to render a chart; returns the SVG text. */
async function renderChart(kind, spec) {
  const response = await fetch(`/ui/charts/${kind}`, {
    method: 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify(spec),
  });
  if (!response.ok) throw new ApiError(response.status, 'chart', await response.text());
  return response.text();
}

/** An error box: the server's message verbatim, plus what to do for the cases we can explain. */
function errorBox(err, cls = '') {
  const box = h('div', { class: `error-box ${cls}`, role: 'alert' });
  if (err.status === 401) {
    box.append(h('span', { class: 'error-message' },
      'This server requires an API token: paste it into the “API token” field at the top right and press Save.'));
    return box;
  }
  if (err.code) box.append(h('span', { class: 'error-code' }, err.code));
  box.append(h('span', { class: 'error-message' }, err.message));
  return box;
}

// ---------- routing and refresh loops ----------

let generation = 0; // bumped on every navigation; loops of older pages stop themselves

/** Runs `fn` now and then every `ms` until the page changes; failures show in `onError`. */
function every(ms, fn, onError) {
  const mine = generation;
  const tick = async () => {
    if (mine !== generation) return;
    try {
      const keepGoing = await fn();
      if (keepGoing === false) return;
    } catch (e) {
      if (onError) onError(e); else console.error(e);
    }
    if (mine === generation) setTimeout(tick, ms);
  };
  tick();
}

const routes = [
  [/^#\/datasets$/, datasetsPage, 'datasets'],
  [/^#\/jobs$/, jobsPage, 'jobs'],
  [/^#\/jobs\/([\w-]+)$/, jobPage, 'jobs'],
  [/^#\/compare$/, comparePage, 'compare'],
  [/^#\/policies$/, policiesPage, 'policies'],
  [/^#\/policies\/([\w-]+)$/, policyPage, 'policies'],
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

// ---------- datasets ----------

function datasetsPage(view) {
  const fileInput = h('input', { type: 'file', id: 'upload-file', accept: '.jsonl,.json,.csv,.npz,.h5,.hdf5', multiple: true, hidden: true });
  const nameInput = h('input', { id: 'upload-name', placeholder: 'name (default: the file name)' });
  const status = h('div', { id: 'upload-status' });
  const drop = h('div', { class: 'dropzone', id: 'dropzone', tabindex: 0 },
    h('strong', {}, 'Drop a dataset file here'), ' or click to choose one',
    h('div', { class: 'hint' }, 'JSONL, CSV or NPZ (D4RL / DSRL layout). The server validates it and stores it once.'));
  const table = h('div', { id: 'datasets-list' });

  const upload = async (files) => {
    status.replaceChildren();
    for (const file of files) {
      const form = new FormData();
      form.append('file', file, file.name);
      if (nameInput.value.trim() && files.length === 1) form.append('name', nameInput.value.trim());
      status.replaceChildren(h('div', { class: 'muted' }, `Uploading ${file.name} (${fmtBytes(file.size)})…`));
      try {
        const dataset = await api('/v1/datasets', { method: 'POST', form });
        status.replaceChildren(h('div', { class: 'notice', id: 'upload-ok' },
          `Stored “${dataset.name}”: ${fmt(dataset.transitions)} transitions, ${fmt(dataset.episodes)} episodes.`));
        nameInput.value = '';
        await refresh();
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

  const refresh = async () => {
    try {
      const page = await api('/v1/datasets?limit=500');
      table.replaceChildren(datasetsTable(page.items));
    } catch (err) {
      table.replaceChildren(errorBox(err));
    }
  };

  view.append(
    h('h1', {}, 'Datasets'),
    h('div', { class: 'card' }, h('h2', {}, 'Upload'), drop, fileInput,
      h('div', { class: 'form-actions' }, nameInput), status),
    h('div', { class: 'card' }, h('h2', {}, 'Stored datasets'), table),
  );
  refresh();
}

function summaryText(summary) {
  if (!summary) return '—';
  return `${fmt(summary.mean, 3)} ± ${fmt(summary.std, 2)}`;
}

function datasetsTable(items) {
  if (!items.length) {
    return h('div', { class: 'empty' }, 'No datasets yet. Drop a JSONL, CSV or NPZ file above; ',
      h('code', {}, 'safedice datagen --env six-rooms --out demo'), ' writes an unlabeled and a non-preferred set to try.');
  }
  return h('table', { id: 'datasets-table' },
    h('thead', {}, h('tr', {},
      h('th', {}, 'Name'), h('th', {}, 'Format'), h('th', { class: 'num' }, 'Transitions'),
      h('th', { class: 'num' }, 'Episodes'), h('th', { class: 'num' }, 'Obs dim'), h('th', {}, 'Actions'),
      h('th', { class: 'num' }, 'Return / episode'), h('th', { class: 'num' }, 'Cost / episode'),
      h('th', { class: 'num' }, 'Size'), h('th', {}, 'Uploaded'))),
    h('tbody', {}, items.map((d) => h('tr', { 'data-id': d.id },
      h('td', {}, h('strong', {}, d.name), h('div', { class: 'muted mono' }, shortId(d.id))),
      h('td', {}, d.format),
      h('td', { class: 'num' }, fmt(d.transitions)),
      h('td', { class: 'num' }, fmt(d.episodes)),
      h('td', { class: 'num' }, fmt(d.obs_dim)),
      h('td', {}, actionSpaceText(d.action_space)),
      h('td', { class: 'num' }, summaryText(d.stats && d.stats.episode_return)),
      h('td', { class: 'num' }, summaryText(d.stats && d.stats.episode_cost)),
      h('td', { class: 'num' }, fmtBytes(d.bytes)),
      h('td', {}, fmtTime(d.created_at))))));
}

// ---------- jobs ----------

// The main knobs of the job form with the `service` preset's defaults (api/openapi.yaml, CreateJob).
// An empty field is not sent, so the preset chosen decides its value.
const KNOBS = [
  { key: 'iterations', label: 'Iterations', placeholder: '100000', type: 'int' },
  { key: 'seed', label: 'Seed', placeholder: '0', type: 'int' },
  { key: 'batch_size', label: 'Batch size', placeholder: '512', type: 'int' },
  { key: 'hidden_sizes', label: 'Hidden sizes', placeholder: '256,256', type: 'list' },
  { key: 'lr_actor', label: 'Actor learning rate', placeholder: '3e-4 (SafeDICE 1e-4)', type: 'float' },
  { key: 'discriminator_iterations', label: 'Discriminator iterations', placeholder: 'iterations / 10', type: 'int', only: ['safedice'] },
  { key: 'gamma', label: 'Discount γ', placeholder: '0.99', type: 'float', only: ['safedice'] },
  { key: 'eta', label: 'η (DWBC)', placeholder: '0.2', type: 'float', only: ['dwbc'] },
  { key: 'alpha', label: 'α (DExperts)', placeholder: '0.2', type: 'float', only: ['dexperts'] },
];

function parseKnob(knob, text) {
  if (knob.type === 'list') return text.split(/[\s,]+/).filter(Boolean).map(Number);
  return Number(text);
}

/** Whether a policy over `obsDim` observations and `space` actions can act in `env` (mirrors the
 *  server's check: same observation width; discrete n at most the env's, or the same box width). */
function envFits(env, obsDim, space) {
  if (env.obs_dim !== obsDim || env.action_space.type !== space.type) return false;
  return space.type === 'discrete' ? space.n <= env.action_space.n : space.dim === env.action_space.dim;
}

function jobForm(datasets, envs, onCreated) {
  const algorithm = h('select', { name: 'algorithm', id: 'job-algorithm' },
    Object.entries(ALGORITHMS).map(([value, a]) => h('option', { value }, a.label)));
  const datasetOptions = (blank) => [blank && h('option', { value: '' }, blank),
    ...datasets.map((d) => h('option', { value: d.id }, `${d.name} (${fmt(d.transitions)} transitions)`))];
  const unlabeled = h('select', { name: 'unlabeled_dataset', id: 'job-unlabeled' }, datasetOptions(null));
  const nonPreferred = h('select', { name: 'non_preferred_dataset', id: 'job-non-preferred' }, datasetOptions('— none (BC only) —'));
  // Default pairing: the newest dataset as non-preferred, the one before as unlabeled (datagen
  // uploads them in that order); the user changes it in the selects.
  if (datasets.length > 1) { unlabeled.value = datasets[1].id; nonPreferred.value = datasets[0].id; }
  const preset = h('select', { name: 'preset', id: 'job-preset' },
    h('option', { value: 'service' }, 'service (default)'),
    h('option', { value: 'paper' }, 'paper (Tables 2/4)'),
    h('option', { value: 'authors-code' }, "authors' code"));
  const logEvery = h('input', { name: 'log_every', id: 'job-log_every', inputmode: 'numeric', placeholder: '100' });
  const evalEnv = h('select', { name: 'eval_env', id: 'job-eval-env' });
  const evalEvery = h('input', { name: 'eval_every', id: 'job-eval-every', inputmode: 'numeric', placeholder: 'iterations / 10' });
  const evalEpisodes = h('input', { name: 'eval_episodes', id: 'job-eval-episodes', inputmode: 'numeric', placeholder: '500' });
  // Only the environments whose spaces match the unlabeled dataset's can evaluate the policy.
  const showEnvs = () => {
    const dataset = datasets.find((d) => d.id === unlabeled.value);
    const fitting = dataset ? envs.filter((e) => envFits(e, dataset.obs_dim, dataset.action_space)) : [];
    evalEnv.replaceChildren(h('option', { value: '' }, fitting.length ? '— no evaluation —' : '— no built-in environment fits these data —'),
      ...fitting.map((e) => h('option', { value: e.name }, e.name)));
    if (fitting.length) evalEnv.value = fitting[0].name;
  };
  unlabeled.addEventListener('change', showEnvs);
  const knobInputs = KNOBS.map((knob) => {
    const input = h('input', { name: knob.key, id: `job-${knob.key}`, placeholder: knob.placeholder, inputmode: knob.type === 'list' ? 'text' : 'decimal' });
    const label = h('label', { 'data-knob': knob.key }, knob.label, input);
    return { knob, input, label };
  });
  const showKnobs = () => {
    for (const { knob, label } of knobInputs) label.hidden = Boolean(knob.only) && !knob.only.includes(algorithm.value);
  };
  algorithm.addEventListener('change', showKnobs);
  showKnobs();
  showEnvs();
  const result = h('div', { id: 'job-form-result' });
  const submit = h('button', { type: 'submit', id: 'job-submit' }, 'Queue job');

  const form = h('form', { id: 'job-form', class: 'card' },
    h('h2', {}, 'New training job'),
    h('div', { class: 'form-grid' },
      h('label', {}, 'Algorithm', algorithm),
      h('label', {}, 'Unlabeled dataset Dᵁ', unlabeled),
      h('label', {}, 'Non-preferred dataset Dᴺ', nonPreferred),
      h('label', {}, 'Preset', preset),
      knobInputs.map((k) => k.label),
      h('label', {}, 'Record metrics every (steps)', logEvery),
      h('label', {}, 'Evaluate on environment', evalEnv),
      h('label', {}, 'Evaluate every (policy steps)', evalEvery),
      h('label', {}, 'Evaluation episodes', evalEpisodes)),
    h('p', { class: 'hint' }, 'Empty fields take the preset’s value (placeholders show the service preset). The resolved configuration is on the job page. With an environment, the policy is evaluated every N policy-learning steps and at the end (the paper’s metrics, charted on the job page).'),
    h('div', { class: 'form-actions' }, submit), result);

  form.addEventListener('submit', async (event) => {
    event.preventDefault();
    result.replaceChildren();
    const config = { preset: preset.value };
    for (const { knob, input } of knobInputs) {
      if (!input.closest('label').hidden && input.value.trim() !== '') config[knob.key] = parseKnob(knob, input.value.trim());
    }
    const body = { algorithm: algorithm.value, unlabeled_dataset: unlabeled.value, config };
    if (nonPreferred.value) body.non_preferred_dataset = nonPreferred.value;
    if (logEvery.value.trim()) body.runner = { log_every: Number(logEvery.value.trim()) };
    if (evalEnv.value) {
      const iterations = Number(config.iterations || 100000);
      // Default: about ten evaluations over the run.
      body.eval = { env: evalEnv.value, every: Number(evalEvery.value.trim() || Math.max(1, Math.round(iterations / 10))) };
      if (evalEpisodes.value.trim()) body.eval.episodes = Number(evalEpisodes.value.trim());
    }
    submit.disabled = true;
    try {
      const job = await api('/v1/jobs', { method: 'POST', json: body });
      result.replaceChildren(h('div', { class: 'notice', id: 'job-created' }, 'Queued job ',
        h('a', { href: `#/jobs/${job.id}` }, shortId(job.id)), ` (${fmt(job.progress.total)} steps).`));
      onCreated(job);
    } catch (err) {
      result.replaceChildren(errorBox(err, 'job-form-error'));
    } finally {
      submit.disabled = false;
    }
  });
  return form;
}

function jobsTable(jobs, onCancel) {
  if (!jobs.length) {
    return h('div', { class: 'empty' }, 'No jobs yet. Upload an unlabeled and a non-preferred dataset on the ',
      h('a', { href: '#/datasets' }, 'Datasets'), ' page, then queue a job with the form above.');
  }
  return h('table', { id: 'jobs-table' },
    h('thead', {}, h('tr', {}, h('th', {}, 'Job'), h('th', {}, 'Algorithm'), h('th', {}, 'Status'),
      h('th', {}, 'Progress'), h('th', { class: 'num' }, 'Step'), h('th', { class: 'num' }, 'it/s'),
      h('th', { class: 'num' }, 'ETA'), h('th', { class: 'num' }, 'α̂'), h('th', {}, 'Created'), h('th', {}, ''))),
    h('tbody', {}, jobs.map((job) => h('tr', { 'data-id': job.id, 'data-status': job.status },
      h('td', { class: 'mono' }, h('a', { href: `#/jobs/${job.id}` }, shortId(job.id))),
      h('td', {}, algoBadge(job.algorithm)),
      h('td', { class: 'status-cell' }, statusPill(job.status)),
      h('td', {}, progressBar(job), ' ', h('span', { class: 'muted pct' }, `${Math.round(job.progress.fraction * 100)}%`)),
      h('td', { class: 'num step' }, `${fmt(job.progress.step)} / ${fmt(job.progress.total)}`),
      h('td', { class: 'num' }, fmt(job.progress.iterations_per_second, 3)),
      h('td', { class: 'num' }, fmtDuration(job.progress.eta_seconds)),
      h('td', { class: 'num' }, fmt(job.alpha_hat)),
      h('td', {}, fmtTime(job.created_at)),
      h('td', {}, FINAL.has(job.status) ? (job.policy_id ? h('a', { href: `#/policies/${job.policy_id}` }, 'policy') : '')
        : h('button', { class: 'danger cancel', type: 'button', onclick: () => onCancel(job) }, 'Cancel'))))));
}

async function cancelJob(job) {
  await api(`/v1/jobs/${job.id}/cancel`, { method: 'POST' });
}

function jobsPage(view) {
  const formSlot = h('div', {});
  const list = h('div', { id: 'jobs-list' });
  const listError = h('div', {});
  view.append(h('h1', {}, 'Jobs'), formSlot, h('div', { class: 'card' }, h('h2', {}, 'Jobs'), listError, list));

  Promise.all([api('/v1/datasets?limit=500'), api('/v1/envs')]).then(([page, envs]) => {
    if (!page.items.length) {
      formSlot.replaceChildren(h('div', { class: 'card' }, h('div', { class: 'empty' },
        'Upload datasets first: a job trains on an unlabeled dataset and (except BC) a non-preferred one. ',
        h('a', { href: '#/datasets' }, 'Go to Datasets.'))));
    } else {
      formSlot.replaceChildren(jobForm(page.items, envs.items, () => refresh()));
    }
  }).catch((err) => formSlot.replaceChildren(errorBox(err)));

  const onCancel = async (job) => {
    try { await cancelJob(job); } catch (err) { listError.replaceChildren(errorBox(err)); }
    refresh();
  };
  const refresh = async () => {
    const page = await api('/v1/jobs?limit=100');
    listError.replaceChildren();
    list.replaceChildren(jobsTable(page.items, onCancel));
  };
  every(LIST_POLL_MS, refresh, (err) => listError.replaceChildren(errorBox(err)));
}

// ---------- job page: charts of the metrics ----------

// Metric groups of the job page, matched on the metric name.
const METRIC_GROUPS = [
  { key: 'losses', title: 'Losses', y: 'loss', test: (n) => n.endsWith('_loss') },
  { key: 'alpha', title: 'α̂ (Eq. 15)', y: 'α̂', test: (n) => n === 'alpha_hat' },
  { key: 'weights', title: 'Weight statistics', y: 'value', test: (n) => /^(ess|weight|advantage|reward_(mean|std|clipped))/.test(n) },
  { key: 'discriminator', title: 'Discriminator', y: 'value', test: (n) => n.startsWith('discriminator_') },
];

// The evaluation charts of a job with an eval block (the paper's metrics over training steps);
// the other eval/ metrics are listed in the latest-evaluation table.
const EVAL_CHARTS = [
  { key: 'eval-return', title: 'Normalized return', y: 'normalized return (100 = preferred demos)', names: ['eval/normalized_return'] },
  { key: 'eval-cost', title: 'Average cost', y: 'cost per episode', names: ['eval/average_cost'] },
  { key: 'eval-violation', title: 'Cost-violation ratio', y: 'share of episodes with cost > κ', names: ['eval/cost_violation_ratio'] },
  { key: 'eval-cvar', title: 'CVaR k% cost', y: 'mean cost of the worst k% episodes', names: ['eval/cvar_cost_50', 'eval/cvar_cost_20', 'eval/cvar_cost_10', 'eval/cvar_cost_5'] },
];
const isEval = (name) => name.startsWith('eval/');

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
        x_label: 'training step (all phases)',
        y_label: perMetric ? set[0] : group.y,
        series: set.map((name, i) => ({ name, points: series.get(name), color: seriesColor(job, i) })),
      });
    }
  }
  const rest = [...series.keys()].filter((n) => !used.has(n));
  for (const name of rest) {
    specs.push({ key: `other-${name}`, title: name, x_label: 'training step (all phases)', y_label: name,
      series: [{ name, points: series.get(name), color: algoColor(job.algorithm) }] });
  }
  return specs;
}

/** Chart specs of the evaluation metrics recorded so far. */
function evalChartSpecs(job, series) {
  return EVAL_CHARTS.filter((chart) => chart.names.some((n) => series.has(n))).map((chart) => ({
    key: chart.key,
    title: `${chart.title} on ${job.eval.env}`,
    x_label: 'training step (all phases)',
    y_label: chart.y,
    series: chart.names.filter((n) => series.has(n)).map((name, i) => ({
      name: name.replace('eval/cvar_cost_', 'CVaR ').replace(/^CVaR (\d+)$/, 'CVaR $1%'), points: series.get(name), color: seriesColor(job, i) })),
  }));
}

async function chartBoxes(specs) {
  const svgs = await Promise.all(specs.map((spec) => renderChart('line', spec)));
  return specs.map((spec, i) => {
    const box = h('div', { class: 'chart-box', 'data-chart': spec.key });
    box.innerHTML = svgs[i]; // server-rendered SVG: every text in it is escaped on the server
    return box;
  });
}

/** The evaluation section of a job page: charts over steps and the latest evaluation's numbers. */
async function evaluationSection(job, series) {
  const e = job.eval;
  const about = h('p', { class: 'hint' }, `${fmt(e.episodes)} episodes on ${e.env} every ${fmt(e.every)} policy steps and at the end, seed ${e.seed}, ${e.deterministic ? 'deterministic' : 'sampled'} actions.`);
  const names = [...series.keys()].filter(isEval).sort();
  if (!names.length) {
    return h('div', { id: 'evaluation' }, about, h('div', { class: 'empty', id: 'eval-empty' },
      'No evaluation yet: the first one runs after the first evaluation interval of policy learning.'));
  }
  const lastStep = Math.max(...names.map((n) => series.get(n).at(-1)[0]));
  const latest = h('div', { class: 'card', id: 'eval-latest', style: 'margin-top:18px' },
    h('h2', {}, `Latest evaluation (step ${fmt(lastStep)})`),
    h('table', {}, h('tbody', {}, names.map((n) => h('tr', {}, h('td', { class: 'mono' }, n), h('td', { class: 'num' }, fmt(series.get(n).at(-1)[1])))))));
  return h('div', { id: 'evaluation' }, about, h('div', { class: 'grid2', id: 'eval-charts' }, await chartBoxes(evalChartSpecs(job, series))), latest);
}

async function drawCharts(container, evalContainer, job) {
  const metrics = await api(`/v1/jobs/${job.id}/metrics?max_points=300`);
  const series = groupMetrics(metrics.rows);
  if (job.eval) evalContainer.replaceChildren(await evaluationSection(job, series));
  [...series.keys()].filter(isEval).forEach((n) => series.delete(n));
  if (!series.size) {
    container.replaceChildren(h('div', { class: 'empty', id: 'charts-empty' },
      job.status === 'queued' ? 'The job is queued: charts appear once it starts training.'
        : 'No metrics recorded yet: the worker records them every log_every steps (runner option on the Jobs form).'));
    return;
  }
  // Metrics recorded once (e.g. alpha-hat diagnostics at the end of the discriminator phase)
  // read better as numbers than as one-point charts.
  const once = [...series.entries()].filter(([name, points]) => points.length === 1 && name !== 'alpha_hat');
  once.forEach(([name]) => series.delete(name));
  const boxes = await chartBoxes(chartSpecs(job, series));
  const onceTable = once.length ? h('div', { class: 'card', id: 'single-values', style: 'margin-top:18px' },
    h('h2', {}, 'Recorded once'), h('table', {}, h('tbody', {}, once.map(([name, [[step, value]]]) =>
      h('tr', {}, h('td', { class: 'mono' }, name), h('td', { class: 'num' }, fmt(value)), h('td', { class: 'muted' }, `at step ${fmt(step)}`)))))) : null;
  container.replaceChildren(h('div', { class: 'grid2', id: 'charts' }, boxes), onceTable);
}

function configTable(config) {
  const entries = Object.entries(config || {});
  return h('table', { id: 'job-config' }, h('tbody', {}, entries.map(([key, value]) =>
    h('tr', {}, h('td', { class: 'mono' }, key), h('td', { class: 'mono' }, typeof value === 'object' ? JSON.stringify(value) : String(value))))));
}

function jobSummary(job, onCancel) {
  const p = job.progress;
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
    job.status === 'failed' ? h('div', { class: 'error-box job-error', role: 'alert' },
      h('strong', {}, 'This job failed: '), h('span', { class: 'error-message' }, job.error || 'no reason recorded'),
      h('div', { class: 'hint' }, 'Fix what the message names (a knob of the config or the data) and queue a new job on the Jobs page.')) : null,
    job.cancel_requested && job.status === 'running' ? h('div', { class: 'hint' }, 'Cancel requested; the job stops within a second.') : null);
}

function jobPage(view, id) {
  const summary = h('div', {});
  const charts = h('div', { id: 'charts-slot' }, h('div', { class: 'muted' }, 'Loading metrics…'));
  const evaluation = h('div', { id: 'eval-slot' });
  const evalHeading = h('h2', { hidden: true }, 'Evaluation');
  const details = h('div', {});
  const problem = h('div', {});
  view.append(h('h1', {}, 'Job ', h('span', { class: 'mono' }, shortId(id))), problem, summary,
    evalHeading, evaluation, h('h2', {}, 'Training metrics'), charts, details);
  let lastChartStep = -1;
  let shownDetails = false;
  every(JOB_POLL_MS, async () => {
    const job = await api(`/v1/jobs/${id}`);
    problem.replaceChildren();
    summary.replaceChildren(jobSummary(job, async () => {
      try { await cancelJob(job); } catch (err) { problem.replaceChildren(errorBox(err)); }
    }));
    if (job.progress.step !== lastChartStep || FINAL.has(job.status)) {
      lastChartStep = job.progress.step;
      evalHeading.hidden = !job.eval;
      await drawCharts(charts, evaluation, job);
    }
    if (!shownDetails) {
      shownDetails = true;
      details.replaceChildren(h('div', { class: 'grid2', style: 'margin-top:18px' },
        h('div', { class: 'card' }, h('h2', {}, 'Resolved configuration'), configTable(job.config),
          h('h2', { style: 'margin-top:14px' }, 'Runner'), configTable(job.runner),
          job.eval ? [h('h2', { style: 'margin-top:14px' }, 'Evaluation'), configTable(job.eval)] : null),
        h('div', { class: 'card' }, h('h2', {}, 'Job'), h('dl', { class: 'kv' },
          h('dt', {}, 'id'), h('dd', { class: 'mono' }, job.id),
          h('dt', {}, 'unlabeled dataset'), h('dd', { class: 'mono' }, job.unlabeled_dataset),
          h('dt', {}, 'non-preferred dataset'), h('dd', { class: 'mono' }, job.non_preferred_dataset || '—'),
          h('dt', {}, 'created'), h('dd', {}, fmtTime(job.created_at)),
          h('dt', {}, 'started'), h('dd', {}, fmtTime(job.started_at)),
          h('dt', {}, 'finished'), h('dd', {}, fmtTime(job.finished_at))))));
    }
    return !FINAL.has(job.status);
  }, (err) => problem.replaceChildren(errorBox(err)));
}

// ---------- compare ----------

/** The last recorded value of every metric of a job (max_points=2 keeps the last point exactly). */
async function finalMetrics(job) {
  const metrics = await api(`/v1/jobs/${job.id}/metrics?max_points=2`);
  const last = {};
  for (const row of metrics.rows) last[row.name] = row.value;
  return last;
}

/** The default scatter axis: for the first pattern (e.g. average cost, then any cost) that
 *  matches, an evaluation metric, else any metric; failing all, a metric every chosen job has
 *  (other than `avoid`). */
function pickAxis(names, common, patterns, avoid) {
  for (const pattern of patterns) {
    const found = names.find((n) => isEval(n) && pattern.test(n)) || names.find((n) => pattern.test(n));
    if (found) return found;
  }
  return common.find((n) => n !== avoid) || common[0] || names[0] || '';
}

function comparePage(view) {
  const picker = h('div', { class: 'checklist', id: 'compare-jobs' });
  const output = h('div', { id: 'compare-output' });
  view.append(h('h1', {}, 'Compare finished jobs'),
    h('div', { class: 'card' }, h('h2', {}, 'Jobs'), picker,
      h('p', { class: 'hint' }, 'Evaluation metrics (return, average cost, violation ratio, CVaR) are compared when the jobs recorded them (metric names starting with “eval”); otherwise the final training metrics are.')),
    output);
  const cache = new Map();
  let jobs = [];

  const draw = async () => {
    const chosen = jobs.filter((j) => picker.querySelector(`input[value="${j.id}"]`).checked);
    if (!chosen.length) {
      output.replaceChildren(h('div', { class: 'empty' }, 'Tick two or more jobs above to compare them.'));
      return;
    }
    const finals = await Promise.all(chosen.map(async (j) => {
      if (!cache.has(j.id)) cache.set(j.id, await finalMetrics(j));
      return cache.get(j.id);
    }));
    const names = [...new Set(finals.flatMap((f) => Object.keys(f)))]
      .sort((a, b) => (/^eval/.test(b) - /^eval/.test(a)) || a.localeCompare(b));
    const table = h('table', { id: 'compare-table' },
      h('thead', {}, h('tr', {}, h('th', {}, 'Metric (last value)'), chosen.map((j) =>
        h('th', { class: 'num' }, algoBadge(j.algorithm), ' ', h('span', { class: 'mono' }, shortId(j.id)))))),
      h('tbody', {},
        h('tr', {}, h('td', {}, 'α̂'), chosen.map((j) => h('td', { class: 'num' }, fmt(j.alpha_hat)))),
        h('tr', {}, h('td', {}, 'iterations · seed'), chosen.map((j) => h('td', { class: 'num' }, `${fmt(j.config.iterations)} · ${j.config.seed}`))),
        h('tr', {}, h('td', {}, 'evaluated on'), chosen.map((j) => h('td', { class: 'num eval-env' }, j.eval ? `${j.eval.env} · ${fmt(j.eval.episodes)} episodes` : '—'))),
        names.map((n) => h('tr', {}, h('td', { class: 'mono' }, n), finals.map((f) => h('td', { class: 'num' }, fmt(f[n])))))));
    const xSelect = h('select', { id: 'scatter-x' }, names.map((n) => h('option', { value: n }, n)));
    const ySelect = h('select', { id: 'scatter-y' }, names.map((n) => h('option', { value: n }, n)));
    const common = names.filter((n) => finals.every((f) => typeof f[n] === 'number'));
    xSelect.value = pickAxis(names, common, [/average_cost/, /cost/], null);
    ySelect.value = pickAxis(names, common, [/normalized_return/, /return/], xSelect.value);
    const scatter = h('div', { class: 'chart-box', 'data-chart': 'scatter' });
    const drawScatter = async () => {
      const [x, y] = [xSelect.value, ySelect.value];
      scatter.innerHTML = await renderChart('scatter', {
        title: /cost/.test(x) && /return/.test(y) ? 'Cost vs return' : `${y} vs ${x}`,
        x_label: x, y_label: y,
        points: chosen.map((j, i) => ({ label: shortId(j.id), x: finals[i][x], y: finals[i][y],
          group: (ALGORITHMS[j.algorithm] || { label: j.algorithm }).label, color: algoColor(j.algorithm) }))
          .filter((p) => typeof p.x === 'number' && typeof p.y === 'number'),
      });
    };
    xSelect.addEventListener('change', drawScatter);
    ySelect.addEventListener('change', drawScatter);
    output.replaceChildren(h('div', { class: 'grid2' },
      h('div', { class: 'card' }, h('h2', {}, 'Side by side'), table),
      h('div', { class: 'card' }, h('h2', {}, 'Scatter'),
        h('div', { class: 'axis-pick' }, 'x', xSelect, 'y', ySelect), scatter)));
    await drawScatter();
  };

  api('/v1/jobs?status=succeeded&limit=500').then((page) => {
    jobs = page.items;
    if (!jobs.length) {
      picker.replaceChildren(h('div', { class: 'empty' }, 'No finished jobs yet. Queue jobs on the ',
        h('a', { href: '#/jobs' }, 'Jobs'), ' page; succeeded jobs appear here.'));
      return;
    }
    picker.replaceChildren(...jobs.map((j, i) => h('label', {},
      h('input', { type: 'checkbox', value: j.id, checked: i < 4, onchange: () => draw().catch((e) => output.replaceChildren(errorBox(e))) }),
      algoBadge(j.algorithm), h('span', { class: 'mono' }, shortId(j.id)),
      h('span', { class: 'muted' }, `${fmt(j.config.iterations)} iterations, seed ${j.config.seed}, finished ${fmtTime(j.finished_at)}`))));
    return draw();
  }).catch((err) => output.replaceChildren(errorBox(err)));
}

// ---------- policies ----------

function policiesPage(view) {
  const list = h('div', { id: 'policies-list' });
  view.append(h('h1', {}, 'Policies'), h('div', { class: 'card' }, list));
  api('/v1/policies?limit=500').then((page) => {
    if (!page.items.length) {
      list.replaceChildren(h('div', { class: 'empty' }, 'No policies yet: a job that succeeds stores its policy here. ',
        h('a', { href: '#/jobs' }, 'Queue a job.')));
      return;
    }
    list.replaceChildren(h('table', { id: 'policies-table' },
      h('thead', {}, h('tr', {}, h('th', {}, 'Policy'), h('th', {}, 'Algorithm'), h('th', {}, 'Job'),
        h('th', { class: 'num' }, 'Obs dim'), h('th', {}, 'Actions'), h('th', { class: 'num' }, 'α̂'), h('th', {}, 'Created'))),
      h('tbody', {}, page.items.map((p) => h('tr', { 'data-id': p.id },
        h('td', { class: 'mono' }, h('a', { href: `#/policies/${p.id}` }, shortId(p.id))),
        h('td', {}, algoBadge(p.algorithm)),
        h('td', { class: 'mono' }, h('a', { href: `#/jobs/${p.job_id}` }, shortId(p.job_id))),
        h('td', { class: 'num' }, fmt(p.obs_dim)),
        h('td', {}, actionSpaceText(p.action_space)),
        h('td', { class: 'num' }, fmt(p.alpha_hat)),
        h('td', {}, fmtTime(p.created_at)))))));
  }).catch((err) => list.replaceChildren(errorBox(err)));
}

/** Observations typed by a person: JSON ([[..], ..] or [..]) or one row per line of numbers. */
function parseObservations(text) {
  const trimmed = text.trim();
  if (!trimmed) throw new Error('Paste at least one observation.');
  if (trimmed.startsWith('[')) {
    const parsed = JSON.parse(trimmed);
    return Array.isArray(parsed[0]) ? parsed : [parsed];
  }
  return trimmed.split('\n').filter((line) => line.trim()).map((line) =>
    line.trim().split(/[\s,;]+/).map((cell) => {
      const v = Number(cell);
      if (Number.isNaN(v)) throw new Error(`“${cell}” is not a number`);
      return v;
    }));
}

function snippets(policy) {
  const origin = location.origin;
  const zeros = JSON.stringify(Array(policy.obs_dim).fill(0));
  const auth = token() ? ' \\\n  -H "Authorization: Bearer $SAFEDICE_API_TOKEN"' : '';
  const act = `curl -s ${origin}/v1/policies/${policy.id}/act${auth} \\\n  -H 'Content-Type: application/json' \\\n  -d '{"observations": [${zeros}], "deterministic": true}'`;
  const oip = `curl -s ${origin}/v2/models/${policy.id}/infer${auth} \\\n  -H 'Content-Type: application/json' \\\n  -d '{"inputs": [{"name": "observations", "shape": [1, ${policy.obs_dim}], "datatype": "FP32", "data": ${zeros}}]}'`;
  return { act, oip };
}

async function downloadWeights(policy) {
  const response = await api(`/v1/policies/${policy.id}/weights`, { raw: true });
  const url = URL.createObjectURL(await response.blob());
  const a = h('a', { href: url, download: `policy-${policy.id}.safetensors` });
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
}

const RUNNING = new Set(['queued', 'running']);

function evaluationsTable(items) {
  if (!items.length) return h('div', { class: 'empty', id: 'evaluations-empty' }, 'No evaluations of this policy yet.');
  const m = (e, key) => (e.metrics ? fmt(e.metrics[key]) : '—');
  return h('table', { id: 'evaluations-table' },
    h('thead', {}, h('tr', {}, h('th', {}, 'Environment'), h('th', { class: 'num' }, 'Episodes'), h('th', { class: 'num' }, 'Seed'),
      h('th', {}, 'Actions'), h('th', {}, 'Status'), h('th', { class: 'num' }, 'Normalized return'), h('th', { class: 'num' }, 'Average cost'),
      h('th', { class: 'num' }, 'Violation ratio'), h('th', { class: 'num' }, 'CVaR 10%'), h('th', { class: 'num' }, 'CVaR 5%'), h('th', {}, 'Finished'))),
    h('tbody', {}, items.map((e) => h('tr', { 'data-id': e.id, 'data-status': e.status },
      h('td', {}, e.env), h('td', { class: 'num' }, fmt(e.episodes)), h('td', { class: 'num' }, String(e.seed)),
      h('td', {}, e.deterministic ? 'deterministic' : 'sampled'),
      h('td', {}, statusPill(e.status), e.error ? h('div', { class: 'error-message' }, e.error) : null),
      h('td', { class: 'num eval-return' }, m(e, 'normalized_return')), h('td', { class: 'num eval-cost' }, m(e, 'average_cost')),
      h('td', { class: 'num' }, m(e, 'cost_violation_ratio')),
      h('td', { class: 'num' }, e.metrics ? fmt(e.metrics.cvar_cost['10']) : '—'),
      h('td', { class: 'num' }, e.metrics ? fmt(e.metrics.cvar_cost['5']) : '—'),
      h('td', {}, fmtTime(e.finished_at))))));
}

/** Evaluate the policy on a built-in environment (background task) and list its evaluations. */
function evaluationCard(policy, envs) {
  const fitting = envs.filter((e) => envFits(e, policy.obs_dim, policy.action_space));
  const list = h('div', { id: 'evaluations-list' });
  const problem = h('div', {});
  const refresh = async () => {
    const page = await api(`/v1/evaluations?policy_id=${policy.id}&limit=50`);
    problem.replaceChildren();
    list.replaceChildren(evaluationsTable(page.items));
    return page.items.some((e) => RUNNING.has(e.status));
  };
  // One polling loop at a time; it ends once no evaluation is queued or running.
  let polling = false;
  const poll = () => {
    if (polling) return;
    polling = true;
    every(1000, async () => {
      const more = await refresh();
      polling = more;
      return more;
    }, (err) => problem.replaceChildren(errorBox(err)));
  };
  const card = h('div', { class: 'card', id: 'evaluate-card' }, h('h2', {}, 'Evaluate on a built-in environment'));
  if (!fitting.length) {
    card.append(h('div', { class: 'empty' }, 'No built-in environment has this policy’s observation and action spaces (see GET /v1/envs).'), list, problem);
    poll();
    return card;
  }
  const env = h('select', { id: 'eval-env' }, fitting.map((e) => h('option', { value: e.name }, e.name)));
  const episodes = h('input', { id: 'eval-episodes', inputmode: 'numeric', placeholder: '500', style: 'width:110px' });
  const seed = h('input', { id: 'eval-seed', inputmode: 'numeric', placeholder: '0', style: 'width:90px' });
  const deterministic = h('input', { type: 'checkbox', id: 'eval-deterministic' });
  const submit = h('button', { type: 'submit', id: 'eval-submit' }, 'Evaluate');
  const form = h('form', { id: 'evaluate-form', class: 'form-actions' }, h('label', {}, 'Environment ', env),
    h('label', {}, 'Episodes ', episodes), h('label', {}, 'Seed ', seed), h('label', {}, deterministic, ' deterministic'), submit);
  form.addEventListener('submit', async (event) => {
    event.preventDefault();
    const body = { env: env.value, deterministic: deterministic.checked };
    if (episodes.value.trim()) body.episodes = Number(episodes.value.trim());
    if (seed.value.trim()) body.seed = Number(seed.value.trim());
    submit.disabled = true;
    try {
      await api(`/v1/policies/${policy.id}/evaluate`, { method: 'POST', json: body });
      problem.replaceChildren();
      poll();
    } catch (err) {
      problem.replaceChildren(errorBox(err, 'eval-error'));
    } finally {
      submit.disabled = false;
    }
  });
  card.append(form, h('p', { class: 'hint' }, 'The paper’s metrics over the episodes (sampled actions unless deterministic): normalized return (100 = the preferred demonstrations), average cost, share of episodes over the cost threshold κ, CVaR k% cost. Same seed, same numbers.'),
    problem, list);
  poll();
  return card;
}

function policyPage(view, id) {
  const slot = h('div', {});
  view.append(h('h1', {}, 'Policy ', h('span', { class: 'mono' }, shortId(id))), slot);
  Promise.all([api(`/v1/policies/${id}`), api('/v1/envs')]).then(([policy, envs]) => {
    const input = h('textarea', { id: 'act-input', spellcheck: 'false',
      placeholder: `One observation per line (${policy.obs_dim} numbers), or JSON like [${Array(policy.obs_dim).fill(0).join(', ')}]` });
    input.value = Array(policy.obs_dim).fill(0).join(', ');
    const deterministic = h('input', { type: 'checkbox', id: 'act-deterministic', checked: true });
    const seed = h('input', { id: 'act-seed', placeholder: 'seed (sampling only)', inputmode: 'numeric', style: 'width:170px' });
    const output = h('div', { id: 'act-output' });
    const actButton = h('button', { type: 'submit', id: 'act-submit' }, 'Get actions');
    const actForm = h('form', { class: 'card', id: 'act-form' }, h('h2', {}, 'Try it: observations → actions'), input,
      h('div', { class: 'form-actions' }, actButton, h('label', {}, deterministic, ' deterministic'), seed), output);
    actForm.addEventListener('submit', async (event) => {
      event.preventDefault();
      output.replaceChildren();
      let observations;
      try { observations = parseObservations(input.value); } catch (e) {
        output.replaceChildren(errorBox({ code: 'input', message: e.message }, 'act-error'));
        return;
      }
      const body = { observations, deterministic: deterministic.checked };
      if (seed.value.trim()) body.seed = Number(seed.value.trim());
      try {
        const result = await api(`/v1/policies/${id}/act`, { method: 'POST', json: body });
        output.replaceChildren(h('pre', { id: 'act-result' }, JSON.stringify(result.actions, null, 0).replace(/\],\[/g, '],\n[')));
      } catch (err) {
        output.replaceChildren(errorBox(err, 'act-error'));
      }
    });
    const downloadError = h('div', {});
    const { act, oip } = snippets(policy);
    const finals = Object.entries(policy.final_metrics || {});
    slot.replaceChildren(
      h('div', { class: 'grid2' },
        h('div', { class: 'card', id: 'policy-meta' }, h('h2', {}, 'Metadata'), h('dl', { class: 'kv' },
          h('dt', {}, 'algorithm'), h('dd', {}, algoBadge(policy.algorithm)),
          h('dt', {}, 'id'), h('dd', { class: 'mono' }, policy.id),
          h('dt', {}, 'trained by job'), h('dd', { class: 'mono' }, h('a', { href: `#/jobs/${policy.job_id}` }, policy.job_id)),
          h('dt', {}, 'observation dim'), h('dd', {}, fmt(policy.obs_dim)),
          h('dt', {}, 'action space'), h('dd', {}, actionSpaceText(policy.action_space)),
          h('dt', {}, 'α̂'), h('dd', {}, fmt(policy.alpha_hat)),
          h('dt', {}, 'created'), h('dd', {}, fmtTime(policy.created_at))),
          h('div', { class: 'form-actions' },
            h('button', { type: 'button', class: 'secondary', id: 'weights-download', onclick: () => downloadWeights(policy).catch((e) => downloadError.replaceChildren(errorBox(e))) }, 'Download weights (.safetensors)')),
          h('p', { class: 'hint' }, 'The JSON spec needed to rebuild the policy comes with the download as the x-safedice-policy-spec header.'),
          downloadError),
        h('div', { class: 'card' }, h('h2', {}, 'Final training metrics'), finals.length
          ? h('table', {}, h('tbody', {}, finals.map(([k, v]) => h('tr', {}, h('td', { class: 'mono' }, k), h('td', { class: 'num' }, fmt(v))))))
          : h('div', { class: 'empty' }, 'No metrics were recorded for this policy.'))),
      evaluationCard(policy, envs.items),
      actForm,
      h('div', { class: 'card' }, h('h2', {}, 'Call it from an agent'),
        h('p', { class: 'hint' }, 'JSON API:'), h('pre', { id: 'snippet-curl' }, act),
        h('p', { class: 'hint' }, 'Open Inference Protocol (KServe v2), for standard inference clients:'), h('pre', { id: 'snippet-oip' }, oip)));
  }).catch((err) => slot.replaceChildren(errorBox(err)));
}

// ---------- start ----------

window.addEventListener('hashchange', route);
window.addEventListener('DOMContentLoaded', () => { setupToken(); route(); });
