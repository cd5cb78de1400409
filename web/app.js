// Minimal live page: camera frames and telemetry over /ws/live, sessions over REST.
"use strict";

const canvas = document.getElementById("camera");
const ctx2d = canvas.getContext("2d");
const linkState = document.getElementById("link-state");
let liveSession = null;
let socket = null;
let token = sessionStorage.getItem("steelscan-token");

function authHeaders() { return token ? { Authorization: `Bearer ${token}` } : {}; }

async function api(path) {
  const res = await fetch(path, { headers: authHeaders() });
  if (res.status === 401) { showLogin(); throw new Error("signed out"); }
  return res;
}

function showLogin() {
  document.getElementById("login").hidden = false;
  document.querySelector("main").hidden = true;
}

document.getElementById("login").addEventListener("submit", async (e) => {
  e.preventDefault();
  const form = new FormData(e.target);
  const res = await fetch("/api/auth/token", { method: "POST", body: new URLSearchParams(form) });
  if (!res.ok) { text(document.getElementById("login-error"), "wrong user name or password"); return; }
  token = (await res.json()).access_token;
  sessionStorage.setItem("steelscan-token", token);
  document.getElementById("login").hidden = true;
  document.querySelector("main").hidden = false;
  start();
});

function text(el, value) { el.textContent = value; }

function connect() {
  const proto = location.protocol === "https:" ? "wss" : "ws";
  const query = token ? `?token=${encodeURIComponent(token)}` : "";
  socket = new WebSocket(`${proto}://${location.host}/ws/live${query}`);
  socket.binaryType = "arraybuffer";
  socket.onopen = () => { text(linkState, "live link up"); linkState.classList.add("ok"); };
  socket.onclose = () => {
    text(linkState, "reconnecting…"); linkState.classList.remove("ok");
    setTimeout(connect, 1000);
  };
  socket.onmessage = (ev) => {
    if (typeof ev.data === "string") { onEvent(JSON.parse(ev.data)); } else { onFrame(ev.data); }
  };
}

function onFrame(buffer) {
  const view = new DataView(buffer);
  const headLen = view.getUint32(0, true);
  const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 4, headLen)));
  liveSession = header.session_id;
  const blob = new Blob([new Uint8Array(buffer, 4 + headLen)], { type: "image/jpeg" });
  createImageBitmap(blob).then((bmp) => {
    ctx2d.drawImage(bmp, 0, 0, canvas.width, canvas.height);
    bmp.close();
    canvas.dataset.frames = String(Number(canvas.dataset.frames || 0) + 1);
    text(document.getElementById("frame-info"), `session ${header.session_id.slice(0, 8)} · frame #${header.seq}`);
  });
}

function fmt(v, digits = 3) { return typeof v === "number" ? v.toFixed(digits) : String(v); }

function onEvent(ev) {
  if (ev.type === "telemetry") {
    liveSession = ev.session_id;
    const d = ev.data;
    const rows = [
      ["pose x, y (m)", d.pose ? `${fmt(d.pose.x)}, ${fmt(d.pose.y)}` : "–"],
      ["heading (°)", d.pose ? fmt(d.pose.yaw * 180 / Math.PI, 1) : "–"],
      ["distance (m)", fmt(d.distance_m, 2)],
      ["wheel speeds (m/s)", (d.wheel_speed_mps || []).map((v) => fmt(v, 2)).join(" ")],
      ["IR ranges (m)", (d.ir_range_m || []).map((v) => fmt(v, 3)).join(" ")],
      ["no surface under", (d.ir_no_surface || []).join(", ") || "none"],
      ["battery 12 V / 7.4 V", d.battery_v ? `${fmt(d.battery_v.main, 2)} / ${fmt(d.battery_v.logic, 2)}` : "–"],
      ["adhesion margin (eq. 1)", fmt(d.adhesion_margin, 2)],
      ["link pending / resent", d.link ? `${d.link.pending} / ${d.link.resent}` : "–"],
    ];
    const dl = document.getElementById("telemetry");
    dl.replaceChildren(...rows.flatMap(([k, v]) => {
      const dt = document.createElement("dt"); dt.textContent = k;
      const dd = document.createElement("dd"); dd.textContent = v;
      if (k === "no surface under" && v !== "none") dd.className = "warn";
      return [dt, dd];
    }));
  } else if (ev.type === "session") {
    loadSessions();
  } else if (ev.type === "command_result") {
    text(document.getElementById("command-result"), ev.ok ? `${ev.cmd} sent` : `error: ${ev.error}`);
  }
}

function send(cmd, args = {}) {
  if (!socket || socket.readyState !== WebSocket.OPEN || !liveSession) {
    text(document.getElementById("command-result"), "no live robot");
    return;
  }
  socket.send(JSON.stringify({ session_id: liveSession, cmd, args }));
}

document.getElementById("estop").addEventListener("click", () => send("estop"));
document.querySelectorAll("button[data-cmd]").forEach((b) => b.addEventListener("click", () => send(b.dataset.cmd)));
document.addEventListener("keydown", (e) => { if (e.code === "Space") { e.preventDefault(); send("estop"); } });

async function loadSessions() {
  const res = await api("/api/sessions");
  if (!res.ok) return;
  const body = await res.json();
  const tbody = document.querySelector("#sessions tbody");
  tbody.replaceChildren(...body.data.map((s) => {
    const tr = document.createElement("tr");
    const jobs = s.jobs.map((j) => `${j.kind}: ${j.state}${j.state === "running" ? ` ${Math.round(j.progress * 100)}%` : ""}`).join(", ");
    for (const v of [s.structure, new Date(s.started_at).toLocaleString(), s.status, s.frames, s.clouds, s.defects, jobs || "–"]) {
      const td = document.createElement("td"); td.textContent = v; tr.appendChild(td);
    }
    tr.addEventListener("click", () => showSession(s));
    return tr;
  }));
}

function showSession(s) {
  const div = document.getElementById("session-detail");
  div.replaceChildren();
  const h = document.createElement("h3");
  h.textContent = `${s.structure} — ${s.id}`;
  div.appendChild(h);
  const stitch = s.jobs.find((j) => j.kind === "stitch" && j.state === "done");
  const canvasEl = document.createElement("canvas");
  canvasEl.id = "mosaic";
  div.appendChild(canvasEl);
  const table = document.createElement("table");
  table.id = "defects";
  div.appendChild(table);
  const defectsReq = api(`/api/sessions/${s.id}/defects?source=mosaic`).then((r) => r.json());
  if (stitch) {
    api(`/api/sessions/${s.id}/results/mosaic_overview.png`).then((r) => r.blob()).then(createImageBitmap).then(async (bmp) => {
      canvasEl.width = bmp.width; canvasEl.height = bmp.height;
      const ctx = canvasEl.getContext("2d");
      ctx.drawImage(bmp, 0, 0);
      const scale = stitch.result.overview_scale || 1;
      const defects = (await defectsReq).data;
      ctx.lineWidth = 2; ctx.font = "bold 14px system-ui";
      for (const d of defects) {
        ctx.strokeStyle = ctx.fillStyle = d.defect_class === "crack" ? "#ff3b30" : "#ffcc00";
        ctx.strokeRect(d.bbox_x * scale - 3, d.bbox_y * scale - 3, d.bbox_w * scale + 6, d.bbox_h * scale + 6);
        ctx.fillText(String(d.id), d.bbox_x * scale, d.bbox_y * scale - 6);
      }
    });
  }
  defectsReq.then((body) => {
    const head = ["#", "class", "length (mm)", "max width (mm)", "area (mm²)", "x (m)", "y (m)", "review", "CS", "comment"];
    const rows = body.data.map((d) => {
      const tr = document.createElement("tr");
      tr.dataset.defect = d.id;
      for (const v of [d.id, d.defect_class, d.length_mm, d.max_width_mm, d.area_mm2, d.world_x_m, d.world_y_m]) {
        const td = document.createElement("td");
        td.textContent = typeof v === "number" && !Number.isInteger(v) ? v.toFixed(2) : v ?? "–";
        tr.appendChild(td);
      }
      tr.append(reviewCell(s.id, d, "review_status", ["unreviewed", "confirmed", "rejected"]),
                reviewCell(s.id, d, "condition_state", ["", "CS1", "CS2", "CS3", "CS4"]),
                reviewCell(s.id, d, "comment", null));
      return tr;
    });
    const hr = document.createElement("tr");
    for (const c of head) { const th = document.createElement("th"); th.textContent = c; hr.appendChild(th); }
    table.replaceChildren(hr, ...rows);
  });
  const mapJob = s.jobs.find((j) => j.kind === "map" && j.state === "done");
  if (mapJob) {
    // the 3D view (viser, proxied by the station): map, trajectory and defect markers
    const button = document.createElement("button");
    button.textContent = "Show 3D map";
    button.addEventListener("click", async () => {
      const res = await fetch(`/api/sessions/${s.id}/view3d`, { method: "POST", headers: authHeaders() });
      if (!res.ok) { button.textContent = `3D view unavailable (${res.status})`; return; }
      const frame = document.getElementById("view3d") || document.createElement("iframe");
      frame.id = "view3d";
      frame.title = "3D map";
      frame.src = `/viser/${token ? `?token=${encodeURIComponent(token)}` : ""}`;
      div.appendChild(frame);
    });
    div.appendChild(button);
  }
  div.appendChild(exportLinks(s));
}

function reviewCell(sessionId, d, field, options) {
  // one review field of a defect, saved (PATCH) as soon as it changes
  const td = document.createElement("td");
  const input = options ? document.createElement("select") : document.createElement("input");
  input.name = field;
  input.setAttribute("aria-label", `${field} of defect ${d.id}`);
  if (options) {
    for (const o of options) { const opt = document.createElement("option"); opt.value = o; opt.textContent = o || "–"; input.appendChild(opt); }
  }
  input.value = d[field] ?? "";
  input.addEventListener("change", async () => {
    const body = field === "condition_state" && !input.value ? { clear_condition_state: true } : { [field]: input.value };
    const res = await fetch(`/api/sessions/${sessionId}/defects/${d.id}`, {
      method: "PATCH", headers: { ...authHeaders(), "Content-Type": "application/json" }, body: JSON.stringify(body),
    });
    input.classList.toggle("saved", res.ok);
    input.classList.toggle("failed", !res.ok);
    input.title = res.ok ? "saved" : `not saved (${res.status})`;
  });
  td.appendChild(input);
  return td;
}

async function download(path, filename, status) {
  // authenticated download; an export that is still being made (202) is waited for
  for (let attempt = 0; attempt < 600; attempt++) {
    const res = await api(path);
    if (res.status === 202) {
      const job = await res.json();
      text(status, `preparing… ${Math.round(job.progress * 100)}%`);
      await new Promise((r) => setTimeout(r, 1000));
      continue;
    }
    if (!res.ok) { text(status, `failed (${res.status})`); return; }
    const url = URL.createObjectURL(await res.blob());
    const a = document.createElement("a");
    a.href = url; a.download = filename;
    document.body.appendChild(a); a.click(); a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 60000);
    text(status, "");
    return;
  }
}

function exportLinks(s) {
  const box = document.createElement("div");
  box.className = "exports";
  box.id = "exports";
  const status = document.createElement("span");
  const done = (kind) => s.jobs.some((j) => j.kind === kind && j.state === "done");
  const items = [
    ["PDF report", "report.pdf", `${s.id}-report.pdf`, true],
    ["Defects CSV", "defects.csv", `${s.id}-defects.csv`, true],
    ["Report JSON", "report.json", `${s.id}-report.json`, true],
    ["Session MCAP (Foxglove)", "export.mcap", `${s.id}.mcap`, true],
    ["Mosaic overview PNG", "results/mosaic_overview.png", `${s.id}-mosaic.png`, done("stitch")],
    ["Map PLY", "results/map.ply", `${s.id}-map.ply`, done("map")],
    ["Trajectory TUM", "results/trajectory.tum", `${s.id}-trajectory.tum`, done("map")],
  ];
  for (const [label, path, filename, available] of items) {
    if (!available) continue;
    const b = document.createElement("button");
    b.textContent = label;
    b.dataset.export = path;
    b.addEventListener("click", () => download(`/api/sessions/${s.id}/${path}`, filename, status));
    box.appendChild(b);
  }
  box.appendChild(status);
  return box;
}

let started = false;

async function start() {
  const me = await api("/api/auth/me").then((r) => r.json()).catch(() => null);
  if (!me) return;
  text(document.getElementById("who"), `${me.name} (${me.role})`);
  if (started) return;
  started = true;
  connect();
  loadSessions();
  setInterval(() => loadSessions().catch(() => {}), 3000);
}

start();
