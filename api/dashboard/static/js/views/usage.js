// The key's use against its quotas (GET /v1/usage), shown above the jobs: stored bytes, active and
// running jobs, experiments. Refreshed every 10 s (the stored bytes are summed from the store).

import { getJSON } from "../api.js";
import { h } from "../dom.js";
import { poll } from "../poll.js";

const POLL_MS = 10000;
const SHOWN = [["stored_bytes", "Stored"], ["active_jobs", "Active jobs"], ["running_jobs", "Running"],
  ["experiments", "Experiments"]];

function amount(key, value) {
  if (key !== "stored_bytes") return String(value);
  const mib = value / (1 << 20);
  return mib >= 1024 ? `${(mib / 1024).toFixed(1)} GiB` : `${mib.toFixed(1)} MiB`;
}

export function usageStrip() {
  const strip = h("div.usage-strip", { dataset: { testid: "usage" }, hidden: true });
  let alive = true;
  async function refresh() {
    const usage = await getJSON("/v1/usage");
    if (!alive) return;
    strip.replaceChildren(...SHOWN.map(([key, label]) => {
      const quota = usage[key];
      const full = quota.limit > 0 && quota.used >= quota.limit;
      return h(`span.tag${full ? ".text-error" : ""}`, { title: quota.setting, dataset: { testid: `usage-${key}` } },
        `${label}: ${amount(key, quota.used)} / ${quota.limit > 0 ? amount(key, quota.limit) : "no cap"}`);
    }));
    strip.hidden = false;
  }
  // an older API without /v1/usage: nothing to show
  const poller = poll(refresh, POLL_MS, { hidden: true, onError: () => { strip.hidden = true; } });
  return { element: strip, stop: () => { alive = false; poller.stop(); } };
}
