// The runs table of the experiment page: sortable by any column, filtered by text and status,
// each run linking to its job page, with a "compare" checkbox (two runs side by side).

import { fmtDuration, fmtNum, h, statusBadge } from "../dom.js";

const show = (value) => (value === null || value === undefined ? "—"
  : typeof value === "number" ? fmtNum(value, 4) : typeof value === "string" ? value : JSON.stringify(value));

/** Columns: [key, title, value(row), numeric]. */
function columns(fields) {
  return [
    ["index", "#", (r) => r.index, true],
    ...fields.map((f) => [`varied:${f}`, f, (r) => r.varied[f], false]),
    ["seed", "seed", (r) => r.seed, true],
    ["status", "status", (r) => r.status, false],
    ["iterations", "iterations", (r) => r.iterations, true],
    ["final_parameter_error", "final error", (r) => r.final_parameter_error, true],
    ["final_loss", "final loss", (r) => r.final_loss, true],
    ["seconds", "compute s", (r) => r.seconds, true],
    ["time_to_error", "time to error", (r) => r.time_to_error, true],
  ];
}

function compare(a, b) {
  if (a === b) return 0;
  if (a === null || a === undefined) return 1;
  if (b === null || b === undefined) return -1;
  if (typeof a === "number" && typeof b === "number") return a - b;
  return JSON.stringify(a).localeCompare(JSON.stringify(b), undefined, { numeric: true });
}

export function runsTable({ onSelect }) {
  const state = { rows: [], fields: [], sort: { key: "index", dir: 1 }, query: "", status: "", selected: [] };
  const head = h("thead");
  const body = h("tbody");
  const query = h("input.input.input-small", { type: "search", placeholder: "filter: any value, e.g. prb",
    dataset: { testid: "runs-filter" }, oninput: () => { state.query = query.value.trim().toLowerCase(); draw(); } });
  const status = h("select.input.select-small", { dataset: { testid: "runs-status-filter" },
    onchange: () => { state.status = status.value; draw(); } },
  ["", "pending", "queued", "running", "succeeded", "failed", "canceled"].map((s) => h("option", { value: s }, s || "any status")));
  const count = h("span.muted.small", { dataset: { testid: "runs-count" } });
  const table = h("table.table.table-compact.runs-table", { dataset: { testid: "runs-table" } }, head, body);
  const element = h("div", h("div.toolbar", query, status, count), h("div.table-scroll", table));

  function visible() {
    const cols = columns(state.fields);
    return state.rows.filter((r) => (!state.status || r.status === state.status)
      && (!state.query || cols.some(([, , value]) => String(show(value(r))).toLowerCase().includes(state.query))
        || (r.job || "").includes(state.query)));
  }

  function draw() {
    const cols = columns(state.fields);
    const current = cols.find(([key]) => key === state.sort.key) || cols[0];
    head.replaceChildren(h("tr", h("th", "compare"), cols.map(([key, title]) => h("th.sortable", {
      dataset: { testid: "sort-header", key, dir: key === state.sort.key ? (state.sort.dir > 0 ? "asc" : "desc") : "" },
      onclick: () => {
        state.sort = { key, dir: state.sort.key === key ? -state.sort.dir : 1 };
        draw();
      },
    }, title, key === state.sort.key ? (state.sort.dir > 0 ? " ▲" : " ▼") : ""))));
    const rows = visible().sort((a, b) => state.sort.dir * compare(current[2](a), current[2](b)) || a.index - b.index);
    count.textContent = `${rows.length} of ${state.rows.length} runs`;
    body.replaceChildren(...rows.map((r) => {
      const box = h("input", { type: "checkbox", checked: state.selected.includes(r.index), disabled: !r.job,
        dataset: { testid: "compare-pick" }, onchange: () => toggle(r.index, box.checked) });
      return h("tr", { dataset: { testid: "run-row", index: r.index, status: r.status } },
        h("td", box),
        cols.map(([key, , value, numeric]) => {
          if (key === "index") {
            return h("td.num", r.job ? h("a", { href: `#/jobs/${r.job}`, dataset: { testid: "run-link" } }, `#${r.index}`) : `#${r.index}`);
          }
          if (key === "status") return h("td", statusBadge(r.status), r.error ? h("div.sub.text-error", { title: r.error }, r.error.slice(0, 60)) : null);
          if (key === "seconds" || key === "time_to_error") return h("td.num", value(r) === null ? "—" : fmtDuration(value(r)));
          if (key === "iterations") return h("td.num", `${r.iterations} / ${show(r.iterations_planned)}`);
          return h(numeric ? "td.num" : "td", { dataset: { key } }, show(value(r)));
        }));
    }));
  }

  function toggle(index, on) {
    state.selected = state.selected.filter((i) => i !== index);
    if (on) state.selected.push(index);
    if (state.selected.length > 2) state.selected = state.selected.slice(-2);
    draw();
    onSelect(state.selected.map((i) => state.rows.find((r) => r.index === i)).filter(Boolean));
  }

  return {
    element,
    update(rows, fields) {
      state.rows = rows;
      state.fields = fields;
      draw();
    },
    select(indices) {
      state.selected = indices.slice(-2);
      draw();
      onSelect(state.selected.map((i) => state.rows.find((r) => r.index === i)).filter(Boolean));
    },
  };
}
