// The scene of a new job: a built-in scene, or an uploaded Mitsuba XML with the files it names
// (paths relative to the XML; choosing a folder keeps its layout). Asks the API for the scene's
// optimizable parameters and sensors whenever the choice changes.

import { getJSON, postJSON } from "../api.js";
import { h, problemText } from "../dom.js";
import { clearErrors, errorSlot, field, fileBase64, showErrors } from "./form.js";

function radio(name, value, label, testid, checked) {
  return h("label.radio", h("input", { type: "radio", name, value, checked, dataset: { testid } }), label);
}

/** onChange({source, info}) when a scene is loaded, onChange(null) while there is none. */
export function scenePicker(onChange) {
  let entries = [], loaded = null, token = 0;

  const builtin = h("select.input", { dataset: { testid: "field-scene.builtin" } });
  const description = h("span.help");
  const files = h("input.file", { type: "file", multiple: true, accept: ".xml,.obj,.ply,.serialized,.png,.jpg,.jpeg,.exr,.hdr",
    dataset: { testid: "field-scene.files" } });
  const folder = h("input.file", { type: "file", webkitdirectory: true, dataset: { testid: "field-scene.folder" } });
  const main = h("select.input", { dataset: { testid: "field-scene.xml" } });
  const list = h("ul.file-list");
  const status = h("p.help.scene-status", { dataset: { testid: "scene-status" } });
  const builtinPart = h("div.scene-part", field("Built-in scene", builtin, { path: "scene.builtin" }), description);
  const uploadPart = h("div.scene-part", { hidden: true },
    h("div.field-row",
      field("Scene files", files, { help: "the XML and the files it names" }),
      field("…or a folder", folder, { help: "keeps sub-folders (meshes/, textures/)" })),
    h("div.field-row", field("Main XML", main, { path: "scene.xml" }),
      h("div.field.field-wide", { dataset: { field: "scene.files" } }, h("label.label", "Uploaded with it"), list,
        errorSlot("scene.files"))));
  const modes = h("div.radio-row",
    radio("scene-mode", "builtin", "Built-in scene", "scene-mode-builtin", true),
    radio("scene-mode", "upload", "Upload a Mitsuba 3 XML", "scene-mode-upload", false));

  const element = h("fieldset.card.form-section", { dataset: { field: "scene" } },
    h("legend", "Scene"), modes, builtinPart, uploadPart, status, errorSlot("scene"));

  const mode = () => element.querySelector("input[name=scene-mode]:checked").value;

  function pick(input) {
    entries = [...input.files].map((file) => ({ file, path: file.webkitRelativePath || file.name }));
    (input === files ? folder : files).value = "";
    const xmls = entries.filter((e) => e.path.toLowerCase().endsWith(".xml"))
      .sort((a, b) => a.path.split("/").length - b.path.split("/").length || (b.path.endsWith("scene.xml") - a.path.endsWith("scene.xml")));
    main.replaceChildren(...xmls.map((e) => h("option", { value: e.path }, e.path)));
    load();
  }

  /** The files other than the main XML, by path relative to the XML's folder. */
  function relative() {
    const dir = main.value.includes("/") ? main.value.slice(0, main.value.lastIndexOf("/") + 1) : "";
    const inside = [], outside = [];
    for (const entry of entries) {
      if (entry.path === main.value) continue;
      if (entry.path.startsWith(dir)) inside.push({ ...entry, relative: entry.path.slice(dir.length) });
      else outside.push(entry);
    }
    list.replaceChildren(...inside.map((e) => h("li.mono", e.relative)),
      ...outside.map((e) => h("li.mono.muted", { title: "not under the XML's folder: not sent" }, `${e.path} (ignored)`)));
    if (!inside.length && !outside.length) list.append(h("li.muted", "no other files"));
    return inside;
  }

  async function load() {
    const mine = ++token;
    loaded = null;
    onChange(null);
    clearErrors(element);
    try {
      let source;
      if (mode() === "builtin") {
        if (!builtin.value) return;
        source = { builtin: builtin.value };
        const option = builtin.selectedOptions[0];
        description.textContent = option ? option.title : "";
      } else {
        const xml = entries.find((e) => e.path === main.value);
        const others = relative();
        if (!xml) { status.textContent = "Choose the scene's XML file and the files it names."; return; }
        const encoded = await Promise.all(others.map(async (e) => [e.relative, await fileBase64(e.file)]));
        source = { xml: await xml.file.text(), files: Object.fromEntries(encoded) };
      }
      status.textContent = "Loading the scene's parameters…";
      const info = source.builtin
        ? await getJSON(`/v1/scenes/${encodeURIComponent(source.builtin)}/parameters`)
        : await postJSON("/v1/scenes/parameters", source);
      if (mine !== token) return;
      loaded = { source, info };
      const films = info.sensors.map(([w, hgt]) => `${w}×${hgt}`).join(", ");
      status.textContent = `${info.parameters.length} optimizable parameter(s); ${info.sensors.length} sensor(s): ${films}.`;
      onChange(loaded);
    } catch (error) {
      if (mine !== token) return;
      status.textContent = `The scene could not be loaded: ${problemText(error)}`;
      if (error.errors) showErrors(element, error.errors);
    }
  }

  modes.addEventListener("change", () => {
    const upload = mode() === "upload";
    builtinPart.hidden = upload;
    uploadPart.hidden = !upload;
    load();
  });
  builtin.addEventListener("change", load);
  main.addEventListener("change", load);
  files.addEventListener("change", () => pick(files));
  folder.addEventListener("change", () => pick(folder));

  getJSON("/v1/scenes").then((scenes) => {
    builtin.replaceChildren(...scenes.map((s) => h("option", { value: s.name, title: s.description }, s.name)));
    load();
  }).catch((error) => { status.textContent = `Could not list the scenes: ${problemText(error)}`; });

  return { element, source: () => loaded && loaded.source };
}
