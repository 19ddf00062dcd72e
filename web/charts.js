// SafeDICE dashboard, charts drawn in the browser: line charts of metric histories on uPlot
// (web/vendor, MIT; values under the cursor, drag to zoom, double-click to reset, a log scale
// when every value is positive) and the Compare page's scatter as plain SVG. The points come
// from the metrics endpoint, which downsamples long runs with LTTB on the server, so spikes
// survive.
'use strict';

const CHART_HEIGHT = 240;
/** Point markers only on short series; longer ones would be a smear of dots. */
const MARKER_LIMIT = 60;

/** uPlot wants one x array for all series: the union of their steps, with gaps (null) where a
 *  series has no value at a step. */
function alignSeries(series) {
  const xs = [...new Set(series.flatMap((s) => s.points.map((p) => p[0])))].sort((a, b) => a - b);
  const at = new Map(xs.map((x, i) => [x, i]));
  const columns = series.map((s) => {
    const column = new Array(xs.length).fill(null);
    for (const [x, y] of s.points) column[at.get(x)] = Number.isFinite(y) ? y : null;
    return column;
  });
  return [xs, ...columns];
}

const allPositive = (series) => series.every((s) => s.points.every((p) => !Number.isFinite(p[1]) || p[1] > 0));

/** An axis title cut with an ellipsis to `room` px (uPlot draws a y title along the plot's
 *  height in bold 12 px and clips what does not fit); the chart's title and note say it whole. */
function fitAxisLabel(label, room) {
  if (!label) return label;
  const context = document.createElement('canvas').getContext('2d');
  context.font = `bold 12px ${getComputedStyle(document.body).fontFamily}`;
  if (context.measureText(label).width <= room) return label;
  let cut = label;
  while (cut.length > 1 && context.measureText(`${cut}…`).width > room) cut = cut.slice(0, -1);
  return `${cut.trimEnd()}…`;
}

/** An x range with room around a lone x value (one evaluation per job: uPlot would draw the
 *  points on the frame's edge). */
function xRange(u, min, max) {
  if (min !== max) return [min, max];
  const pad = Math.abs(min) * 0.1 || 1;
  return [min - pad, max + pad];
}

function uplotOptions(spec, width, log) {
  const markers = spec.series.every((s) => s.points.length <= MARKER_LIMIT);
  let y = log ? { distr: 3 } : {};
  // A fixed range (e.g. probabilities on [0, 1]) unless the values leave it.
  if (spec.yRange && !log) y = { range: (u, min, max) => [Math.min(min, spec.yRange[0]), Math.max(max, spec.yRange[1])] };
  return {
    width,
    height: CHART_HEIGHT,
    scales: { x: { time: false, range: xRange }, y },
    axes: [
      { label: spec.xLabel, values: (u, ticks) => ticks.map((t) => fmt(t)) },
      { label: fitAxisLabel(spec.yLabel, CHART_HEIGHT - 70), size: 64, values: (u, ticks) => ticks.map((t) => fmt(t, 3)) },
    ],
    series: [
      { label: spec.xName || 'step', value: (u, v) => (v === null || v === undefined ? '—' : fmt(v)) },
      ...spec.series.map((s) => ({
        label: s.name, stroke: s.color, width: s.width || 1.6, spanGaps: true, dash: s.dash,
        // Markers on short series (a series of one point has no line to draw), never on the
        // edges of a band.
        points: { show: !s.band && (markers || s.points.length === 1), size: 6, width: 1, fill: s.color },
        value: (u, v) => (v === null || v === undefined ? '—' : fmt(v)),
      })),
    ],
    // Shaded bands between two series (1-based as uPlot counts them, the x column being 0):
    // spec.bands = [{series: [upper, lower], fill}], e.g. a mean ± standard error.
    bands: spec.bands,
    cursor: { drag: { x: true, y: false } },
  };
}

/** A line chart of `spec` = {key, title, xLabel, xName? (the legend's name of x, default
 *  `step`), yLabel, yRange?, note?, series: [{name,
 *  points: [[x, y]], color, width?, dash?, thin?, band?}], bands?}: a .chart-box with the title,
 *  a log-scale switch, the plot and its legend (which shows the values under the cursor). `box.update(spec)` draws new points of the same series
 *  in place (keeping a zoom the user made). */
function lineChart(spec) {
  const plot = h('div', { class: 'plot' });
  const logBox = h('input', { type: 'checkbox', class: 'log-scale' });
  const logLabel = h('label', { class: 'muted chart-option', title: 'Logarithmic y axis (only when every value is positive)' }, logBox, ' log y');
  const box = h('div', { class: 'chart-box', 'data-chart': spec.key },
    h('div', { class: 'chart-head' }, h('span', { class: 'chart-title' }, spec.title), logLabel), plot,
    h('div', { class: 'hint chart-hint' }, spec.note ? `${spec.note} ` : '', 'Drag to zoom, double-click to reset.'));
  let current = spec;
  let chart = null;
  let zoomed = false;
  const width = () => Math.max(240, (plot.clientWidth || box.clientWidth || 560) - 4);
  const record = () => {
    box.dataset.series = JSON.stringify(current.series.map((s) => [s.name, s.points.length]));
  };
  const build = () => {
    if (chart) chart.destroy();
    const options = uplotOptions(current, width(), logBox.checked);
    options.hooks = { setSelect: [(u) => { if (u.select.width > 0) zoomed = true; }] };
    chart = new uPlot(options, alignSeries(current.series), plot);
    plot.addEventListener('dblclick', () => { zoomed = false; }, { once: true });
    box.uplot = chart;
    record();
  };
  const syncLog = () => {
    const positive = allPositive(current.series) && !current.yRange;
    logBox.disabled = !positive;
    if (!positive) logBox.checked = false;
    logLabel.title = positive ? 'Logarithmic y axis' : current.yRange ? 'A fixed linear scale' : 'A log scale needs every value positive';
  };
  logBox.addEventListener('change', build);
  box.update = (next) => {
    const same = next.series.length === current.series.length
      && next.series.every((s, i) => s.name === current.series[i].name);
    current = next;
    const wasLog = logBox.checked;
    syncLog();
    if (!same || !chart || wasLog !== logBox.checked) { build(); return; }
    chart.setData(alignSeries(current.series), !zoomed);
    record();
  };
  syncLog();
  // uPlot draws at a fixed width: build once the box is in the page, redraw when it resizes.
  requestAnimationFrame(build);
  new ResizeObserver(() => { if (chart && Math.abs(chart.width - width()) > 2) chart.setSize({ width: width(), height: CHART_HEIGHT }); })
    .observe(plot);
  return box;
}

/** Round ticks covering [lo, hi]: 1, 2 or 5 times a power of ten apart. */
function niceTicks(lo, hi, count = 5) {
  if (!(hi > lo)) { const pad = Math.abs(lo) * 0.1 || 1; lo -= pad; hi += pad; }
  const raw = (hi - lo) / count;
  const power = 10 ** Math.floor(Math.log10(raw));
  const step = [1, 2, 5, 10].map((m) => m * power).find((s) => s >= raw);
  const first = Math.floor(lo / step) * step;
  const ticks = [];
  for (let t = first; t <= hi + step * 0.5; t += step) ticks.push(Number(t.toPrecision(12)));
  if (ticks.at(-1) < hi) ticks.push(Number((ticks.at(-1) + step).toPrecision(12)));
  return ticks;
}

const SVG_NS = 'http://www.w3.org/2000/svg';
function s(tag, attrs, ...children) {
  const el = document.createElementNS(SVG_NS, tag);
  for (const [k, v] of Object.entries(attrs || {})) if (v !== null && v !== undefined) el.setAttribute(k, v);
  for (const c of children.flat(Infinity)) if (c !== null && c !== undefined) el.append(c instanceof Node ? c : document.createTextNode(String(c)));
  return el;
}

// Point labels are 11 px text (style.css svg.scatter .point-label), measured in the page's font.
const LABEL_FONT_PX = 11;
const LABEL_HEIGHT = 12;
const LABEL_MAX_CHARS = 28;
let measureContext = null;

/** The drawn width of a point label, in SVG units (the scatter's viewBox is its CSS size or
 *  larger, so a label never takes more room than this). */
function labelWidth(text) {
  if (!measureContext) {
    measureContext = document.createElement('canvas').getContext('2d');
    measureContext.font = `${LABEL_FONT_PX}px ${getComputedStyle(document.body).fontFamily}`;
  }
  return measureContext.measureText(text).width + 2;
}

/** `text` cut to `max` characters in its middle: its start and its end stay, the end being
 *  where names of one run differ (“… · seed 2”). */
function cutMiddle(text, max) {
  if (text.length <= max) return text;
  const head = Math.ceil((max - 1) / 2);
  return `${text.slice(0, head).trimEnd()}…${text.slice(text.length - (max - 1 - head)).trimStart()}`;
}

/** Point labels short enough to write beside a point and still told apart: labels over
 *  `max` characters lose the parts every label starts with (an experiment's name before its
 *  “ · ”), then their middle; where that makes two alike, each keeps its end instead. The
 *  point's tooltip and data-label keep the whole name. */
function shortLabels(texts, max = LABEL_MAX_CHARS) {
  if (texts.every((t) => t.length <= max)) return texts;
  let prefix = texts.length > 1 ? texts.reduce((a, b) => { let i = 0; while (i < a.length && a[i] === b[i]) i += 1; return a.slice(0, i); }) : '';
  // Up to the last separator in it (“browser grid · ”), so every label keeps whole parts.
  const end = Math.max(...[' · ', ' / ', ', ', ': ', ' — '].map((sep) => { const i = prefix.lastIndexOf(sep); return i < 0 ? 0 : i + sep.length; }));
  prefix = prefix.slice(0, end);
  const cut = texts.map((t) => (t.length <= max ? t
    : cutMiddle(prefix.length > 3 ? `…${t.slice(prefix.length)}` : t, max)));
  if (new Set(cut).size === new Set(texts).size) return cut;
  return texts.map((t) => (t.length <= max ? t : `…${t.slice(t.length - (max - 1))}`));
}

/** Where to write each point's label ({x, y, text} in SVG units): the first of eight spots
 *  around the point whose box stays inside `frame` and overlaps no label placed before nor any
 *  point; when none is free, the spot that overlaps least. Long labels are shortened by
 *  shortLabels (the point's tooltip has the whole name). Returns {x, y, anchor, text, box}
 *  per point. */
function placeLabels(points, frame) {
  const boxes = [];
  const dots = points.map((p) => ({ x0: p.x - 6, x1: p.x + 6, y0: p.y - 6, y1: p.y + 6 }));
  const overlap = (a, b) => Math.max(0, Math.min(a.x1, b.x1) - Math.max(a.x0, b.x0))
    * Math.max(0, Math.min(a.y1, b.y1) - Math.max(a.y0, b.y0));
  const texts = shortLabels(points.map((p) => p.text));
  return points.map((p, i) => {
    const text = texts[i];
    const w = labelWidth(text);
    // [anchor, x offset, baseline offset]: right, left, above, below, then the diagonals.
    const spots = [['start', 9, 4], ['end', -9, 4], ['middle', 0, -10], ['middle', 0, 18],
      ['start', 8, -7], ['end', -8, -7], ['start', 8, 15], ['end', -8, 15]];
    let best = null;
    for (const [anchor, dx, dy] of spots) {
      const x = p.x + dx; const y = p.y + dy;
      const x0 = anchor === 'start' ? x : anchor === 'end' ? x - w : x - w / 2;
      const box = { x0, x1: x0 + w, y0: y - LABEL_HEIGHT + 2, y1: y + 3 };
      const outside = box.x0 < frame.left + 2 || box.x1 > frame.right - 2 || box.y0 < frame.top || box.y1 > frame.bottom;
      const cost = (outside ? 1e6 : 0) + boxes.reduce((sum, b) => sum + overlap(box, b), 0)
        + dots.reduce((sum, d, j) => sum + (j === i ? 0 : overlap(box, d)), 0);
      if (!best || cost < best.cost) best = { x, y, anchor, text, box, cost };
      if (cost === 0) break;
    }
    boxes.push(best.box);
    return best;
  });
}

/** A scatter plot of labelled points ({label, x, y, color, group, xErr?, yErr?}) as SVG. With
 *  `fromZero` both axes include 0, so a small difference is drawn small (cost and return are on
 *  ratio scales); without it the axes fit the points. Each point is a <g class="point"> with its
 *  label, and its exact values on hover; xErr / yErr (e.g. standard errors) draw error bars. */
function scatterChart({ key, title, xLabel, yLabel, points, fromZero }) {
  const W = 640; const H = 360; const L = 70; const R = 20; const T = 34; const B = 48;
  const shown = points.filter((p) => Number.isFinite(p.x) && Number.isFinite(p.y));
  // A margin around the points, so none sits on the frame (a 0 kept by fromZero stays the edge).
  const extent = (values) => {
    let lo = Math.min(...values); let hi = Math.max(...values);
    if (!values.length) { lo = 0; hi = 1; }
    const pad = (hi - lo) * 0.08 || Math.abs(hi) * 0.08 || 1;
    lo = fromZero && lo >= 0 ? lo : lo - pad;
    hi = fromZero && hi <= 0 ? hi : hi + pad;
    if (fromZero) { lo = Math.min(lo, 0); hi = Math.max(hi, 0); }
    return niceTicks(lo, hi);
  };
  const err = (e) => (Number.isFinite(e) ? e : 0);
  const xt = extent(shown.flatMap((p) => [p.x - err(p.xErr), p.x + err(p.xErr)]));
  const yt = extent(shown.flatMap((p) => [p.y - err(p.yErr), p.y + err(p.yErr)]));
  const bar = (x1, y1, x2, y2, cap) => [s('line', { x1, y1, x2, y2, class: 'error-bar' }),
    cap === 'h' ? [s('line', { x1: x1 - 4, x2: x1 + 4, y1, y2: y1, class: 'error-bar' }), s('line', { x1: x2 - 4, x2: x2 + 4, y1: y2, y2, class: 'error-bar' })]
      : [s('line', { x1, x2: x1, y1: y1 - 4, y2: y1 + 4, class: 'error-bar' }), s('line', { x1: x2, x2, y1: y2 - 4, y2: y2 + 4, class: 'error-bar' })]];
  const px = (x) => L + ((x - xt[0]) / (xt.at(-1) - xt[0])) * (W - L - R);
  const py = (y) => H - B - ((y - yt[0]) / (yt.at(-1) - yt[0])) * (H - T - B);
  const svg = s('svg', { viewBox: `0 0 ${W} ${H}`, role: 'img', 'aria-label': title, class: 'scatter' },
    s('text', { x: L, y: 20, class: 'title' }, title),
    xt.map((t) => [s('line', { x1: px(t), x2: px(t), y1: T, y2: H - B, class: 'grid' }),
      s('text', { x: px(t), y: H - B + 16, 'text-anchor': 'middle', class: 'tick' }, fmt(t, 3))]),
    yt.map((t) => [s('line', { x1: L, x2: W - R, y1: py(t), y2: py(t), class: 'grid' }),
      s('text', { x: L - 6, y: py(t) + 4, 'text-anchor': 'end', class: 'tick' }, fmt(t, 3))]),
    s('text', { x: (L + W - R) / 2, y: H - 8, 'text-anchor': 'middle', class: 'x-label' }, xLabel),
    s('text', { x: 14, y: (T + H - B) / 2, 'text-anchor': 'middle', transform: `rotate(-90 14 ${(T + H - B) / 2})`, class: 'y-label' }, yLabel),
    placeLabels(shown.map((p) => ({ x: px(p.x), y: py(p.y), text: p.label })), { left: L, right: W - R, top: T, bottom: H - B })
      .map((spot, i) => [shown[i], spot]).map(([p, spot]) => {
      const x = px(p.x); const y = py(p.y);
      return s('g', { class: 'point', 'data-label': p.label, 'data-x': p.x, 'data-y': p.y,
        'data-x-err': Number.isFinite(p.xErr) ? p.xErr : null, 'data-y-err': Number.isFinite(p.yErr) ? p.yErr : null },
        Number.isFinite(p.xErr) && p.xErr > 0 ? bar(px(p.x - p.xErr), y, px(p.x + p.xErr), y, 'h') : null,
        Number.isFinite(p.yErr) && p.yErr > 0 ? bar(x, py(p.y - p.yErr), x, py(p.y + p.yErr), 'v') : null,
        s('circle', { cx: x, cy: y, r: 5.5, fill: p.color, stroke: '#111827', 'stroke-width': 0.6 },
          s('title', {}, `${p.label} (${p.group}): ${xLabel} ${fmt(p.x)}, ${yLabel} ${fmt(p.y)}`)),
        s('text', { x: spot.x, y: spot.y, 'text-anchor': spot.anchor, class: 'point-label' }, spot.text));
    }),
    shown.length ? null : s('text', { x: W / 2, y: H / 2, 'text-anchor': 'middle', class: 'tick' }, 'No job has both metrics.'));
  const groups = [...new Map(shown.map((p) => [p.group, p.color])).entries()];
  return h('div', { class: 'chart-box', 'data-chart': key },
    svg, h('div', { class: 'legend' }, groups.map(([g, c]) => h('span', { class: 'legend-item' }, h('span', { class: 'swatch', style: `background:${c}` }), g))));
}
