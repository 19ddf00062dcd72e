// The Compare page: finished jobs side by side, their paper metrics under one evaluation
// protocol (GET /v1/results, the server's rule) and their last training diagnostics, as a table
// and a scatter plot. A plain script like app.js (globals, loaded before it).
'use strict';

/** The last recorded value of every training diagnostic of a job (max_points=2 keeps the last
 *  point exactly); its `eval/*` values come from /v1/results, under one protocol. */
async function finalDiagnostics(job) {
  const metrics = await api(`/v1/jobs/${job.id}/metrics?max_points=2`);
  const last = {};
  for (const row of metrics.rows) if (!row.name.startsWith('eval/')) last[row.name] = row.value;
  return last;
}

/** The jobs' paper metrics under one evaluation protocol (the server's rule, as an experiment's
 *  results follow it): `protocol` a key, or null for the default. A protocol none of them has
 *  any more falls back to the default. */
async function comparedResults(chosen, protocol) {
  const params = { jobs: chosen.map((j) => j.id).join(','), protocol };
  try {
    return await api(withParams('/v1/results', params));
  } catch (err) {
    if (err.status !== 404 || !protocol) throw err;
    return api(withParams('/v1/results', { jobs: params.jobs }));
  }
}

/** Which protocol the numbers are under, and a picker when the jobs have several. */
function protocolPicker(results, onPick) {
  if (!results.protocol) return null;
  if (results.protocols.length === 1) {
    return h('p', { class: 'hint', id: 'compare-protocol-line' }, 'Evaluation protocol: ',
      h('span', { id: 'compare-protocol', 'data-key': results.protocol.key }, results.protocol.label), '.');
  }
  const evaluated = results.jobs.filter((j) => j.protocols.length).length;
  const select = h('select', { id: 'compare-protocol', 'aria-label': 'Evaluation protocol', onchange: () => onPick(select.value) },
    results.protocols.map((p) => h('option', { value: p.protocol.key, selected: p.protocol.key === results.protocol.key },
      `${p.protocol.label} (${p.jobs} of ${evaluated} jobs)`)));
  const why = results.protocol_choice === 'most_jobs' ? ' No protocol is shared by every job: shown, the one most of them have.' : '';
  return h('div', { class: 'notice warn', id: 'compare-mixed' },
    h('p', {}, `These jobs were evaluated under ${results.protocols.length} protocols; the numbers below are under one of them, never mixed.${why}`),
    h('label', { class: 'protocol-pick' }, 'Compare under ', select));
}

// The paper's metrics, in the order the paper reports them (the server's vocabulary); everything
// else a job records is a training diagnostic.
const PAPER_METRICS = PAPER_METRIC_INFO.map((m) => m.history_name);

/** The default scatter axis: the first of `wanted` every chosen job has, else any such metric. */
function pickAxis(names, wanted, avoid) {
  return wanted.find((n) => names.includes(n) && n !== avoid) || names.find((n) => n !== avoid) || names[0] || '';
}

function comparePage(view) {
  const picker = h('div', { class: 'checklist', id: 'compare-jobs' });
  const more = h('button', { type: 'button', class: 'secondary', id: 'compare-more', hidden: true }, 'Load older jobs');
  const output = h('div', { id: 'compare-output' });
  view.append(h('h1', {}, 'Compare finished jobs'),
    h('div', { class: 'card' }, h('h2', {}, 'Jobs'), picker, more,
      h('p', { class: 'hint' }, 'The paper’s metrics (normalized return, average cost, violation ratio, CVaR) come first, from the newest evaluation of each job’s policy under one evaluation protocol (environment, episodes, seed, deterministic or sampled, runtime), else from its last evaluation during training; the training diagnostics are listed below them.')),
    output);
  const cache = new Map();
  const jobs = [];
  let nextToken = null;
  let protocol = null; // the key picked; null: the server's default
  const showDiagnostics = h('input', { type: 'checkbox', id: 'scatter-diagnostics' });
  const fromZero = h('input', { type: 'checkbox', id: 'scatter-zero', checked: true });

  const draw = async () => {
    const chosen = jobs.filter((j) => picker.querySelector(`input[value="${j.id}"]`).checked);
    if (!chosen.length) {
      output.replaceChildren(h('div', { class: 'empty' }, 'Tick two or more jobs above to compare them.'));
      return;
    }
    const [results, diagnosticsOf] = await Promise.all([comparedResults(chosen, protocol),
      Promise.all(chosen.map(async (j) => {
        if (!cache.has(j.id)) cache.set(j.id, await finalDiagnostics(j));
        return cache.get(j.id);
      }))]);
    const finals = results.jobs.map((r, i) => ({ ...diagnosticsOf[i],
      ...Object.fromEntries(Object.entries(r.metrics).map(([n, v]) => [`eval/${n}`, v])) }));
    const recorded = new Set(finals.flatMap((f) => Object.keys(f)));
    const paper = PAPER_METRICS.filter((n) => recorded.has(n));
    const diagnostics = [...recorded].filter((n) => !PAPER_METRICS.includes(n)).sort();
    const head = h('tr', {}, h('th', {}, 'Metric'), chosen.map((j) =>
      h('th', { class: 'num' }, algoBadge(j.algorithm), ' ', h('span', { class: j.name ? '' : 'mono' }, jobTitle(j)))));
    const metricRow = (n) => h('tr', { 'data-metric': n }, h('td', { class: 'mono' }, n), finals.map((f) => h('td', { class: 'num' }, fmt(f[n]))));
    const facts = [
      ['α̂', chosen.map((j) => j.alpha_hat)],
      ['iterations', chosen.map((j) => j.config.iterations)],
      ['seed', chosen.map((j) => j.config.seed)],
      ['evaluation', results.jobs.map((r) => r.metrics_from)],
    ];
    const unevaluated = chosen.filter((j, i) => !results.jobs[i].protocols.length);
    const otherProtocol = chosen.filter((j, i) => results.jobs[i].protocols.length && !results.jobs[i].protocol);
    const table = tableWrap(h('table', { id: 'compare-table' }, h('thead', {}, head),
      h('tbody', {}, facts.map(([label, values]) => h('tr', { 'data-fact': label }, h('td', {}, label), values.map((v) => h('td', { class: 'num' }, fmt(v))))),
        paper.length ? h('tr', { class: 'section' }, h('td', { colspan: chosen.length + 1 }, 'Paper metrics (newest evaluation under the protocol)')) : null,
        paper.map(metricRow))));
    const missing = unevaluated.length ? h('p', { class: 'hint', id: 'compare-unevaluated' },
      'No evaluation yet for ', unevaluated.map((j, i) => [i ? ', ' : '', j.policy_id
        ? h('a', { href: `#/policies/${j.policy_id}` }, jobTitle(j)) : jobTitle(j)]),
      ': evaluate a policy on its page (or record one from your simulator) to give it the paper’s metrics.') : null;
    const notUnder = otherProtocol.length ? h('p', { class: 'hint', id: 'compare-other-protocol' },
      'No evaluation under this protocol for ', otherProtocol.map((j, i) => [i ? ', ' : '', jobTitle(j)]),
      ': pick another protocol above, or evaluate them under this one.') : null;
    const picker2 = protocolPicker(results, (key) => { protocol = key; redraw(); });
    const diagnosticsTable = diagnostics.length ? h('details', { id: 'compare-diagnostics' },
      h('summary', {}, `Training diagnostics (${diagnostics.length})`),
      tableWrap(h('table', {}, h('tbody', {}, diagnostics.map(metricRow))))) : null;
    const exportCsv = h('button', { type: 'button', class: 'secondary', id: 'compare-csv', onclick: () => saveCsv([
      ['metric', ...chosen.map((j) => `${jobTitle(j)} (${j.id})`)],
      ['algorithm', ...chosen.map((j) => j.algorithm)],
      ['protocol', ...results.jobs.map((r) => r.protocol || '')],
      ...facts.map(([label, values]) => [label, ...values]),
      ...[...paper, ...diagnostics].map((n) => [n, ...finals.map((f) => f[n])]),
    ], 'compare.csv') }, 'Export CSV');

    // Training diagnostics only when asked: several are SafeDICE's alone, so they would leave
    // the other algorithms without a point.
    const axisNames = () => [...paper, ...(showDiagnostics.checked ? diagnostics : [])]
      .filter((n) => finals.some((f) => typeof f[n] === 'number'));
    const xSelect = h('select', { id: 'scatter-x' });
    const ySelect = h('select', { id: 'scatter-y' });
    const fillAxes = () => {
      const names = axisNames();
      for (const select of [xSelect, ySelect]) {
        const was = select.value;
        select.replaceChildren(...names.map((n) => h('option', { value: n }, n)));
        if (names.includes(was)) select.value = was;
      }
      if (!names.includes(xSelect.dataset.chosen)) xSelect.value = pickAxis(names, ['eval/average_cost'], null);
      if (!names.includes(ySelect.dataset.chosen)) ySelect.value = pickAxis(names, ['eval/normalized_return'], xSelect.value);
    };
    const scatter = h('div', {});
    const drawScatter = () => {
      if (!axisNames().length) {
        scatter.replaceChildren(h('div', { class: 'empty', id: 'scatter-empty' }, 'None of these jobs has an evaluation yet, so there are no paper metrics to plot (tick “offer training diagnostics” to plot those).'));
        return;
      }
      const [x, y] = [xSelect.value, ySelect.value];
      xSelect.dataset.chosen = x;
      ySelect.dataset.chosen = y;
      scatter.replaceChildren(scatterChart({
        key: 'scatter',
        title: x === 'eval/average_cost' && y === 'eval/normalized_return' ? 'Cost vs return' : `${y} vs ${x}`,
        xLabel: x, yLabel: y, fromZero: fromZero.checked,
        points: chosen.map((j, i) => ({ label: jobTitle(j), x: finals[i][x], y: finals[i][y],
          group: algoLabel(j.algorithm), color: algoColor(j.algorithm) })),
      }));
    };
    xSelect.addEventListener('change', drawScatter);
    ySelect.addEventListener('change', drawScatter);
    fromZero.onchange = drawScatter;
    showDiagnostics.onchange = () => { fillAxes(); drawScatter(); };
    fillAxes();
    // One card above the other: the table takes the page's width, a column per job.
    output.replaceChildren(h('div', {},
      h('div', { class: 'card', id: 'compare-side-by-side' }, h('div', { class: 'card-head' }, h('h2', {}, 'Side by side'), exportCsv), picker2, table, missing, notUnder, diagnosticsTable),
      h('div', { class: 'card', id: 'compare-scatter' }, h('h2', {}, 'Scatter'),
        h('div', { class: 'axis-pick' }, 'x', xSelect, 'y', ySelect),
        h('div', { class: 'axis-options' }, h('label', {}, fromZero, ' axes from 0'), h('label', {}, showDiagnostics, ' offer training diagnostics')),
        scatter)));
    drawScatter();
  };

  const redraw = () => draw().catch((e) => output.replaceChildren(errorBox(e)));
  const loadPage = async () => {
    const page = await api(withParams('/v1/jobs', { status: SUCCESS, limit: 50, page_token: nextToken }));
    const first = jobs.length === 0;
    jobs.push(...page.items);
    nextToken = page.next_page_token || null;
    more.hidden = !nextToken || jobs.length >= page.total;
    if (!jobs.length) {
      picker.replaceChildren(h('div', { class: 'empty' }, 'No finished jobs yet. Queue jobs on the ',
        h('a', { href: '#/jobs' }, 'Jobs'), ' page; succeeded jobs appear here.'));
      return;
    }
    picker.append(...page.items.map((j, i) => h('label', {},
      h('input', { type: 'checkbox', value: j.id, checked: first && i < 4, onchange: redraw }),
      algoBadge(j.algorithm), h('span', { class: j.name ? 'job-name' : 'mono job-name' }, jobTitle(j)), tagChips(j.tags),
      h('span', { class: 'muted' }, `${fmt(j.config.iterations)} iterations, seed ${j.config.seed}, finished ${fmtTime(j.finished_at)}`))));
    if (first) await draw();
  };
  more.addEventListener('click', () => loadPage().catch((err) => output.replaceChildren(errorBox(err))));
  loadPage().catch((err) => output.replaceChildren(errorBox(err)));
}
