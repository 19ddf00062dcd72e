// The job form of the Jobs page: the knobs of the server's algorithm table, the chosen preset's
// values as placeholders, the step plan and its expected duration, the datasets and the optional
// evaluation and registration. A plain script like app.js (globals, loaded before it).
'use strict';

// The main knobs of the job form, from the server's algorithm table: each algorithm's (common
// ones first), each key once. Placeholders show the chosen algorithm's and preset's values; an
// empty field is not sent, so the preset decides its value. A pretraining knob's value follows
// the iterations unless set (pretrainingShare), so its placeholder names the rule instead.
const KNOBS = [...new Map(ALGORITHM_TABLE.flatMap((a) => a.knobs).map((k) => [k.key, k])).values()];

/** The resolved configuration of `preset` for `algorithm` (every knob with its value). */
function presetConfig(algorithm, preset) {
  const found = (ALGORITHMS[algorithm]?.presets || []).find((p) => p.name === preset);
  return found ? found.config : {};
}

function knobText(value) {
  return Array.isArray(value) ? value.join(',') : String(value);
}

function parseKnob(knob, text) {
  if (knob.type === 'list') return text.split(/[\s,]+/).filter(Boolean).map(Number);
  return Number(text);
}

/** The share of the iterations a preset's pretraining phase takes unless set, read off the
 *  server's resolved preset (service SafeDICE: 1, the others: a tenth). */
function pretrainingShare(defaults, key) {
  return Number(defaults[key]) / Number(defaults.iterations);
}

/** The placeholder of a pretraining knob: the preset's rule in words. */
function pretrainingRule(defaults, key) {
  const share = pretrainingShare(defaults, key);
  if (share === 1) return 'iterations';
  if (share === 0.1) return 'iterations / 10';
  return `${share} × iterations`;
}

/** The steps of a run as the server plans them (the `steps` of POST /v1/algorithms/{name}/plan). */
function stepPlanText(steps) {
  if (!steps.pretraining_steps) return `${fmt(steps.total_steps)} steps`;
  return `${fmt(steps.total_steps)} steps = ${fmt(steps.pretraining_steps)} ${steps.pretraining_phase} + ${fmt(steps.iterations)} policy iterations`;
}

/** The server's plan of `config` for `algorithm`: its resolved configuration and steps, or the
 *  error a job with it would be refused with. */
async function planOf(algorithm, config) {
  return api(`/v1/algorithms/${encodeURIComponent(algorithm)}/plan`, { method: 'POST', json: config });
}

/** Seconds per step of the newest succeeded job with the same algorithm, network sizes and batch
 *  as the resolved `config`, measured from its start and finish times; null if there is none. */
function measuredPace(finished, algorithm, config) {
  const hidden = knobText(config.hidden_sizes);
  const job = finished.find((j) => j.algorithm === algorithm && knobText(j.config.hidden_sizes) === hidden
    && j.config.batch_size === config.batch_size && j.started_at && j.finished_at && j.progress.total > 0);
  if (!job) return null;
  const seconds = (new Date(job.finished_at) - new Date(job.started_at)) / 1000;
  return seconds > 0 ? { job, secondsPerStep: seconds / job.progress.total } : null;
}

/** Whether a policy over `obsDim` observations and `space` actions can act in `env` (mirrors the
 *  server's check: same observation width; discrete n at most the env's, or the same box width). */
function envFits(env, obsDim, space) {
  if (env.obs_dim !== obsDim || env.action_space.type !== space.type) return false;
  return space.type === 'discrete' ? space.n <= env.action_space.n : space.dim === env.action_space.dim;
}

/** The datasets a select offers for `role`: those uploaded in that role first, then those whose
 *  role was not given; never the other role's (the server refuses those in this place). */
function datasetChoices(datasets, role) {
  return [...datasets.filter((d) => d.role === role), ...datasets.filter((d) => !d.role)];
}

/** "a, b" → ["a", "b"]: tags as typed in a field. */
const parseTags = (text) => text.split(',').map((t) => t.trim()).filter(Boolean);

function jobForm(datasets, envs, finished, models, onCreated) {
  const algorithm = h('select', { name: 'algorithm', id: 'job-algorithm' },
    Object.entries(ALGORITHMS).map(([value, a]) => h('option', { value }, a.label)));
  const option = (d) => h('option', { value: d.id }, `${d.name} (${fmt(d.transitions)} transitions)`);
  const unlabeledChoices = datasetChoices(datasets, 'unlabeled');
  const nonPreferredChoices = datasetChoices(datasets, 'non_preferred');
  const unlabeled = h('select', { name: 'unlabeled_dataset', id: 'job-unlabeled' }, unlabeledChoices.map(option));
  const nonPreferred = h('select', { name: 'non_preferred_dataset', id: 'job-non-preferred' },
    h('option', { value: '' }, '— none (BC only) —'), nonPreferredChoices.map(option));
  // Defaults: the newest dataset uploaded in each role (lists are newest first).
  if (unlabeledChoices.length) unlabeled.value = unlabeledChoices[0].id;
  const np = nonPreferredChoices.find((d) => d.id !== unlabeled.value);
  nonPreferred.value = np ? np.id : '';
  const presetLabels = { service: 'service (default)', paper: 'paper (Tables 2/4)', 'authors-code': "authors' code" };
  const preset = h('select', { name: 'preset', id: 'job-preset' },
    (ALGORITHM_TABLE[0]?.presets || []).map((p) => h('option', { value: p.name }, presetLabels[p.name] || p.name)));
  const name = h('input', { name: 'name', id: 'job-name', placeholder: 'e.g. safedice walker 256x256', maxlength: 200 });
  const tags = h('input', { name: 'tags', id: 'job-tags', placeholder: 'e.g. walker, v2' });
  const notes = h('input', { name: 'notes', id: 'job-notes', placeholder: 'what this run tries' });
  const logEvery = h('input', { name: 'log_every', id: 'job-log_every', inputmode: 'numeric', placeholder: '100' });
  const evalEnv = h('select', { name: 'eval_env', id: 'job-eval-env' });
  const evalEvery = h('input', { name: 'eval_every', id: 'job-eval-every', inputmode: 'numeric', placeholder: 'at the end' });
  const evalEpisodes = h('input', { name: 'eval_episodes', id: 'job-eval-episodes', inputmode: 'numeric', placeholder: '500' });
  const estimate = h('p', { class: 'estimate', id: 'job-estimate' });
  const register = registerFields(models);
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
    const input = h('input', { name: knob.key, id: `job-${knob.key}`, inputmode: knob.type === 'list' ? 'text' : 'decimal' });
    const label = h('label', { 'data-knob': knob.key }, knob.label, input);
    return { knob, input, label };
  });
  const chosenConfig = () => {
    const config = { preset: preset.value };
    for (const { knob, input, label } of knobInputs) {
      if (!label.hidden && input.value.trim() !== '') config[knob.key] = parseKnob(knob, input.value.trim());
    }
    return config;
  };
  // How many steps the run takes (the server's plan, as the knobs are typed) and, from a finished
  // job of the same shape, about how long; or why the server would refuse the configuration.
  // Only the newest request's answer is shown.
  let planned = 0;
  const showEstimate = async () => {
    const asked = (planned += 1);
    let plan;
    try {
      plan = await planOf(algorithm.value, chosenConfig());
    } catch (err) {
      if (asked !== planned) return;
      estimate.classList.add('invalid');
      estimate.textContent = err.status === 422 ? `Not a configuration a job accepts: ${err.message}` : '';
      return;
    }
    if (asked !== planned) return;
    estimate.classList.remove('invalid');
    const pace = measuredPace(finished, algorithm.value, plan.config);
    const time = pace
      ? `about ${fmtDuration(pace.secondsPerStep * plan.steps.total_steps)} at the pace of “${jobTitle(pace.job)}” (same algorithm, network and batch)`
      : 'no finished job with this algorithm, network and batch yet to time it by';
    estimate.replaceChildren(h('strong', {}, stepPlanText(plan.steps)), `: ${time}.`);
  };
  // A knob shows when the chosen algorithm has it, with the chosen preset's value as placeholder.
  const showKnobs = () => {
    const config = presetConfig(algorithm.value, preset.value);
    for (const { knob, input, label } of knobInputs) {
      label.hidden = !(knob.key in config);
      input.placeholder = knob.pretraining && knob.key in config ? pretrainingRule(config, knob.key)
        : (knob.key in config ? knobText(config[knob.key]) : '');
    }
    showEstimate();
  };
  // BC reads no Dᴺ: the select is disabled and nothing is sent (a job that named a dataset it
  // does not use would keep that dataset from being deleted).
  const showNonPreferred = () => {
    nonPreferred.disabled = !ALGORITHMS[algorithm.value]?.needs_non_preferred;
  };
  algorithm.addEventListener('change', showKnobs);
  algorithm.addEventListener('change', showNonPreferred);
  showNonPreferred();
  preset.addEventListener('change', showKnobs);
  knobInputs.forEach(({ input }) => input.addEventListener('input', showEstimate));
  showKnobs();
  showEnvs();
  const result = h('div', { id: 'job-form-result' });
  const submit = h('button', { type: 'submit', id: 'job-submit' }, 'Queue job');

  const form = h('form', { id: 'job-form', class: 'card' },
    h('h2', {}, 'New training job'),
    h('div', { class: 'form-grid' },
      h('label', {}, 'Name', name),
      h('label', {}, 'Tags', tags),
      h('label', { class: 'wide' }, 'Notes', notes),
      h('label', {}, 'Algorithm', algorithm),
      h('label', {}, 'Unlabeled dataset Dᵁ', unlabeled),
      h('label', {}, 'Non-preferred dataset Dᴺ', nonPreferred),
      h('label', {}, 'Preset', preset),
      knobInputs.map((k) => k.label),
      h('label', {}, 'Record metrics every (steps)', logEvery),
      h('label', {}, 'Evaluate on environment', evalEnv),
      h('label', {}, 'Evaluate every (policy steps)', evalEvery),
      h('label', {}, 'Evaluation episodes', evalEpisodes),
      register.labels),
    estimate,
    h('p', { class: 'hint' }, 'Empty fields take the preset’s value (the placeholders). SafeDICE first trains its discriminator (as many steps as the iterations in the service preset, a tenth in the others) and PPL its reward model (a tenth), unless set; those steps count in the job’s progress. With an environment, the policy is evaluated at the end of training and, if “Evaluate every” is set, every N policy steps (the paper’s metrics, charted on the job page).'),
    h('div', { class: 'form-actions' }, submit), result);

  form.addEventListener('submit', async (event) => {
    event.preventDefault();
    result.replaceChildren();
    const config = chosenConfig();
    const body = { algorithm: algorithm.value, unlabeled_dataset: unlabeled.value, config };
    if (name.value.trim()) body.name = name.value.trim();
    if (parseTags(tags.value).length) body.tags = parseTags(tags.value);
    if (notes.value.trim()) body.notes = notes.value.trim();
    if (nonPreferred.value && !nonPreferred.disabled) body.non_preferred_dataset = nonPreferred.value;
    if (logEvery.value.trim()) body.runner = { log_every: Number(logEvery.value.trim()) };
    if (evalEnv.value) {
      // No `every`: the server evaluates once, at the end of training.
      body.eval = { env: evalEnv.value };
      if (evalEvery.value.trim()) body.eval.every = Number(evalEvery.value.trim());
      if (evalEpisodes.value.trim()) body.eval.episodes = Number(evalEpisodes.value.trim());
    }
    if (register.value()) body.register = register.value();
    submit.disabled = true;
    try {
      const job = await api('/v1/jobs', { method: 'POST', json: body });
      result.replaceChildren(h('div', { class: 'notice', id: 'job-created' }, 'Queued job ',
        h('a', { href: `#/jobs/${job.id}` }, jobTitle(job)), ` (${stepPlanText(stepPlanOf(job))}).`));
      onCreated(job);
    } catch (err) {
      result.replaceChildren(errorBox(err, 'job-form-error'));
    } finally {
      submit.disabled = false;
    }
  });
  return form;
}

/** The steps of a created job as the server counted them (the phase named by the algorithm table). */
function stepPlanOf(job) {
  const phase = ALGORITHMS[job.algorithm]?.knobs.find((k) => k.pretraining)?.pretraining ?? null;
  return { pretraining_steps: job.pretraining_steps, pretraining_phase: phase,
    iterations: job.progress.total - job.pretraining_steps, total_steps: job.progress.total };
}
