// The job's plan, rendered generically: objects as definition lists, lists of objects as tables,
// so keys added later (an `effects` section with a reason per decision) show up without changes.

import { fmtNum, h } from "../dom.js";

const FIRST = ["method", "auto", "fields", "effects", "warnings"];
const INLINE_ITEMS = 16;

function title(key) {
  return String(key).replace(/_/g, " ");
}

function primitive(value) {
  if (value === null || value === undefined) return h("span.muted", "—");
  if (typeof value === "boolean") return h(`span.pill.${value ? "pill-on" : "pill-off"}`, value ? "yes" : "no");
  if (typeof value === "number") return h("span.num", fmtNum(value));
  return h("span", String(value));
}

function isPrimitive(value) {
  return value === null || typeof value !== "object";
}

function list(values) {
  if (!values.length) return h("span.muted", "none");
  const shown = values.slice(0, INLINE_ITEMS).map((v) => (typeof v === "number" ? fmtNum(v) : v === null ? "—" : String(v)));
  const rest = values.length - shown.length;
  return h("span.mono.plan-list", shown.join(", "), rest > 0 ? h("span.muted", ` … (${values.length} values)`) : null);
}

function table(rows) {
  const columns = [...new Set(rows.flatMap((r) => Object.keys(r)))];
  return h("table.table.table-compact", h("thead", h("tr", columns.map((c) => h("th", title(c))))),
    h("tbody", rows.map((r) => h("tr", columns.map((c) => h("td", value(r[c], 2)))))));
}

function value(v, depth) {
  if (isPrimitive(v)) return primitive(v);
  if (Array.isArray(v)) {
    if (v.every(isPrimitive)) return list(v);
    if (v.every((item) => item && typeof item === "object" && !Array.isArray(item))) return table(v);
    return h("ol.plan-items", v.map((item) => h("li", value(item, depth + 1))));
  }
  const entries = Object.entries(v);
  const dl = h("dl.plan", entries.map(([k, item]) => [h("dt", title(k)), h("dd", value(item, depth + 1))]));
  const nested = entries.filter(([, item]) => item && typeof item === "object").length;
  if (depth >= 1 && (entries.length > 6 || nested > 1)) {
    return h("details.plan-details", h("summary", `${entries.length} settings`), dl);
  }
  return dl;
}

/** A definition list of the plan, its most telling keys first. */
export function planView(plan) {
  if (!plan) return h("p.muted", "The plan is written when the job starts.");
  const keys = [...FIRST.filter((k) => k in plan), ...Object.keys(plan).filter((k) => !FIRST.includes(k))];
  return h("dl.plan.plan-top", { dataset: { testid: "job-plan" } },
    keys.map((k) => [h("dt", title(k)), h("dd", value(plan[k], 0))]));
}
