// #/jobs: every job with its progress, refreshed every 2 s (the pages already shown, newest first).

import { getJSON } from "../api.js";
import { poll } from "../poll.js";
import { usageStrip } from "./usage.js";
import { clear, fmtDuration, fmtNum, fmtTime, h, maxAbsError, problemText, statusBadge } from "../dom.js";

const PAGE = 50;
const POLL_MS = 2000;

function progress(job) {
  const done = job.iteration === null || job.iteration === undefined ? 0 : job.iteration + 1;
  const fraction = job.iterations ? Math.min(1, done / job.iterations) : 0;
  return h("div.progress-cell",
    h("div.progress", h(`div.progress-bar.progress-${job.status}`, { style: { width: `${(fraction * 100).toFixed(1)}%` } })),
    h("span.num", { dataset: { testid: "job-progress" } }, `${done} / ${job.iterations}`));
}

function finalError(job) {
  if (job.error) return h("span.text-error", { title: job.field ? `${job.field}: ${job.error}` : job.error },
    job.error.length > 60 ? `${job.error.slice(0, 57)}…` : job.error);
  const worst = maxAbsError(job.estimate, job.target_values);
  return worst === null ? h("span.muted", "—") : h("span.num", { title: "max |parameter − target|" }, fmtNum(worst, 3));
}

function row(job) {
  const link = `#/jobs/${encodeURIComponent(job.id)}`;
  return h("tr.clickable", { dataset: { testid: "job-row", jobId: job.id, status: job.status },
    onclick: (event) => { if (!event.target.closest("a")) location.hash = link; } },
  h("td", statusBadge(job.status, { dataset: { testid: "job-status" } })),
  h("td", h("a.job-name", { href: link }, job.name || "untitled"), h("div.sub.mono", job.id)),
  h("td", h("span.tag", job.method)),
  h("td", job.scene),
  h("td", progress(job)),
  h("td.num", fmtDuration(job.elapsed_seconds)),
  h("td.num", job.eta_seconds === null || job.eta_seconds === undefined ? h("span.muted", "—") : fmtDuration(job.eta_seconds)),
  h("td.num", fmtNum(job.metrics ? job.metrics.loss : null, 3)),
  h("td", finalError(job)),
  h("td.num.muted", fmtTime(job.created)));
}

export function jobsView(root) {
  let pages = 1, alive = true, hasMore = false;
  const body = h("tbody");
  const count = h("span.count");
  const banner = h("div.alert.alert-error", { hidden: true });
  const more = h("button.btn.btn-ghost", { type: "button", hidden: true, onclick: () => { pages += 1; poller.now(); } },
    "Show older jobs");
  const table = h("table.table.jobs-table", { dataset: { testid: "jobs-table" } },
    h("thead", h("tr", ["Status", "Job", "Method", "Scene", "Iterations", "Elapsed", "ETA", "Loss",
      h("span", { title: "the failure, or max |parameter − target| for synthetic targets" }, "Error"), "Created"]
      .map((title) => h("th", title)))),
    body);
  const empty = h("div.empty-state", { hidden: true }, h("p", "No jobs yet."),
    h("a.btn.btn-primary", { href: "#/submit" }, "Submit a job"));
  const usage = usageStrip();
  clear(root,
    h("div.page-head", h("h1", "Jobs ", count), h("span.spacer"), h("span.live-dot", { title: "refreshed every 2 s" }, "live"),
      h("a.btn.btn-primary", { href: "#/submit", dataset: { testid: "new-job" } }, "New job")),
    usage.element,
    banner,
    h("div.card.card-flush", h("div.table-scroll", table), empty),
    h("div.center", more));

  async function refresh() {
    const jobs = [];
    let cursor = null;
    for (let page = 0; page < pages; page++) {
      const query = new URLSearchParams({ limit: String(PAGE) });
      if (cursor) query.set("cursor", cursor);
      const result = await getJSON(`/v1/jobs?${query}`);
      jobs.push(...result.items);
      cursor = result.next_cursor;
      if (!cursor) break;
    }
    if (!alive) return;
    hasMore = Boolean(cursor);
    body.replaceChildren(...jobs.map(row));
    count.textContent = `${jobs.length}${hasMore ? "+" : ""}`;
    empty.hidden = jobs.length > 0;
    table.hidden = jobs.length === 0;
    more.hidden = !hasMore;
    banner.hidden = true;
  }
  const poller = poll(refresh, POLL_MS, { onError: (error) => {
    banner.textContent = `Could not load the jobs: ${problemText(error)}`;
    banner.hidden = false;
  } });
  return () => { alive = false; poller.stop(); usage.stop(); };
}
