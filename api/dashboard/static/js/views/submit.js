// #/submit: a new job. Scene, parameters (init, bounds, target values), target, method and budget;
// POST /v1/jobs, then the job page. A 422 problem puts each message next to its control.

import { ApiError, postJSON } from "../api.js";
import { clear, fmtNum, h, problemText } from "../dom.js";
import { clearErrors, errorSlot, field, fileBase64, numberInput, readNumber, readScalars, setPath, showErrors } from "./form.js";
import { scenePicker } from "./scene-picker.js";

const METHODS = [
  ["auto", "choose the whole recipe (method, optimizer, views per iteration); the plan says why"],
  ["ndrf-lhs", "NDRF, LHS query: dL_θ at the camera hits (most accurate)"],
  ["ndrf-rhs", "NDRF, RHS query: one bounce, then dL_θ at the secondary hits"],
  ["radiance-cache", "Radiance cache: L_φ at the secondary hits, no indirect derivative"],
  ["direct", "Direct illumination only (no fields)"],
  ["prb", "Mitsuba's Path Replay Backpropagation (reference)"],
];

// [path, label, placeholder (the API default), help]
const BUDGET = [
  ["iterations", "Iterations", "60"],
  ["learning_rate", "Learning rate", "0.05", "Adam, scene parameters"],
  ["render.spp", "Render spp", "1", "candidate render"],
  ["render.gradient_spp", "Gradient spp", "1"],
  ["seed", "Seed", "0"],
];
const TRAINING = [
  ["training.warmup_steps", "Warm-up steps", "400", "before the first gradient"],
  ["training.steps_per_iteration", "Steps per iteration", "20"],
  ["training.residual_points", "Residual points N", "4096"],
  ["training.incident_samples", "Incident samples M", "16"],
];
const ADVANCED = [
  ["final_learning_rate_ratio", "Final learning-rate ratio", "0.1"],
  ["render.max_depth", "Max path depth", "∞", "empty = unbounded, Russian roulette keeps it unbiased"],
  ["images_every", "Images every", "auto", "iterations; empty = 5% of the time"],
  ["checkpoint_every", "Checkpoint every", "10", "iterations"],
];

const fmtList = (values) => values.map((v) => fmtNum(v, 4)).join(", ");

function numbers(rows) {
  return h("div.field-grid", rows.map(([path, label, placeholder, help]) =>
    field(label, numberInput(path, { placeholder }), { path, help: help || `default ${placeholder}` })));
}

export function submitView(root) {
  let scene = null, alive = true;

  const paramBody = h("tbody");
  const paramSection = h("fieldset.card.form-section", { dataset: { field: "parameters" } },
    h("legend", "Parameters to recover"),
    h("p.help", "Tick the parameters to optimize. Values are one number (broadcast) or one per component, "
      + "separated by commas; empty init = the scene's value, empty bounds = [0, 1] for BSDFs, [0, ∞) for emitters."),
    h("div.table-scroll", h("table.table.table-compact.param-form", { dataset: { testid: "param-table" } },
      h("thead", h("tr", ["Parameter", "Scene value", "Init", "Bounds", h("span.target-col", "Target value")].map((c) => h("th", c)))),
      paramBody)),
    errorSlot("parameters"));

  const sensorsBox = h("div.field-grid");
  const syntheticSpp = numberInput("targets.synthetic.spp", { placeholder: "256" });
  const targetMode = h("div.radio-row",
    h("label.radio", h("input", { type: "radio", name: "target-mode", value: "synthetic", checked: true,
      dataset: { testid: "target-mode-synthetic" } }), "Synthetic: render it from the target values"),
    h("label.radio", h("input", { type: "radio", name: "target-mode", value: "images",
      dataset: { testid: "target-mode-images" } }), "Upload images (PNG, EXR or NPY, one per sensor)"));
  const syntheticPart = h("div.field-grid", field("Target spp", syntheticSpp, { path: "targets.synthetic.spp", help: "default 256" }));
  const imagesPart = h("div", { hidden: true }, sensorsBox);
  const targetSection = h("fieldset.card.form-section", { dataset: { field: "targets" } },
    h("legend", "Target"), targetMode, syntheticPart, imagesPart, errorSlot("targets"));

  const method = h("select.input", { dataset: { testid: "field-method" } },
    METHODS.map(([value, text]) => h("option", { value }, `${value} — ${text}`)));
  const name = h("input.input", { type: "text", placeholder: "optional label", maxlength: 200, dataset: { testid: "field-name" } });
  const width = numberInput("render.resolution.width", { placeholder: "film", step: 1 });
  const height = numberInput("render.resolution.height", { placeholder: "film", step: 1 });
  const loss = h("select.input", { dataset: { testid: "field-loss" } }, h("option", { value: "l2" }, "L2 (mean squared)"),
    h("option", { value: "l1" }, "L1 (mean absolute)"));

  const picker = scenePicker((loaded) => { scene = loaded; parameterRows(); sensorRows(); });
  const banner = h("div.alert.alert-error", { hidden: true, dataset: { testid: "form-banner" } });
  const button = h("button.btn.btn-primary.btn-large", { type: "submit", dataset: { testid: "submit-button" } }, "Submit job");

  const form = h("form.submit-form", { novalidate: true, dataset: { testid: "submit-form" } },
    h("div.page-head", h("h1", "New job"), h("span.spacer"), h("a.btn.btn-ghost", { href: "#/jobs" }, "Cancel")),
    banner,
    h("div.grid-2.form-top",
      h("fieldset.card.form-section", h("legend", "Job"),
        field("Name", name, { path: "name" }),
        field("Method", method, { path: "method", help: "how dI/dp is computed" })),
      picker.element),
    paramSection,
    targetSection,
    h("div.grid-2",
      h("fieldset.card.form-section", h("legend", "Budget"), numbers(BUDGET),
        h("div.field-grid", h("div.field", { dataset: { field: "render.resolution" } }, h("label.label", "Resolution (W × H)"),
          h("div.pair", width, h("span.muted", "×"), height), h("span.help", "empty = the scene's film"),
          errorSlot("render.resolution")))),
      h("fieldset.card.form-section", { dataset: { field: "training" } }, h("legend", "Training of the fields"),
        h("p.help", "Used by ndrf-lhs, ndrf-rhs and radiance-cache."), numbers(TRAINING), errorSlot("training"))),
    h("details.card.form-section.advanced", h("summary", "Advanced"),
      h("div.field-grid", field("Loss", loss, { path: "loss" })), numbers(ADVANCED)),
    h("div.form-actions", button));

  root.replaceChildren(form);
  targetMode.addEventListener("change", () => {
    const synthetic = targetMode.querySelector("input:checked").value === "synthetic";
    syntheticPart.hidden = !synthetic;
    imagesPart.hidden = synthetic;
    form.classList.toggle("no-target-values", !synthetic);
  });

  // ---------------------------------------------------------- parameter rows
  function parameterRows() {
    if (!scene) {
      paramBody.replaceChildren(h("tr", h("td.muted", { colSpan: 5 }, "Loading the scene…")));
      return;
    }
    paramBody.replaceChildren(...scene.info.parameters.map((p) => {
      const enable = h("input", { type: "checkbox", dataset: { testid: "param-enable" } });
      const input = (testid, placeholder, value = "") => h("input.input.input-small", { type: "text", placeholder, value,
        disabled: true, dataset: { testid } });
      const init = input("param-init", "scene value");
      const lower = input("param-lower", "0");
      const upper = input("param-upper", p.owner === "emitter" ? "∞" : "1");
      const target = input("param-target", "", fmtList(p.value));
      const row = h("tr.param-row", { dataset: { testid: "param-row", key: p.key } },
        h("td", h("label.check", enable, h("span.mono", p.key)), h("div.sub", `${p.owner_type} · ${p.size} scalar${p.size > 1 ? "s" : ""}`)),
        h("td.num.mono.small", fmtList(p.value)),
        h("td", { dataset: { role: "init" } }, init, errorSlot()),
        h("td", { dataset: { role: "bounds" } }, h("div.pair", lower, h("span.muted", "–"), upper), errorSlot()),
        h("td.target-col", { dataset: { field: `targets.synthetic.values.${p.key}` } }, target,
          errorSlot(`targets.synthetic.values.${p.key}`)));
      enable.addEventListener("change", () => {
        for (const el of [init, lower, upper, target]) el.disabled = !enable.checked;
        row.classList.toggle("selected", enable.checked);
      });
      return row;
    }));
  }

  function sensorRows() {
    const sensors = scene ? scene.info.sensors : [];
    width.placeholder = sensors.length ? String(sensors[0][0]) : "film";
    height.placeholder = sensors.length ? String(sensors[0][1]) : "film";
    sensorsBox.replaceChildren(...sensors.map(([w, hgt], s) => field(`Sensor ${s} (${w}×${hgt})`,
      h("input.file", { type: "file", accept: ".png,.exr,.npy", dataset: { testid: `target-image-${s}`, sensor: s } }))));
  }

  // ---------------------------------------------------------------- the job
  /** The job document, or throws a list of client-side {field, message}. */
  async function build() {
    const errors = [];
    const attempt = (path, read) => { try { return read(); } catch (error) { errors.push({ field: path, message: error.message }); } };
    const source = picker.source();
    if (!source) throw [{ field: "scene", message: "choose a scene and wait for its parameters to load" }];
    const synthetic = targetMode.querySelector("input:checked").value === "synthetic";
    const job = { scene: source, method: method.value, parameters: [], loss: loss.value };
    if (name.value.trim()) job.name = name.value.trim();

    const values = {};
    const rows = [...paramBody.querySelectorAll("tr.param-row")];
    rows.forEach((row) => { for (const cell of row.querySelectorAll("td[data-role]")) delete cell.dataset.field; });
    rows.filter((row) => row.querySelector("[data-testid=param-enable]").checked).forEach((row, i) => {
      const key = row.dataset.key, get = (testid) => row.querySelector(`[data-testid=${testid}]`);
      row.querySelector("td[data-role=init]").dataset.field = `parameters[${i}].init`;
      row.querySelector("td[data-role=bounds]").dataset.field = `parameters[${i}].bounds`;
      const parameter = { key };
      const init = attempt(`parameters[${i}].init`, () => readScalars(get("param-init")));
      if (init !== undefined) parameter.init = init;
      const lower = attempt(`parameters[${i}].bounds`, () => readNumber(get("param-lower")));
      const upper = attempt(`parameters[${i}].bounds`, () => readNumber(get("param-upper")));
      if (lower !== undefined && upper !== undefined) parameter.bounds = [lower, upper];
      else if (lower !== undefined || upper !== undefined) errors.push({ field: `parameters[${i}].bounds`, message: "give both bounds, or neither" });
      if (synthetic) {
        const path = `targets.synthetic.values.${key}`;
        const target = attempt(path, () => readScalars(get("param-target")));
        if (target === undefined) errors.push({ field: path, message: "a target value is needed" });
        values[key] = target;
      }
      job.parameters.push(parameter);
    });
    if (!job.parameters.length) errors.push({ field: "parameters", message: "tick at least one parameter" });

    if (synthetic) {
      job.targets = { synthetic: { values } };
      const spp = attempt("targets.synthetic.spp", () => readNumber(syntheticSpp));
      if (spp !== undefined) job.targets.synthetic.spp = spp;
    } else {
      const inputs = [...sensorsBox.querySelectorAll("input[type=file]")];
      inputs.forEach((input) => { delete input.closest(".field").dataset.field; });
      const chosen = inputs.filter((input) => input.files.length);
      chosen.forEach((input, j) => { input.closest(".field").dataset.field = `targets.images[${j}]`; });
      job.targets = { images: await Promise.all(chosen.map(async (input) =>
        ({ sensor: Number(input.dataset.sensor), data: await fileBase64(input.files[0]) }))) };
      if (!chosen.length) errors.push({ field: "targets", message: "choose a target image for at least one sensor" });
    }

    for (const input of form.querySelectorAll("input[data-path]")) {
      if (input.dataset.path.startsWith("render.resolution") || input === syntheticSpp) continue;
      const value = attempt(input.dataset.path, () => readNumber(input));
      if (value !== undefined) setPath(job, input.dataset.path, value);
    }
    const w = attempt("render.resolution", () => readNumber(width));
    const hgt = attempt("render.resolution", () => readNumber(height));
    if (w !== undefined || hgt !== undefined) setPath(job, "render.resolution", [w ?? hgt, hgt ?? w]);
    if (errors.length) throw errors;
    return job;
  }

  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    clearErrors(form);
    banner.hidden = true;
    button.disabled = true;
    button.textContent = "Checking the job…";
    try {
      const job = await build();
      const accepted = await postJSON("/v1/jobs", job);
      if (alive) location.hash = `#/jobs/${encodeURIComponent(accepted.id)}`;
    } catch (error) {
      if (!alive) return;
      const errors = Array.isArray(error) ? error : error instanceof ApiError ? error.errors : [];
      const rest = showErrors(form, errors);
      const headline = Array.isArray(error) ? "Please correct the highlighted fields." : problemText(error);
      clear(banner, h("strong", errors.length && !rest.length ? "The job was refused: see the highlighted fields." : headline),
        rest.length ? h("ul", rest.map((e) => h("li", h("span.mono", e.field), `: ${e.message}`))) : null);
      banner.hidden = false;
    } finally {
      button.disabled = false;
      button.textContent = "Submit job";
    }
  });

  parameterRows();
  return () => { alive = false; };
}
