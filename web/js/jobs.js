// The session page's processing bar: each stage's state and a button to run it again
// (operator role; a finished stage asks first, its results being replaced), the running
// job's progress (wherever its worker is) and a button to cancel it; the page reloads the
// session when the job is done.
import { api, apiJSON, el, text } from "./api.js";

const STAGES = [
  ["stitch", "mosaic"],
  ["map", "3D map"],
  ["detect", "defect detection"],
  ["export", "MCAP export"],
];

const said = new Map(); // session id -> the bar's last message (kept across the page's reload)
const watching = new Set(); // ids of jobs a bar is following

export function jobsBar(s, reload) {
  const out = el("span", { id: "job-status", class: "small", role: "status" }, said.get(s.id) || "");
  const say = (message) => {
    said.set(s.id, message);
    text(out, message);
  };
  const latest = (kind) => s.jobs.filter((j) => j.kind === kind).pop();
  const buttons = STAGES.map(([kind, label]) => {
    const j = latest(kind);
    const state = j ? `${j.state}${j.error ? `: ${j.error}` : ""}` : "not run";
    return el(
      "button",
      {
        dataset: { job: kind },
        title: `${label}: ${state}`,
        onclick: () => {
          const again = `Run the ${label} again? Its results are replaced when the new run finishes.`;
          if (latest(kind)?.state !== "done" || window.confirm(again)) run(kind, label);
        },
      },
      `${j?.state === "done" ? "Re-run" : "Run"} ${label}`,
    );
  });
  const cancel = el("button", { id: "job-cancel", hidden: true }, "Cancel");
  const labelOf = (kind) => (STAGES.find(([k]) => k === kind) || [kind, kind])[1];
  async function run(kind, label) {
    const res = await api(`/api/sessions/${s.id}/jobs`, {
      method: "POST",
      headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ kind }),
    });
    if (!res.ok) {
      say(`${label}: not started (HTTP ${res.status}: ${(await res.json().catch(() => ({}))).detail || ""})`);
      return;
    }
    await watch(await res.json(), label);
  }
  async function watch(job, label) {
    cancel.hidden = false;
    cancel.onclick = async () => {
      const res = await api(`/api/jobs/${job.id}/cancel`, { method: "POST" });
      if (!res.ok) say(`${label}: not cancelled (HTTP ${res.status})`);
    };
    text(cancel, `Cancel ${label}`);
    while (job.state === "queued" || job.state === "running") {
      const where = job.worker ? ` on ${job.worker}` : "";
      say(
        `${label}: ${job.state}${where} ${Math.round((job.progress || 0) * 100)} %` +
          `${job.message ? ` (${job.message})` : ""}`,
      );
      await new Promise((r) => setTimeout(r, 1000));
      job = await apiJSON(`/api/jobs/${job.id}`);
    }
    cancel.hidden = true;
    say(job.state === "done" ? `${label}: done` : `${label}: ${job.state}${job.error ? ` — ${job.error}` : ""}`);
    if (job.state === "done") reload();
  }
  // a job already under way when the page opens is followed too
  const active = s.jobs.filter((j) => j.state === "queued" || j.state === "running").pop();
  if (active && !watching.has(active.id)) {
    watching.add(active.id);
    watch(active, labelOf(active.kind)).finally(() => watching.delete(active.id));
  }
  return el(
    "div",
    { class: "exports", id: "jobs-bar" },
    el("span", { class: "muted" }, "Processing:"),
    ...buttons,
    cancel,
    out,
  );
}
