// Form helpers of the submit page: labelled fields, values read from inputs, files as base64,
// and problem+json field errors shown next to the control whose data-field matches the path.

import { h } from "../dom.js";

/** A labelled control; `path` (the JSON path the API names in errors) goes on the wrapper. */
export function field(label, control, { path, help, wide = false } = {}) {
  return h(`div.field${wide ? ".field-wide" : ""}`, { dataset: path ? { field: path } : {} },
    h("label.label", label), control, help ? h("span.help", help) : null, errorSlot(path));
}

export function errorSlot(path) {
  return h("span.field-error", { hidden: true, dataset: { testid: "field-error", for: path || "" } });
}

/** <input type=number> whose value goes to `path` of the job when filled. */
export function numberInput(path, { placeholder, step = "any", min } = {}) {
  return h("input.input", { type: "number", step, min, placeholder, inputmode: "decimal",
    dataset: { testid: `field-${path}`, path } });
}

/** The number typed in an input: undefined when empty; throws a message for what is not a number. */
export function readNumber(input) {
  if (input.validity && input.validity.badInput) throw new Error("not a number");
  const text = input.value.trim();
  if (!text) return undefined;
  const value = Number(text);
  if (!Number.isFinite(value)) throw new Error("not a number");
  return value;
}

/** "0.5" -> 0.5, "0.57, 0.04 0.04" -> [0.57, 0.04, 0.04]; undefined when empty. */
export function readScalars(input) {
  const parts = input.value.split(/[\s,;]+/).filter(Boolean);
  if (!parts.length) return undefined;
  const values = parts.map(Number);
  if (values.some((v) => !Number.isFinite(v))) throw new Error("a number, or one number per component separated by commas");
  return values.length === 1 ? values[0] : values;
}

/** Set `value` at a dotted path of `target` ("render.spp"), creating the objects on the way. */
export function setPath(target, path, value) {
  const keys = path.split(".");
  let node = target;
  for (const key of keys.slice(0, -1)) node = node[key] ??= {};
  node[keys[keys.length - 1]] = value;
}

export function fileBase64(file) {
  return new Promise((resolve, reject) => {
    const reader = new FileReader();
    reader.onload = () => resolve(String(reader.result).slice(String(reader.result).indexOf(",") + 1));
    reader.onerror = () => reject(reader.error);
    reader.readAsDataURL(file);
  });
}

function parent(path) {
  const trimmed = path.replace(/(\[[^\]]*\]|\.[^.[\]]*)$/, "");
  return trimmed === path ? "" : trimmed;
}

function visible(el) {
  return !el.closest("[hidden]") && !el.closest("fieldset:disabled");
}

export function clearErrors(form) {
  for (const slot of form.querySelectorAll(".field-error")) { slot.hidden = true; slot.textContent = ""; }
  for (const el of form.querySelectorAll(".has-error")) el.classList.remove("has-error");
}

/** Show each {field, message} next to the closest matching control; returns those with no control. */
export function showErrors(form, errors) {
  const unmatched = [];
  let first = null;
  for (const error of errors) {
    let path = error.field || "", target = null;
    while (path && !target) {
      const candidate = [...form.querySelectorAll("[data-field]")].find((el) => el.dataset.field === path && visible(el));
      if (candidate) target = candidate;
      else path = parent(path);
    }
    if (!target) { unmatched.push(error); continue; }
    const slot = target.querySelector(":scope > .field-error") || target.appendChild(errorSlot(path));
    slot.dataset.for = target.dataset.field;
    slot.textContent = slot.hidden || !slot.textContent ? error.message : `${slot.textContent}; ${error.message}`;
    slot.hidden = false;
    target.classList.add("has-error");
    first ??= target;
  }
  if (first) {
    first.scrollIntoView({ block: "center", behavior: "smooth" });
    first.querySelector("input, select, textarea")?.focus({ preventScroll: true });
  }
  return unmatched;
}
