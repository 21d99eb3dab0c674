// #/experiments: every experiment with its progress over runs, refreshed every 2 s.

import { FINISHED, getJSON } from "../api.js";
import { poll } from "../poll.js";
import { clear, fmtTime, h, problemText, statusBadge } from "../dom.js";

const POLL_MS = 2000;

/** A stacked bar of the runs by status, and "done / total". */
export function runsProgress(experiment) {
  const counts = experiment.counts || {};
  const total = experiment.runs || 0;
  const done = [...FINISHED].reduce((sum, s) => sum + (counts[s] || 0), 0);
  const segment = (status) => counts[status]
    ? h(`div.progress-bar.progress-${status}`, { style: { width: `${(100 * counts[status] / Math.max(total, 1)).toFixed(1)}%` },
      title: `${counts[status]} ${status}` }) : null;
  return h("div.progress-cell",
    h("div.progress.progress-stack", ["succeeded", "failed", "canceled", "running", "queued"].map(segment)),
    h("span.num", { dataset: { testid: "experiment-progress" } }, `${done} / ${total}`));
}

function row(experiment) {
  const link = `#/experiments/${encodeURIComponent(experiment.id)}`;
  const counts = Object.entries(experiment.counts || {}).map(([s, n]) => `${n} ${s}`).join(", ");
  return h("tr.clickable", { dataset: { testid: "experiment-row", experimentId: experiment.id, status: experiment.status },
    onclick: (event) => { if (!event.target.closest("a")) location.hash = link; } },
  h("td", statusBadge(experiment.status)),
  h("td", h("a.job-name", { href: link }, experiment.name || "untitled"), h("div.sub.mono", experiment.id)),
  h("td", experiment.varied.length ? experiment.varied.map((v) => h("span.tag", v)) : h("span.muted", "—")),
  h("td", h("span.tag", experiment.base_method), " ", experiment.base_scene),
  h("td", runsProgress(experiment), h("div.sub", counts)),
  h("td.num", String(experiment.max_concurrent)),
  h("td.num.muted", fmtTime(experiment.created)));
}

export function experimentsView(root) {
  let alive = true;
  const body = h("tbody");
  const count = h("span.count");
  const banner = h("div.alert.alert-error", { hidden: true });
  const table = h("table.table.jobs-table", { dataset: { testid: "experiments-table" } },
    h("thead", h("tr", ["Status", "Experiment", "Varied", "Base job", "Runs", "At once", "Created"].map((t) => h("th", t)))),
    body);
  const empty = h("div.empty-state", { hidden: true }, h("p", "No experiments yet."),
    h("p.muted", "Open a job and choose “Sweep this job”, or post an experiment to /v1/experiments."),
    h("a.btn", { href: "#/jobs" }, "Jobs"));
  clear(root,
    h("div.page-head", h("h1", "Experiments ", count), h("span.spacer"),
      h("span.live-dot", { title: "refreshed every 2 s" }, "live")),
    banner,
    h("div.card.card-flush", h("div.table-scroll", table), empty));

  async function refresh() {
    const page = await getJSON("/v1/experiments?limit=100");
    if (!alive) return;
    body.replaceChildren(...page.items.map(row));
    count.textContent = String(page.items.length);
    empty.hidden = page.items.length > 0;
    table.hidden = page.items.length === 0;
    banner.hidden = true;
  }
  const poller = poll(refresh, POLL_MS, { onError: (error) => {
    banner.textContent = `Could not load the experiments: ${problemText(error)}`;
    banner.hidden = false;
  } });
  return () => { alive = false; poller.stop(); };
}
