// The parameters of a job: each parameter key's scalars over the iterations, with the targets of a
// synthetic job as dashed lines, and a table of init, current and target values and dz/dp; then
// the textures' summaries (./job-textures.js), whose texels are not listed scalars.

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

/** The newest parameter values: after the last step, or the initial ones. */
export function currentValues(plan, records) {
  const last = records[records.length - 1];
  return last ? last.updated_parameters : plan?.init;
}

export function parametersPanel() {
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
    const labels = plan.scalars, targets = plan.target_values;
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
      const options = { height: 170,
        series: scalars.map((i, n) => ({ label: labels[i], color: color(n), points: trajectory(i) })),
        guides: targets ? scalars.map((i, n) => ({ y: targets[i], color: color(n) })) : [] };
      return { chart, options, element: h("div.param-chart", h("div.param-key.mono", key), chart, legend(items)) };
    });
    paramCharts.replaceChildren(...charts.map((c) => c.element));
    for (const { chart, options } of charts) lineChart(chart, options);     // in the page: they measure their width
    const values = currentValues(plan, records);
    const gradient = records.length ? records[records.length - 1].dz_dp : null;
    paramTable.replaceChildren(h("table.table.table-compact.param-table", { dataset: { testid: "parameter-table" } },
      h("thead", h("tr", ["scalar", "init", "current", "target", "|Δ|", "dz/dp"].map((c) => h("th", c)))),
      h("tbody", labels.map((label, i) => h("tr",
        h("td.mono", label), h("td.num", fmtNum(plan.init?.[i])), h("td.num", fmtNum(values?.[i])),
        h("td.num", targets ? fmtNum(targets[i]) : "—"),
        h("td.num", targets && values ? fmtNum(Math.abs(values[i] - targets[i]), 3) : "—"),
        h("td.num", gradient ? fmtNum(gradient[i], 3) : "—"))))));
  }

  return { element: h("div", paramCharts, paramTable, textures.element), update };
}
