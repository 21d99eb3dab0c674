// The key's use against its quotas (GET /v1/usage), shown above the jobs: stored bytes, active and
// running jobs, experiments. Refreshed every 10 s (the stored bytes are summed from the store).

import { getJSON } from "../api.js";
import { h } from "../dom.js";

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
  let timer = null, alive = true;
  async function refresh() {
    try {
      const usage = await getJSON("/v1/usage");
      if (!alive) return;
      strip.replaceChildren(...SHOWN.map(([key, label]) => {
        const quota = usage[key];
        const full = quota.limit > 0 && quota.used >= quota.limit;
        return h(`span.tag${full ? ".text-error" : ""}`, { title: quota.setting, dataset: { testid: `usage-${key}` } },
          `${label}: ${amount(key, quota.used)} / ${quota.limit > 0 ? amount(key, quota.limit) : "no cap"}`);
      }));
      strip.hidden = false;
    } catch (error) {
      strip.hidden = true;     // an older API without /v1/usage: nothing to show
    }
    if (alive) timer = setTimeout(refresh, POLL_MS);
  }
  refresh();
  return { element: strip, stop: () => { alive = false; clearTimeout(timer); } };
}
