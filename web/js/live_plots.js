// The Drive page's plots of any telemetry field the robot sends, beside the fixed ones: the
// user picks fields (names and units as the station lists them for the session, from the
// protocol's key suffixes), one plot per unit, the last minute; the choice is kept with the
// user's preferences.
import uPlot from "/vendor/uplot/uPlot.esm.js";
import { apiJSON, el, text } from "./api.js";
import { byUnit } from "./plan_view.js";
import { keep, preferences } from "./preferences.js";

const WINDOW_S = 60;
const MAX_FIELDS = 12;
const COLOURS = ["#e0a030", "#3fae6a", "#4a90d9", "#d9443c", "#b07cd8", "#2ec4b6"];
const state = { sid: null, fields: [], units: {}, t: [], values: new Map(), plots: [], listed: 0 };

// Every finite number in a sample by its flattened path (as robot_link.telemetry_fields).
export function numericFields(sample, path = "", out = {}, depth = 0) {
  if (sample === null || typeof sample === "boolean" || depth > 6) return out;
  if (typeof sample === "number") {
    if (Number.isFinite(sample)) out[path] = sample;
  } else if (Array.isArray(sample)) {
    sample.forEach((v, i) => numericFields(v, `${path}[${i}]`, out, depth + 1));
  } else if (typeof sample === "object") {
    for (const [k, v] of Object.entries(sample)) numericFields(v, path ? `${path}.${k}` : k, out, depth + 1);
  }
  return out;
}

function box() {
  return document.getElementById("live-plots");
}

function rebuild() {
  for (const p of state.plots) p.plot.destroy();
  state.plots = [];
  const target = box();
  if (!target) return;
  target.replaceChildren();
  target.dataset.fields = state.fields.join(",");
  const groups = byUnit(state.fields, (f) => state.units[f]);
  let colour = 0;
  for (const [unit, names] of groups) {
    const node = el("div", { class: "plot", dataset: { unit: unit || "none" } });
    target.append(node);
    const plot = new uPlot(
      {
        title: unit ? `${names.join(", ")} (${unit})` : names.join(", "),
        width: 300,
        height: 140,
        legend: { show: true, live: false },
        cursor: { show: false },
        scales: { x: { time: true } },
        axes: [
          { stroke: "#8b96a0", grid: { stroke: "#2a323a" } },
          { stroke: "#8b96a0", grid: { stroke: "#2a323a" }, label: unit, size: 50 },
        ],
        series: [
          { label: "time" },
          ...names.map((n) => ({ label: n, stroke: COLOURS[colour++ % COLOURS.length], width: 1.5 })),
        ],
      },
      [[], ...names.map(() => [])],
      node,
    );
    state.plots.push({ plot, names });
  }
}

// The session's fields as checkboxes (read again when the list is opened: new fields appear).
async function listFields() {
  const list = document.getElementById("live-field-list");
  if (!list || !state.sid) return;
  const sid = state.sid;
  const body = await apiJSON(`/api/sessions/${sid}/telemetry/fields`).catch(() => null);
  if (!body || sid !== state.sid) return;
  for (const f of body.fields) state.units[f.name] = f.unit;
  state.listed = body.fields.length;
  text(document.querySelector("#live-fields summary"), `More telemetry to plot (${body.fields.length} fields)`);
  list.replaceChildren(
    ...body.fields.map((f) => {
      const input = el("input", { type: "checkbox", value: f.name });
      input.checked = state.fields.includes(f.name);
      input.addEventListener("change", () => {
        state.fields = [...list.querySelectorAll("input:checked")].map((i) => i.value).slice(0, MAX_FIELDS);
        keep({ drive_plot_fields: state.fields });
        rebuild();
      });
      return el("label", { class: "small" }, input, ` ${f.name}${f.unit ? ` (${f.unit})` : ""}`);
    }),
  );
  rebuild();
}

// No robot any more: no stale values.
export function resetLivePlots() {
  state.sid = null;
  state.t = [];
  state.values = new Map();
  for (const { plot, names } of state.plots) plot.setData([[], ...names.map(() => [])]);
}

// One telemetry sample of the session on view.
export function recordLivePlots(sid, data) {
  if (sid !== state.sid) {
    resetLivePlots();
    state.sid = sid;
    listFields();
  }
  const t = data.t || Date.now() / 1000;
  const values = numericFields(data);
  state.t.push(t);
  for (const f of state.fields) {
    if (!state.values.has(f)) state.values.set(f, new Array(state.t.length - 1).fill(null));
    state.values.get(f).push(values[f] ?? null);
  }
  while (state.t.length && state.t[0] < t - WINDOW_S) {
    state.t.shift();
    for (const v of state.values.values()) v.shift();
  }
}

export function redrawLivePlots() {
  const target = box();
  if (target) target.dataset.points = String(state.t.length);
  for (const { plot, names } of state.plots) {
    plot.setData([
      state.t,
      ...names.map((n) => {
        const v = state.values.get(n) || [];
        return v.length === state.t.length ? v : [...new Array(state.t.length - v.length).fill(null), ...v];
      }),
    ]);
  }
}

export async function initLivePlots() {
  const prefs = await preferences();
  state.fields = Array.isArray(prefs.drive_plot_fields) ? prefs.drive_plot_fields.slice(0, MAX_FIELDS) : [];
  document.getElementById("live-fields")?.addEventListener("toggle", (e) => {
    if (e.target.open) listFields();
  });
  rebuild();
}
