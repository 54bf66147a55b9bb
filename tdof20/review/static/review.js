// Shared by every page: the JSON API (a POST is always application/json and carries the journal
// revision the page shows: one made from an older revision is refused with 409 and the page
// reloads), the buttons that call it, and the watch on the scene (another tab's correction, a
// tdof20 annotate run on the same scene): the page reloads when either changed it.
"use strict";
const reviewKnown = {
  revision: Number(document.body.dataset.revision || 0),
  version: Number(document.body.dataset.version || 0),
};
let reviewInflight = 0;
function reviewTake(state) {       // an answer's state: what this page now shows
  if (state && state.revision !== undefined) {
    reviewKnown.revision = state.revision;
    reviewKnown.version = state.scene_version;
  }
}
function reviewReload(msg) {
  reviewSay(msg, true);
  window.reviewReloading = true;
  setTimeout(() => window.location.reload(), 700);
}
async function reviewApi(path, body) {
  body = Object.assign({base_revision: reviewKnown.revision}, body || {});
  reviewInflight++;
  try {
    const r = await fetch(path, {method: "POST", headers: {"Content-Type": "application/json"},
                                 body: JSON.stringify(body)});
    let j = {};
    try { j = await r.json(); } catch (e) { j = {detail: r.statusText}; }
    if (r.status === 409 && j.stale) {
      reviewReload(`${j.detail} (reloading)`);
      const err = new Error(j.detail); err.body = j; err.stale = true; throw err;
    }
    reviewTake(j.state);
    if (!r.ok) { const err = new Error(j.detail || r.statusText); err.body = j; throw err; }
    return j;
  } finally {
    reviewInflight--;
  }
}
function reviewSay(msg, bad) {
  const el = document.getElementById("status");
  if (el) { el.textContent = msg; el.className = bad ? "err" : "ok"; }
}
async function reviewWatch() {
  if (reviewInflight || window.reviewReloading) return;
  try {
    const r = await (await fetch("/api/revision")).json();
    if (reviewInflight || window.reviewReloading) return;
    if (r.scene_version !== reviewKnown.version && !r.busy) {
      reviewReload("the scene changed on disk (a tdof20 annotate run): reloading");
    } else if (r.revision !== reviewKnown.revision) {
      reviewReload(`another tab made a correction (journal revision ${r.revision}): reloading`);
    }
  } catch (e) { /* the app is gone or restarting: try again later */ }
}
setInterval(reviewWatch, Number(document.body.dataset.watchMs || 1500));
document.addEventListener("click", async (ev) => {
  const b = ev.target.closest("[data-api]");
  if (!b) return;
  ev.preventDefault();
  if (b.dataset.confirm && !window.confirm(b.dataset.confirm)) return;
  const relabel = b.dataset.api === "/api/relabel";
  document.querySelectorAll("[data-api]").forEach(x => x.disabled = true);
  reviewSay(relabel ? "relabelling: place, label and QA run again..." : "saving...");
  try {
    const j = await reviewApi(b.dataset.api, JSON.parse(b.dataset.body || "{}"));
    if (relabel) {
      const msg = `relabelled: ${j.labelled} frames labelled, ${j.unresolved_flags.length} unresolved flags`;
      reviewSay(msg);
      sessionStorage.setItem("reviewMsg", msg);
    }
    if (window.reviewAfter) window.reviewAfter(j); else window.location.reload();
  } catch (e) {
    if (!e.stale) reviewSay(e.message, true);
  } finally {
    document.querySelectorAll("[data-api]").forEach(x => x.disabled = false);
  }
});
window.addEventListener("DOMContentLoaded", () => {
  const msg = sessionStorage.getItem("reviewMsg");
  if (msg) { reviewSay(msg); sessionStorage.removeItem("reviewMsg"); }
});
