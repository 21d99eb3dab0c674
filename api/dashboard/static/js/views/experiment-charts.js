// Charts of the experiment page (inline SVG, like charts.js): many series against a real-valued x
// (iterations or compute seconds, log y, shaded spread), and parallel coordinates of the varied
// fields against the objective. Containers get data-series / data-lines for tests.

import { PALETTE } from "../charts.js";
import { fmtNum, h } from "../dom.js";

const NS = "http://www.w3.org/2000/svg";
const M = { left: 60, right: 16, top: 12, bottom: 34 };

function svg(tag, attrs = {}, text) {
  const el = document.createElementNS(NS, tag);
  for (const [k, v] of Object.entries(attrs)) el.setAttribute(k, v);
  if (text !== undefined) el.textContent = text;
  return el;
}

function niceTicks(lo, hi, count = 5) {
  const span = hi - lo || 1;
  const raw = span / count;
  const mag = 10 ** Math.floor(Math.log10(raw));
  const norm = raw / mag;
  const step = (norm < 1.5 ? 1 : norm < 3 ? 2 : norm < 7 ? 5 : 10) * mag;
  const out = [];
  for (let v = Math.ceil(lo / step - 1e-9) * step; v <= hi + step * 1e-9; v += step) out.push(Math.abs(v) < step * 1e-9 ? 0 : v);
  return out;
}

/** A categorical colour per distinct value (in first-seen order). */
export function colorScale(values) {
  const keys = [...new Set(values.map((v) => JSON.stringify(v)))];
  return (value) => PALETTE[keys.indexOf(JSON.stringify(value)) % PALETTE.length];
}

/**
 * series: [{label, color, points: [[x, y]], band: [[x, lo, hi]], step}] drawn against x (linear) and
 * y (log with logY); a step series holds each value until the next x. Hover shows the nearest
 * point of every series.
 */
export function xyChart(el, { series, logY = true, xLabel = "", height = 260 }) {
  const width = Math.max(300, Math.floor(el.clientWidth || 560));
  const root = svg("svg", { viewBox: `0 0 ${width} ${height}`, width, height, class: "chart-svg" });
  const ok = ([x, y]) => Number.isFinite(x) && Number.isFinite(y) && (!logY || y > 0);
  const lines = series.map((s) => ({ ...s, points: s.points.filter(ok) })).filter((s) => s.points.length);
  el.dataset.series = String(lines.length);
  if (!lines.length) {
    root.append(svg("text", { x: width / 2, y: height / 2, "text-anchor": "middle", class: "chart-empty" }, "no finished iterations yet"));
    el.replaceChildren(root);
    return;
  }
  const ty = logY ? Math.log10 : (y) => y;
  const all = lines.flatMap((s) => s.points);
  const bandValues = lines.flatMap((s) => (s.band || []).flatMap(([, lo, hi]) => [lo, hi])).filter((v) => ok([0, v]));
  const ys = all.map((p) => ty(p[1])).concat(bandValues.map(ty));
  let [y0, y1] = [Math.min(...ys), Math.max(...ys)];
  if (y1 - y0 < (logY ? 0.3 : 1e-9)) { y0 -= logY ? 0.15 : 0.5; y1 += logY ? 0.15 : 0.5; }
  const pad = (y1 - y0) * 0.05;
  y0 -= pad; y1 += pad;
  const x1 = Math.max(...all.map((p) => p[0]), 1e-9);
  const x0 = Math.min(0, ...all.map((p) => p[0]));
  const pw = width - M.left - M.right, ph = height - M.top - M.bottom;
  const sx = (x) => M.left + ((x - x0) / (x1 - x0)) * pw;
  const sy = (v) => M.top + (1 - (v - y0) / (y1 - y0)) * ph;
  const grid = svg("g", { class: "chart-grid" });
  const yTicks = logY ? niceTicks(y0, y1, 4).filter((v) => Math.abs(v - Math.round(v)) < 1e-9 || y1 - y0 < 2) : niceTicks(y0, y1, 4);
  for (const t of yTicks) {
    grid.append(svg("line", { x1: M.left, x2: M.left + pw, y1: sy(t), y2: sy(t) }));
    grid.append(svg("text", { x: M.left - 6, y: sy(t) + 3.5, "text-anchor": "end" }, fmtNum(logY ? 10 ** t : t, 2)));
  }
  grid.append(svg("line", { x1: M.left, x2: M.left + pw, y1: M.top + ph, y2: M.top + ph, class: "chart-axis" }));
  for (const t of niceTicks(x0, x1, Math.max(2, Math.floor(pw / 80)))) {
    grid.append(svg("text", { x: sx(t), y: M.top + ph + 15, "text-anchor": "middle" }, fmtNum(t, 3)));
  }
  if (xLabel) grid.append(svg("text", { x: M.left + pw / 2, y: height - 3, "text-anchor": "middle" }, xLabel));
  root.append(grid);
  for (const s of lines) {
    const band = (s.band || []).filter(([x, lo, hi]) => ok([x, lo]) && ok([x, hi]));
    if (band.length > 1) {
      const top = band.map(([x, , hi]) => `${sx(x).toFixed(1)},${sy(ty(hi)).toFixed(1)}`);
      const bottom = band.slice().reverse().map(([x, lo]) => `${sx(x).toFixed(1)},${sy(ty(lo)).toFixed(1)}`);
      root.append(svg("polygon", { points: top.concat(bottom).join(" "), fill: s.color, "fill-opacity": 0.13 }));
    }
    if (s.points.length === 1) {
      root.append(svg("circle", { cx: sx(s.points[0][0]), cy: sy(ty(s.points[0][1])), r: 3, fill: s.color }));
    } else {
      const points = s.step ? s.points.flatMap((p, i) => (i ? [[p[0], s.points[i - 1][1]], p] : [p])) : s.points;
      const d = points.map(([x, y], i) => `${i ? "L" : "M"}${sx(x).toFixed(1)},${sy(ty(y)).toFixed(1)}`).join("");
      root.append(svg("path", { d, stroke: s.color, class: "chart-line", "stroke-width": s.width || 1.8,
        "stroke-opacity": s.opacity ?? 1, "data-label": s.label }));
    }
  }
  const readout = svg("text", { x: M.left + 6, y: M.top + 10, class: "chart-readout", visibility: "hidden" });
  const cursor = svg("line", { y1: M.top, y2: M.top + ph, class: "chart-cursor", visibility: "hidden" });
  root.append(cursor, readout);
  root.addEventListener("mousemove", (event) => {
    const box = root.getBoundingClientRect();
    const x = x0 + (((event.clientX - box.left) / box.width) * width - M.left) / pw * (x1 - x0);
    const near = lines.map((s) => [s, s.points.reduce((a, b) => (Math.abs(b[0] - x) < Math.abs(a[0] - x) ? b : a))])
      .slice(0, 5).map(([s, p]) => `${s.label}: ${fmtNum(p[1], 3)}`);
    cursor.setAttribute("x1", sx(Math.min(Math.max(x, x0), x1)));
    cursor.setAttribute("x2", sx(Math.min(Math.max(x, x0), x1)));
    readout.textContent = `${fmtNum(x, 3)} — ${near.join(" · ")}`;
    cursor.setAttribute("visibility", "visible");
    readout.setAttribute("visibility", "visible");
  });
  root.addEventListener("mouseleave", () => { cursor.setAttribute("visibility", "hidden"); readout.setAttribute("visibility", "hidden"); });
  el.replaceChildren(root);
}

/**
 * Parallel coordinates: one vertical axis per varied field and a last one for the objective;
 * one polyline per run. Categorical fields (strings, lists) get evenly spaced categories;
 * numbers a linear axis (log when they span more than a decade). `color(run)` colours a line.
 */
export function parallelCoordinates(el, { fields, objective, runs, color, height = 280 }) {
  const width = Math.max(360, Math.floor(el.clientWidth || 640));
  const root = svg("svg", { viewBox: `0 0 ${width} ${height}`, width, height, class: "chart-svg" });
  const axes = [...fields.map((f) => ({ name: f, value: (r) => r.values[f] })), { name: objective.label, value: objective.value }];
  const usable = runs.filter((r) => Number.isFinite(objective.value(r)));
  el.dataset.lines = String(usable.length);
  if (!usable.length) {
    root.append(svg("text", { x: width / 2, y: height / 2, "text-anchor": "middle", class: "chart-empty" }, "no finished run with an objective value yet"));
    el.replaceChildren(root);
    return;
  }
  const top = 26, bottom = height - 26, left = 50, right = width - 60;
  const step = axes.length > 1 ? (right - left) / (axes.length - 1) : 0;
  const scales = axes.map((axis) => {
    const values = usable.map((r) => axis.value(r));
    if (values.every((v) => typeof v === "number" && Number.isFinite(v))) {
      const positive = values.every((v) => v > 0);
      const [lo, hi] = [Math.min(...values), Math.max(...values)];
      const log = positive && hi / lo > 10;
      const t = log ? Math.log10 : (v) => v;
      const [a, b] = [t(lo), t(hi)];
      const pos = (v) => (b - a < 1e-12 ? (top + bottom) / 2 : bottom - ((t(v) - a) / (b - a)) * (bottom - top));
      return { pos, labels: [[lo, pos(lo)], [hi, pos(hi)]] };
    }
    const keys = [...new Set(values.map((v) => JSON.stringify(v)))];
    const pos = (v) => (keys.length === 1 ? (top + bottom) / 2
      : bottom - (keys.indexOf(JSON.stringify(v)) / (keys.length - 1)) * (bottom - top));
    return { pos, labels: keys.map((k) => [JSON.parse(k), pos(JSON.parse(k))]) };
  });
  axes.forEach((axis, i) => {
    const x = left + i * step;
    root.append(svg("line", { x1: x, x2: x, y1: top, y2: bottom, stroke: "#94a3b8" }));
    root.append(svg("text", { x, y: 14, "text-anchor": "middle", class: "pc-axis" }, axis.name));
    for (const [value, y] of scales[i].labels) {
      root.append(svg("text", { x: x + 5, y: y + 4, class: "pc-label" }, typeof value === "number" ? fmtNum(value, 3) : String(value)));
    }
  });
  for (const run of usable) {
    const points = axes.map((axis, i) => `${(left + i * step).toFixed(1)},${scales[i].pos(axis.value(run)).toFixed(1)}`);
    const line = svg("polyline", { points: points.join(" "), fill: "none", stroke: color(run), "stroke-width": 1.6,
      "stroke-opacity": 0.75, class: "pc-line" });
    line.append(svg("title", {}, `#${run.index}: ${fmtNum(objective.value(run), 4)}`));
    root.append(line);
  }
  el.replaceChildren(root);
}

export function legendOf(entries) {
  return h("div.legend", entries.map(([label, color]) =>
    h("span.legend-item", h("span.swatch", { style: { borderColor: color, background: color } }), label)));
}
