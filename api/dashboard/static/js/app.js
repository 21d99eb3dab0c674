// Entry point: the API-key prompt, the top bar and the hash router (#/jobs, #/jobs/<id>, #/submit,
// #/experiments, #/experiments/<id>, #/sweep/<job id>).

import { apiKey, forgetKey, setKeyPrompt } from "./api.js";
import { h } from "./dom.js";
import { experimentView } from "./views/experiment.js";
import { experimentsView } from "./views/experiments.js";
import { jobView } from "./views/job.js";
import { jobsView } from "./views/jobs.js";
import { submitView } from "./views/submit.js";
import { sweepView } from "./views/sweep.js";

const view = document.getElementById("view");
const forget = document.getElementById("forget-key");
let dispose = () => {};

/** Ask for the API key with the <dialog> of index.html; resolves with what was entered. */
function askKey(rejected) {
  const dialog = document.getElementById("key-dialog");
  const form = document.getElementById("key-form");
  document.getElementById("key-error").hidden = !rejected;
  form.reset();
  return new Promise((resolve) => {
    const submit = (event) => {
      event.preventDefault();
      const key = form.elements.key.value.trim();
      if (!key) return;
      form.removeEventListener("submit", submit);
      dialog.close();
      forget.hidden = false;
      resolve(key);
    };
    form.addEventListener("submit", submit);
    dialog.showModal();
    form.elements.key.focus();
  });
}

function route() {
  dispose();
  dispose = () => {};
  const hash = location.hash.replace(/^#\/?/, "");
  const [page, id] = hash.split("/");
  for (const link of document.querySelectorAll("[data-nav]")) {
    const section = page === "submit" ? "submit" : page === "experiments" || page === "sweep" ? "experiments" : "jobs";
    link.classList.toggle("active", link.dataset.nav === section);
  }
  view.replaceChildren();
  document.title = "NDRF · inverse rendering";
  if (page === "submit") dispose = submitView(view) || dispose;
  else if (page === "jobs" && id) dispose = jobView(view, decodeURIComponent(id)) || dispose;
  else if (page === "jobs" || page === "") dispose = jobsView(view) || dispose;
  else if (page === "experiments" && id) dispose = experimentView(view, decodeURIComponent(id)) || dispose;
  else if (page === "experiments") dispose = experimentsView(view) || dispose;
  else if (page === "sweep" && id) dispose = sweepView(view, decodeURIComponent(id)) || dispose;
  else view.append(h("div.card.empty-state", h("h2", "Page not found"), h("a", { href: "#/jobs" }, "Back to the jobs")));
  window.scrollTo(0, 0);
}

setKeyPrompt(askKey);
document.getElementById("key-dialog").addEventListener("cancel", (event) => event.preventDefault());  // key needed
forget.hidden = !apiKey();
forget.addEventListener("click", () => {
  forgetKey();
  forget.hidden = true;
  route();
});
window.addEventListener("hashchange", route);
route();
