// Telemetry of the selected robot: figure with the IR edge sensors, values with warnings, and
// small time-series plots (uPlot) of the last minute.
import uPlot from "/vendor/uplot/uPlot.esm.js";
import { el, fmt, text } from "./api.js";
import { selectedSession, stats } from "./drive.js";
import { on } from "./live.js";

const WINDOW_S = 60;
const LOW_MAIN_V = 11.4; // 12 V pack (3S): warn below 3.8 V per cell
const LOW_LOGIC_V = 7.0; // 7.4 V pack (2S)
const MIN_ADHESION = 1.5; // eq. (1) safety margin the operator should keep
const series = { t: [], speed: [], main: [], logic: [], adhesion: [], ack: [] };
const plots = [];
let lastEdge = "none";
let lastAt = 0;

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
    ...row("speed (m/s)", d.drive ? `${fmt(d.drive.linear_mps)} · turn ${fmt(d.drive.angular_radps)} rad/s` : fmt(wheels.reduce((a, v) => a + v, 0) / (wheels.length || 1))),
    ...row("wheel speeds (m/s)", wheels.map((v) => fmt(v)).join(" ") || "–"),
    ...row("distance, Hall (m)", fmt(d.distance_m, 2)),
    ...row("battery 12 V / 7.4 V", `${fmt(b.main)} / ${fmt(b.logic)} V${lowMain || lowLogic ? " — LOW" : ""}`, lowMain || lowLogic),
    ...row("adhesion margin (eq. 1)", `${fmt(d.adhesion_margin)} at ${fmt(d.inclination_deg, 0)}°`, d.adhesion_margin < MIN_ADHESION),
    ...row("edge sensors", (d.ir_no_surface || []).length ? `no surface: ${d.ir_no_surface.join(", ")}` : "all on steel", (d.ir_no_surface || []).length > 0),
    ...row("e-stop", d.estop ? "ENGAGED" : "off", Boolean(d.estop)),
    ...row("auto capture", d.auto_capture ? `${d.auto_capture.on ? "on" : "off"}, every ${fmt(d.auto_capture.spacing_m * 100, 0)} cm` : "route"),
    ...row("link: ACK latency", `${fmt(link.ack_latency_ms, 1)} ms · command ${cmd === null ? "–" : `${cmd.toFixed(1)} ms`}`),
    ...row("link: pending / resent", `${link.pending ?? "–"} / ${link.resent ?? "–"} · reconnects ${link.reconnects ?? 0} · video dropped ${link.video_dropped ?? 0}`),
  );
  for (const name of ["front_left", "front_right", "rear_left", "rear_right"]) {
    document.getElementById(`ir-${name}`).classList.toggle("nosurface", (d.ir_no_surface || []).includes(name));
  }
  for (const axle of ["front", "rear"]) document.getElementById(`lift-${axle}-mark`).classList.toggle("up", Boolean(d.lift?.[axle]));
  if (d.edge_action && d.edge_action !== lastEdge && d.edge_action !== "none") {
    const list = document.getElementById("edge-events");
    list.prepend(el("li", {}, `${new Date().toLocaleTimeString()} — ${d.edge_action.replaceAll("_", " ")} (${(d.ir_no_surface || []).join(", ")})`));
    while (list.children.length > 20) list.lastChild.remove();
  }
  lastEdge = d.edge_action || "none";
}

function record(d) {
  const t = d.t || Date.now() / 1000;
  const wheels = d.wheel_speed_mps || [];
  const values = { speed: wheels.length ? wheels.reduce((a, v) => a + v, 0) / wheels.length : null, main: d.battery_v?.main ?? null,
    logic: d.battery_v?.logic ?? null, adhesion: d.adhesion_margin ?? null, ack: d.link?.ack_latency_ms ?? null };
  series.t.push(t);
  for (const [k, v] of Object.entries(values)) series[k].push(v);
  while (series.t.length && series.t[0] < t - WINDOW_S) for (const k of Object.keys(series)) series[k].shift();
}

function makePlot(title, keys, colours, units) {
  const target = el("div", { class: "plot" });
  document.getElementById("plots").appendChild(target);
  const opts = {
    title, width: 300, height: 120, legend: { show: false }, cursor: { show: false },
    scales: { x: { time: true } },
    axes: [{ stroke: "#8b96a0", grid: { stroke: "#2a323a" } }, { stroke: "#8b96a0", grid: { stroke: "#2a323a" }, label: units, size: 50 }],
    series: [{}, ...keys.map((k, i) => ({ label: k, stroke: colours[i], width: 1.5 }))],
  };
  const plot = new uPlot(opts, [[], ...keys.map(() => [])], target);
  plots.push({ plot, keys });
}

function redraw() {
  if (document.getElementById("view-drive").hidden) return;
  for (const { plot, keys } of plots) plot.setData([series.t, ...keys.map((k) => series[k])]);
}

export function initTelemetry() {
  makePlot("speed", ["speed"], ["#e0a030"], "m/s");
  makePlot("batteries", ["main", "logic"], ["#3fae6a", "#4a90d9"], "V");
  makePlot("adhesion margin", ["adhesion"], ["#d9443c"], "");
  makePlot("ACK latency", ["ack"], ["#b07cd8"], "ms");
  on("event", (ev) => {
    if (ev.type !== "telemetry") return;
    const sid = selectedSession();
    if (sid && ev.session_id !== sid) return;
    lastAt = Date.now();
    render(ev.data);
    record(ev.data);
  });
  setInterval(() => {
    redraw();
    text(document.getElementById("telemetry-age"), lastAt ? `${((Date.now() - lastAt) / 1000).toFixed(1)} s ago` : "waiting for a robot");
  }, 500);
}
