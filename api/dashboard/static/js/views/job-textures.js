// The textures of a job (plan.textures): their texels are not listed scalars, so each iteration
// record carries a summary per texture key (mean per channel, min, max, gradient_rms and, against
// a synthetic target, rmse and psnr). Per texture: its mean per channel with min and max and the
// target's mean dashed, its PSNR in dB when the records carry one, the RMS of dz/dp (log scale),
// and a compact table of every texture's shape, current mean and PSNR.

import { PALETTE, RGB, legend, lineChart } from "../charts.js";
import { fmtNum, h } from "../dom.js";

const RANGE = "#94a3b8";            // min and max: thin grey lines beside the channel means

/** Channel names of a texture of C channels: R, G, B (A) for colour, "mean" for one channel. */
function channelNames(channels) {
  if (channels === 1) return ["mean"];
  if (channels <= 4) return ["R", "G", "B", "A"].slice(0, channels);
  return Array.from({ length: channels }, (_, c) => `[${c}]`);
}

/** The texture summaries of `key` over the records: [[iteration, summary]]. */
function summaries(records, key) {
  return records.filter((r) => r.textures && r.textures[key]).map((r) => [r.iteration, r.textures[key]]);
}

/** The charts of one texture; `entry` is its plan.textures item, `rows` its summaries. */
function textureCharts(entry, rows) {
  const key = entry.key;
  const channels = (entry.shape || [])[2] ?? entry.init?.mean?.length ?? 1;
  const names = channelNames(channels);
  const colors = channels === 3 ? RGB : PALETTE;
  const color = (c) => colors[c % colors.length];
  const start = rows.length ? null : entry.init;      // before the first record: the initial value
  const points = (value) => (start ? [[0, value(start)]] : rows.map(([k, s]) => [k, value(s)]));
  const targetMean = entry.target?.mean;

  const meanChart = h("div.chart.chart-small", { dataset: { testid: "texture-mean-chart", key } });
  const meanItems = names.map((label, c) => ({ label, color: color(c) })).concat([{ label: "min / max", color: RANGE }]);
  if (targetMean) meanItems.push({ label: "target mean", color: "#64748b", dashed: true });
  const charts = [{ chart: meanChart, options: { height: 170,
    series: names.map((label, c) => ({ label, color: color(c), points: points((s) => s.mean?.[c]) }))
      .concat([{ label: "min", color: RANGE, points: points((s) => s.min) },
        { label: "max", color: RANGE, points: points((s) => s.max) }]),
    guides: targetMean ? targetMean.map((y, c) => ({ y, color: color(c) })) : [] } }];
  const panels = [h("div.texture-chart", h("div.muted.small", "mean per channel"), meanChart, legend(meanItems))];

  const small = [];
  if (rows.some(([, s]) => Number.isFinite(s.psnr))) {
    const psnrChart = h("div.chart.chart-small", { dataset: { testid: "texture-psnr-chart", key } });
    charts.push({ chart: psnrChart, options: { height: 150,
      series: [{ label: "PSNR", color: PALETTE[0], points: points((s) => s.psnr) }], format: (v) => fmtNum(v, 3) } });
    small.push(h("div.texture-chart", h("div.muted.small", "PSNR against the target (dB)"), psnrChart));
  }
  const gradientChart = h("div.chart.chart-small", { dataset: { testid: "texture-gradient-chart", key } });
  charts.push({ chart: gradientChart, options: { height: 150, logY: true,
    series: [{ label: "RMS of dz/dp", color: PALETTE[3], points: points((s) => s.gradient_rms) }] } });
  small.push(h("div.texture-chart", h("div.muted.small", "RMS of dz/dp (log scale)"), gradientChart));
  panels.push(h("div.texture-chart-row", small));

  const element = h("div.param-chart", { dataset: { testid: "texture-chart", key } },
    h("div.param-key.mono", `${key} `, h("span.muted", `(${(entry.shape || []).join(" × ")})`)), ...panels);
  return { element, charts };
}

function textureTable(textures, records) {
  const last = (key) => { const rows = summaries(records, key); return rows.length ? rows[rows.length - 1][1] : null; };
  return h("table.table.table-compact.param-table", { dataset: { testid: "texture-table" } },
    h("thead", h("tr", ["texture", "shape", "mean", "PSNR (dB)"].map((c) => h("th", c)))),
    h("tbody", textures.map((entry) => {
      const summary = last(entry.key) || entry.init || {};
      return h("tr", { dataset: { testid: "texture-row", key: entry.key } },
        h("td.mono", entry.key), h("td.num", (entry.shape || []).join("×")),
        h("td.num", (summary.mean || []).map((m) => fmtNum(m, 3)).join(", ") || "—"),
        h("td.num", fmtNum(summary.psnr, 3)));
    })));
}

export function texturesPanel() {
  const charts = h("div.param-charts", { dataset: { testid: "texture-charts" } });
  const table = h("div.table-scroll");
  const element = h("div.textures-panel", { hidden: true }, charts, table);

  /** Redraw from the plan (its `textures` list) and the records sorted by iteration. */
  function update(plan, records) {
    const textures = (plan && plan.textures) || [];
    element.hidden = textures.length === 0;
    if (!textures.length) {
      charts.replaceChildren();
      table.replaceChildren();
      return;
    }
    const drawn = textures.map((entry) => textureCharts(entry, summaries(records, entry.key)));
    charts.replaceChildren(...drawn.map((d) => d.element));
    for (const { chart, options } of drawn.flatMap((d) => d.charts)) lineChart(chart, options);  // in the page
    table.replaceChildren(textureTable(textures, records));
  }

  return { element, update };
}
