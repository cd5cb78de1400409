// The drive page: live video, drive controls (buttons, keys, gamepad), robot selection and
// control, capture and lift. Drive commands repeat every REPEAT_MS while an input is held;
// the robot stops by itself when they stop arriving (its dead-man hold), and this page sends
// an explicit stop when the input is released, the tab is hidden or loses focus.
import { text } from "./api.js";
import { EVENT } from "./events.js";
import { link, on, send } from "./live.js";

const REPEAT_MS = 50;
const TURN_RADPS = 0.5;
const canvas = document.getElementById("camera");
const ctx2d = canvas.getContext("2d");
const robots = new Map(); // session id -> {connected, name, holder, holderId, lastTelemetry}
const held = new Set(); // drive inputs held: forward, back, left, right (keys and pad buttons)
let selected = null;
let moving = false;
let refusedAt = 0; // when the robot last refused a command
const REFUSAL_KEPT_MS = 3000;
let drawing = false;
const frameTimes = [];

// what the teleop benchmark and the tests read
export const stats = { video: [], command: [], frames: 0 };
window.steelscanStats = stats;

export function selectedSession() {
  return selected;
}

export function robotLabel(sid) {
  const name = robots.get(sid)?.name;
  return name ? `${name} (session ${sid.slice(0, 8)})` : `session ${sid.slice(0, 8)}`;
}

function refreshRobots() {
  const select = document.getElementById("robot-select");
  const live = [...robots.entries()].filter(([, r]) => r.connected);
  if (!selected || !robots.get(selected)?.connected) selected = live.length ? live[live.length - 1][0] : null;
  select.replaceChildren(
    ...live.map(([sid]) => {
      const o = document.createElement("option");
      o.value = sid;
      o.textContent = robotLabel(sid);
      o.selected = sid === selected;
      return o;
    }),
  );
  const state = document.getElementById("robot-state");
  text(state, selected ? `robot: ${robotLabel(selected)}` : "no robot connected");
  state.classList.toggle("ok", Boolean(selected));
  if (!selected && canvas.dataset.live !== "false") blankCamera();
  refreshControl();
  refreshAlerts();
}

// No robot on view: the camera says so instead of keeping the last frame as if it were live.
function blankCamera(message = "no robot connected") {
  ctx2d.fillStyle = "#000";
  ctx2d.fillRect(0, 0, canvas.width, canvas.height);
  ctx2d.fillStyle = "#8b96a0";
  ctx2d.font = "24px system-ui, sans-serif";
  ctx2d.textAlign = "center";
  ctx2d.fillText(message, canvas.width / 2, canvas.height / 2);
  canvas.dataset.live = "false";
  text(document.getElementById("video-info"), "");
  text(document.getElementById("frame-info"), message);
}

// The e-stop banner (any connected robot stopped) and why the selected robot will not drive
// (its edge sensors block the commanded direction).
function refreshAlerts() {
  const stopped = [...robots.entries()]
    .filter(([, r]) => r.connected && r.lastTelemetry?.estop)
    .map(([sid]) => robotLabel(sid));
  const banner = document.getElementById("estop-banner");
  banner.hidden = stopped.length === 0;
  text(
    document.getElementById("estop-text"),
    `EMERGENCY STOP ENGAGED: ${stopped.join(", ")} will not move until the e-stop is reset`,
  );
  const t = robots.get(selected)?.lastTelemetry;
  const blockedBy = t?.drive?.blocked_by || [];
  const notice = document.getElementById("drive-blocked");
  notice.hidden = blockedBy.length === 0;
  if (blockedBy.length) {
    const way = t.edge_action === "block_reverse" ? "Reverse" : "Forward";
    text(
      notice,
      `${way} blocked at the plate edge: ${blockedBy.join(", ").replaceAll("_", " ")} ` +
        `${blockedBy.length > 1 ? "see" : "sees"} no steel. ` +
        `${way === "Forward" ? "Reverse" : "Drive forward"} or turn away from the edge.`,
    );
  }
}

function iDrive() {
  const r = robots.get(selected);
  return Boolean(r && r.holderId !== null && r.holderId === link.watcherId);
}

function refreshControl() {
  const r = robots.get(selected);
  const state = document.getElementById("control-state");
  const button = document.getElementById("take-control");
  if (!r) {
    text(state, "no robot connected");
    state.classList.remove("ok");
    text(button, "Take control"); // nothing is held on a robot that is gone
    button.disabled = true;
    return;
  }
  button.disabled = false;
  if (r.holder === null || r.holder === undefined) {
    text(state, "nobody drives");
    text(button, "Take control");
  } else if (iDrive()) {
    text(state, "you drive");
    text(button, "Release control");
  } else {
    text(state, `driven by ${r.holder}`);
    text(button, "Take control");
  }
  state.classList.toggle("ok", iDrive());
}

function robot(sid) {
  if (!robots.has(sid)) robots.set(sid, { connected: false, name: "", holder: null, holderId: null });
  return robots.get(sid);
}

export function command(cmd, args = {}, sentMs = Date.now()) {
  if (!selected) {
    text(document.getElementById("command-result"), "no live robot");
    return false;
  }
  if (stats.mute) return true; // the teleop benchmark's stand-in for a hung tab or a lost link
  return send({ session_id: selected, cmd, args: { ...args, sent_ms: sentMs } });
}

function estopAll() {
  // any operator may stop every robot, whoever drives it
  for (const [sid, r] of robots) {
    if (r.connected) send({ session_id: sid, cmd: "estop", args: { sent_ms: Date.now() } });
  }
  held.clear();
  moving = false;
}

function velocity() {
  const speed = Number(document.getElementById("speed").value);
  let v = 0;
  let w = 0;
  if (held.has("forward")) v += speed;
  if (held.has("back")) v -= speed;
  // the robot's yaw rate: about its z axis, which points into the surface (x forward, y to
  // its right), so a turn to the right is positive and a turn to the left negative
  if (held.has("left")) w -= TURN_RADPS;
  if (held.has("right")) w += TURN_RADPS;
  const pad = gamepad();
  if (pad) {
    v += -pad.y * speed;
    w += pad.x * TURN_RADPS;
  }
  return [v, w];
}

function gamepad() {
  const pads = navigator.getGamepads ? [...navigator.getGamepads()].filter(Boolean) : [];
  if (!pads.length) return null;
  const p = pads[0];
  const dead = (a) => (Math.abs(a) < 0.15 ? 0 : a);
  // B: stop
  if (p.buttons[1]?.pressed) {
    held.clear();
    return null;
  }
  const x = dead(p.axes[0] || 0);
  const y = dead(p.axes[1] || 0);
  return x || y ? { x, y } : null;
}

function tick(keyAt = null) {
  const [v, w] = velocity();
  if (v || w) {
    // the first command after a key press carries the key event's time: latency is measured from the key
    const args =
      keyAt === null ? { linear_mps: v, angular_radps: w } : { linear_mps: v, angular_radps: w, key_event: true };
    if (command("drive", args, keyAt === null ? Date.now() : keyAt)) moving = true;
  } else if (moving) {
    command("stop");
    moving = false;
  }
}

function release(reason) {
  if (held.size || moving) {
    held.clear();
    command("stop", { reason });
    moving = false;
  }
}

const KEYS = {
  ArrowUp: "forward",
  KeyW: "forward",
  ArrowDown: "back",
  KeyS: "back",
  ArrowLeft: "left",
  KeyA: "left",
  ArrowRight: "right",
  KeyD: "right",
};

function typing(e) {
  return (
    ["INPUT", "SELECT", "TEXTAREA"].includes(e.target.tagName) &&
    e.target.type !== "range" &&
    e.target.type !== "checkbox"
  );
}

// A focused control keeps its own keys: arrows move a slider, Space presses a button or
// ticks a box. Esc (e-stop) always passes, and so do WASD.
function ownKey(e) {
  const t = e.target;
  if (t.type === "range" && e.code.startsWith("Arrow")) return true;
  return e.code === "Space" && (t.tagName === "BUTTON" || t.type === "checkbox");
}

function onKeyDown(e) {
  if (document.getElementById("view-drive").hidden) return;
  if (e.code === "Escape") {
    estopAll();
    return;
  }
  if (typing(e) || ownKey(e)) return;
  if (e.code === "Space") {
    e.preventDefault();
    release("space");
    command("stop");
    return;
  }
  if (e.code === "KeyC" && !e.repeat) {
    command("capture");
    return;
  }
  const input = KEYS[e.code];
  if (!input) return;
  e.preventDefault();
  if (!held.has(input)) {
    held.add(input);
    tick(performance.timeOrigin + e.timeStamp); // at once, not on the next repeat
  }
}

function onKeyUp(e) {
  const input = KEYS[e.code];
  if (!input || !held.has(input)) return;
  held.delete(input);
  if (!held.size) release("key released");
}

function drawFrame(header, jpeg) {
  if (header.session_id !== selected) return; // only the selected robot's camera
  if (drawing) return; // never queue frames: draw the newest, drop what arrives meanwhile
  drawing = true;
  createImageBitmap(new Blob([jpeg], { type: "image/jpeg" }))
    .then((bmp) => {
      // decoding takes a while: the robot may have left, or another been chosen, meanwhile
      if (header.session_id !== selected) {
        bmp.close();
        return;
      }
      ctx2d.drawImage(bmp, 0, 0, canvas.width, canvas.height);
      bmp.close();
      const now = Date.now();
      const latency = now - header.t * 1000;
      stats.video.push(latency);
      if (stats.video.length > 5000) stats.video.shift();
      stats.frames += 1;
      canvas.dataset.frames = String(stats.frames);
      canvas.dataset.live = "true";
      frameTimes.push(now);
      while (frameTimes.length && frameTimes[0] < now - 2000) frameTimes.shift();
      text(
        document.getElementById("video-info"),
        `${(frameTimes.length / 2).toFixed(0)} fps · ${latency.toFixed(0)} ms`,
      );
      text(
        document.getElementById("frame-info"),
        `${robotLabel(header.session_id)} · ${header.video ? "live" : `frame #${header.seq}`}`,
      );
    })
    .catch(() => {})
    .finally(() => {
      drawing = false;
    });
}

function onEvent(ev) {
  if (ev.type === EVENT.ROBOT) {
    const r = robot(ev.session_id);
    r.connected = ev.connected;
    if (ev.robot) r.name = ev.robot;
    if (!ev.connected) r.lastTelemetry = null;
    refreshRobots();
  } else if (ev.type === EVENT.CONTROL) {
    const r = robot(ev.session_id);
    r.holder = ev.holder;
    r.holderId = ev.holder_id;
    refreshControl();
  } else if (ev.type === EVENT.COMMAND_ACK && typeof ev.latency_ms === "number") {
    stats.command.push(ev.latency_ms);
    if (stats.command.length > 5000) stats.command.shift();
    if (!ev.accepted && ev.reason) {
      refusedAt = Date.now();
      text(document.getElementById("command-result"), `robot refused ${ev.cmd}: ${ev.reason}`);
    } else if (ev.accepted && ev.cmd !== "stop") {
      refusedAt = 0;
    }
  } else if (ev.type === EVENT.COMMAND_RESULT) {
    // a robot's refusal (e-stopped, say) stays in view while the commands it refuses keep
    // going out: "sent" only says the station passed them on
    if (ev.ok && Date.now() - refusedAt < REFUSAL_KEPT_MS) return;
    text(document.getElementById("command-result"), ev.ok ? `${ev.cmd} sent` : `${ev.cmd || "command"}: ${ev.error}`);
  } else if (ev.type === EVENT.TELEMETRY) {
    const r = robot(ev.session_id);
    r.lastTelemetry = ev.data;
    if (ev.session_id === selected && ev.data.lift) {
      for (const axle of ["front", "rear"]) {
        document.getElementById(`lift-${axle}`).setAttribute("aria-pressed", String(Boolean(ev.data.lift[axle])));
      }
    }
    if (ev.session_id === selected && ev.data.drive) {
      text(document.getElementById("hold-ms"), String(ev.data.drive.hold_ms));
    }
    refreshAlerts();
  } else if (ev.type === EVENT.SESSION && ev.event === "session_end") {
    const r = robot(ev.session_id);
    r.connected = false;
    r.lastTelemetry = null;
    r.holder = null; // an ended session is driven by nobody
    r.holderId = null;
    const wasSelected = ev.session_id === selected;
    refreshRobots();
    if (wasSelected && !selected) blankCamera("session ended: no robot connected");
  } else if (ev.type === "link" && !ev.open) {
    held.clear();
    moving = false;
  }
}

export function initDrive() {
  on("event", onEvent);
  on("frame", drawFrame);
  document.getElementById("estop").addEventListener("click", estopAll);
  document.getElementById("robot-select").addEventListener("change", (e) => {
    release("robot changed");
    selected = e.target.value;
    refreshControl();
  });
  document.getElementById("take-control").addEventListener("click", () => {
    if (!selected) return;
    send({ type: "control", session_id: selected, action: iDrive() ? "release" : "take" });
  });
  document
    .querySelectorAll("button[data-cmd]")
    .forEach((b) => b.addEventListener("click", () => command(b.dataset.cmd)));
  document.querySelectorAll("button[data-drive]").forEach((b) => {
    const input = b.dataset.drive;
    b.addEventListener("pointerdown", (e) => {
      b.setPointerCapture(e.pointerId);
      held.add(input);
      tick();
    });
    for (const type of ["pointerup", "pointercancel", "lostpointercapture"]) {
      b.addEventListener(type, () => {
        if (held.delete(input) && !held.size) release("button released");
      });
    }
  });
  document
    .querySelectorAll("button[data-sweep]")
    .forEach((b) => b.addEventListener("click", () => command("sweep", { action: b.dataset.sweep })));
  document.querySelectorAll("button[data-lift]").forEach((b) =>
    b.addEventListener("click", () => {
      command("lift", { axle: b.dataset.lift, up: b.getAttribute("aria-pressed") !== "true" });
    }),
  );
  const autoCapture = () =>
    command("auto_capture", {
      on: document.getElementById("auto-capture").checked,
      spacing_m: Number(document.getElementById("capture-spacing").value) / 100,
    });
  document.getElementById("auto-capture").addEventListener("change", autoCapture);
  document.getElementById("capture-spacing").addEventListener("change", autoCapture);
  document.getElementById("end-session").addEventListener("click", () => {
    if (confirm("End the robot's inspection session? Processing starts when it ends.")) command("end_session");
  });
  const speed = document.getElementById("speed");
  speed.addEventListener("input", () =>
    text(document.getElementById("speed-value"), `${Number(speed.value).toFixed(2)} m/s`),
  );
  document.addEventListener("keydown", onKeyDown);
  document.addEventListener("keyup", onKeyUp);
  window.addEventListener("blur", () => release("window lost focus"));
  document.addEventListener("visibilitychange", () => {
    if (document.hidden) release("tab hidden");
  });
  window.addEventListener("pagehide", () => release("page closed"));
  setInterval(tick, REPEAT_MS);
  refreshRobots();
}
