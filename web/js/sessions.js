// The list of inspection sessions with their job states; searched and narrowed on the station.
import { api, apiJSON, duration, el, text } from "./api.js";

let timer = null;

function jobCell(jobs) {
  if (!jobs.length) return "–";
  return el(
    "div",
    { class: "jobs" },
    ...jobs.map((j) =>
      el(
        "span",
        { class: `job ${j.state}`, title: j.error || j.message || j.state },
        `${j.kind} `,
        j.state === "running" || j.state === "queued"
          ? el("progress", { max: "1", value: String(j.progress) })
          : el("b", {}, j.state === "done" ? "✓" : j.state === "failed" ? "✗" : j.state),
      ),
    ),
  );
}

export async function loadSessions() {
  const q = document.getElementById("session-search").value.trim();
  const status = document.getElementById("session-status").value;
  const params = new URLSearchParams({ limit: "200", q, status });
  if (!status) params.delete("status");
  const body = await apiJSON(`/api/sessions?${params}`);
  const tbody = document.querySelector("#sessions tbody");
  const open = (s) => {
    location.hash = `#/session/${s.id}`;
  };
  tbody.replaceChildren(
    ...body.data.map((s) =>
      el(
        "tr",
        {
          dataset: { session: s.id },
          tabindex: "0",
          onclick: () => open(s),
          onkeydown: (e) => {
            if (e.key === "Enter") open(s);
          },
        },
        el("td", {}, s.structure),
        el("td", {}, s.location || "–"),
        el("td", {}, s.robot_name || (s.imported ? "imported" : "–")),
        el("td", {}, s.operator || "–"),
        el("td", {}, new Date(s.started_at).toLocaleString()),
        el("td", { class: "num" }, duration(s.duration_s)),
        el("td", {}, s.status),
        el("td", { class: "num" }, String(s.frames)),
        el("td", { class: "num" }, String(s.defects)),
        el("td", {}, jobCell(s.jobs)),
        el("td", { class: "muted mono", title: s.id }, s.id.slice(0, 8)),
      ),
    ),
  );
  text(
    document.getElementById("session-count"),
    body.count > body.data.length
      ? `${body.data.length} of ${body.count} sessions`
      : `${body.count} session${body.count === 1 ? "" : "s"}`,
  );
}

// An MCAP log (as this station exports it) becomes a new session, processed like any other.
async function importMcap(input) {
  const file = input.files[0];
  if (!file) return;
  const out = document.getElementById("import-status");
  text(out, `importing ${file.name}…`);
  const body = new FormData();
  body.append("file", file);
  const res = await api("/api/sessions/import", { method: "POST", body });
  input.value = "";
  if (!res.ok) {
    text(out, `${file.name}: not imported (HTTP ${res.status}: ${(await res.json().catch(() => ({}))).detail || ""})`);
    return;
  }
  const r = await res.json();
  text(out, `${file.name}: ${r.frames ?? 0} frames, ${r.clouds ?? 0} clouds imported`);
  location.hash = `#/session/${r.session_id}`;
}

export function initSessions() {
  document.getElementById("import-mcap").addEventListener("change", (e) => importMcap(e.target));
  const later = () => {
    clearTimeout(timer);
    timer = setTimeout(() => loadSessions().catch(() => {}), 250);
  };
  document.getElementById("session-search").addEventListener("input", later);
  document.getElementById("session-status").addEventListener("change", later);
}
