// Shared by every page: the JSON API (a POST is always application/json) and the buttons that call it.
"use strict";
async function reviewApi(path, body) {
  const r = await fetch(path, {method: "POST", headers: {"Content-Type": "application/json"},
                               body: JSON.stringify(body || {})});
  let j = {};
  try { j = await r.json(); } catch (e) { j = {detail: r.statusText}; }
  if (!r.ok) { const err = new Error(j.detail || r.statusText); err.body = j; throw err; }
  return j;
}
function reviewSay(msg, bad) {
  const el = document.getElementById("status");
  if (el) { el.textContent = msg; el.className = bad ? "err" : "ok"; }
}
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
    reviewSay(e.message, true);
  } finally {
    document.querySelectorAll("[data-api]").forEach(x => x.disabled = false);
  }
});
window.addEventListener("DOMContentLoaded", () => {
  const msg = sessionStorage.getItem("reviewMsg");
  if (msg) { reviewSay(msg); sessionStorage.removeItem("reviewMsg"); }
});
