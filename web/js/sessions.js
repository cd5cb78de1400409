// The list of inspection sessions with their job states.
import { apiJSON, el } from "./api.js";

function jobCell(jobs) {
  if (!jobs.length) return "–";
  return el("div", { class: "jobs" }, ...jobs.map((j) => el("span", { class: `job ${j.state}`, title: j.error || j.message || j.state },
    `${j.kind} `, j.state === "running" || j.state === "queued"
      ? el("progress", { max: "1", value: String(j.progress) })
      : el("b", {}, j.state === "done" ? "✓" : j.state === "failed" ? "✗" : j.state))));
}

export async function loadSessions() {
  const body = await apiJSON("/api/sessions?limit=200");
  const tbody = document.querySelector("#sessions tbody");
  tbody.replaceChildren(...body.data.map((s) => {
    const tr = el("tr", { dataset: { session: s.id }, tabindex: "0", onclick: () => { location.hash = `#/session/${s.id}`; },
      onkeydown: (e) => { if (e.key === "Enter") location.hash = `#/session/${s.id}`; } },
    el("td", {}, s.structure), el("td", {}, s.location || "–"), el("td", {}, new Date(s.started_at).toLocaleString()),
    el("td", {}, s.operator || "–"), el("td", {}, s.status), el("td", {}, String(s.frames)),
    el("td", {}, String(s.defects)), el("td", {}, jobCell(s.jobs)));
    return tr;
  }));
}
