// SafeDICE dashboard, the policies pages: the list, and a policy's page (metadata and
// downloads, its final training metrics, evaluations on a built-in environment, a box that turns
// observations into actions, the snippets an agent needs, and its registration as a version of
// a model). Loaded after models.js and before app.js, whose route table names these pages.
'use strict';

function policiesPage(view) {
  const list = h('div', { id: 'policies-list' });
  const render = (items) => {
    if (!items.length) {
      list.replaceChildren(h('div', { class: 'empty' }, 'No policies yet: a job that succeeds stores its policy here. ',
        h('a', { href: '#/jobs' }, 'Queue a job.')));
      return;
    }
    list.replaceChildren(tableWrap(h('table', { id: 'policies-table' },
      h('thead', {}, h('tr', {}, h('th', {}, 'Policy'), h('th', {}, 'Algorithm'), h('th', {}, 'Job'),
        h('th', { class: 'num' }, 'Obs dim'), h('th', {}, 'Actions'), h('th', { class: 'num' }, 'α̂'), h('th', {}, 'Created'))),
      h('tbody', {}, items.map((p) => h('tr', { 'data-id': p.id },
        h('td', {}, h('a', { href: `#/policies/${p.id}`, class: p.job_name ? 'policy-name' : 'mono' }, p.job_name || shortId(p.id))),
        h('td', {}, algoBadge(p.algorithm)),
        h('td', { class: 'mono' }, h('a', { href: `#/jobs/${p.job_id}` }, shortId(p.job_id))),
        h('td', { class: 'num' }, fmt(p.obs_dim)),
        h('td', {}, actionSpaceText(p.action_space)),
        h('td', { class: 'num' }, fmt(p.alpha_hat)),
        h('td', {}, fmtTime(p.created_at))))))));
  };
  const pages = pagedList({ path: '/v1/policies', size: PAGE_SIZE, id: 'policies-pager', render });
  view.append(h('h1', {}, 'Policies'), h('div', { class: 'card' }, list, pages.nav));
  pages.reload().catch((err) => list.replaceChildren(errorBox(err)));
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

function evaluationsTable(items) {
  if (!items.length) return h('div', { class: 'empty', id: 'evaluations-empty' }, 'No evaluations of this policy yet.');
  const m = (e, key) => (e.metrics ? fmt(e.metrics[key]) : '—');
  return tableWrap(h('table', { id: 'evaluations-table' },
    h('thead', {}, h('tr', {}, h('th', {}, 'Environment'), h('th', { class: 'num' }, 'Episodes'), h('th', { class: 'num' }, 'Seed'),
      h('th', {}, 'Actions'), h('th', {}, 'Status'), h('th', { class: 'num' }, 'Normalized return'), h('th', { class: 'num' }, 'Average cost'),
      h('th', { class: 'num' }, 'Violation ratio'), h('th', { class: 'num' }, 'CVaR 10%'), h('th', { class: 'num' }, 'CVaR 5%'), h('th', {}, 'Finished'))),
    h('tbody', {}, items.map((e) => h('tr', { 'data-id': e.id, 'data-status': e.status },
      h('td', {}, e.env, e.source === 'external' ? h('span', { class: 'tag source-external', title: 'Run in your own simulator and recorded with POST /v1/policies/{id}/evaluations' }, 'external') : null,
        e.training_step != null ? h('span', { class: 'tag source-training', title: `Taken by the job’s worker at step ${fmt(e.training_step)}, the end of training (its eval block)` }, 'end of training') : null),
      h('td', { class: 'num' }, fmt(e.episodes)), h('td', { class: 'num' }, String(e.seed)),
      h('td', {}, e.deterministic ? 'deterministic' : 'sampled'),
      h('td', {}, statusPill(e.status), e.error ? h('div', { class: 'error-message' }, e.error) : null),
      h('td', { class: 'num eval-return' }, m(e, 'normalized_return')), h('td', { class: 'num eval-cost' }, m(e, 'average_cost')),
      h('td', { class: 'num' }, m(e, 'cost_violation_ratio')),
      h('td', { class: 'num' }, e.metrics ? fmt(e.metrics.cvar_cost['10']) : '—'),
      h('td', { class: 'num' }, e.metrics ? fmt(e.metrics.cvar_cost['5']) : '—'),
      h('td', {}, fmtTime(e.finished_at)))))));
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
  const episodes = h('input', { id: 'eval-episodes', inputmode: 'numeric', placeholder: '500', size: 8 });
  const seed = h('input', { id: 'eval-seed', inputmode: 'numeric', placeholder: '0', size: 8 });
  const deterministic = h('input', { type: 'checkbox', id: 'eval-deterministic' });
  const submit = h('button', { type: 'submit', id: 'eval-submit' }, 'Evaluate');
  const form = h('form', { id: 'evaluate-form', class: 'form-actions wrap' }, h('label', {}, 'Environment ', env),
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

/** One row per observation: the safety scores of its action, past the alarm line (log-ratio
 *  at or above 0, out-of-support at or above 1) marked. */
function safetyTable(safety) {
  const cell = (value, alarm) => h('td', { class: `num${value >= alarm ? ' safety-alarm-cell' : ''}` }, fmt(value));
  return tableWrap(h('table', { id: 'act-safety' },
    h('thead', {}, h('tr', {}, h('th', { class: 'num' }, 'Row'), h('th', { class: 'num' }, 'non_preferred_log_ratio'), h('th', { class: 'num' }, 'out_of_support'))),
    h('tbody', {}, safety.non_preferred_log_ratio.map((ratio, i) => h('tr', { 'data-row': i },
      h('td', { class: 'num' }, String(i + 1)), cell(ratio, 0), cell(safety.out_of_support[i], 1))))));
}

function actCard(policy) {
  const input = h('textarea', { id: 'act-input', spellcheck: 'false',
    placeholder: `One observation per line (${policy.obs_dim} numbers), or JSON like [${Array(Math.min(policy.obs_dim, 4)).fill(0).join(', ')}, …]` });
  input.value = Array(policy.obs_dim).fill(0).join(', ');
  const deterministic = h('input', { type: 'checkbox', id: 'act-deterministic', checked: true });
  const seed = h('input', { id: 'act-seed', placeholder: 'seed (sampling only)', inputmode: 'numeric', size: 20 });
  // Only SafeDICE policies carry the discriminator the safety scores come from.
  const safety = policy.algorithm === 'safedice' ? h('input', { type: 'checkbox', id: 'act-safety' }) : null;
  const output = h('div', { id: 'act-output' });
  const actButton = h('button', { type: 'submit', id: 'act-submit' }, 'Get actions');
  const actForm = h('form', { class: 'card', id: 'act-form' }, h('h2', {}, 'Try it: observations → actions'), input,
    h('div', { class: 'form-actions wrap' }, actButton, h('label', {}, deterministic, ' deterministic'), seed,
      safety ? h('label', { title: 'the log-ratio of the action against the non-preferred demonstrations, and how far the observation is from the training data (docs/safety-scores.md)' }, safety, ' safety scores') : null),
    output);
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
    if (safety && safety.checked) body.safety_score = true;
    try {
      const result = await api(`/v1/policies/${policy.id}/act`, { method: 'POST', json: body });
      output.replaceChildren(h('pre', { id: 'act-result' }, JSON.stringify(result.actions, null, 0).replace(/\],\[/g, '],\n[')),
        result.safety ? safetyTable(result.safety) : null);
    } catch (err) {
      output.replaceChildren(errorBox(err, 'act-error'));
    }
  });
  return actForm;
}

function policyMeta(policy) {
  const problem = h('div', {});
  const fail = (err) => problem.replaceChildren(errorBox(err));
  const remove = confirmButton('Delete policy', 'Really delete the policy and its evaluations?', async () => {
    try {
      await api(`/v1/policies/${policy.id}`, { method: 'DELETE' });
      location.hash = '#/policies';
    } catch (err) {
      problem.replaceChildren(errorBox(err, 'policy-delete-error'));
    }
  }, { id: 'policy-delete' });
  return h('div', { class: 'card', id: 'policy-meta' }, h('h2', {}, 'Metadata'), h('dl', { class: 'kv' },
    h('dt', {}, 'algorithm'), h('dd', {}, algoBadge(policy.algorithm)),
    h('dt', {}, 'id'), h('dd', { class: 'mono' }, policy.id),
    h('dt', {}, 'trained by job'), h('dd', { class: 'mono' }, h('a', { href: `#/jobs/${policy.job_id}` }, policy.job_id)),
    h('dt', {}, 'observation dim'), h('dd', {}, fmt(policy.obs_dim)),
    h('dt', {}, 'action space'), h('dd', {}, actionSpaceText(policy.action_space)),
    h('dt', {}, 'α̂'), h('dd', {}, fmt(policy.alpha_hat)),
    h('dt', {}, 'created'), h('dd', {}, fmtTime(policy.created_at))),
  h('div', { class: 'form-actions wrap' },
    h('button', { type: 'button', class: 'secondary', id: 'weights-download', onclick: () => download(`/v1/policies/${policy.id}/weights`, `policy-${policy.id}.safetensors`).catch(fail) }, 'Weights (.safetensors)'),
    h('button', { type: 'button', class: 'secondary', id: 'onnx-download', onclick: () => download(`/v1/policies/${policy.id}/export?format=onnx`, `policy-${policy.id}.onnx`).catch(fail) }, 'ONNX model'),
    remove),
  h('p', { class: 'hint' }, 'The safetensors file carries the spec and the training run in its metadata; the ONNX model runs in onnxruntime and other ONNX runtimes.'),
  problem);
}

/** A final training metric as words where its number is a code: SafeDICE's early-stopping
 *  steps (discriminator_stopped_at is -1 when the discriminator did not stop early). */
function finalMetricText(name, value) {
  if (name === 'discriminator_stopped_at') return value < 0 ? 'did not stop early' : `stopped early at step ${fmt(value)}`;
  if (name === 'discriminator_best_step') return `step ${fmt(value)}`;
  return fmt(value);
}

function policyPage(view, id) {
  const slot = h('div', {});
  const title = h('span', { class: 'mono', id: 'policy-title' }, shortId(id));
  view.append(h('h1', {}, 'Policy ', title), slot);
  Promise.all([api(`/v1/policies/${id}`), api('/v1/envs'), api('/v1/models?limit=100').catch(() => ({ items: [] }))]).then(([policy, envs, models]) => {
    // Named by its job, as the policies list names it; the id stays beside the name.
    if (policy.job_name) {
      title.className = '';
      title.replaceChildren(policy.job_name, ' ', h('span', { class: 'muted mono policy-id' }, shortId(id)));
    }
    const { act, oip } = snippets(policy);
    const finals = Object.entries(policy.final_metrics || {});
    slot.replaceChildren(
      h('div', { class: 'grid2' }, policyMeta(policy),
        h('div', { class: 'card' }, h('h2', {}, 'Final training metrics'), finals.length
          ? tableWrap(h('table', { id: 'final-metrics' }, h('tbody', {}, finals.map(([k, v]) => h('tr', { 'data-metric': k },
            h('td', { class: 'mono' }, k), h('td', { class: 'num', title: String(v) }, finalMetricText(k, v)))))))
          : h('div', { class: 'empty' }, 'No metrics were recorded for this policy.'))),
      evaluationCard(policy, envs.items),
      registerPolicyCard(policy, models.items),
      actCard(policy),
      h('div', { class: 'card' }, h('h2', {}, 'Call it from an agent'),
        h('p', { class: 'hint' }, 'JSON API:'), h('pre', { id: 'snippet-curl' }, act),
        h('p', { class: 'hint' }, 'Open Inference Protocol (KServe v2), for standard inference clients:'), h('pre', { id: 'snippet-oip' }, oip)));
  }).catch((err) => slot.replaceChildren(err.status === 404 ? notFound('policy', id, '#/policies', 'policies list') : errorBox(err)));
}
