// A defect's history across a structure's visits: its length (a crack) or area (rust) at each
// visit as a small inline SVG chart, and the entries as a table.
import { el, fmt } from "./api.js";

const NS = "http://www.w3.org/2000/svg";
const W = 380;
const H = 170;
const PAD = { left: 44, right: 40, top: 22, bottom: 34 };

function svg(tag, attrs = {}, ...children) {
  const node = document.createElementNS(NS, tag);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, String(v));
  node.append(...children.filter((c) => c !== null && c !== undefined));
  return node;
}

// The smallest of 1, 2, 2.5 or 5 times a power of ten at or above v.
function niceCeiling(v) {
  const p = 10 ** Math.floor(Math.log10(v));
  return [1, 2, 2.5, 5, 10].map((m) => m * p).find((c) => c >= v);
}

export function historyChart(track, currentSession) {
  const key = track.class === "corrosion" ? "area_mm2" : "length_mm";
  const what = key === "area_mm2" ? "area (mm²)" : "length (mm)";
  const entries = track.entries.map((e) => ({ ...e, t: Date.parse(e.date) }));
  const values = entries.map((e) => e[key]).filter((v) => typeof v === "number");
  const t0 = Math.min(...entries.map((e) => e.t));
  const t1 = Math.max(...entries.map((e) => e.t));
  const span = t1 - t0 || 365 * 86400e3;
  const vmax = niceCeiling(Math.max(1, ...values) * 1.1);
  const x = (t) => PAD.left + ((t - (t1 === t0 ? t0 - span / 2 : t0)) / span) * (W - PAD.left - PAD.right);
  const y = (v) => H - PAD.bottom - (v / vmax) * (H - PAD.top - PAD.bottom);
  const known = entries.filter((e) => typeof e[key] === "number");
  const chart = svg(
    "svg",
    {
      viewBox: `0 0 ${W} ${H}`,
      width: W,
      height: H,
      class: "history-chart",
      id: "history-chart",
      role: "img",
      "aria-label": `${what} of the defect at each visit`,
    },
    svg("line", { x1: PAD.left, y1: H - PAD.bottom, x2: W - PAD.right, y2: H - PAD.bottom, class: "axis" }),
    svg("line", { x1: PAD.left, y1: PAD.top, x2: PAD.left, y2: H - PAD.bottom, class: "axis" }),
    ...[0, vmax / 2, vmax].map((v) =>
      svg("text", { x: PAD.left - 6, y: y(v) + 4, class: "tick", "text-anchor": "end" }, fmt(v, 0)),
    ),
    svg("text", { x: 4, y: 12, class: "tick" }, what),
    known.length > 1
      ? svg("polyline", { points: known.map((e) => `${x(e.t)},${y(e[key])}`).join(" "), class: "trend" })
      : null,
    ...entries.flatMap((e) => {
      const cx = x(e.t);
      const label = svg("text", { x: cx, y: H - PAD.bottom + 16, class: "tick", "text-anchor": "middle" }, e.date);
      if (typeof e[key] !== "number") {
        const cy = y(0);
        return [
          label,
          svg(
            "path",
            {
              d: `M${cx - 5},${cy - 5}L${cx + 5},${cy + 5}M${cx - 5},${cy + 5}L${cx + 5},${cy - 5}`,
              class: `mark ${e.status}`,
            },
            svg("title", {}, `${e.date}: ${e.status}`),
          ),
        ];
      }
      const current = e.session_id === currentSession ? " current" : "";
      return [
        label,
        svg(
          "circle",
          { cx, cy: y(e[key]), r: 4.5, class: `point ${e.status}${current}` },
          svg("title", {}, `${e.date}: ${fmt(e[key], 1)} ${what.split(" ")[1]} (${e.status})`),
        ),
        svg("text", { x: cx, y: y(e[key]) - 8, class: "value", "text-anchor": "middle" }, fmt(e[key], 0)),
      ];
    }),
  );
  const rows = track.entries.map((e) =>
    el(
      "tr",
      { class: e.session_id === currentSession ? "selected" : "" },
      el("td", {}, e.date),
      el("td", {}, el("span", { class: `badge ${e.status}` }, e.status)),
      el("td", {}, e.number === null ? "–" : `#${e.number}`),
      el("td", { class: "num" }, fmt(e.length_mm, 1)),
      el("td", { class: "num" }, fmt(e.width_mm, 2)),
      el("td", { class: "num" }, fmt(e.area_mm2, 0)),
    ),
  );
  return el(
    "div",
    { class: "history", dataset: { track: track.track_id } },
    el("h4", {}, `History (track ${track.track_id}, ${track.entries.length} visits)`),
    chart,
    el(
      "table",
      { class: "history-table" },
      el("tr", {}, ...["visit", "status", "#", "length (mm)", "width (mm)", "area (mm²)"].map((h) => el("th", {}, h))),
      ...rows,
    ),
  );
}
