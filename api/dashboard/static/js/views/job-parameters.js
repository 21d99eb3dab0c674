// The parameters of a job: each parameter key's scalars over the iterations (the answer: the
// estimate, with a band of ± 2 standard errors; the raw iterates faint), with the targets of a
// synthetic job as dashed lines, and a table of init, estimate ± standard error, the last iterate,
// target values and dz/dp, under why the run stopped; then the textures' summaries
// (./job-textures.js), whose texels are not listed scalars.

import { PALETTE, RGB, legend, lineChart } from "../charts.js";
import { fmtNum, h } from "../dom.js";
import { texturesPanel } from "./job-textures.js";

/** Scalars grouped by their parameter key: [{key, scalars: [index]}]. */
function groups(plan) {
  const labels = plan.scalars || [];
  const keys = plan.keys || [...new Set(labels.map((l) => l.replace(/\[\d+\]$/, "")))];
  return keys.map((key) => ({ key, scalars: labels.map((l, i) => [l, i]).filter(([l]) => l === key || l.startsWith(`${key}[`))
    .map(([, i]) => i) })).filter((group) => group.scalars.length > 0);   // textures have no listed scalars
}

/** The answer now: the last record's estimate (its last step's parameters before the run had
 * one), or the initial values. */
export function currentValues(plan, records) {
  const last = records[records.length - 1];
  return last ? (last.estimate || last.updated_parameters) : plan?.init;
}

/** Why the run stopped (the plan's last `stop` event), or null while it runs. */
export function stopReason(plan) {
  const events = plan?.events || [];
  const last = events[events.length - 1];
  return last && last.what === "stop" ? last.reason : null;
}

export function parametersPanel() {
  const stopped = h("p.muted", { dataset: { testid: "stop-reason" } });
  const paramCharts = h("div.param-charts", { dataset: { testid: "parameter-charts" } });
  const paramTable = h("div.table-scroll");
  const textures = texturesPanel();

  function update(plan, records) {
    textures.update(plan, records);
    if (!plan || !plan.scalars) {
      paramCharts.replaceChildren(h("p.muted", "The parameters appear when the job starts."));
      paramTable.replaceChildren();
      return;
    }
    if (!plan.scalars.length) {        // a pure texture job: its textures are all there is
      if (plan.textures?.length) paramCharts.replaceChildren();
      else paramCharts.replaceChildren(h("p.muted", "No scalar parameters."));
      paramTable.replaceChildren();
      return;
    }
    const reason = stopReason(plan);
    stopped.textContent = reason ? `Stopped: ${reason}.` : "";
    const labels = plan.scalars, targets = plan.target_values;
    const estimated = records.filter((r) => r.estimate);
    const estimate = (i) => estimated.map((r) => [r.iteration, r.estimate[i]]);
    const band = (i) => estimated.filter((r) => r.standard_error)
      .map((r) => [r.iteration, r.estimate[i] - 2 * r.standard_error[i], r.estimate[i] + 2 * r.standard_error[i]]);
    const trajectory = (i) => {
      const points = records.map((r) => [r.iteration, r.parameters[i]]);
      const last = records[records.length - 1];
      if (last) points.push([last.iteration + 1, last.updated_parameters[i]]);
      return points.length ? points : [[0, plan.init[i]]];
    };
    const charts = groups(plan).map(({ key, scalars }) => {
      const colors = scalars.length === 3 ? RGB : PALETTE;
      const color = (n) => colors[n % colors.length];
      const chart = h("div.chart.chart-small", { dataset: { key } });
      const items = scalars.map((i, n) => ({ label: labels[i].slice(key.length) || key, color: color(n) }));
      if (targets) items.push({ label: "target", color: "#64748b", dashed: true });
      if (estimated.length) items.push({ label: "iterates", color: "#94a3b8" });
      const answers = estimated.length ? scalars.map((i, n) => ({ label: `${labels[i]} estimate`, color: color(n),
        points: estimate(i) })) : [];
      const options = { height: 170,
        series: [...answers, ...scalars.map((i, n) => ({ label: labels[i], color: color(n), points: trajectory(i),
          faint: estimated.length > 0 }))],
        bands: scalars.map((i, n) => ({ color: color(n), points: band(i) })),
        guides: targets ? scalars.map((i, n) => ({ y: targets[i], color: color(n) })) : [] };
      return { chart, options, element: h("div.param-chart", h("div.param-key.mono", key), chart, legend(items)) };
    });
    paramCharts.replaceChildren(...charts.map((c) => c.element));
    for (const { chart, options } of charts) lineChart(chart, options);     // in the page: they measure their width
    const values = currentValues(plan, records);
    const last = records.length ? records[records.length - 1] : null;
    const errors = last?.standard_error;
    paramTable.replaceChildren(h("table.table.table-compact.param-table", { dataset: { testid: "parameter-table" } },
      h("thead", h("tr", ["scalar", "init", "estimate", "± SE", "last iterate", "target", "|Δ|", "dz/dp"]
        .map((c) => h("th", c)))),
      h("tbody", labels.map((label, i) => h("tr",
        h("td.mono", label), h("td.num", fmtNum(plan.init?.[i])), h("td.num", fmtNum(values?.[i])),
        h("td.num", errors ? fmtNum(errors[i], 2) : "—"),
        h("td.num", last ? fmtNum(last.updated_parameters[i]) : "—"),
        h("td.num", targets ? fmtNum(targets[i]) : "—"),
        h("td.num", targets && values ? fmtNum(Math.abs(values[i] - targets[i]), 3) : "—"),
        h("td.num", last ? fmtNum(last.dz_dp[i], 3) : "—"))))));
  }

  return { element: h("div", stopped, paramCharts, paramTable, textures.element), update };
}
