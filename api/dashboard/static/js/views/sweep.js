// #/sweep/<job id>: "sweep this job". Pick fields of an existing job and the values to try, the
// seeds and how many runs at once; POST /v1/experiments with base_job = that job. A 422 names
// the run and the field (runs[3].learning_rate): the message goes next to that field's row.

import { ApiError, getJSON, postJSON } from "../api.js";
import { clear, fmtNum, h, problemText } from "../dom.js";

const METHODS = ["ndrf-lhs", "ndrf-rhs", "radiance-cache", "direct", "prb"];
const FIELDS = [
  ["learning_rate", "Adam learning rate"],
  ["iterations", "iterations"],
  ["render.spp", "candidate spp", (plan) => plan?.render?.spp],
  ["render.gradient_spp", "gradient spp", (plan) => plan?.render?.gradient_spp],
  ["training.warmup_steps", "warm-up steps", (plan) => plan?.training?.warmup_steps],
  ["training.steps_per_iteration", "training steps per iteration", (plan) => plan?.training?.steps_per_iteration],
  ["training.residual_points", "residual points N", (plan) => plan?.training?.residual_points],
  ["training.incident_samples", "incident samples M", (plan) => plan?.training?.incident_samples],
  ["final_learning_rate_ratio", "final learning-rate ratio"],
];

/** "0.01, 0.05" -> [0.01, 0.05]; "[0.2,0.2,0.2]; 0.5" -> [[0.2,0.2,0.2], 0.5] (";" separates when present). */
export function parseValues(text) {
  const parts = (text.includes(";") ? text.split(";") : text.split(",")).map((p) => p.trim()).filter(Boolean);
  return parts.map((p) => { try { return JSON.parse(p); } catch { return p; } });
}

function fieldPath(error) {
  return (error.field || "").replace(/^runs\[\d+\]\./, "").replace(/^grid\./, "");
}

export function sweepView(root, jobId) {
  let alive = true, job = null;
  const rows = h("tbody");
  const name = h("input.input", { type: "text", maxlength: 200, dataset: { testid: "sweep-name" } });
  const seeds = h("input.input", { type: "text", value: "0, 1, 2", dataset: { testid: "sweep-seeds" } });
  const concurrent = h("input.input", { type: "number", min: 1, max: 64, value: 2, dataset: { testid: "sweep-max-concurrent" } });
  const targetError = h("input.input", { type: "number", step: "any", value: 0.05, dataset: { testid: "sweep-target-error" } });
  const metric = h("select.input", { dataset: { testid: "sweep-objective" } },
    ["parameter_error", "loss", "time_to_error", "seconds"].map((m) => h("option", { value: m }, m)));
  const banner = h("div.alert.alert-error", { hidden: true, dataset: { testid: "sweep-banner" } });
  const count = h("span.muted", { dataset: { testid: "sweep-count" } });
  const button = h("button.btn.btn-primary.btn-large", { type: "submit", dataset: { testid: "sweep-submit" } }, "Create experiment");
  const form = h("form.submit-form", { novalidate: true },
    h("div.page-head", h("a.back", { href: `#/jobs/${jobId}` }, "← Job"), h("h1", "Sweep this job"), h("span.spacer")),
    banner,
    h("fieldset.card.form-section", h("legend", "Experiment"),
      h("div.field-grid",
        h("div.field", h("label.label", "Name"), name),
        h("div.field", { dataset: { field: "seeds" } }, h("label.label", "Seeds"), seeds, h("span.help", "each configuration runs once per seed")),
        h("div.field", { dataset: { field: "max_concurrent" } }, h("label.label", "Runs at once"), concurrent),
        h("div.field", h("label.label", "Objective"), metric),
        h("div.field", { dataset: { field: "target_error" } }, h("label.label", "Target error"), targetError,
          h("span.help", "for the time-to-error column")))),
    h("fieldset.card.form-section", h("legend", "What to vary"),
      h("p.help", "Tick a field and list its values, separated by commas (or by ';' when a value is a list, "
        + "e.g. [0.2,0.2,0.2]; [0.5,0.5,0.5]). Every combination runs, once per seed."),
      h("div.table-scroll", h("table.table.table-compact.param-form", h("thead", h("tr", ["vary", "field", "this job", "values"].map((t) => h("th", t)))), rows))),
    h("div.form-actions", count, button));
  clear(root, form);

  function row(path, label, current, control) {
    const enable = h("input", { type: "checkbox", dataset: { testid: "sweep-enable" } });
    const slot = h("span.field-error", { hidden: true, dataset: { testid: "field-error" } });
    const tr = h("tr.param-row", { dataset: { testid: "sweep-row", path } },
      h("td", enable), h("td", h("span.mono", path), h("div.sub", label)), h("td.num.mono.small", current ?? "—"),
      h("td", { dataset: { field: path } }, control, slot));
    enable.addEventListener("change", () => { tr.classList.toggle("selected", enable.checked); estimate(); });
    control.addEventListener("input", () => { if (!enable.checked) { enable.checked = true; tr.classList.add("selected"); } estimate(); });
    control.addEventListener("change", estimate);
    return tr;
  }

  function build() {
    const grid = {};
    for (const tr of rows.querySelectorAll("tr.param-row")) {
      if (!tr.querySelector("[data-testid=sweep-enable]").checked) continue;
      const path = tr.dataset.path;
      const methods = [...tr.querySelectorAll("input[data-method]")];
      grid[path] = methods.length ? methods.filter((m) => m.checked).map((m) => m.dataset.method)
        : parseValues(tr.querySelector("input[data-testid=sweep-values]").value);
    }
    const seedList = seeds.value.split(/[\s,;]+/).filter(Boolean).map(Number);
    const spec = { base_job: jobId, grid, seeds: seedList, max_concurrent: Number(concurrent.value) || 1,
      target_error: Number(targetError.value) || 0.05, objective: { metric: metric.value, goal: "min" } };
    if (name.value.trim()) spec.name = name.value.trim();
    return spec;
  }

  function estimate() {
    const spec = build();
    const runs = Object.values(spec.grid).reduce((n, values) => n * Math.max(values.length, 0), 1) * Math.max(spec.seeds.length, 1);
    count.textContent = `${runs} run${runs === 1 ? "" : "s"}`;
  }

  async function load() {
    try {
      job = await getJSON(`/v1/jobs/${encodeURIComponent(jobId)}`);
    } catch (error) {
      if (alive) clear(root, h("div.card.empty-state", h("h2", "No such job"), h("p", problemText(error))));
      return;
    }
    if (!alive) return;
    name.value = `sweep of ${job.name || job.id}`.slice(0, 200);
    const plan = job.plan || {};
    const methodBoxes = h("div.radio-row", METHODS.map((m) => h("label.check",
      h("input", { type: "checkbox", checked: m === job.method, dataset: { method: m, testid: `sweep-method-${m}` } }), m)));
    const list = [row("method", "gradient method", job.method, methodBoxes)];
    const current = { iterations: job.iterations };
    for (const [path, label, read] of FIELDS) {
      const value = read ? read(plan) : current[path];
      list.push(row(path, label, value === undefined ? null : fmtNum(value, 4),
        h("input.input.input-small", { type: "text", placeholder: "e.g. 0.02, 0.05, 0.1", dataset: { testid: "sweep-values" } })));
    }
    (plan.keys || []).forEach((key, i) => {
      list.push(row(`parameters[${key}].init`, `initial value of parameter ${i}`, null,
        h("input.input.input-small", { type: "text", placeholder: "0.2; [0.1,0.5,0.5]", dataset: { testid: "sweep-values" } })));
    });
    rows.replaceChildren(...list);
    estimate();
  }

  seeds.addEventListener("input", estimate);

  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    banner.hidden = true;
    for (const slot of form.querySelectorAll(".field-error")) { slot.hidden = true; slot.textContent = ""; }
    for (const el of form.querySelectorAll(".has-error")) el.classList.remove("has-error");
    button.disabled = true;
    button.textContent = "Checking every run…";
    try {
      const accepted = await postJSON("/v1/experiments", build());
      if (alive) location.hash = `#/experiments/${accepted.id}`;
    } catch (error) {
      if (!alive) return;
      const errors = error instanceof ApiError ? error.errors : [];
      const rest = [];
      for (const e of errors) {
        const path = fieldPath(e);
        const cell = [...form.querySelectorAll("[data-field]")].find((el) => el.dataset.field === path
          || path.startsWith(`${el.dataset.field}.`) || path.startsWith(`${el.dataset.field}[`));
        const slot = cell?.querySelector(".field-error") || (cell && cell.appendChild(h("span.field-error", { dataset: { testid: "field-error" } })));
        if (slot) {
          slot.textContent = e.message;
          slot.hidden = false;
          cell.classList.add("has-error");
        } else rest.push(e);
      }
      clear(banner, h("strong", problemText(error)),
        rest.length ? h("ul", rest.map((e) => h("li", h("span.mono", e.field), `: ${e.message}`))) : null);
      banner.hidden = false;
    } finally {
      button.disabled = false;
      button.textContent = "Create experiment";
    }
  });

  load();
  return () => { alive = false; };
}
