// Two runs side by side: the final render (beside the shared target) and the gradient image of
// every scalar, from the last iteration of each run that wrote images.

import { authUrl, getJSON } from "../api.js";
import { colorBar } from "../charts.js";
import { clear, fmtNum, h } from "../dom.js";

function image(src, testid, caption) {
  const img = h("img.pixelated", { alt: caption, dataset: { testid }, src });
  return h("figure.image-figure", img, h("figcaption", caption));
}

async function column(row) {
  const base = `/v1/jobs/${row.job}`;
  const [job, records] = await Promise.all([getJSON(base), getJSON(`${base}/iterations`)]);
  const last = records.findLast((r) => r.images);
  const values = Object.entries({ ...row.varied, seed: row.seed }).map(([k, v]) => `${k}=${typeof v === "string" ? v : JSON.stringify(v)}`);
  const labels = job.plan?.scalars || [];
  const head = h("div.compare-head", h("a", { href: `#/jobs/${row.job}` }, `run #${row.index}`),
    h("div.sub.mono", values.join(" · ")),
    h("div.sub", `final error ${fmtNum(row.final_parameter_error, 3)} · loss ${fmtNum(row.final_loss, 3)}`));
  if (!last) return h("div.compare-column", { dataset: { testid: "compare-column", index: row.index } }, head, h("p.muted", "no images yet"));
  const k = last.iteration;
  return h("div.compare-column", { dataset: { testid: "compare-column", index: row.index } }, head,
    h("div.image-pair",
      image(authUrl(`${base}/iterations/${k}/render.png`), "compare-render", `render, iteration ${k}`),
      image(authUrl(`${base}/targets/0.png`), "compare-target", "target")),
    h("div.gradient-grid", labels.map((label, p) => h("figure.gradient-figure",
      h("img.pixelated", { alt: `dI/d ${label}`, src: authUrl(`${base}/iterations/${k}/gradients/${p}.png`),
        dataset: { testid: "compare-gradient" } }),
      h("figcaption", label), colorBar(last.preview_scales?.[p])))));
}

export function comparePanel() {
  const body = h("div.compare-body", { dataset: { testid: "compare-panel" } },
    h("p.muted", "Tick “compare” on two runs of the table."));
  let generation = 0;
  return {
    element: body,
    async show(rows) {
      const mine = ++generation;
      if (rows.length < 2) {
        clear(body, h("p.muted", rows.length ? `Run #${rows[0].index} picked: tick one more.` : "Tick “compare” on two runs of the table."));
        return;
      }
      try {
        const columns = await Promise.all(rows.map(column));
        if (mine === generation) clear(body, h("div.grid-2", columns));
      } catch (error) {
        if (mine === generation) clear(body, h("p.text-error", `Could not load the runs: ${error.message}`));
      }
    },
  };
}
