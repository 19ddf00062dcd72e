// SafeDICE dashboard, the models pages: named models for deployment (/v1/models), their numbered
// versions (each a trained policy) and their aliases with the history of every move, and the
// job form's "register as a version" fields. Loaded after lib.js and before app.js, whose route
// table and job form use these functions.
'use strict';

/** The rule the server applies to model and alias names (src/domain/model.rs, NAME_RULE). The
 *  page states it; the server checks it and its 422 message is shown as it comes. */
const MODEL_NAME_RULE = '1-64 characters from ASCII letters, digits and - _ . (dash, underscore, dot), starting with a letter or a digit';
/** Who the alias moves made here are recorded as, in the model's history. */
const DASHBOARD_ACTOR = 'dashboard';

const vText = (version) => (version === null || version === undefined ? '—' : `v${version}`);
const modelHref = (name) => `#/models/${encodeURIComponent(name)}`;
const modelPath = (name) => `/v1/models/${encodeURIComponent(name)}`;
const pctText = (weight) => `${Number((weight * 100).toPrecision(4))}%`;
const canaryText = (canary) => (canary ? `${vText(canary.version)} takes ${pctText(canary.weight)}` : null);
const shadowText = (shadow) => (shadow ? `${vText(shadow.version)} on ${pctText(shadow.sample)}` : null);

/** "production → v2" (and its canary), as the list and the model page show an alias. */
function aliasChip(alias) {
  return h('span', { class: 'alias-chip', 'data-alias': alias.alias },
    h('strong', {}, alias.alias), ` → ${vText(alias.version)}`,
    alias.canary ? h('span', { class: 'muted' }, ` (canary ${canaryText(alias.canary)})`) : null,
    alias.shadow ? h('span', { class: 'muted' }, ` (shadow ${shadowText(alias.shadow)})`) : null);
}

// ---------- the list ----------

function modelsTable(items) {
  if (!items.length) {
    return h('div', { class: 'empty' }, 'No models yet. Create one above, then register trained policies as its versions ',
      '(from the job form, or POST /v1/models/{name}/versions).');
  }
  return tableWrap(h('table', { id: 'models-table' },
    h('thead', {}, h('tr', {}, h('th', {}, 'Model'), h('th', { class: 'num' }, 'Latest'), h('th', { class: 'num' }, 'Versions'),
      h('th', {}, 'Aliases'), h('th', {}, 'Updated'))),
    h('tbody', {}, items.map((m) => h('tr', { 'data-name': m.name },
      h('td', {}, h('a', { href: modelHref(m.name), class: 'model-name' }, m.name),
        m.description ? h('div', { class: 'muted' }, m.description) : null, h('div', { class: 'tags' }, tagChips(m.tags))),
      h('td', { class: 'num latest' }, vText(m.latest_version)),
      h('td', { class: 'num' }, fmt(m.version_count)),
      h('td', { class: 'aliases' }, m.aliases.length ? m.aliases.map(aliasChip) : h('span', { class: 'muted' }, 'none')),
      h('td', {}, fmtTime(m.updated_at)))))));
}

function modelForm(onCreated) {
  const name = h('input', { id: 'model-name', name: 'name', placeholder: 'e.g. pilot', spellcheck: 'false', autocomplete: 'off' });
  const description = h('input', { id: 'model-description', name: 'description', placeholder: 'what it is for' });
  const tags = h('input', { id: 'model-tags', name: 'tags', placeholder: 'comma-separated, e.g. walker' });
  const submit = h('button', { type: 'submit', id: 'model-submit' }, 'Create model');
  const result = h('div', { id: 'model-form-result' });
  const form = h('form', { id: 'model-form', class: 'card', autocomplete: 'off' }, h('h2', {}, 'New model'),
    h('div', { class: 'form-grid' },
      h('label', {}, 'Name', name),
      h('label', {}, 'Tags', tags),
      h('label', { class: 'wide' }, 'Description', description)),
    h('p', { class: 'hint', id: 'model-name-rule' }, `Name: ${MODEL_NAME_RULE}. Agents call it as name (the latest version) or name@alias.`),
    h('div', { class: 'form-actions' }, submit), result);
  form.addEventListener('submit', async (event) => {
    event.preventDefault();
    result.replaceChildren();
    const body = { name: name.value.trim(), description: description.value.trim(), tags: parseTags(tags.value) };
    submit.disabled = true;
    try {
      const model = await api('/v1/models', { method: 'POST', json: body });
      result.replaceChildren(h('div', { class: 'notice', id: 'model-created' }, 'Created model ',
        h('a', { href: modelHref(model.name) }, model.name), '. Register versions from the job form or the API.'));
      form.reset();
      onCreated(model);
    } catch (err) {
      result.replaceChildren(errorBox(err, 'model-form-error'));
    } finally {
      submit.disabled = false;
    }
  });
  return form;
}

function modelsPage(view) {
  const list = h('div', { id: 'models-list' });
  const pages = pagedList({ path: '/v1/models', size: PAGE_SIZE, id: 'models-pager',
    render: (items) => list.replaceChildren(modelsTable(items)) });
  const reload = () => pages.reload().catch((err) => list.replaceChildren(errorBox(err)));
  view.append(h('h1', {}, 'Models'), modelForm(reload),
    h('div', { class: 'card' }, h('h2', {}, 'Models'), list, pages.nav));
  reload();
}

// ---------- one model ----------

/** The page's one confirmation dialog (a <dialog>, so it is part of the page and tests can drive
 *  it). `open` fills it: a title, fields, the question, and the action its Confirm button runs;
 *  an error of the action stays in the dialog, success closes it. */
function actionDialog() {
  const title = h('h2', { id: 'dialog-title' });
  const fields = h('div', { id: 'dialog-fields' });
  const question = h('p', { id: 'dialog-question', class: 'dialog-question' });
  const reason = h('input', { id: 'dialog-reason', maxlength: 200, autocomplete: 'off', placeholder: 'e.g. v2 passed the cost check' });
  const reasonLabel = h('label', { class: 'dialog-reason' }, 'Reason (kept in the alias history)', reason);
  const problem = h('div', { id: 'dialog-error' });
  const confirm = h('button', { type: 'submit', id: 'dialog-confirm' }, 'Confirm');
  const cancel = h('button', { type: 'button', class: 'secondary', id: 'dialog-cancel' }, 'Cancel');
  const form = h('form', { method: 'dialog' }, title, fields, reasonLabel, question, problem, h('div', { class: 'form-actions' }, confirm, cancel));
  const dialog = h('dialog', { id: 'model-dialog', class: 'modal' }, form);
  let action = null;
  cancel.addEventListener('click', () => dialog.close('cancel'));
  form.addEventListener('submit', async (event) => {
    event.preventDefault();
    if (!action || confirm.disabled) return;
    problem.replaceChildren();
    confirm.disabled = true;
    try {
      await action();
      dialog.close('confirm');
    } catch (err) {
      problem.replaceChildren(errorBox(err, 'dialog-error'));
    } finally {
      confirm.disabled = false;
    }
  });
  /** Sets the question, and whether Confirm can be pressed. */
  const ask = (text, ok) => {
    question.textContent = text;
    confirm.disabled = !ok;
  };
  const show = (spec) => {
    title.textContent = spec.title;
    fields.replaceChildren(...(spec.fields || []));
    // Alias moves take a reason; other actions (an experiment's cancel) have none to give.
    reasonLabel.hidden = !spec.reason;
    reason.value = '';
    problem.replaceChildren();
    confirm.textContent = spec.confirmLabel || 'Confirm';
    action = spec.action;
    ask(spec.question, true);
    if (!dialog.open) dialog.showModal();
  };
  /** The reason typed, else the move's own description (`fallback`). */
  const reasonOr = (fallback) => reason.value.trim() || fallback;
  return { element: dialog, show, ask, reasonOr };
}

function modelMeta(model, onDeleted) {
  const problem = h('div', {});
  const remove = confirmButton('Delete model', 'Really delete the model, its versions and history?', async () => {
    try {
      await api(modelPath(model.name), { method: 'DELETE' });
      onDeleted();
    } catch (err) {
      problem.replaceChildren(errorBox(err, 'model-delete-error'));
    }
  }, { id: 'model-delete' });
  const served = `${location.origin}/v1/models/${model.name}@<alias>/act`;
  return h('div', { class: 'card', id: 'model-meta' }, h('h2', {}, 'About'),
    h('dl', { class: 'kv' },
      h('dt', {}, 'description'), h('dd', { id: 'model-description-text' }, model.description || h('span', { class: 'muted' }, 'none')),
      h('dt', {}, 'tags'), h('dd', { id: 'model-tags-list' }, model.tags.length ? tagChips(model.tags) : h('span', { class: 'muted' }, 'none')),
      h('dt', {}, 'latest version'), h('dd', { id: 'model-latest' }, vText(model.latest_version)),
      h('dt', {}, 'versions'), h('dd', {}, fmt(model.version_count)),
      h('dt', {}, 'created'), h('dd', {}, fmtTime(model.created_at)),
      h('dt', {}, 'updated'), h('dd', {}, fmtTime(model.updated_at)),
      h('dt', {}, 'served at'), h('dd', { class: 'mono served-at' }, served)),
    h('div', { class: 'form-actions wrap' }, remove),
    h('p', { class: 'hint' }, 'A model can be deleted once no alias points at its versions (its policies stay).'),
    problem);
}

function aliasesCard(model, actions) {
  const body = model.aliases.length
    ? tableWrap(h('table', { id: 'aliases-table', class: 'sticky-actions' },
      h('thead', {}, h('tr', {}, h('th', {}, 'Alias'), h('th', {}, 'Version'), h('th', {}, 'Canary'), h('th', {}, 'Shadow'), h('th', {}, 'Moved'), h('th', {}, ''))),
      h('tbody', {}, model.aliases.map((a) => h('tr', { 'data-alias': a.alias },
        h('td', { class: 'alias' }, h('strong', {}, a.alias)),
        h('td', { class: 'version' }, vText(a.version)),
        h('td', { class: 'canary' }, h('span', { class: 'canary-text' }, a.canary ? canaryText(a.canary) : h('span', { class: 'muted' }, 'none')),
          h('span', { class: 'row-actions canary-actions' },
            h('button', { type: 'button', class: 'secondary canary-set', onclick: () => actions.canary(a) }, a.canary ? 'Change…' : 'Set…'),
            a.canary ? h('button', { type: 'button', class: 'secondary canary-clear', onclick: () => actions.clearCanary(a) }, 'End') : null)),
        h('td', { class: 'shadow' }, h('span', { class: 'shadow-text' }, a.shadow ? shadowText(a.shadow) : h('span', { class: 'muted' }, 'none')),
          h('span', { class: 'row-actions shadow-actions' },
            h('button', { type: 'button', class: 'secondary shadow-set', onclick: () => actions.shadow(a) }, a.shadow ? 'Change…' : 'Set…'),
            a.shadow ? h('button', { type: 'button', class: 'secondary shadow-promote', onclick: () => actions.promoteShadow(a) }, 'Promote') : null,
            a.shadow ? h('button', { type: 'button', class: 'secondary shadow-clear', onclick: () => actions.clearShadow(a) }, 'End') : null)),
        h('td', { class: 'moved' }, fmtTime(a.updated_at)),
        h('td', { class: 'row-actions' },
          h('button', { type: 'button', class: 'secondary rollback', onclick: () => actions.rollback(a) }, 'Roll back'),
          h('button', { type: 'button', class: 'danger remove-alias', onclick: () => actions.remove(a) }, 'Remove')))))))
    : h('div', { class: 'empty', id: 'aliases-empty' }, 'No aliases yet: promote a version below to create one (e.g. production).');
  return h('div', { class: 'card', id: 'aliases-card' }, h('h2', {}, 'Aliases'), body,
    h('p', { class: 'hint' }, 'A canary sends a share of an alias’s requests to another version (the same requests every time when clients send x-safedice-request-key). ',
      'A shadow runs another version on a share of the requests beside the answer and compares its actions, never returning them (see Shadows below); Promote points the alias at it. ',
      'Roll back points an alias where it pointed before its latest move (see the history below). Agents calling a removed alias get 404.'));
}

/** Minutes from now to an RFC 3339 time (negative: before now), to a tenth. */
const minutesAgo = (time, now) => Math.round((Date.parse(time) - now) / 6000) / 10;

/** How a shadow compares with the versions that answered (GET /v1/models/{name}/shadow, the last
 *  60 minutes): per series a summary and charts of the difference and of the safety scores by
 *  minute. */
function shadowCard(model, report, promote) {
  const series = (report && report.series) || [];
  if (!series.length && !model.aliases.some((a) => a.shadow)) return null;
  const now = Date.now();
  const num = (v, digits = 3) => (v === null || v === undefined ? '—' : fmt(v, digits));
  const summary = (s) => {
    const t = s.total;
    const diff = s.actions === 'discrete'
      ? `disagreement ${t.disagreement_rate === null || t.disagreement_rate === undefined ? '—' : pctText(t.disagreement_rate)}`
      : `mean L2 ${num(t.mean_l2)} (max ${num(t.max_l2)}), mean max-abs ${num(t.mean_max_abs)}`;
    const given = (v) => v !== null && v !== undefined;
    const scores = given(t.shadow_mean_log_ratio) || given(t.production_mean_log_ratio)
      ? `; mean log-ratio ${num(t.shadow_mean_log_ratio)} (answering ${vText(s.production_version)}: ${num(t.production_mean_log_ratio)}), out-of-support ${num(t.shadow_mean_out_of_support)}` : '';
    return `${fmt(t.requests)} requests shadowed (${fmt(t.skipped)} skipped, ${fmt(t.failed)} failed), ${fmt(t.observations)} observations: ${diff}${scores}; ${num(t.mean_shadow_ms)} ms per request off the response path.`;
  };
  const charts = (s) => {
    const points = (field) => s.points.filter((p) => p[field] !== null && p[field] !== undefined).map((p) => [minutesAgo(p.minute, now), p[field]]);
    const key = `${s.alias}-${s.production_version}-${s.shadow_version}`;
    const specs = [s.actions === 'discrete'
      ? { key: `${key}-diff`, title: `Disagreement rate: ${vText(s.shadow_version)} vs ${vText(s.production_version)}`, xLabel: 'minutes from now', xName: 'minute', yLabel: 'share of observations', yRange: [0, 1],
        series: [{ name: 'disagreement', points: points('disagreement_rate'), color: '#c0392b' }] }
      : { key: `${key}-diff`, title: `Action difference: ${vText(s.shadow_version)} vs ${vText(s.production_version)}`, xLabel: 'minutes from now', xName: 'minute', yLabel: 'L2 distance',
        series: [{ name: 'mean L2', points: points('mean_l2'), color: '#2e86c1' }, { name: 'max L2', points: points('max_l2'), color: '#c0392b', dash: [4, 3] }] }];
    const scored = (p) => ['shadow_mean_log_ratio', 'production_mean_log_ratio', 'shadow_mean_out_of_support'].some((f) => p[f] !== null && p[f] !== undefined);
    if (s.points.some(scored)) {
      specs.push({ key: `${key}-safety`, title: 'Safety scores (means)', xLabel: 'minutes from now', xName: 'minute', yLabel: 'score',
        series: [{ name: `log-ratio ${vText(s.shadow_version)}`, points: points('shadow_mean_log_ratio'), color: '#8e44ad' },
          { name: `log-ratio ${vText(s.production_version)}`, points: points('production_mean_log_ratio'), color: '#7f8c8d', dash: [4, 3] },
          { name: `out-of-support ${vText(s.shadow_version)}`, points: points('shadow_mean_out_of_support'), color: '#d68910' }] });
    }
    return h('div', { class: 'grid2' }, specs.map(lineChart));
  };
  const active = (s) => model.aliases.find((a) => a.alias === s.alias && a.shadow && a.shadow.version === s.shadow_version && a.version === s.production_version);
  return h('div', { class: 'card', id: 'shadow-card' }, h('h2', {}, 'Shadows'),
    series.length ? series.map((s) => {
      const alias = active(s);
      return h('div', { class: 'shadow-series', 'data-alias': s.alias, 'data-production': s.production_version, 'data-shadow': s.shadow_version },
        h('h3', {}, `${s.alias}: ${vText(s.shadow_version)} shadowing ${vText(s.production_version)}`, alias ? '' : h('span', { class: 'muted' }, ' (ended)')),
        h('p', { class: 'shadow-summary' }, summary(s)),
        alias ? h('div', { class: 'form-actions' }, h('button', { type: 'button', class: 'shadow-promote', onclick: () => promote(alias) }, `Promote ${vText(s.shadow_version)} to ${s.alias}`)) : null,
        charts(s));
    }) : h('div', { class: 'empty', id: 'shadow-empty' }, 'No request has been shadowed in the last 60 minutes.'),
    h('p', { class: 'hint' }, 'Every node of the service adds to these minutes. Discrete actions: the share of observations where the two versions chose differently; continuous: the distance between the two actions in the action’s units (sampled requests share one seed, so the noise is the same for both). See docs/shadow.md.'));
}

/** What `GET /v1/results` says of the versions' jobs: per job id its result, and the protocol
 *  the numbers are under (the Compare page's rule); null when it could not be read. */
async function versionResults(versions) {
  const ids = [...new Set(versions.items.map((v) => v.job_id))].slice(0, 100);
  if (!ids.length) return null;
  const results = await api(withParams('/v1/results', { jobs: ids.join(',') }));
  return { protocol: results.protocol, protocols: results.protocols, byJob: new Map(results.jobs.map((r) => [r.job_id, r])) };
}

/** “job 0190abcd” for a job's registration (the whole source in its title), else the source. */
function sourceText(source) {
  const match = /^job ([\w-]+)$/.exec(source);
  return match ? `job ${shortId(match[1])}` : source;
}

/** The safety scores each version of the model answered on this node since it started
 *  (GET /v2/models/{name}/stats, `safety_scores`): the share of each score's bins as bars, the
 *  bins past the alarm line (log-ratio at or above 0, out-of-support at or above 1) in red.
 *  Null when no version answered any. */
function safetyCard(stats) {
  const served = ((stats && stats.model_stats) || []).filter((s) => s.safety_scores);
  if (!served.length) return null;
  const edge = (value, fallback) => (value === undefined ? fallback : String(value).replace('-', '−'));
  const histogram = (title, score, alarmAt) => {
    const total = score.counts.reduce((a, b) => a + b, 0);
    const most = Math.max(1, ...score.counts);
    return h('div', { class: 'safety-histogram', 'data-score': title },
      h('div', { class: 'safety-title' }, h('code', {}, title), ` ${total.toLocaleString()} scored`),
      score.counts.map((count, i) => {
        const low = edge(score.edges[i - 1], '−∞');
        const alarm = i > 0 && score.edges[i - 1] >= alarmAt;
        return h('div', { class: `safety-bin${alarm ? ' safety-alarm' : ''}`, 'data-bin': i },
          h('span', { class: 'safety-range' }, `${low} to ${edge(score.edges[i], '∞')}`),
          h('span', { class: 'safety-track' }, h('span', { class: 'safety-bar', style: `width: ${(100 * count / most).toFixed(1)}%` })),
          h('span', { class: 'safety-count num' }, `${count.toLocaleString()} · ${pctText(count / Math.max(1, total))}`));
      }));
  };
  return h('div', { class: 'card', id: 'safety-card' }, h('h2', {}, 'Safety scores served'),
    served.map((s) => h('div', { class: 'safety-version', 'data-version': s.version },
      h('h3', {}, vText(s.version)),
      h('div', { class: 'safety-pair' },
        histogram('non_preferred_log_ratio', s.safety_scores.non_preferred_log_ratio, 0),
        histogram('out_of_support', s.safety_scores.out_of_support, 1)))),
    h('p', { class: 'hint' }, 'Scores this node answered to requests that asked for them (safety_score), by version, since it started. ',
      'Red bins: actions that look at least as much like the non-preferred demonstrations as like the data (log-ratio ≥ 0), states farther from the training data than 99% of its own (out-of-support ≥ 1). See docs/safety-scores.md.'));
}

function versionsCard(model, versions, results, onPromote) {
  const pointing = (version) => model.aliases.filter((a) => a.version === version);
  const metric = (v, key) => {
    const r = results && results.byJob.get(v.job_id);
    const value = r && r.metrics ? r.metrics[key] : undefined;
    const why = !r ? null : value !== undefined ? r.metrics_from
      : r.protocols.length ? 'evaluated under another protocol only' : 'not evaluated yet';
    return h('td', { class: `num metric-${key}`, title: why }, value === undefined ? '—' : fmt(value));
  };
  const body = versions.items.length
    ? tableWrap(h('table', { id: 'versions-table', class: 'sticky-actions' },
      h('thead', {}, h('tr', {}, h('th', {}, 'Version'), h('th', {}, 'Aliases'), h('th', { class: 'num' }, 'Return'), h('th', { class: 'num' }, 'Cost'),
        h('th', {}, 'Policy'), h('th', {}, 'Job'), h('th', {}, 'Source'), h('th', {}, 'Description'), h('th', {}, 'Registered'), h('th', {}, ''))),
      h('tbody', {}, versions.items.map((v) => h('tr', { 'data-version': v.version },
        h('td', { class: 'version' }, h('strong', {}, vText(v.version))),
        h('td', { class: 'aliases' }, pointing(v.version).map((a) => h('span', { class: 'tag alias-tag' }, a.alias))),
        metric(v, 'normalized_return'),
        metric(v, 'average_cost'),
        h('td', { class: 'mono' }, h('a', { href: `#/policies/${v.policy_id}`, class: 'policy-link', title: 'the policy: evaluations, actions, downloads' }, shortId(v.policy_id))),
        h('td', { class: 'mono' }, h('a', { href: `#/jobs/${v.job_id}`, class: 'job-link', title: v.job_name ? `${v.job_name}: training and evaluation metrics` : 'the job: training and evaluation metrics' }, v.job_name || shortId(v.job_id))),
        h('td', { class: 'source', title: v.source }, sourceText(v.source)),
        h('td', { class: 'description' }, v.description || h('span', { class: 'muted' }, '—')),
        h('td', { class: 'registered' }, fmtTime(v.created_at)),
        h('td', { class: 'row-actions' },
          h('button', { type: 'button', class: 'promote', onclick: () => onPromote(v) }, 'Promote to…')))))))
    : h('div', { class: 'empty', id: 'versions-empty' }, 'No versions yet. A job with “Register as a version of model” set registers its policy when it succeeds, and a policy’s page registers one already trained (or ',
      h('code', {}, `POST /v1/models/${model.name}/versions {"policy_id": …}`), ').');
  const more = versions.total > versions.items.length
    ? h('p', { class: 'hint' }, `The newest ${versions.items.length} of ${versions.total} versions.`) : null;
  const under = results && results.protocol ? h('p', { class: 'hint', id: 'versions-protocol' },
    'Return (normalized, 100 = the preferred demonstrations) and cost (per episode): each version’s policy’s newest evaluation under ',
    h('span', { class: 'protocol-label' }, results.protocol.label),
    results.protocols.length > 1 ? ` (the versions were evaluated under ${results.protocols.length} protocols; Compare shows the others)` : '', '.') : null;
  return h('div', { class: 'card', id: 'versions-card' }, h('h2', {}, 'Versions'), body, under, more);
}

function historyText(move) {
  if (move.from_version === null || move.from_version === undefined) return `created at ${vText(move.to_version)}`;
  if (move.to_version === null || move.to_version === undefined) return `${vText(move.from_version)} → deleted`;
  return `${vText(move.from_version)} → ${vText(move.to_version)}`;
}

function historyCard(history) {
  const body = history.items.length
    ? tableWrap(h('table', { id: 'history-table' },
      h('thead', {}, h('tr', {}, h('th', { class: 'num' }, 'Seq'), h('th', {}, 'Alias'), h('th', {}, 'Move'), h('th', {}, 'Canary'), h('th', {}, 'Shadow'),
        h('th', {}, 'Actor'), h('th', {}, 'Reason'), h('th', {}, 'When'))),
      h('tbody', {}, history.items.map((m) => h('tr', { 'data-seq': m.seq },
        h('td', { class: 'num' }, String(m.seq)),
        h('td', { class: 'alias' }, m.alias),
        h('td', { class: 'move' }, historyText(m)),
        h('td', {}, m.canary ? canaryText(m.canary) : '—'),
        h('td', { class: 'shadow' }, m.shadow ? shadowText(m.shadow) : '—'),
        h('td', { class: 'actor' }, m.actor),
        h('td', { class: 'reason' }, m.reason || '—'),
        h('td', {}, fmtTime(m.moved_at)))))))
    : h('div', { class: 'empty', id: 'history-empty' }, 'No alias has been moved yet.');
  return h('div', { class: 'card', id: 'history-card' }, h('h2', {}, 'Alias history'), body);
}

function modelPage(view, name) {
  const slot = h('div', {});
  const notice = h('div', { id: 'model-notice' });
  const dialog = actionDialog();
  view.append(h('h1', {}, 'Model ', h('span', { class: 'mono', id: 'model-title' }, name)), notice, slot, dialog.element);
  const mine = generation;
  let model;

  const moved = (move) => {
    let text = `${move.alias} now points at ${vText(move.to_version)} (was ${vText(move.from_version)}).`;
    if (move.from_version === null || move.from_version === undefined) text = `${move.alias} now points at ${vText(move.to_version)}.`;
    else if (move.from_version === move.to_version) {
      text = `${move.alias} stays at ${vText(move.to_version)}, ${move.canary ? `with ${vText(move.canary.version)} taking ${pctText(move.canary.weight)} of its requests` : 'with no canary'}${move.shadow ? `, shadowed by ${shadowText(move.shadow)}` : move.from_shadow ? '; its shadow ended' : ''}.`;
    }
    notice.replaceChildren(h('div', { class: 'notice', id: 'model-moved' }, text));
    // The move is done: a failure to redraw shows on the page, not as the move's error.
    return load().catch((err) => slot.replaceChildren(errorBox(err)));
  };

  // `keep`: the canary and shadow the alias keeps (a move without them ends them).
  const setAlias = async (alias, version, reason, keep, expected) => {
    const body = { version, actor: DASHBOARD_ACTOR, reason: dialog.reasonOr(reason) };
    if (keep && keep.canary) body.canary = keep.canary;
    if (keep && keep.shadow) body.shadow = keep.shadow;
    if (expected !== null && expected !== undefined) body.expected_version = expected;
    const move = await api(`${modelPath(name)}/aliases/${encodeURIComponent(alias)}`, { method: 'PUT', json: body });
    await moved(move);
  };

  // The API moves an alias whatever it points at now, so a move confirmed on a page that is out
  // of date would undo someone else's: the alias is read again first and the move is refused here
  // if it no longer points where the question said (null: the alias did not exist). Returns the
  // alias as it is now, whose canary and shadow a move that keeps them sends.
  const unmoved = async (alias, asked) => {
    const now = (await api(modelPath(name))).aliases.find((a) => a.alias === alias);
    const version = now ? now.version : null;
    if (version !== asked) {
      await load().catch(() => {});
      let what = `${alias} points at ${vText(version)} now, not ${vText(asked)} as this page showed: it was moved meanwhile.`;
      if (version === null) what = `${alias} was removed meanwhile.`;
      else if (asked === null) what = `${alias} was created meanwhile, at ${vText(version)}.`;
      throw new ApiError(0, null, `${what} Nothing was moved; the page shows the current state, check it and try again.`);
    }
    return now || {};
  };

  const onPromote = (version) => {
    const existing = model.aliases;
    const choice = h('select', { id: 'promote-alias' },
      existing.map((a) => h('option', { value: a.alias }, `${a.alias} (now ${vText(a.version)})`)),
      h('option', { value: '' }, 'a new alias…'));
    const typed = h('input', { id: 'promote-new-alias', placeholder: 'alias name, e.g. production', spellcheck: 'false', autocomplete: 'off' });
    const typedLabel = h('label', {}, 'New alias', typed);
    const aliasName = () => choice.value || typed.value.trim();
    const ask = () => {
      typedLabel.hidden = choice.value !== '';
      const alias = aliasName();
      const current = existing.find((a) => a.alias === alias);
      if (!alias) dialog.ask('Choose an alias or type a new one.', false);
      else if (current && current.version === version.version && !current.canary) dialog.ask(`${alias} already points at ${vText(version.version)}.`, false);
      else if (current) dialog.ask(`Point ${alias} from ${vText(current.version)} to ${vText(version.version)}?${current.canary ? ` Its canary (${canaryText(current.canary)}) ends.` : ''}${current.shadow ? ` Its shadow (${shadowText(current.shadow)}) ends.` : ''}`, true);
      else dialog.ask(`Point the new alias ${alias} at ${vText(version.version)}?`, true);
    };
    choice.addEventListener('change', ask);
    typed.addEventListener('input', ask);
    dialog.show({
      title: `Promote ${vText(version.version)} of ${name}`,
      fields: [h('div', { class: 'form-grid' }, h('label', {}, 'Alias', choice), typedLabel),
        h('p', { class: 'hint' }, `Alias names follow the model name rule (${MODEL_NAME_RULE}); not all digits, not “latest”.`)],
      question: '',
      confirmLabel: 'Promote',
      reason: true,
      action: async () => {
        const alias = aliasName();
        const asked = existing.find((a) => a.alias === alias);
        await unmoved(alias, asked ? asked.version : null);
        await setAlias(alias, version.version, `promoted ${vText(version.version)} from the dashboard`, {}, asked ? asked.version : null);
      },
    });
    ask();
  };

  const onRollback = async (alias) => {
    notice.replaceChildren();
    try {
      // The alias's latest move, read now (not from when the page loaded): it says where the
      // alias pointed before; the move before it, where that version's canary stood.
      const { items } = await api(withParams(`${modelPath(name)}/history`, { alias: alias.alias, limit: 2 }));
      const [latest, before] = items;
      const target = latest ? latest.from_version : null;
      if (target === null || target === undefined) {
        notice.replaceChildren(errorBox({ message: `${alias.alias} was created at ${vText(alias.version)} and has pointed nowhere else: there is nothing to roll back to.` }, 'rollback-error'));
        return;
      }
      const canary = before && before.to_version === target ? before.canary : null;
      const now = latest.to_version;
      dialog.show({
        title: `Roll back ${alias.alias}`,
        fields: [h('p', { class: 'hint' }, `Its latest move (seq ${latest.seq}, by ${latest.actor}, ${fmtTime(latest.moved_at)}) was ${historyText(latest)}.`)],
        question: `Roll ${alias.alias} back from ${vText(now)} to ${vText(target)}${canary ? `, with ${canaryText(canary)} as before` : ''}?${alias.shadow ? ` Its shadow (${shadowText(alias.shadow)}) ends.` : ''}`,
        confirmLabel: 'Roll back',
        reason: true,
        action: async () => {
          await unmoved(alias.alias, now);
          await setAlias(alias.alias, target, `rolled back from ${vText(now)} to ${vText(target)}`, { canary }, now);
        },
      });
    } catch (err) {
      notice.replaceChildren(errorBox(err, 'rollback-error'));
    }
  };

  const onRemove = (alias) => {
    notice.replaceChildren();
    dialog.show({
      title: `Remove ${alias.alias}`,
      fields: [h('p', { class: 'hint' }, `Agents calling ${name}@${alias.alias} get 404 from then on; the move is kept in the history.`)],
      question: `Remove the alias ${alias.alias} (now at ${vText(alias.version)})?`,
      confirmLabel: 'Remove',
      reason: true,
      action: async () => {
        await api(withParams(`${modelPath(name)}/aliases/${encodeURIComponent(alias.alias)}`,
          { actor: DASHBOARD_ACTOR, reason: dialog.reasonOr('removed from the dashboard'), expected_version: alias.version }), { method: 'DELETE' });
        notice.replaceChildren(h('div', { class: 'notice', id: 'model-moved' }, `Removed ${alias.alias} (it pointed at ${vText(alias.version)}).`));
        await load().catch((err) => slot.replaceChildren(errorBox(err)));
      },
    });
  };

  // A canary: another version answers a share of the alias's requests (PUT with `canary`),
  // set or changed here, ended by onClearCanary (PUT without it).
  const onCanary = (alias) => {
    notice.replaceChildren();
    const others = versionList.items.filter((v) => v.version !== alias.version);
    if (!others.length) {
      notice.replaceChildren(errorBox({ message: `${name} has no version other than ${vText(alias.version)} to send a share of ${alias.alias}’s requests to.` }, 'canary-error'));
      return;
    }
    const version = h('select', { id: 'canary-version' }, others.map((v) => h('option', { value: v.version }, vText(v.version))));
    const share = h('input', { id: 'canary-share', inputmode: 'decimal', placeholder: 'e.g. 10', autocomplete: 'off' });
    if (alias.canary) { version.value = String(alias.canary.version); share.value = String(Number((alias.canary.weight * 100).toPrecision(6))); }
    const percent = () => Number(share.value.trim());
    const ask = () => {
      const p = percent();
      if (!share.value.trim() || !(p >= 0.01 && p <= 99.99)) dialog.ask('Give the canary’s share of the requests, 0.01 to 99.99 %.', false);
      else dialog.ask(`Send ${pctText(p / 100)} of ${alias.alias}’s requests to v${version.value} (${vText(alias.version)} answers the rest)?`, true);
    };
    version.addEventListener('change', ask);
    share.addEventListener('input', ask);
    dialog.show({
      title: `Canary for ${alias.alias}`,
      fields: [h('div', { class: 'form-grid' }, h('label', {}, 'Canary version', version), h('label', {}, 'Share of requests (%)', share))],
      question: '',
      confirmLabel: 'Set canary',
      reason: true,
      action: async () => {
        const current = await unmoved(alias.alias, alias.version);
        const canary = { version: Number(version.value), weight: Number((percent() / 100).toFixed(4)) };
        await setAlias(alias.alias, alias.version, `canary ${vText(canary.version)} at ${pctText(canary.weight)}`, { canary, shadow: current.shadow }, alias.version);
      },
    });
    ask();
  };
  const onClearCanary = (alias) => {
    notice.replaceChildren();
    dialog.show({
      title: `End ${alias.alias}’s canary`,
      fields: [],
      question: `End the canary of ${alias.alias} (${canaryText(alias.canary)})? ${vText(alias.version)} answers every request.`,
      confirmLabel: 'End canary',
      reason: true,
      action: async () => {
        const current = await unmoved(alias.alias, alias.version);
        await setAlias(alias.alias, alias.version, `canary ${vText(alias.canary.version)} ended`, { shadow: current.shadow }, alias.version);
      },
    });
  };

  // A shadow: another version runs on a share of the alias's requests and is compared with the
  // answer (PUT with `shadow`); promoted (the alias moves to it) or ended (PUT without it).
  const onShadow = (alias) => {
    notice.replaceChildren();
    const others = versionList.items.filter((v) => v.version !== alias.version);
    if (!others.length) {
      notice.replaceChildren(errorBox({ message: `${name} has no version other than ${vText(alias.version)} to run beside ${alias.alias}.` }, 'shadow-error'));
      return;
    }
    const version = h('select', { id: 'shadow-version' }, others.map((v) => h('option', { value: v.version }, vText(v.version))));
    const share = h('input', { id: 'shadow-share', inputmode: 'decimal', placeholder: 'e.g. 100', autocomplete: 'off' });
    share.value = alias.shadow ? String(Number((alias.shadow.sample * 100).toPrecision(6))) : '100';
    if (alias.shadow) version.value = String(alias.shadow.version);
    const percent = () => Number(share.value.trim());
    const ask = () => {
      const p = percent();
      if (!share.value.trim() || !(p >= 0.01 && p <= 100)) dialog.ask('Give the share of requests to shadow, 0.01 to 100 %.', false);
      else dialog.ask(`Run v${version.value} beside ${vText(alias.version)} on ${pctText(p / 100)} of ${alias.alias}’s requests and compare? Its actions are never returned.`, true);
    };
    version.addEventListener('change', ask);
    share.addEventListener('input', ask);
    dialog.show({
      title: `Shadow for ${alias.alias}`,
      fields: [h('div', { class: 'form-grid' }, h('label', {}, 'Shadow version', version), h('label', {}, 'Share of requests (%)', share))],
      question: '',
      confirmLabel: 'Set shadow',
      reason: true,
      action: async () => {
        const current = await unmoved(alias.alias, alias.version);
        const shadow = { version: Number(version.value), sample: Number((percent() / 100).toFixed(4)) };
        await setAlias(alias.alias, alias.version, `shadow ${vText(shadow.version)} on ${pctText(shadow.sample)}`, { canary: current.canary, shadow }, alias.version);
      },
    });
    ask();
  };
  const onClearShadow = (alias) => {
    notice.replaceChildren();
    dialog.show({
      title: `End ${alias.alias}’s shadow`,
      fields: [],
      question: `End the shadow of ${alias.alias} (${shadowText(alias.shadow)})? Its comparisons stay in the series.`,
      confirmLabel: 'End shadow',
      reason: true,
      action: async () => {
        const current = await unmoved(alias.alias, alias.version);
        await setAlias(alias.alias, alias.version, `shadow ${vText(alias.shadow.version)} ended`, { canary: current.canary }, alias.version);
      },
    });
  };
  const onPromoteShadow = (alias) => {
    notice.replaceChildren();
    const target = alias.shadow.version;
    dialog.show({
      title: `Promote ${alias.alias}’s shadow`,
      fields: [],
      question: `Point ${alias.alias} from ${vText(alias.version)} to its shadow ${vText(target)}?${alias.canary ? ` Its canary (${canaryText(alias.canary)}) ends.` : ''} The shadow ends: ${vText(target)} answers every request.`,
      confirmLabel: 'Promote',
      reason: true,
      action: async () => {
        await unmoved(alias.alias, alias.version);
        await setAlias(alias.alias, target, `promoted shadow ${vText(target)} from the dashboard`, {}, alias.version);
      },
    });
  };

  let versionList = { items: [], total: 0 };
  const load = async () => {
    const [m, versions, history] = await Promise.all([api(modelPath(name)),
      api(withParams(`${modelPath(name)}/versions`, { limit: 500 })), api(withParams(`${modelPath(name)}/history`, { limit: 200 }))]);
    // The versions' numbers are a convenience: the page works without them.
    const results = await versionResults(versions).catch(() => null);
    // This node's serving statistics: a model no node has loaded yet has none.
    const stats = await api(`/v2/models/${encodeURIComponent(name)}/stats`).catch(() => null);
    const shadows = await api(`${modelPath(name)}/shadow`).catch(() => null);
    if (mine !== generation) return;
    model = m;
    versionList = versions;
    // The aliases take the page's width: each row has its canary and its actions.
    slot.replaceChildren(
      modelMeta(model, () => { location.hash = '#/models'; }),
      aliasesCard(model, { rollback: onRollback, remove: onRemove, canary: onCanary, clearCanary: onClearCanary,
        shadow: onShadow, clearShadow: onClearShadow, promoteShadow: onPromoteShadow }),
      ...[shadowCard(model, shadows, onPromoteShadow)].filter(Boolean),
      versionsCard(model, versions, results, onPromote),
      ...[safetyCard(stats)].filter(Boolean),
      historyCard(history));
  };
  load().catch((err) => slot.replaceChildren(err.status === 404
    ? h('div', { class: 'error-box not-found', role: 'alert' },
      h('span', { class: 'error-message' }, `There is no model named ${name}: it was deleted, or the link is wrong. `),
      h('a', { href: '#/models' }, 'Go to the models list.'))
    : errorBox(err)));
}

// ---------- the job form's registration ----------

/** The job form's "Register as a version of model" select and alias field: `labels` go into the
 *  form's grid, `value()` is the job's `register` (or null). */
function registerFields(models) {
  const model = h('select', { name: 'register_model', id: 'job-register-model' },
    h('option', { value: '' }, models.length ? '— do not register —' : '— no models yet —'),
    models.map((m) => h('option', { value: m.name }, m.latest_version ? `${m.name} (latest ${vText(m.latest_version)})` : m.name)));
  const alias = h('input', { name: 'register_alias', id: 'job-register-alias', placeholder: 'optional, e.g. staging', spellcheck: 'false', disabled: true });
  model.addEventListener('change', () => { alias.disabled = !model.value; });
  return {
    labels: [h('label', {}, 'Register as a version of model', model), h('label', {}, 'and point alias', alias)],
    value: () => {
      if (!model.value) return null;
      const register = { model: model.value };
      if (alias.value.trim()) register.alias = alias.value.trim();
      return register;
    },
  };
}

// ---------- the policy page's registration ----------

/** The policy page's “Register as a model version”: a model, a description and optionally an
 *  alias to move to the new version (POST /v1/models/{name}/versions, actor `dashboard`). */
function registerPolicyCard(policy, models) {
  const card = h('div', { class: 'card', id: 'register-card' }, h('h2', {}, 'Register as a model version'));
  if (!models.length) {
    card.append(h('div', { class: 'empty', id: 'register-empty' }, 'No models yet: ', h('a', { href: '#/models' }, 'create one'),
      ', then register this policy as its next version here.'));
    return card;
  }
  const model = h('select', { id: 'register-model' },
    models.map((m) => h('option', { value: m.name }, m.latest_version ? `${m.name} (latest ${vText(m.latest_version)})` : m.name)));
  const description = h('input', { id: 'register-description', placeholder: 'what this version is', maxlength: 10000 });
  const alias = h('input', { id: 'register-alias', placeholder: 'optional, e.g. staging', spellcheck: 'false', autocomplete: 'off' });
  const submit = h('button', { type: 'submit', id: 'register-submit' }, 'Register');
  const result = h('div', { id: 'register-result' });
  const form = h('form', { id: 'register-form', autocomplete: 'off' },
    h('div', { class: 'form-grid' }, h('label', {}, 'Model', model), h('label', {}, 'Description', description), h('label', {}, 'and point alias', alias)),
    h('div', { class: 'form-actions' }, submit), result);
  form.addEventListener('submit', async (event) => {
    event.preventDefault();
    result.replaceChildren();
    const body = { policy_id: policy.id, description: description.value.trim(), actor: DASHBOARD_ACTOR };
    if (alias.value.trim()) body.alias = alias.value.trim();
    submit.disabled = true;
    try {
      const version = await api(`${modelPath(model.value)}/versions`, { method: 'POST', json: body });
      result.replaceChildren(h('div', { class: 'notice', id: 'register-ok' }, `Registered as ${vText(version.version)} of `,
        h('a', { href: modelHref(version.model) }, version.model), body.alias ? `; ${body.alias} points at it.` : '.'));
      form.reset();
    } catch (err) {
      result.replaceChildren(errorBox(err, 'register-error'));
    } finally {
      submit.disabled = false;
    }
  });
  card.append(h('p', { class: 'hint' }, 'The policy becomes the model’s next version; agents reach it as the model’s latest, or through the alias.'), form);
  return card;
}
