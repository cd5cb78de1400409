// Telemetry of the selected robot: figure with the IR edge sensors, values with warnings, and
// small time-series plots (uPlot) of the last minute.
import uPlot from "/vendor/uplot/uPlot.esm.js";
import { el, fmt, text } from "./api.js";
import { selectedSession, stats } from "./drive.js";
import { EVENT } from "./events.js";
import { on } from "./live.js";
import { recordLivePlots, redrawLivePlots, resetLivePlots } from "./live_plots.js";

const WINDOW_S = 60;
const LOW_MAIN_V = 11.4; // 12 V pack (3S): warn below 3.8 V per cell
const LOW_LOGIC_V = 7.0; // 7.4 V pack (2S)
const MIN_ADHESION = 1.5; // eq. (1) safety margin the operator should keep
const series = { t: [], speed: [], main: [], logic: [], adhesion: [], ack: [] };
const plots = [];
let lastEdge = "none";
let lastAt = 0;
let shown = null; // the session whose telemetry is on view

// No robot any more: no stale values, plots or age.
function clear() {
  shown = null;
  lastAt = 0;
  lastEdge = "none";
  for (const k of Object.keys(series)) series[k].length = 0;
  document.getElementById("telemetry").replaceChildren(...row("robot", "no robot connected"));
  for (const { plot, keys } of plots) plot.setData([[], ...keys.map(() => [])]);
  resetLivePlots();
  for (const name of ["front_left", "front_right", "rear_left", "rear_right"]) {
    document.getElementById(`ir-${name}`).classList.remove("nosurface");
  }
}

// The robot's speed; when its edge sensors hold it still, what was commanded and why not.
function speedText(drive) {
  const turn = ` · turn ${fmt(drive.angular_radps)} rad/s`;
  if (!drive.blocked_by?.length) return `${fmt(drive.linear_mps)}${turn}`;
  return (
    `${fmt(drive.linear_mps)} (commanded ${fmt(drive.commanded_linear_mps)}: ` +
    `blocked by ${drive.blocked_by.join(", ").replaceAll("_", " ")})${turn}`
  );
}

// What the edge action of Algorithm 1 (or the teleoperated robot's edge guard) means.
const EDGE_WORDS = {
  back_off_turn_left: "backing off, turning left",
  back_off_turn_right: "backing off, turning right",
  stop_and_wait: "stopped: waiting for commands",
  block_forward: "forward blocked",
  block_reverse: "reverse blocked",
  edge_near: "edge near",
};

function row(label, value, warn = false) {
  return [el("dt", {}, label), el("dd", { class: warn ? "warn" : "" }, value)];
}

function render(d) {
  const dl = document.getElementById("telemetry");
  const b = d.battery_v || {};
  const wheels = d.wheel_speed_mps || [];
  const link = d.link || {};
  const cmd = stats.command.length ? stats.command[stats.command.length - 1] : null;
  const lowMain = b.main !== undefined && b.main < LOW_MAIN_V;
  const lowLogic = b.logic !== undefined && b.logic < LOW_LOGIC_V;
  dl.replaceChildren(
    ...row("pose x, y (m)", d.pose ? `${fmt(d.pose.x, 3)}, ${fmt(d.pose.y, 3)}` : "–"),
    ...row("heading (°)", d.pose ? fmt((d.pose.yaw * 180) / Math.PI, 1) : "–"),
    ...row(
      "speed (m/s)",
      d.drive ? speedText(d.drive) : fmt(wheels.reduce((a, v) => a + v, 0) / (wheels.length || 1)),
      Boolean(d.drive?.blocked_by?.length),
    ),
    ...row("wheel speeds (m/s)", wheels.map((v) => fmt(v)).join(" ") || "–"),
    ...row("distance, Hall (m)", fmt(d.distance_m, 2)),
    ...row(
      "battery 12 V / 7.4 V",
      `${fmt(b.main)} / ${fmt(b.logic)} V${lowMain || lowLogic ? " — LOW" : ""}`,
      lowMain || lowLogic,
    ),
    ...row(
      "adhesion margin (eq. 1)",
      `${fmt(d.adhesion_margin)} at ${fmt(d.inclination_deg, 0)}°`,
      d.adhesion_margin < MIN_ADHESION,
    ),
    ...row(
      "edge sensors",
      (d.ir_no_surface || []).length ? `no surface: ${d.ir_no_surface.join(", ")}` : "all on steel",
      (d.ir_no_surface || []).length > 0,
    ),
    ...row("e-stop", d.estop ? "ENGAGED" : "off", Boolean(d.estop)),
    ...row(
      "auto capture",
      d.auto_capture
        ? `${d.auto_capture.on ? "on" : "off"}, every ${fmt(d.auto_capture.spacing_m * 100, 0)} cm`
        : "route",
    ),
    ...(d.sweep
      ? row(
          "coverage sweep",
          `${d.sweep.state}: ${d.sweep.phase} · ${d.sweep.lanes_done} lanes done`,
          d.sweep.state === "paused",
        )
      : []),
    ...(d.mcu ? row("MCU line", d.mcu.error || `ok · ${d.mcu.bad_frames} damaged frames`, Boolean(d.mcu.error)) : []),
    ...(d.safety?.length ? row("on-board safety", d.safety.join("; "), true) : []),
    ...(d.onboard
      ? row(
          "on-board computer",
          `CPU ${fmt(d.onboard.cpu_percent, 0)} % · ${d.onboard.temperature_c ?? "–"} °C · ` +
            `camera ${fmt(d.onboard.camera_hz, 1)} Hz` +
            (d.onboard.camera_error ? ` — ${d.onboard.camera_error}` : ""),
          Boolean(d.onboard.camera_error),
        )
      : []),
    ...row(
      "link: ACK latency",
      `${fmt(link.ack_latency_ms, 1)} ms · command ${cmd === null ? "–" : `${cmd.toFixed(1)} ms`}`,
    ),
    ...row(
      "link: pending / resent",
      `${link.pending ?? "–"} / ${link.resent ?? "–"} · ` +
        `reconnects ${link.reconnects ?? 0} · video dropped ${link.video_dropped ?? 0}`,
    ),
  );
  for (const name of ["front_left", "front_right", "rear_left", "rear_right"]) {
    document.getElementById(`ir-${name}`).classList.toggle("nosurface", (d.ir_no_surface || []).includes(name));
  }
  for (const axle of ["front", "rear"]) {
    document.getElementById(`lift-${axle}-mark`).classList.toggle("up", Boolean(d.lift?.[axle]));
  }
  if (d.edge_action && d.edge_action !== lastEdge && d.edge_action !== "none") {
    const list = document.getElementById("edge-events");
    const where = (d.ir_no_surface || []).join(", ").replaceAll("_", " ");
    list.prepend(
      el(
        "li",
        {},
        `${new Date().toLocaleTimeString()} — ` +
          `${EDGE_WORDS[d.edge_action] || d.edge_action.replaceAll("_", " ")}` +
          `${where ? ` (no steel under ${where})` : ""}`,
      ),
    );
    while (list.children.length > 20) list.lastChild.remove();
  }
  lastEdge = d.edge_action || "none";
}

function record(d) {
  const t = d.t || Date.now() / 1000;
  const wheels = d.wheel_speed_mps || [];
  const values = {
    speed: wheels.length ? wheels.reduce((a, v) => a + v, 0) / wheels.length : null,
    main: d.battery_v?.main ?? null,
    logic: d.battery_v?.logic ?? null,
    adhesion: d.adhesion_margin ?? null,
    ack: d.link?.ack_latency_ms ?? null,
  };
  series.t.push(t);
  for (const [k, v] of Object.entries(values)) series[k].push(v);
  while (series.t.length && series.t[0] < t - WINDOW_S) for (const k of Object.keys(series)) series[k].shift();
}

// A y range that always shows at least ``span`` around the data: an idle robot's speed of 0
// is drawn on a ±0.1 m/s axis, not on 0–100.
function rangeOf(span) {
  return (_u, lo, hi) => {
    if (lo === null || hi === null || !Number.isFinite(lo) || !Number.isFinite(hi)) return [-span / 2, span / 2];
    const mid = (lo + hi) / 2;
    const half = Math.max(((hi - lo) / 2) * 1.1, span / 2);
    return [mid - half, mid + half];
  };
}

function makePlot(title, keys, labels, colours, units, span) {
  const target = el("div", { class: "plot", dataset: { plot: title } });
  document.getElementById("plots").appendChild(target);
  const opts = {
    title: `${title} (${units})`,
    width: 300,
    height: 140,
    legend: { show: true, live: false },
    cursor: { show: false },
    scales: { x: { time: true }, y: { range: rangeOf(span) } },
    axes: [
      { stroke: "#8b96a0", grid: { stroke: "#2a323a" } },
      { stroke: "#8b96a0", grid: { stroke: "#2a323a" }, label: units, size: 50 },
    ],
    series: [{ label: "time" }, ...keys.map((_key, i) => ({ label: labels[i], stroke: colours[i], width: 1.5 }))],
  };
  const plot = new uPlot(opts, [[], ...keys.map(() => [])], target);
  plots.push({ plot, keys });
}

// what the tests read: each plot's title and y range
stats.plots = () =>
  plots.map(({ plot }) => ({
    title: plot.root.querySelector(".u-title")?.textContent,
    min: plot.scales.y.min,
    max: plot.scales.y.max,
    legend: [...plot.root.querySelectorAll(".u-legend .u-label")].map((l) => l.textContent),
  }));

function redraw() {
  if (document.getElementById("view-drive").hidden) return;
  for (const { plot, keys } of plots) plot.setData([series.t, ...keys.map((k) => series[k])]);
  redrawLivePlots();
}

export function initTelemetry() {
  makePlot("speed", ["speed"], ["mean wheel speed"], ["#e0a030"], "m/s", 0.2);
  makePlot("batteries", ["main", "logic"], ["main 12 V pack", "logic 7.4 V pack"], ["#3fae6a", "#4a90d9"], "V", 1.0);
  makePlot("adhesion margin", ["adhesion"], ["margin, eq. (1)"], ["#d9443c"], "× needed", 1.0);
  makePlot("ACK latency", ["ack"], ["robot ← station"], ["#b07cd8"], "ms", 20);
  on("event", (ev) => {
    const gone =
      (ev.type === EVENT.ROBOT && !ev.connected) || (ev.type === EVENT.SESSION && ev.event === "session_end");
    if (gone && (!selectedSession() || ev.session_id === selectedSession() || ev.session_id === shown)) {
      clear();
      return;
    }
    if (ev.type !== "telemetry") return;
    const sid = selectedSession();
    if (sid && ev.session_id !== sid) return;
    if (ev.session_id !== shown) {
      clear();
      shown = ev.session_id;
    }
    lastAt = Date.now();
    render(ev.data);
    record(ev.data);
    recordLivePlots(ev.session_id, ev.data);
  });
  setInterval(() => {
    redraw();
    text(
      document.getElementById("telemetry-age"),
      lastAt ? `${((Date.now() - lastAt) / 1000).toFixed(1)} s ago` : "waiting for a robot",
    );
  }, 500);
}
