// #/jobs/<id>: one job, live. History from GET /iterations, then the SSE stream from the last
// event id the server reported with it (X-Last-Event-ID).

import { FINISHED, authUrl, getJSON, postJSON, request, subscribe } from "../api.js";
import { PALETTE, legend, lineChart, stackedBars } from "../charts.js";
import { clear, fmtDuration, fmtNum, h, problemText, statusBadge } from "../dom.js";
import { imagesPanel } from "./job-images.js";
import { orbitPanel } from "./job-orbit.js";
import { currentValues, parametersPanel } from "./job-parameters.js";
import { planView } from "./plan.js";

const PHASES = [["training", "#6366f1"], ["gradient", "#10b981"], ["images", "#f59e0b"]];

function card(title, testid, ...body) {
  return h("section.card", { dataset: { testid } }, h("div.card-head", h("h2", title)), ...body);
}

function stat(label, testid) {
  const value = h("div.stat-value.num", { dataset: { testid } }, "—");
  const sub = h("div.stat-sub");
  return { element: h("div.stat", h("div.stat-label", label), value, sub), value, sub };
}

export function jobView(root, jobId) {
  const base = `/v1/jobs/${encodeURIComponent(jobId)}`;
  const state = { job: null, records: new Map(), measuredAt: 0, lastSeq: 0, checkpoint: null, canceling: false,
    warmup: null };
  let stream = null, alive = true, frame = 0, retry = null, planShown = "";

  // ------------------------------------------------------------------ skeleton
  const title = h("h1.job-title", "Job");
  const idLine = h("div.sub.mono", jobId);
  const badge = h("span");
  const connection = h("span.connection", { dataset: { testid: "connection" } });
  const cancel = h("button.btn.btn-danger", { type: "button", hidden: true, dataset: { testid: "cancel-button" },
    onclick: () => cancelJob() }, "Cancel job");
  const imagesNow = h("button.btn", { type: "button", hidden: true, dataset: { testid: "images-button" },
    title: "Render every view and the gradient images at the next iteration (by default they take at most 5% of the run)",
    onclick: () => requestImages() }, "Images now");
  const alert = h("div.alert.alert-error", { hidden: true, dataset: { testid: "job-error" } });
  const stats = {
    iteration: stat("Iteration", "iteration-counter"), loss: stat("Loss", "loss-value"),
    error: stat("max |p − target|", "parameter-error"), elapsed: stat("Elapsed", "elapsed"), eta: stat("ETA", "eta"),
  };
  const lossChart = h("div.chart", { dataset: { testid: "loss-chart" } });
  const warmupBar = h("div.progress-bar", { style: { width: "0%" } });
  const warmupText = h("div.warmup-text.num", { dataset: { testid: "warmup-text" } });
  const warmup = h("div.warmup", { hidden: true, dataset: { testid: "warmup" } }, h("div.progress", warmupBar), warmupText);
  const sweep = h("a.btn", { href: `#/sweep/${encodeURIComponent(jobId)}`, dataset: { testid: "sweep-link" } }, "Sweep this job");
  const experimentLink = h("a.sub", { hidden: true, dataset: { testid: "experiment-link" } });
  const timeChart = h("div.chart", { dataset: { testid: "timing-chart" } });
  const parameters = parametersPanel();
  const images = imagesPanel(jobId);
  const orbitViewer = orbitPanel(jobId);
  const plan = h("div.plan-body");
  const downloads = h("ul.downloads", { dataset: { testid: "downloads" } });

  clear(root,
    h("div.page-head", h("a.back", { href: "#/jobs" }, "← Jobs"),
      h("div.title-block", h("div.title-line", title, badge, connection), idLine, experimentLink),
      h("span.spacer"), sweep, imagesNow, cancel),
    alert,
    h("div.stats", Object.values(stats).map((s) => s.element)),
    h("div.grid-2",
      h("div.stack",
        card("Loss", "loss-card", warmup, lossChart, h("p.muted.small", "Image loss per iteration (log scale).")),
        card("Seconds per phase", "timing-card", timeChart, legend(PHASES.map(([label, color]) => ({ label, color }))),
          h("p.muted.small", "Seconds of each iteration: field training, candidate render, gradient query."))),
      h("div.stack",
        card("Parameters", "parameters-card", parameters.element),
        card("Downloads", "downloads-card", downloads))),
    images.element,
    orbitViewer.element,
    card("Plan", "plan-card", plan));

  // --------------------------------------------------------------------- data
  const sorted = () => [...state.records.values()].sort((a, b) => a.iteration - b.iteration);
  const schedule = () => { if (!frame) frame = requestAnimationFrame(() => { frame = 0; if (alive) draw(); }); };

  function lastRecorded() {
    let last = -1;
    for (const k of state.records.keys()) last = Math.max(last, k);
    return last;
  }

  /** Completed iterations: the newest record, or the job's own count if it is ahead. */
  const done = () => Math.max(lastRecorded(), state.job?.iteration ?? -1) + 1;

  async function load() {
    try {
      const response = await request(`${base}/iterations`);
      const after = Number(response.headers.get("X-Last-Event-ID") || 0);
      for (const record of await response.json()) state.records.set(record.iteration, record);
      setJob(await getJSON(base));
      if (!FINISHED.has(state.job.status)) follow(after);
      else await catchUp();
    } catch (error) {
      if (!alive) return;
      if (error.status === 404) {
        clear(root, h("div.card.empty-state", h("h2", "No such job"), h("p.mono", jobId),
          h("a.btn", { href: "#/jobs" }, "Back to the jobs")));
        alive = false;
        return;
      }
      showAlert(`Could not load the job: ${problemText(error)}`);
    }
    schedule();
  }

  /** Records written after the history was read by a job that has finished since. */
  async function catchUp() {
    const last = lastRecorded();
    if (state.job.iteration !== null && state.job.iteration > last) {
      for (const record of await getJSON(`${base}/iterations?after=${last}`)) state.records.set(record.iteration, record);
    }
    setConnection("finished");
  }

  function setJob(job) {
    state.job = job;
    state.measuredAt = performance.now();
  }

  function follow(after) {
    stream?.close();
    state.lastSeq = after;
    const seen = (handler) => (data, seq) => { if (seq) state.lastSeq = seq; handler(data); schedule(); };
    stream = subscribe(jobId, after, {
      status: seen(onStatus),
      plan: seen((event) => { state.job.plan = event.plan; }),
      iteration: seen((event) => { state.records.set(event.iteration, event); state.job.iteration = event.iteration; }),
      checkpoint: seen((event) => { state.checkpoint = event.iteration; }),
      warmup: seen((event) => { state.warmup = event; }),
      preparing: seen((event) => { state.warmup = { preparing: event.what }; }),
      resumed: seen((event) => {          // a new attempt recomputes the iterations after its checkpoint
        for (const k of [...state.records.keys()]) if (k >= event.iteration) state.records.delete(k);
        state.job.iteration = event.iteration - 1;
      }),
    }, onConnection);
  }

  function onStatus(event) {
    const job = state.job;
    if (event.status === "running" && job.status !== "running") {
      job.elapsed_seconds = job.elapsed_seconds ?? 0;
      state.measuredAt = performance.now();
    }
    job.status = event.status;
    if ("error" in event) job.error = event.error;
    if ("field" in event) job.field = event.field;
    if (FINISHED.has(event.status)) {
      stream?.close();
      stream = null;
      setConnection("finished");
      getJSON(base).then((fresh) => { if (alive) { setJob(fresh); schedule(); } }).catch(() => {});
    }
  }

  function onConnection(status) {
    setConnection(status);
    if (status !== "closed" || !alive || FINISHED.has(state.job.status)) return;
    // refused (a 401 after a key change, a restart): check the job with fetch, which asks for a key
    clearTimeout(retry);
    retry = setTimeout(async () => {
      try {
        setJob(await getJSON(base));
        if (alive && !FINISHED.has(state.job.status)) follow(state.lastSeq);
        else if (alive) await catchUp();
      } catch { onConnection("closed"); }
      schedule();
    }, 3000);
  }

  function setConnection(status) {
    connection.className = `connection connection-${status}`;
    connection.textContent = { live: "live", reconnecting: "reconnecting…", closed: "disconnected", finished: "" }[status] ?? status;
  }

  function showAlert(text) {
    alert.textContent = text;
    alert.hidden = !text;
  }

  async function cancelJob() {
    state.canceling = true;
    schedule();
    try {
      setJob(await postJSON(`${base}/cancel`));
    } catch (error) {
      if (error.status !== 409) showAlert(`Cancel failed: ${problemText(error)}`);
      state.canceling = false;
    }
    schedule();
  }

  async function requestImages() {
    imagesNow.disabled = true;
    try {
      setJob(await postJSON(`${base}/images`));
    } catch (error) {
      if (error.status !== 409) showAlert(`Asking for images failed: ${problemText(error)}`);
    }
    schedule();
  }

  // --------------------------------------------------------------------- view
  function draw() {
    const job = state.job;
    if (!job) return;
    const records = sorted();
    const finished = FINISHED.has(job.status);
    title.textContent = job.name || "Untitled job";
    document.title = `${job.name || job.id} · NDRF`;
    badge.replaceChildren(statusBadge(job.status, { dataset: { testid: "status-badge" } }));
    cancel.hidden = finished;
    cancel.disabled = state.canceling;
    imagesNow.hidden = job.status !== "running";
    imagesNow.disabled = Boolean(job.images_requested);
    imagesNow.textContent = job.images_requested ? "Images at the next iteration…" : "Images now";
    cancel.textContent = state.canceling ? "Canceling…" : "Cancel job";
    if (job.error) showAlert(job.field ? `${job.field}: ${job.error}` : job.error);

    drawStats(job, records, finished);
    drawWarmup(job, records);
    lineChart(lossChart, { series: [{ label: "loss", color: PALETTE[0], points: records.map((r) => [r.iteration, r.loss]) }],
      logY: true });
    stackedBars(timeChart, { x: records.map((r) => r.iteration),
      layers: PHASES.map(([phase, color]) => ({ label: phase, color, values: records.map((r) => (r.seconds || {})[phase]) })) });
    parameters.update(job.plan, records);
    images.update(records, job.plan);
    drawDownloads(records, job.plan);
    const planText = JSON.stringify(job.plan);
    if (planText !== planShown) {
      planShown = planText;
      plan.replaceChildren(planView(job.plan));
    }
  }


  /** Warm-up (inside iteration 0, minutes on large scenes): training steps done of planned and
   * both residual norms, from the loop's warmup events, until the first iteration arrives. */
  function drawWarmup(job, records) {
    if (job.experiment) {
      experimentLink.hidden = false;
      experimentLink.href = `#/experiments/${job.experiment}`;
      experimentLink.textContent = `run of experiment ${job.experiment}`;
    }
    const event = state.warmup;
    warmup.hidden = !event || records.length > 0 || job.status !== "running";
    if (warmup.hidden) return;
    if (event.preparing) {              // before the first iteration: scene, effect probe, targets
      warmupBar.style.width = "0%";
      warmupText.dataset.steps = "0";   // no training step yet
      warmupText.textContent = `Preparing: ${event.preparing}`;
      return;
    }
    const fraction = event.planned ? Math.min(1, event.steps / event.planned) : 0;
    warmupBar.style.width = `${(100 * fraction).toFixed(1)}%`;
    warmupText.dataset.steps = String(event.steps);
    warmupText.textContent = `Warm-up: ${event.steps} / ${event.planned} training steps before the first gradient`
      + ` · residual L_φ ${fmtNum(event.residual_radiance, 3)} · dL_θ ${fmtNum(event.residual_differential, 3)}`;
  }

  function drawStats(job, records, finished) {
    const count = done();
    stats.iteration.value.textContent = `${count} / ${job.iterations}`;
    stats.iteration.value.dataset.value = String(count);
    stats.iteration.sub.textContent = job.plan?.method && job.plan.method !== job.method
      ? `${job.method}: ${job.plan.method}` : job.method;
    const last = records[records.length - 1];
    stats.loss.value.textContent = fmtNum(last ? last.loss : job.metrics?.loss, 4);
    stats.loss.sub.textContent = last && last.residual_radiance !== undefined
      ? `residuals ${fmtNum(last.residual_radiance, 2)} / ${fmtNum(last.residual_differential, 2)}` : "";
    const targets = job.plan?.target_values;
    const values = currentValues(job.plan, records);
    stats.error.value.textContent = targets?.length && values     // none listed: a pure texture job
      ? fmtNum(Math.max(...targets.map((t, i) => Math.abs(values[i] - t))), 3) : "—";
    stats.error.sub.textContent = targets ? "the estimate against the synthetic target" : "no known target";
    tick(finished, records);
  }

  function tick(finished = FINISHED.has(state.job?.status), records = sorted()) {
    const job = state.job;
    if (!job) return;
    const running = job.status === "running" && job.elapsed_seconds !== null && job.elapsed_seconds !== undefined;
    const elapsed = running ? job.elapsed_seconds + (performance.now() - state.measuredAt) / 1000 : job.elapsed_seconds;
    stats.elapsed.value.textContent = fmtDuration(elapsed);
    stats.elapsed.sub.textContent = job.status === "queued" ? "waiting for a worker" : "";
    const recent = records.slice(-5).map((r) => Object.values(r.seconds || {}).reduce((a, b) => a + b, 0));
    const remaining = job.iterations - done();
    stats.eta.value.textContent = finished ? "—" : recent.length ? fmtDuration((recent.reduce((a, b) => a + b, 0) / recent.length) * remaining) : "—";
    stats.eta.sub.textContent = finished ? job.status : `${remaining} iterations left`;
  }

  function drawDownloads(records, plan) {
    const last = records[records.length - 1];
    // the P x H x W x 3 stack has the listed scalars only: a pure texture job writes none
    const withImages = (plan?.scalars || []).length ? records.findLast((r) => r.images) : null;
    const item = (href, label, note, testid) => h("li", h("a", { href: authUrl(href), download: "",
      dataset: testid ? { testid } : {} }, label), note ? h("span.muted", ` ${note}`) : null);
    clear(downloads,
      last ? item(`${base}/checkpoints/latest`, "Latest checkpoint (.pt)", state.checkpoint !== null
        ? `resumes at iteration ${state.checkpoint}` : "fields, optimizers, parameters") : null,
      withImages ? item(`${base}/iterations/${withImages.iteration}/gradients.npy`,
        `Gradients of iteration ${withImages.iteration} (.npy)`, "float32 P × H × W × 3",
        "gradients-download") : null,
      item(`${base}/iterations`, "Iteration records (JSON)"),
      item(base, "Job record (JSON)"));
  }

  const ticker = setInterval(() => { if (state.job && !FINISHED.has(state.job.status)) tick(); }, 1000);
  const resize = () => schedule();
  window.addEventListener("resize", resize);
  load();
  return () => {
    alive = false;
    stream?.close();
    clearInterval(ticker);
    clearTimeout(retry);
    cancelAnimationFrame(frame);
    window.removeEventListener("resize", resize);
  };
}
