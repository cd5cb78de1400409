// The dashboard: sign-in, the live link, and its views (#/drive, #/sessions, #/session/<id>,
// #/structures, #/structure/<id>, #/admin).
import { loadAdmin } from "./admin.js";
import { api, apiJSON, onSignedOut, setToken, text } from "./api.js";
import { initCoverage } from "./coverage.js";
import { initDrive } from "./drive.js";
import { EVENT } from "./events.js";
import { connect, on } from "./live.js";
import { initLivePlots } from "./live_plots.js";
import { initPanels } from "./panels.js";
import { initReview, showSession } from "./review.js";
import { initSessions, loadSessions } from "./sessions.js";
import { showStructure, showStructures } from "./structures.js";
import { initTelemetry } from "./telemetry.js";
import { initTimeline } from "./timeline.js";

let started = false;

// The station refuses robot data (robots keep it and send it again) while its disk is below
// the reserve: say so in the header.
async function watchStorage() {
  const pill = document.getElementById("storage-state");
  try {
    const { storage } = await apiJSON("/api/health");
    pill.hidden = storage.accepting;
    const mib = (b) => `${Math.round(b / 2 ** 20)} MiB`;
    text(
      pill,
      `storage full: ${mib(storage.free_bytes)} free (reserve ${mib(storage.reserve_bytes)}); robots hold their data`,
    );
  } catch {
    // the link pill already says the station is unreachable
  }
}

function showLogin() {
  document.body.classList.add("signed-out");
  document.getElementById("login").hidden = false;
  document.querySelectorAll("main.view").forEach((m) => {
    m.hidden = true;
  });
  document.querySelector("#login input[name=username]").focus();
}

// What the station said about a refused sign-in, in words: a throttled one says when to retry.
async function loginError(res) {
  if (res.status === 401) return "wrong user name or password";
  if (res.status === 429) {
    const wait = Number(res.headers.get("Retry-After") || 0);
    const at = new Date(Date.now() + wait * 1000).toLocaleTimeString();
    let why = "too many wrong passwords";
    try {
      why = (await res.json()).detail.split(";")[0] || why;
    } catch {
      // not JSON
    }
    return `${why}: wait ${wait} s (until ${at}) and try again`;
  }
  let detail = "";
  try {
    detail = (await res.json()).detail;
  } catch {
    // not JSON
  }
  return `sign-in failed (HTTP ${res.status}${detail ? `: ${detail}` : ""})`;
}

async function signOut() {
  try {
    await api("/api/auth/token", { method: "DELETE" });
  } catch {
    // signed out already
  }
  setToken("");
  location.hash = "";
  location.reload();
}

function route() {
  if (!started) return;
  const hash = location.hash || "#/drive";
  const [, name, id, sub, number] = hash.split("/");
  const viewName =
    name === "session" && id
      ? "session"
      : name === "structure" && id
        ? "structures"
        : ["sessions", "structures", "admin"].includes(name)
          ? name
          : "drive";
  document.querySelectorAll("main.view").forEach((m) => {
    m.hidden = m.id !== `view-${viewName}`;
  });
  document
    .querySelectorAll("nav a")
    .forEach((a) =>
      a.classList.toggle(
        "active",
        a.dataset.view === viewName || (viewName === "session" && a.dataset.view === "sessions"),
      ),
    );
  if (viewName === "sessions") loadSessions().catch(() => {});
  if (viewName === "structures") {
    const shown = name === "structure" ? showStructure(id, sub === "visit" ? number : null) : showStructures();
    shown.catch((e) => text(document.getElementById("structures-page"), `cannot show structures: ${e.message}`));
  }
  if (viewName === "admin") {
    loadAdmin({ opening: true }).catch((e) =>
      text(document.getElementById("admin"), `cannot show accounts: ${e.message}`),
    );
  }
  if (viewName === "session") {
    showSession(id, sub === "defect" ? number : null).catch((e) =>
      text(document.getElementById("session-detail"), `cannot show the session: ${e.message}`),
    );
  }
}

document.getElementById("login").addEventListener("submit", async (e) => {
  e.preventDefault();
  const res = await fetch("/api/auth/token", { method: "POST", body: new URLSearchParams(new FormData(e.target)) });
  if (!res.ok) {
    text(document.getElementById("login-error"), await loginError(res));
    return;
  }
  setToken((await res.json()).access_token);
  text(document.getElementById("login-error"), "");
  document.getElementById("login").hidden = true;
  document.body.classList.remove("signed-out");
  start();
});

async function start() {
  const auth = document.querySelector("meta[name=steelscan-auth]")?.content;
  if (auth === "required" && !sessionStorage.getItem("steelscan-token")) {
    showLogin();
    return;
  }
  let me;
  try {
    me = await apiJSON("/api/auth/me");
  } catch {
    return;
  }
  document.body.classList.remove("signed-out");
  text(document.getElementById("who"), `${me.name} (${me.role})`);
  document.getElementById("sign-out").hidden = auth !== "required";
  document.getElementById("nav-admin").hidden = me.role !== "admin";
  if (started) {
    route();
    return;
  }
  started = true;
  initDrive();
  initTelemetry();
  initLivePlots();
  initPanels();
  initCoverage();
  initReview();
  initTimeline();
  initSessions();
  document.getElementById("sign-out").addEventListener("click", signOut);
  connect();
  on("event", (ev) => {
    if (ev.type === EVENT.SESSION && location.hash === "#/sessions") loadSessions().catch(() => {});
  });
  setInterval(() => {
    if (location.hash === "#/sessions") loadSessions().catch(() => {});
  }, 3000);
  watchStorage();
  setInterval(watchStorage, 5000);
  window.addEventListener("hashchange", route);
  route();
}

onSignedOut(showLogin);
start();
