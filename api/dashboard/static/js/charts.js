// Charts drawn as inline SVG: line charts (linear or log y), stacked bars, legends, colour bars.
// Each call redraws its container from scratch; containers get data-points for tests.

import { fmtNum, h } from "./dom.js";

const NS = "http://www.w3.org/2000/svg";
const MARGIN = { left: 58, right: 16, top: 12, bottom: 30 };

export const PALETTE = ["#2563eb", "#dc2626", "#16a34a", "#9333ea", "#ea580c", "#0891b2", "#ca8a04", "#db2777"];
export const RGB = ["#dc2626", "#16a34a", "#2563eb"];

// Moreland's cool-to-warm anchors, the colour map of the server's gradient previews (-1 .. +1).
const DIVERGING = ["#3b4cc0", "#8db0fe", "#dddddd", "#f49a7b", "#b40426"];

function svg(tag, attrs = {}, text) {
  const el = document.createElementNS(NS, tag);
  for (const [key, value] of Object.entries(attrs)) el.setAttribute(key, value);
  if (text !== undefined) el.textContent = text;
  return el;
}

function niceStep(span, count) {
  const raw = span / Math.max(count, 1);
  const magnitude = 10 ** Math.floor(Math.log10(raw));
  const norm = raw / magnitude;
  return (norm < 1.5 ? 1 : norm < 3 ? 2 : norm < 7 ? 5 : 10) * magnitude;
}

function linearTicks(lo, hi, count, integer = false) {
  const step = integer ? Math.max(1, Math.round(niceStep(hi - lo, count))) : niceStep(hi - lo, count);
  const ticks = [];
  for (let v = Math.ceil(lo / step - 1e-9) * step; v <= hi + step * 1e-9; v += step) {
    ticks.push(Math.abs(v) < step * 1e-9 ? 0 : v);
  }
  return ticks;
}

/** Ticks of a log axis; lo and hi are log10 values. */
function logTicks(lo, hi) {
  const decades = Math.ceil(hi) - Math.floor(lo);
  const multiples = decades <= 1 ? [1, 2, 5] : decades <= 3 ? [1, 3] : [1];
  const every = Math.max(1, Math.ceil(decades / 6));
  const ticks = [];
  for (let d = Math.floor(lo); d <= Math.ceil(hi); d++) {
    if (d % every !== 0) continue;
    for (const m of multiples) {
      const v = Math.log10(m) + d;
      if (v >= lo - 1e-9 && v <= hi + 1e-9) ticks.push(v);
    }
  }
  return ticks;
}

/** [min, max] of an array (a loop: spreading long arrays into Math.min overflows the stack). */
function extent(values) {
  let lo = Infinity, hi = -Infinity;
  for (const v of values) { if (v < lo) lo = v; if (v > hi) hi = v; }
  return [lo, hi];
}

function domain(values, pad, minSpan) {
  let [lo, hi] = extent(values);
  if (hi - lo < minSpan) { const mid = (lo + hi) / 2; lo = mid - minSpan / 2; hi = mid + minSpan / 2; }
  const extra = (hi - lo) * pad;
  return [lo - extra, hi + extra];
}

function frame(el, height) {
  const width = Math.max(260, Math.floor(el.clientWidth || 560));
  const root = svg("svg", { viewBox: `0 0 ${width} ${height}`, width, height, class: "chart-svg" });
  return { root, width, plotW: width - MARGIN.left - MARGIN.right, plotH: height - MARGIN.top - MARGIN.bottom };
}

function empty(el, root, width, height, text = "waiting for the first iteration") {
  root.append(svg("text", { x: width / 2, y: height / 2, class: "chart-empty", "text-anchor": "middle" }, text));
  el.replaceChildren(root);
  el.dataset.points = "0";
}

function axes(root, f, xTicks, yTicks, sx, sy) {
  const grid = svg("g", { class: "chart-grid" });
  for (const t of yTicks) {
    const y = sy(t.value);
    grid.append(svg("line", { x1: MARGIN.left, x2: MARGIN.left + f.plotW, y1: y, y2: y }));
    grid.append(svg("text", { x: MARGIN.left - 6, y: y + 3.5, "text-anchor": "end" }, t.label));
  }
  const bottom = MARGIN.top + f.plotH;
  grid.append(svg("line", { x1: MARGIN.left, x2: MARGIN.left + f.plotW, y1: bottom, y2: bottom, class: "chart-axis" }));
  for (const t of xTicks) {
    grid.append(svg("text", { x: sx(t), y: bottom + 17, "text-anchor": "middle" }, String(t)));
  }
  root.append(grid);
}

/**
 * Line chart of `series` [{label, color, points: [[x, y]], dashed, faint}] with optional horizontal
 * dashed `guides` [{y, color}] (targets) and shaded `bands` [{color, points: [[x, low, high]]}]
 * (an estimate ± 2 standard errors). Log y drops non-positive values. Hovering shows the values at
 * the nearest x of the first series.
 */
export function lineChart(el, { series, guides = [], bands = [], logY = false, height = 210, format = fmtNum }) {
  const f = frame(el, height);
  const ok = ([x, y]) => Number.isFinite(x) && Number.isFinite(y) && (!logY || y > 0);
  const lines = series.map((s) => ({ ...s, points: s.points.filter(ok) }));
  const all = lines.flatMap((s) => s.points);
  if (!all.length) return empty(el, f.root, f.width, height);
  const ty = logY ? Math.log10 : (y) => y;
  const [xMin, xMax] = extent(all.map((p) => p[0]));
  const [x0, x1] = [xMin, Math.max(xMax, xMin + 1)];
  const spans = bands.map((b) => ({ ...b, points: b.points.filter(([x, lo, hi]) => [x, lo, hi].every(Number.isFinite)
    && (!logY || lo > 0)) }));
  const ys = all.map((p) => ty(p[1])).concat(guides.filter((g) => Number.isFinite(g.y)).map((g) => ty(g.y)))
    .concat(spans.flatMap((b) => b.points.flatMap(([, lo, hi]) => [ty(lo), ty(hi)])));
  const [y0, y1] = domain(ys, 0.06, logY ? 0.5 : Math.max(1e-3, Math.abs(ys[0]) * 0.2));
  const sx = (x) => MARGIN.left + ((x - x0) / (x1 - x0)) * f.plotW;
  const sy = (v) => MARGIN.top + (1 - (v - y0) / (y1 - y0)) * f.plotH;
  const yTicks = (logY ? logTicks(y0, y1) : linearTicks(y0, y1, 4))
    .map((v) => ({ value: v, label: format(logY ? 10 ** v : v) }));
  axes(f.root, f, linearTicks(x0, x1, Math.max(2, Math.floor(f.plotW / 70)), true), yTicks, sx, sy);

  for (const b of spans) {
    if (b.points.length < 2) continue;
    const upper = b.points.map(([x, , hi]) => `${sx(x).toFixed(1)},${sy(ty(hi)).toFixed(1)}`);
    const lower = b.points.slice().reverse().map(([x, lo]) => `${sx(x).toFixed(1)},${sy(ty(lo)).toFixed(1)}`);
    f.root.append(svg("path", { d: `M${upper.join("L")}L${lower.join("L")}Z`, fill: b.color, class: "chart-band" }));
  }
  for (const g of guides) {
    if (!Number.isFinite(g.y) || (logY && g.y <= 0)) continue;
    f.root.append(svg("line", { x1: MARGIN.left, x2: MARGIN.left + f.plotW, y1: sy(ty(g.y)), y2: sy(ty(g.y)),
      stroke: g.color, class: "chart-guide" }));
  }
  for (const s of lines) {
    if (s.points.length === 1) {
      const [x, y] = s.points[0];
      f.root.append(svg("circle", { cx: sx(x), cy: sy(ty(y)), r: 3, fill: s.color }));
      continue;
    }
    const d = s.points.map(([x, y], i) => `${i ? "L" : "M"}${sx(x).toFixed(1)},${sy(ty(y)).toFixed(1)}`).join("");
    const style = s.dashed ? "chart-line chart-dashed" : s.faint ? "chart-line chart-faint" : "chart-line";
    f.root.append(svg("path", { d, stroke: s.color, class: style }));
  }
  hover(el, f, lines, sx, sy, ty, format);
  el.replaceChildren(f.root);
  el.dataset.points = String(lines[0] ? lines[0].points.length : 0);
}

function hover(el, f, lines, sx, sy, ty, format) {
  const marker = svg("line", { y1: MARGIN.top, y2: MARGIN.top + f.plotH, class: "chart-cursor", visibility: "hidden" });
  const label = svg("text", { y: MARGIN.top + 10, class: "chart-readout", visibility: "hidden" });
  f.root.append(marker, label);
  const xs = [...new Set(lines.flatMap((s) => s.points.map((p) => p[0])))].sort((a, b) => a - b);
  f.root.addEventListener("mousemove", (event) => {
    const box = f.root.getBoundingClientRect();
    const px = ((event.clientX - box.left) / box.width) * f.width;
    let best = xs[0];
    for (const x of xs) if (Math.abs(sx(x) - px) < Math.abs(sx(best) - px)) best = x;
    const values = lines.map((s) => s.points.find((p) => p[0] === best)).filter(Boolean)
      .slice(0, 4).map((p) => format(p[1]));
    marker.setAttribute("x1", sx(best));
    marker.setAttribute("x2", sx(best));
    const right = sx(best) > MARGIN.left + f.plotW * 0.6;
    label.setAttribute("x", sx(best) + (right ? -6 : 6));
    label.setAttribute("text-anchor", right ? "end" : "start");
    label.textContent = `#${best}: ${values.join(", ")}`;
    marker.setAttribute("visibility", "visible");
    label.setAttribute("visibility", "visible");
  });
  f.root.addEventListener("mouseleave", () => {
    marker.setAttribute("visibility", "hidden");
    label.setAttribute("visibility", "hidden");
  });
}

/** Stacked bars: one bar per x, one segment per layer [{label, color, values}]. */
export function stackedBars(el, { x, layers, height = 210 }) {
  const f = frame(el, height);
  if (!x.length) return empty(el, f.root, f.width, height);
  const totals = x.map((_, i) => layers.reduce((sum, l) => sum + Math.max(0, l.values[i] || 0), 0));
  const top = extent(totals)[1] * 1.08 || 1;
  const [x0, x1] = [x[0] - 0.5, x[x.length - 1] + 0.5];
  const sx = (v) => MARGIN.left + ((v - x0) / (x1 - x0)) * f.plotW;
  const sy = (v) => MARGIN.top + (1 - v / top) * f.plotH;
  const yTicks = linearTicks(0, top, 4).map((v) => ({ value: v, label: fmtNum(v, 3) }));
  axes(f.root, f, linearTicks(x[0], Math.max(x[x.length - 1], x[0] + 1), Math.max(2, Math.floor(f.plotW / 70)), true),
    yTicks, sx, sy);
  const width = Math.min(28, f.plotW / Math.max(x1 - x0, 1));
  const gap = width > 6 ? 1.5 : 0;
  const bars = svg("g");
  x.forEach((iteration, i) => {
    let base = 0;
    for (const layer of layers) {
      const v = Math.max(0, layer.values[i] || 0);
      if (v > 0) {
        bars.append(svg("rect", { x: sx(iteration) - width / 2 + gap / 2, width: Math.max(0.6, width - gap),
          y: sy(base + v), height: Math.max(0, sy(base) - sy(base + v)), fill: layer.color },
        ));
        bars.lastChild.append(svg("title", {}, `#${iteration} ${layer.label}: ${fmtNum(v)} s`));
      }
      base += v;
    }
  });
  f.root.append(bars);
  el.replaceChildren(f.root);
  el.dataset.points = String(x.length);
}

export function legend(items) {
  return h("div.legend", items.map((item) =>
    h("span.legend-item", h(`span.swatch${item.dashed ? ".swatch-dashed" : ""}`,
      { style: { borderColor: item.color, background: item.dashed ? "transparent" : item.color } }), item.label)));
}

/** The diverging colour bar of a gradient preview: full blue = -scale, grey = 0, full red = +scale. */
export function colorBar(scale) {
  const s = Number.isFinite(scale) ? scale : null;
  return h("div.colorbar", { title: "colour of the RGB sum of dI/dp; full red = +scale" },
    h("div.colorbar-ramp", { style: { background: `linear-gradient(to right, ${DIVERGING.join(", ")})` } }),
    h("div.colorbar-labels", h("span", s === null ? "−" : `−${fmtNum(s, 3)}`), h("span", "0"),
      h("span", s === null ? "+" : `+${fmtNum(s, 3)}`)));
}
