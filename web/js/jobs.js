// The session page's processing bar: each stage's state and a button to run it again
// (operator role); the page reloads the session when the job is done.
import { api, apiJSON, el, text } from "./api.js";

const STAGES = [["stitch", "mosaic"], ["map", "3D map"], ["detect", "defect detection"], ["export", "MCAP export"]];

const said = new Map(); // session id -> the bar's last message (kept across the page's reload)

export function jobsBar(s, reload) {
  const out = el("span", { id: "job-status", class: "small", role: "status" }, said.get(s.id) || "");
  const say = (message) => { said.set(s.id, message); text(out, message); };
  const latest = (kind) => s.jobs.filter((j) => j.kind === kind).pop();
  const buttons = STAGES.map(([kind, label]) => {
    const j = latest(kind);
    const state = j ? `${j.state}${j.error ? `: ${j.error}` : ""}` : "not run";
    return el("button", { dataset: { job: kind }, title: `${label}: ${state}`, onclick: () => run(kind, label) },
      `${j?.state === "done" ? "Re-run" : "Run"} ${label}`);
  });
  async function run(kind, label) {
    const res = await api(`/api/sessions/${s.id}/jobs`, { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify({ kind }) });
    if (!res.ok) { say(`${label}: not started (HTTP ${res.status}: ${(await res.json().catch(() => ({}))).detail || ""})`); return; }
    let job = await res.json();
    while (job.state === "queued" || job.state === "running") {
      say(`${label}: ${job.state} ${Math.round((job.progress || 0) * 100)} %${job.message ? ` (${job.message})` : ""}`);
      await new Promise((r) => setTimeout(r, 1000));
      job = await apiJSON(`/api/jobs/${job.id}`);
    }
    say(job.state === "done" ? `${label}: done` : `${label}: ${job.state}${job.error ? ` — ${job.error}` : ""}`);
    if (job.state === "done") reload();
  }
  return el("div", { class: "exports", id: "jobs-bar" }, el("span", { class: "muted" }, "Processing:"), ...buttons, out);
}
