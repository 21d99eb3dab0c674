// The orbit viewer of a job page: the job's trained fields rendered from a camera the user drags
// around the scene (POST /v1/jobs/<id>/views, inline: nothing is stored). It starts at sensor 0;
// dragging turns the camera about that sensor's target point (the point of its axis nearest the
// scene's centre, as the API reports it) and pitches it, keeping the distance. While dragging,
// previews at PREVIEW pixels, 1 spp, one request in flight (the newest camera wins); on release
// the full view at FULL pixels. A scalar picker shows that scalar's dL_theta image beside the
// radiance L_phi. The API keeps the job's checkpoint restored in a warm sandboxed child, so a view
// after the first costs the render only; the last response time is shown.

import { postJSON } from "../api.js";
import { h, problemText } from "../dom.js";

const FULL = 128, PREVIEW = 64, FULL_SPP = 4, PREVIEW_SPP = 1;
const RADIANS_PER_PIXEL = 0.01;

const sub = (a, b) => a.map((v, i) => v - b[i]);
const add = (a, b) => a.map((v, i) => v + b[i]);
const scale = (a, s) => a.map((v) => v * s);
const dot = (a, b) => a.reduce((sum, v, i) => sum + v * b[i], 0);
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm = (a) => scale(a, 1 / Math.hypot(...a));

/** `v` turned by `angle` radians about the unit `axis` (Rodrigues). */
function rotate(v, axis, angle) {
  const c = Math.cos(angle), s = Math.sin(angle);
  return add(add(scale(v, c), scale(cross(axis, v), s)), scale(axis, dot(axis, v) * (1 - c)));
}

/** The camera after a drag of (dx, dy) pixels: yaw about `up` through the target, then pitch about
 * the camera's right axis (stopped short of the poles). */
export function orbit(camera, dx, dy) {
  const up = norm(camera.up);
  let offset = rotate(sub(camera.origin, camera.target), up, -dx * RADIANS_PER_PIXEL);
  const right = norm(cross(up, offset));
  const pitched = rotate(offset, right, -dy * RADIANS_PER_PIXEL);
  if (Math.abs(dot(norm(pitched), up)) < 0.98) offset = pitched;
  return { ...camera, origin: add(camera.target, offset) };
}

export function orbitPanel(jobId) {
  const base = `/v1/jobs/${encodeURIComponent(jobId)}/views`;
  let camera = null, images = {}, scalars = [], inFlight = false, queued = null, dragging = null;

  const radiance = h("img.pixelated.orbit-image", { alt: "radiance L_phi", draggable: "false",
    dataset: { testid: "orbit-radiance" } });
  const gradient = h("img.pixelated.orbit-image", { alt: "gradient image", draggable: "false",
    dataset: { testid: "orbit-image" } });
  const pick = h("select.select-small", { "aria-label": "scalar", dataset: { testid: "orbit-scalar" },
    onchange: () => showImages() });
  const timing = h("span.muted.small.num", { dataset: { testid: "orbit-ms" } });
  const error = h("p.alert.alert-error", { hidden: true, dataset: { testid: "orbit-error" } });
  const open = h("button.btn", { type: "button", dataset: { testid: "orbit-open" }, onclick: () => start() },
    "Open the orbit viewer");
  const stage = h("div.orbit-stage", { hidden: true, dataset: { testid: "orbit-stage" } },
    h("figure.image-figure", radiance, h("figcaption", "Radiance L_phi")),
    h("figure.image-figure", gradient, h("figcaption", "dL_theta of the scalar")));

  const element = h("section.card", { dataset: { testid: "orbit-card" } },
    h("div.card-head", h("h2", "Orbit viewer"), h("span.spacer"), pick, timing),
    h("p.muted.small", "Drag the images to move the camera around the scene; the fields are rendered from it " +
      `(${PREVIEW}×${PREVIEW} while dragging, ${FULL}×${FULL} on release).`),
    open, error, stage);

  function showImages() {
    if (images["radiance.png"]) radiance.src = images["radiance.png"];
    const p = Number(pick.value || 0);
    if (images[`gradient-${p}.png`]) gradient.src = images[`gradient-${p}.png`];
  }

  function setScalars(names) {
    if (names.join("\n") === scalars.join("\n")) return;
    scalars = names;
    pick.replaceChildren(...names.map((name, p) => h("option", { value: String(p) }, name)));
  }

  async function render(body) {
    if (inFlight) { queued = body; return; }              // the newest camera is rendered next
    inFlight = true;
    const started = performance.now();
    try {
      const view = await postJSON(base, { ...body, inline: true });
      const ms = performance.now() - started;
      images = view.images;
      setScalars(view.scalars);
      if (!camera) camera = { origin: view.camera.origin, target: view.camera.target, up: view.camera.up,
        fov: view.camera.fov };
      element.dataset.camera = JSON.stringify(camera.origin);
      timing.textContent = `${view.camera.resolution?.join("×") ?? ""} in ${Math.round(ms)} ms` +
        (view.warm ? " (warm)" : " (child started)");
      timing.dataset.ms = String(Math.round(ms));
      error.hidden = true;
      stage.hidden = false;
      showImages();
    } catch (exc) {
      error.textContent = `No view: ${problemText(exc)}`;
      error.hidden = false;
    } finally {
      inFlight = false;
      if (queued) { const next = queued; queued = null; render(next); }
    }
  }

  const freeCamera = (side, spp) => ({ origin: camera.origin, target: camera.target, up: camera.up, fov: camera.fov,
    resolution: [side, side], spp });

  function start() {
    open.hidden = true;
    render({ sensor: 0, resolution: [FULL, FULL], spp: FULL_SPP });
  }

  function down(event) {
    if (!camera) return;
    dragging = { x: event.clientX, y: event.clientY, moved: false };
    event.target.setPointerCapture?.(event.pointerId);
    event.preventDefault();
  }

  function move(event) {
    if (!dragging) return;
    const dx = event.clientX - dragging.x, dy = event.clientY - dragging.y;
    if (!dx && !dy) return;
    camera = orbit(camera, dx, dy);
    dragging = { x: event.clientX, y: event.clientY, moved: true };
    render(freeCamera(PREVIEW, PREVIEW_SPP));
  }

  function up() {
    if (!dragging) return;
    const moved = dragging.moved;
    dragging = null;
    if (moved) render(freeCamera(FULL, FULL_SPP));
  }

  for (const img of [radiance, gradient]) {
    img.addEventListener("pointerdown", down);
    img.addEventListener("pointermove", move);
    img.addEventListener("pointerup", up);
    img.addEventListener("pointercancel", up);
  }
  return { element };
}
