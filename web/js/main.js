// The dashboard: sign-in, the live link, and three views (#/drive, #/sessions, #/session/<id>).
import { apiJSON, onSignedOut, setToken, text } from "./api.js";
import { initDrive } from "./drive.js";
import { connect, on } from "./live.js";
import { initReview, showSession } from "./review.js";
import { loadSessions } from "./sessions.js";
import { initTelemetry } from "./telemetry.js";

let started = false;

// The station refuses robot data (robots keep it and send it again) while its disk is below
// the reserve: say so in the header.
async function watchStorage() {
  const pill = document.getElementById("storage-state");
  try {
    const { storage } = await apiJSON("/api/health");
    pill.hidden = storage.accepting;
    const mib = (b) => `${Math.round(b / 2 ** 20)} MiB`;
    text(pill, `storage full: ${mib(storage.free_bytes)} free (reserve ${mib(storage.reserve_bytes)}); robots hold their data`);
  } catch { /* the link pill already says the station is unreachable */ }
}

function showLogin() {
  document.getElementById("login").hidden = false;
  document.querySelectorAll("main.view").forEach((m) => { m.hidden = true; });
}

function route() {
  if (!started) return;
  const hash = location.hash || "#/drive";
  const [, name, id] = hash.split("/");
  const viewName = name === "session" && id ? "session" : name === "sessions" ? "sessions" : "drive";
  document.querySelectorAll("main.view").forEach((m) => { m.hidden = m.id !== `view-${viewName}`; });
  document.querySelectorAll("nav a").forEach((a) => a.classList.toggle("active", a.dataset.view === viewName
    || (viewName === "session" && a.dataset.view === "sessions")));
  if (viewName === "sessions") loadSessions().catch(() => {});
  if (viewName === "session") showSession(id).catch((e) => text(document.getElementById("session-detail"), `cannot show the session: ${e.message}`));
}

document.getElementById("login").addEventListener("submit", async (e) => {
  e.preventDefault();
  const res = await fetch("/api/auth/token", { method: "POST", body: new URLSearchParams(new FormData(e.target)) });
  if (!res.ok) { text(document.getElementById("login-error"), "wrong user name or password"); return; }
  setToken((await res.json()).access_token);
  document.getElementById("login").hidden = true;
  start();
});

async function start() {
  const auth = document.querySelector("meta[name=steelscan-auth]")?.content;
  if (auth === "required" && !sessionStorage.getItem("steelscan-token")) { showLogin(); return; }
  let me;
  try { me = await apiJSON("/api/auth/me"); } catch { return; }
  text(document.getElementById("who"), `${me.name} (${me.role})`);
  if (started) { route(); return; }
  started = true;
  initDrive();
  initTelemetry();
  initReview();
  connect();
  on("event", (ev) => { if (ev.type === "session" && location.hash === "#/sessions") loadSessions().catch(() => {}); });
  setInterval(() => { if (location.hash === "#/sessions") loadSessions().catch(() => {}); }, 3000);
  watchStorage();
  setInterval(watchStorage, 5000);
  window.addEventListener("hashchange", route);
  route();
}

onSignedOut(showLogin);
start();
