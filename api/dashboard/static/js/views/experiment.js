// #/experiments/<id>: one experiment, live. The runs table, mean and spread over seeds, curves
// coloured by a chosen field, parallel coordinates against the objective, accuracy against time
// for method sweeps, two runs side by side. Follows the experiment's SSE stream and re-reads the
// runs and curves when something changed (and every few seconds while runs are running).

import { FINISHED, getJSON, postJSON } from "../api.js";
import { clear, fmtDuration, fmtNum, h, problemText, statusBadge } from "../dom.js";
import { poll } from "../poll.js";
import { comparePanel } from "./experiment-compare.js";
import { colorScale, legendOf, parallelCoordinates, xyChart } from "./experiment-charts.js";
import { runsTable } from "./experiment-runs.js";
import { runsProgress } from "./experiments.js";

const METRIC_COLUMN = { parameter_error: "final_parameter_error", loss: "final_loss", seconds: "seconds",
  time_to_error: "time_to_error" };

function card(title, testid, ...body) {
  return h("section.card", { dataset: { testid } }, h("div.card-head", h("h2", title)), ...body);
}

export function experimentView(root, expId) {
  const base = `/v1/experiments/${encodeURIComponent(expId)}`;
  const state = { experiment: null, rows: [], curves: null, colorBy: null, xAxis: "seconds" };
  let alive = true, source = null, pending = null, lastSeq = 0;

  const title = h("h1.job-title", "Experiment");
  const badge = h("span");
  const connection = h("span.connection", { dataset: { testid: "connection" } });
  const alert = h("div.alert.alert-error", { hidden: true, dataset: { testid: "experiment-error" } });
  const csv = h("a.btn.btn-small", { download: "", dataset: { testid: "csv-link" } }, "results.csv");
  const cancel = h("button.btn.btn-danger.btn-small", { type: "button", hidden: true, dataset: { testid: "cancel-experiment" },
    onclick: () => act(`${base}/cancel`) }, "Cancel");
  const retry = h("button.btn.btn-small", { type: "button", hidden: true, dataset: { testid: "retry-experiment" },
    onclick: () => act(`${base}/retry`) }, "Retry failed");
  const seedsInput = h("input.input.input-small", { placeholder: "more seeds: 3, 4", dataset: { testid: "append-seeds" } });
  const append = h("button.btn.btn-small", { type: "button", dataset: { testid: "append-button" }, onclick: () => {
    const seeds = seedsInput.value.split(/[\s,;]+/).filter(Boolean).map(Number);
    if (seeds.length && seeds.every(Number.isInteger)) act(`${base}/runs`, { seeds }).then(() => { seedsInput.value = ""; });
  } }, "Add seeds");
  const stats = h("div.stats");
  const aggregates = h("div.table-scroll", { dataset: { testid: "aggregates" } });
  const compare = comparePanel();
  const runs = runsTable({ onSelect: (rows) => compare.show(rows) });
  const colorPick = h("select.input.select-small", { dataset: { testid: "color-by" }, onchange: () => { state.colorBy = colorPick.value; draw(); } });
  const xPick = h("select.input.select-small", { dataset: { testid: "x-axis" }, onchange: () => { state.xAxis = xPick.value; draw(); } },
    h("option", { value: "seconds" }, "compute seconds"), h("option", { value: "iteration" }, "iteration"));
  const lossChart = h("div.chart", { dataset: { testid: "runs-loss-chart" } });
  const errorChart = h("div.chart", { dataset: { testid: "runs-error-chart" } });
  const curveLegend = h("div");
  const parallel = h("div.chart", { dataset: { testid: "parallel-chart" } });
  const accuracy = h("div.chart", { dataset: { testid: "accuracy-chart" } });
  const accuracyLoss = h("div.chart", { dataset: { testid: "accuracy-loss-chart" } });
  const accuracyLegend = h("div");
  const accuracyCard = card("Accuracy against time, per method (mean over seeds)", "accuracy-card",
    h("p.muted.small", "Parameter error max |p − target| and image loss against compute seconds (the phases of the "
      + "iterations summed, warm-up included); the band spans the best to the worst seed."),
    h("div.grid-2", accuracy, accuracyLoss), accuracyLegend);

  clear(root,
    h("div.page-head", h("a.back", { href: "#/experiments" }, "← Experiments"),
      h("div.title-block", h("div.title-line", title, badge, connection), h("div.sub.mono", expId)),
      h("span.spacer"), seedsInput, append, retry, cancel, csv),
    alert, stats,
    card("Mean and spread over seeds", "aggregates-card", aggregates),
    card("Runs", "runs-card", runs.element),
    accuracyCard,
    card("Curves of every run", "curves-card",
      h("div.toolbar", h("label.label", "colour by"), colorPick, h("label.label", "x"), xPick),
      h("div.grid-2", h("div", h("h3", "loss"), lossChart), h("div", h("h3", "max |p − target|"), errorChart)),
      curveLegend),
    card("Varied fields against the objective", "parallel-card", parallel),
    card("Two runs side by side", "compare-card", compare.element));

  // ---------------------------------------------------------------- data
  /** One read of the experiment, its runs and curves; false once it has finished (the poll pauses
   * until an action or an event calls it again). */
  async function load() {
    const [experiment, rows, curves] = await Promise.all([getJSON(base), getJSON(`${base}/runs`), getJSON(`${base}/curves`)]);
    if (!alive) return false;
    Object.assign(state, { experiment, rows, curves });
    alert.hidden = true;
    draw();
    if (!source && !FINISHED.has(experiment.status)) follow();
    return !FINISHED.has(experiment.status);
  }

  function loadFailed(error) {
    if (error.status === 404) {
      clear(root, h("div.card.empty-state", h("h2", "No such experiment"), h("p.mono", expId), h("a.btn", { href: "#/experiments" }, "Back")));
      alive = false;
      return false;
    }
    alert.textContent = `Could not load the experiment: ${problemText(error)}`;
    alert.hidden = false;
    return true;
  }

  function reloadSoon() {
    if (!pending) pending = setTimeout(() => { pending = null; if (alive) poller.now(); }, 300);
  }

  function follow() {
    const token = state.experiment?.read_token;
    const url = `${base}/events?after=${lastSeq}${token ? `&token=${encodeURIComponent(token)}` : ""}`;
    source = new EventSource(url);
    for (const type of ["status", "run", "retry", "appended", "canceled"]) {
      source.addEventListener(type, (message) => {
        lastSeq = Math.max(lastSeq, Number(message.lastEventId) || 0);
        const event = JSON.parse(message.data);
        if (type === "status" && FINISHED.has(event.status)) { source?.close(); source = null; setConnection("finished"); }
        reloadSoon();
      });
    }
    source.onopen = () => setConnection("live");
    source.onerror = () => {
      if (source && source.readyState === EventSource.CLOSED) { source = null; setConnection("closed"); }
      else setConnection("reconnecting");
    };
  }

  function setConnection(status) {
    connection.className = `connection connection-${status}`;
    connection.textContent = { live: "live", reconnecting: "reconnecting…", closed: "", finished: "" }[status] ?? status;
  }

  async function act(path, body) {
    try {
      await postJSON(path, body);
      if (!source) follow();
      await poller.now();
    } catch (error) {
      alert.textContent = problemText(error);
      alert.hidden = false;
    }
  }

  // ---------------------------------------------------------------- view
  function draw() {
    const { experiment, rows, curves } = state;
    const fields = experiment.varied.filter((f) => f !== "seed");
    const allFields = Object.keys(experiment.sweep.grid || {}).concat(Object.keys(experiment.sweep.random || {}))
      .filter((f, i, list) => list.indexOf(f) === i);
    title.textContent = experiment.name || "Untitled experiment";
    document.title = `${experiment.name || experiment.id} · NDRF`;
    badge.replaceChildren(statusBadge(experiment.status, { dataset: { testid: "experiment-status" } }));
    const token = experiment.read_token ? `?token=${encodeURIComponent(experiment.read_token)}` : "";
    csv.href = `${base}/results.csv${token}`;
    const counts = experiment.counts || {};
    cancel.hidden = FINISHED.has(experiment.status);
    retry.hidden = !(counts.failed || counts.canceled);
    drawStats(experiment, rows);
    drawAggregates(experiment, allFields);
    runs.update(rows, allFields.length ? allFields : fields);

    const choices = [...experiment.varied];
    if (!choices.includes("seed")) choices.push("seed");
    if (!state.colorBy || !choices.includes(state.colorBy)) state.colorBy = choices.find((c) => c !== "seed") || "seed";
    colorPick.replaceChildren(...choices.map((c) => h("option", { value: c, selected: c === state.colorBy }, c)));
    drawCurves(curves, rows);
    const objective = experiment.objective;
    const column = METRIC_COLUMN[objective.metric];
    const valueOf = (run) => run.values[state.colorBy];
    const runsForPc = rows.filter((r) => r.status === "succeeded").map((r) => ({ index: r.index, values: { ...r.varied, seed: r.seed }, row: r }));
    const color = colorScale(runsForPc.map(valueOf));
    parallelCoordinates(parallel, { fields: experiment.varied.length ? experiment.varied : ["seed"], runs: runsForPc,
      objective: { label: `${column} (${objective.goal})`, value: (run) => run.row[column] ?? NaN }, color: (run) => color(valueOf(run)) });
    const methodSweep = experiment.varied.includes("method");
    accuracyCard.hidden = !methodSweep;
    if (methodSweep) drawAccuracy(curves);
  }

  function drawStats(experiment, rows) {
    const best = experiment.best;
    const running = rows.filter((r) => r.status === "running").length;
    const stat = (label, value, testid, sub = "") => h("div.stat", h("div.stat-label", label),
      h("div.stat-value.num", { dataset: { testid } }, value), h("div.stat-sub", sub));
    clear(stats,
      h("div.stat", h("div.stat-label", "Runs"), runsProgress(experiment)),
      stat("Running", String(running), "running-count", `at most ${experiment.max_concurrent} at once`),
      stat(`Best ${experiment.objective.metric.replaceAll("_", " ")}`, best ? fmtNum(best.value, 3) : "—", "best-value",
        best ? h("a", { href: `#/jobs/${best.job}` }, `run #${best.index}`) : "no finished run yet"),
      stat("Varied", experiment.varied.join(", ") || "—", "varied-fields", `${experiment.base_method} on ${experiment.base_scene}`),
      stat("Target error", fmtNum(experiment.sweep.target_error, 3), "target-error", "for the time-to-error column"));
  }

  function drawAggregates(experiment, fields) {
    const groups = experiment.aggregates || [];
    const cell = (m, seconds = false) => {
      if (!m || m.mean === null) return h("td.num.muted", "—");
      const text = seconds ? fmtDuration(m.mean) : fmtNum(m.mean, 3);
      return h("td.num", text, m.std !== null ? h("span.muted", ` ± ${seconds ? fmtNum(m.std, 2) + " s" : fmtNum(m.std, 2)}`) : null);
    };
    aggregates.replaceChildren(h("table.table.table-compact",
      h("thead", h("tr", fields.map((f) => h("th", f)), ["runs", "final error", "final loss", "compute s", "time to error"].map((t) => h("th", t)))),
      h("tbody", groups.map((g) => h("tr", { dataset: { testid: "aggregate-row" } },
        fields.map((f) => h("td", { dataset: { key: f } }, typeof g.configuration[f] === "string" ? g.configuration[f] : JSON.stringify(g.configuration[f]))),
        h("td.num", `${g.succeeded} / ${g.runs}`), cell(g.metrics.final_parameter_error), cell(g.metrics.final_loss),
        cell(g.metrics.seconds, true), cell(g.metrics.time_to_error, true))))));
  }

  function drawCurves(curves, rows) {
    const byIndex = new Map(rows.map((r) => [r.index, r]));
    const runCurves = (curves?.runs || []).map((c) => ({ curve: c, row: byIndex.get(c.runs[0]) })).filter((c) => c.row);
    const value = (row) => (state.colorBy === "seed" ? row.seed : row.varied[state.colorBy]);
    const color = colorScale(runCurves.map(({ row }) => value(row)));
    const x = (c, k) => (state.xAxis === "seconds" ? c.seconds[k] : k);
    const series = (key) => runCurves.map(({ curve, row }) => ({ label: curve.label, color: color(value(row)),
      points: curve[key].map((y, k) => [x(curve, k), y]).filter(([, y]) => y !== null) }));
    const xLabel = state.xAxis === "seconds" ? "compute seconds" : "iteration";
    xyChart(lossChart, { series: series("loss"), xLabel });
    xyChart(errorChart, { series: series("parameter_error"), xLabel });
    const seen = new Map();
    for (const { row } of runCurves) seen.set(JSON.stringify(value(row)), value(row));
    curveLegend.replaceChildren(legendOf([...seen.values()].map((v) => [`${state.colorBy} = ${typeof v === "string" ? v : JSON.stringify(v)}`, color(v)])));
  }

  function drawAccuracy(curves) {
    const configurations = curves?.configurations || [];
    const color = colorScale(configurations.map((c) => c.label));
    const start = (c, key) => (key === "parameter_error" && c.initial_parameter_error !== null ? [[0, c.initial_parameter_error]] : []);
    const series = (key, band) => configurations.map((c) => ({ label: c.label, color: color(c.label), width: 2.4,
      step: key === "parameter_error",
      points: start(c, key).concat(c.seconds.map((t, k) => [t, c[key][k]])).filter(([, y]) => y !== null),
      band: band ? c.seconds.map((t, k) => [t, ...(c.parameter_error_spread?.[k] || [NaN, NaN])]) : [] }));
    xyChart(accuracy, { series: series("parameter_error", true), xLabel: "compute seconds → max |p − target|" });
    xyChart(accuracyLoss, { series: series("loss", false), xLabel: "compute seconds → image loss" });
    accuracyLegend.replaceChildren(legendOf(configurations.map((c) => [c.label, color(c.label)])));
  }

  const resize = () => { if (state.experiment) draw(); };
  window.addEventListener("resize", resize);
  // re-read every 4 s while it runs, also in a hidden tab
  const poller = poll(load, 4000, { hidden: true, onError: loadFailed });
  return () => {
    alive = false;
    source?.close();
    poller.stop();
    clearTimeout(pending);
    window.removeEventListener("resize", resize);
  };
}
