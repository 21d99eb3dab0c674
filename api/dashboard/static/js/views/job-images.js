// The images of a job: the render of an iteration beside the target, and the gradient image of
// every scalar with its colour bar (a texture job: each texture and its gradient texture instead). A slider picks among the iterations that wrote images; at its
// right end it follows the newest one.

import { authUrl } from "../api.js";
import { colorBar } from "../charts.js";
import { h } from "../dom.js";

function picture(testid, alt) {
  const img = h("img.pixelated", { alt, dataset: { testid } });
  img.addEventListener("load", () => img.closest("figure")?.classList.remove("missing"));
  img.addEventListener("error", () => img.closest("figure")?.classList.add("missing"));
  return img;
}

/** Point an <img> at a URL; `retry` asks again for an image that failed to load. */
function setSource(img, url, retry = false) {
  if (img.dataset.src === url && !(retry && img.closest("figure.missing"))) return;
  img.dataset.src = url;
  img.src = authUrl(url);
}

export function imagesPanel(jobId) {
  const base = `/v1/jobs/${encodeURIComponent(jobId)}`;
  let withImages = [], index = -1, follow = true, labels = [], sensors = [0], sensor = 0, started = false;
  let textureKeys = [];

  const render = picture("render-image", "candidate render");
  const target = picture("target-image", "target image");
  const renderCaption = h("figcaption", "Render");
  // a geometry job's silhouettes: the moved shapes now (orange) over the target, its outline (cyan)
  const silhouette = picture("silhouette-image", "silhouettes");
  const silhouetteFigure = h("figure.image-figure.missing", { hidden: true }, silhouette,
    h("figcaption", "Silhouette: now (orange), target (cyan)"));
  let geometry = false;
  const slider = h("input.slider", { type: "range", min: 0, max: 0, step: 1, value: 0, disabled: true,
    dataset: { testid: "iteration-slider" }, "aria-label": "iteration of the images" });
  const sliderLabel = h("span.slider-label.num", { dataset: { testid: "slider-iteration" } }, "—");
  const sensorPick = h("select.select-small", { hidden: true, "aria-label": "sensor",
    onchange: () => { sensor = Number(sensorPick.value); show(true); } });
  const grid = h("div.gradient-grid", { dataset: { testid: "gradient-grid" } });
  const stackLink = h("a.link-small", { download: "" }, "all gradients (.npy)");
  const note = h("p.muted.small", "RGB sum of dI/dp per scalar; red = positive, blue = negative, grey = 0.");
  // dI/dp per listed scalar (hidden for a pure texture job: its gradient is a texture, below)
  const scalarGradients = h("div.gradients", { dataset: { testid: "scalar-gradients" } },
    h("div.card-subhead", h("h3", "Gradient images dI/dp"), h("span.spacer"), stackLink), grid, note);
  // A texture parameter: its value and its gradient dz/dp (a texture too) at the iteration
  const textureGrid = h("div.gradient-grid", { dataset: { testid: "texture-grid" } });
  const textures = h("div.gradients", { hidden: true },
    h("div.card-subhead", h("h3", "Textures and their gradient dz/dp")), textureGrid);

  slider.addEventListener("input", () => {
    index = Number(slider.value);
    follow = index === withImages.length - 1;
    show();
  });

  const element = h("section.card.images-card", { dataset: { testid: "images-card" } },
    h("div.card-head", h("h2", "Images"), h("div.slider-row", h("label.label", "Iteration"), slider, sliderLabel),
      sensorPick),
    h("div.images-body",
      h("div.image-pair",
        h("figure.image-figure.missing", render, renderCaption),
        h("figure.image-figure.missing", target, h("figcaption", "Target")),
        silhouetteFigure),
      scalarGradients,
      textures));

  function figures() {
    grid.replaceChildren(...labels.map((label, p) => h("figure.gradient-figure.missing", { dataset: { scalar: p } },
      picture("gradient-image", `gradient of ${label}`),
      h("figcaption", h("span.mono.ellipsis", { title: label }, label)),
      h("div.colorbar-slot"),
      h("a.link-small", { download: "", dataset: { role: "npy" } }, ".npy"))));
    grid.querySelectorAll("img").forEach((img, p) => { img.dataset.scalar = String(p); });
  }

  function textureFigures() {
    textureGrid.replaceChildren(...textureKeys.flatMap((key) => [key, `${key}.dz_dp`].map((name) =>
      h("figure.gradient-figure.missing", { dataset: { texture: name } },
        picture("texture-image", name), h("figcaption", h("span.mono.ellipsis", { title: name }, name))))
      .concat([h("figure.gradient-figure.missing", { dataset: { target: key } },   // a synthetic job's target
        picture("texture-target", `${key} target`), h("figcaption", h("span.mono.ellipsis", "target")))])));
    textureGrid.querySelectorAll("figure[data-target]").forEach((figure) => {
      setSource(figure.querySelector("img"), `${base}/final/${encodeURIComponent(figure.dataset.target)}.target.png`);
    });
    textures.hidden = textureKeys.length === 0;
  }

  function show(force = false) {
    const record = withImages[index];
    slider.max = String(Math.max(0, withImages.length - 1));
    slider.value = String(Math.max(0, index));
    slider.disabled = withImages.length < 2;
    if (!record) {
      sliderLabel.textContent = "no images yet";
      return;
    }
    const k = record.iteration;
    sliderLabel.textContent = `#${k}${follow ? " (latest)" : ""}`;
    renderCaption.textContent = `Render, iteration ${k}`;
    if (!force && element.dataset.shown === `${k}/${sensor}`) return;
    element.dataset.shown = `${k}/${sensor}`;
    setSource(render, `${base}/iterations/${k}/render.png${sensor ? `?sensor=${sensor}` : ""}`, force);
    setSource(target, `${base}/targets/${sensor}.png`, force);
    if (geometry) setSource(silhouette, `${base}/iterations/${k}/silhouette.png${sensor ? `?sensor=${sensor}` : ""}`, force);
    stackLink.href = authUrl(`${base}/iterations/${k}/gradients.npy`);
    const scales = record.preview_scales || [];
    grid.querySelectorAll("figure").forEach((figure, p) => {
      setSource(figure.querySelector("img"), `${base}/iterations/${k}/gradients/${p}.png`, force);
      figure.querySelector(".colorbar-slot").replaceChildren(colorBar(scales[p]));
      figure.querySelector("[data-role=npy]").href = authUrl(`${base}/iterations/${k}/gradients/${p}.npy`);
    });
    textureGrid.querySelectorAll("figure[data-texture]").forEach((figure) => {
      const name = encodeURIComponent(figure.dataset.texture);
      setSource(figure.querySelector("img"), `${base}/iterations/${k}/textures/${name}.png`, force);
    });
  }

  /** New records (sorted by iteration) or plan: keep the slider and the images in step. */
  function update(records, plan) {
    const scalars = (plan && plan.scalars) || [];
    geometry = ((plan && plan.keys) || []).some((key) => /\.(to_world\.(translate|rotate)|vertex_positions)$/.test(key));
    silhouetteFigure.hidden = !geometry;
    scalarGradients.hidden = scalars.length === 0 && ((plan && plan.textures) || []).length > 0;
    if (scalars.join("\n") !== labels.join("\n")) {
      labels = scalars;
      figures();
      element.dataset.shown = "";
    }
    const keys = ((plan && plan.textures) || []).map((t) => t.key);
    if (keys.join("\n") !== textureKeys.join("\n")) {
      textureKeys = keys;
      textureFigures();
      element.dataset.shown = "";
    }
    const planSensors = (plan && plan.sensors) || [0];
    if (planSensors.join() !== sensors.join()) {
      sensors = planSensors;
      sensorPick.replaceChildren(...sensors.map((s) => h("option", { value: String(s) }, `sensor ${s}`)));
      sensorPick.hidden = sensors.length < 2;
    }
    withImages = records.filter((r) => r.images);
    if (follow || index >= withImages.length) index = withImages.length - 1;
    // a missing image (not written yet when first asked for) is asked for again on the next record
    const retry = started && element.querySelector("figure.missing img[data-src]");
    started = true;
    show(Boolean(retry));
  }

  return { element, update };
}
