// Small DOM and formatting helpers shared by the views.

/**
 * h("div.card#id", {attrs}, ...children): an element. Attributes starting with "on" are listeners,
 * `dataset`/`style` objects are merged, false/null attributes are skipped; children may be
 * strings, nodes, arrays or null.
 */
export function h(tag, attrs = {}, ...children) {
  const [name, ...classes] = tag.split(".");
  const [base, id] = name.split("#");
  const el = document.createElement(base || "div");
  if (id) el.id = id;
  if (classes.length) el.className = classes.join(" ");
  if (attrs === null || attrs === undefined) attrs = {};
  else if (attrs instanceof Node || typeof attrs !== "object" || Array.isArray(attrs)) {
    children.unshift(attrs);
    attrs = {};
  }
  for (const [key, value] of Object.entries(attrs)) {
    if (value === false || value === null || value === undefined) continue;
    if (key.startsWith("on") && typeof value === "function") el.addEventListener(key.slice(2), value);
    else if (key === "dataset" || key === "style") Object.assign(el[key], value);
    else if (key === "class") el.className = [el.className, value].filter(Boolean).join(" ");
    else if (key in el && typeof value !== "string") el[key] = value;
    else el.setAttribute(key, value === true ? "" : value);
  }
  append(el, children);
  return el;
}

function append(el, children) {
  for (const child of children.flat(Infinity)) {
    if (child === null || child === undefined || child === false) continue;
    el.append(child instanceof Node ? child : String(child));
  }
}

export function clear(el, ...children) {
  el.replaceChildren();
  append(el, children);
  return el;
}

export function statusBadge(status, attrs = {}) {
  return h(`span.badge.badge-${status || "unknown"}`, attrs, status || "unknown");
}

/** A number, compactly: 4 significant digits, exponent form when very small or large. */
export function fmtNum(x, digits = 4) {
  if (x === null || x === undefined || Number.isNaN(x)) return "—";
  if (!Number.isFinite(x)) return x > 0 ? "∞" : "−∞";
  if (x === 0) return "0";
  const a = Math.abs(x);
  if (a >= 1e5 || a < 1e-3) return x.toExponential(digits - 2).replace("+", "");
  return String(Number(x.toPrecision(digits)));
}

/** Seconds as "42 s", "3 min 05 s", "1 h 02 min". */
export function fmtDuration(seconds) {
  if (seconds === null || seconds === undefined || !Number.isFinite(seconds)) return "—";
  const s = Math.max(0, Math.round(seconds));
  if (s < 60) return `${seconds < 10 ? Math.max(0, seconds).toFixed(1) : s} s`;
  const m = Math.floor(s / 60);
  if (m < 60) return `${m} min ${String(s % 60).padStart(2, "0")} s`;
  return `${Math.floor(m / 60)} h ${String(m % 60).padStart(2, "0")} min`;
}

export function fmtTime(iso) {
  if (!iso) return "—";
  const date = new Date(iso);
  if (Number.isNaN(date.getTime())) return iso;
  const sameDay = date.toDateString() === new Date().toDateString();
  return sameDay ? date.toLocaleTimeString([], { hour: "2-digit", minute: "2-digit", second: "2-digit" })
    : date.toLocaleString([], { dateStyle: "short", timeStyle: "short" });
}

/** max |value - target| over the scalars both dicts name (null when there is no target). */
export function maxAbsError(values, target) {
  if (!values || !target) return null;
  let worst = null;
  for (const [label, t] of Object.entries(target)) {
    if (typeof values[label] !== "number" || typeof t !== "number") continue;
    worst = Math.max(worst ?? 0, Math.abs(values[label] - t));
  }
  return worst;
}

/** A problem (ApiError) as one line of text. */
export function problemText(error) {
  if (error && error.problem) return [error.problem.title, error.problem.detail].filter(Boolean).join(": ");
  return String(error && error.message ? error.message : error);
}
