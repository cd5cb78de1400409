// One session timeline, as Foxglove's playback is: a slider over every camera frame (and
// play at 1×/4×/16×) that moves every view of the session together — the frame itself, the
// robot and its camera's footprint on the coverage map, the mosaic cursor and the 3D view's
// robot (through ``onMoment``), and the cursor of the telemetry plots. Defects are ticks at
// the frame they were first seen in. Each moment's placement comes from the station
// (GET /api/sessions/{id}/timeline), the same the coverage map and the mosaic use.
import uPlot from "/vendor/uplot/uPlot.esm.js";
import { apiJSON, el, fmt, text } from "./api.js";
import { imageURL } from "./images.js";
import { byUnit } from "./plan_view.js";
import { keep, preferences } from "./preferences.js";
import { drawMap } from "./timeline_map.js";

const SPEEDS = [1, 4, 16];
const TICK_MS = 50; // how often playback advances
const LIVE_POLL_MS = 3000; // a live session's new frames
const DEFAULT_FIELDS = ["wheel_speed_mps[0]", "battery_v.main", "adhesion_margin"];
const PLOT_COLOURS = ["#e0a030", "#3fae6a", "#4a90d9", "#d9443c", "#b07cd8", "#2ec4b6"];

let current = null; // the timeline on view

function clock(seconds) {
  const t = Math.max(0, Math.round(seconds));
  return `${String(Math.floor(t / 60)).padStart(2, "0")}:${String(t % 60).padStart(2, "0")}`;
}

// Which telemetry fields this user plots (kept with their preferences), of those there are.
function chosenFields(available, kept) {
  const names = new Set(available.map((f) => f.name));
  const wanted = Array.isArray(kept) ? kept : DEFAULT_FIELDS;
  const out = wanted.filter((n) => names.has(n));
  return out.length || Array.isArray(kept) ? out : available.slice(0, 2).map((f) => f.name);
}

// The index of the last moment at or before time t (s since the session's start).
function momentAt(frames, t) {
  let lo = 0;
  let hi = frames.length - 1;
  while (lo < hi) {
    const mid = (lo + hi + 1) >> 1;
    if (frames[mid].t_s <= t) lo = mid;
    else hi = mid - 1;
  }
  return lo;
}

function plotWidth(box) {
  return Math.max(240, Math.min(560, box.clientWidth - 8 || 320));
}

// One plot per unit of the chosen fields, each with the timeline's cursor drawn on it;
// a click on a plot moves the timeline to that moment.
async function loadPlots(tl) {
  const box = tl.plotBox;
  for (const p of tl.plots) p.destroy();
  tl.plots = [];
  box.replaceChildren();
  if (!tl.fields.length) {
    box.append(el("p", { class: "muted small" }, "no telemetry field chosen"));
    return;
  }
  const q = tl.fields.map((f) => `field=${encodeURIComponent(f)}`).join("&");
  const s = await apiJSON(`/api/sessions/${tl.sid}/telemetry/series?${q}&max_points=3000`);
  const t = s.timestamps.map((v) => v - tl.data.start);
  const groups = byUnit(tl.fields, (f) => s.units[f]);
  let colour = 0;
  for (const [unit, names] of groups) {
    const target = el("div", { class: "plot", dataset: { unit: unit || "none" } });
    box.append(target);
    const plot = new uPlot(
      {
        title: unit ? `${names.join(", ")} (${unit})` : names.join(", "),
        width: plotWidth(box),
        height: 150,
        legend: { show: true, live: false },
        cursor: { drag: { x: false, y: false } },
        scales: { x: { time: false } },
        axes: [
          { stroke: "#8b96a0", grid: { stroke: "#2a323a" }, label: "s" },
          { stroke: "#8b96a0", grid: { stroke: "#2a323a" }, label: unit, size: 50 },
        ],
        series: [
          { label: "t (s)" },
          ...names.map((n) => ({ label: n, stroke: PLOT_COLOURS[colour++ % PLOT_COLOURS.length], width: 1.5 })),
        ],
        hooks: {
          draw: [
            (u) => {
              const x = u.valToPos(tl.data.frames[tl.index].t_s, "x", true);
              const c = u.ctx;
              c.save();
              c.strokeStyle = "#ffd60a";
              c.lineWidth = 2;
              c.beginPath();
              c.moveTo(x, u.bbox.top);
              c.lineTo(x, u.bbox.top + u.bbox.height);
              c.stroke();
              c.restore();
            },
          ],
        },
      },
      [t, ...names.map((n) => s.series[n])],
      target,
    );
    plot.over.addEventListener("click", (e) => {
      const at = plot.posToVal(e.offsetX, "x");
      tl.show(momentAt(tl.data.frames, at));
    });
    tl.plots.push(plot);
  }
  box.dataset.fields = tl.fields.join(",");
}

function fieldPicker(tl) {
  const boxes = tl.data.telemetry.fields.map((f) => {
    const input = el("input", { type: "checkbox", value: f.name });
    input.checked = tl.fields.includes(f.name);
    input.addEventListener("change", () => {
      tl.fields = [...tl.pickerNode.querySelectorAll("input:checked")].map((i) => i.value).slice(0, 12);
      keep({ plot_fields: tl.fields });
      loadPlots(tl).catch((e) => text(tl.plotBox, `plots unavailable: ${e.message}`));
    });
    return el("label", { class: "small" }, input, ` ${f.name}${f.unit ? ` (${f.unit})` : ""}`);
  });
  tl.pickerNode = el("div", { class: "field-list" }, ...boxes);
  return el(
    "details",
    { id: "timeline-fields" },
    el("summary", {}, `Telemetry to plot (${tl.data.telemetry.fields.length} fields)`),
    tl.pickerNode,
  );
}

// One tick per frame where defects were first seen; a click goes there and selects the
// next of its defects (each click the next, where several were first seen together).
function ticks(tl) {
  const n = tl.data.frames.length;
  const index = new Map(tl.data.frames.map((m, i) => [m.seq, i]));
  const at = new Map(); // frame index -> its defects
  for (const d of tl.defects) {
    if (d.first_seq === null || !index.has(d.first_seq)) continue;
    const i = index.get(d.first_seq);
    if (!at.has(i)) at.set(i, []);
    at.get(i).push(d);
  }
  const name = (d) => `${d.source === "frame" ? "F" : "#"}${d.number ?? d.id}`;
  return [...at.entries()].map(([i, ds]) => {
    let next = 0;
    const names = ds.map((d) => `${name(d)} ${d.defect_class}`).join(", ");
    const classes = [...new Set(ds.map((d) => d.defect_class))].join(" ");
    return el(
      "button",
      {
        class: `timeline-tick ${classes}${ds.length > 1 ? " several" : ""}`,
        style: `left: ${n > 1 ? (100 * i) / (n - 1) : 0}%`,
        title: `${names}: first seen in frame ${tl.data.frames[i].seq}`,
        "aria-label": `${ds.length > 1 ? `defects ${names}` : `defect ${names}`}, first seen at ${clock(tl.data.frames[i].t_s)}`,
        dataset: { defects: ds.map((d) => d.id).join(" "), index: i },
        onclick: () => {
          tl.show(i);
          tl.onDefect?.(ds[next % ds.length].id);
          next += 1;
        },
      },
      ds.length > 1 ? String(ds.length) : "",
    );
  });
}

// The session's timeline; ``defects`` are the page's defect records (for their place on the
// coverage map); ``onMoment(moment)`` moves the page's other views; ``onDefect(id)`` selects.
export function sessionTimeline(sid, { defects = [], onMoment = null, onDefect = null, live = false } = {}) {
  if (current) {
    current.stop?.();
    clearInterval(current.poll);
  }
  const node = el("section", { id: "timeline", class: "moments" }, el("p", { class: "muted small" }, "timeline: …"));
  const tl = { sid, node, index: 0, plots: [], playing: null, speed: 1, onDefect, fields: [] };
  current = tl;
  tl.ids = new Set(defects.map((d) => d.id));
  tl.places = new Map(
    defects
      .filter((d) => d.world_x_m !== null)
      .map((d) => [d.id, [d.world_x_m, d.world_y_m, d.world_w_m || 0, d.world_h_m || 0]]),
  );
  const slider = el("input", {
    id: "timeline-slider",
    type: "range",
    min: "0",
    max: "0",
    step: "1",
    "aria-label": "session timeline: one step a frame",
  });
  const readout = el("span", { id: "timeline-readout", class: "mono small" });
  const play = el("button", { id: "timeline-play", "aria-label": "play the session" }, "▶ Play");
  const speed = el(
    "select",
    { id: "timeline-speed", "aria-label": "playback speed" },
    ...SPEEDS.map((v) => el("option", { value: String(v) }, `${v}×`)),
  );
  const frameImg = el("img", { id: "timeline-frame", alt: "camera frame at this moment" });
  tl.canvas = el("canvas", {
    id: "timeline-map",
    width: "480",
    height: "300",
    "aria-label": "coverage map at this moment",
  });
  tl.plotBox = el("div", { id: "timeline-plots", class: "timeline-plots" });
  // the plots follow the page's width (a window narrowed, a phone turned)
  new ResizeObserver(() => {
    for (const p of tl.plots) p.setSize({ width: plotWidth(tl.plotBox), height: 150 });
  }).observe(tl.plotBox);
  const track = el("div", { class: "timeline-track" }, slider);

  tl.show = (i) => {
    const frames = tl.data.frames;
    i = Math.max(0, Math.min(frames.length - 1, i));
    tl.index = i;
    const m = frames[i];
    slider.value = String(i);
    node.dataset.index = String(i);
    node.dataset.seq = String(m.seq);
    node.dataset.t = String(m.t_s);
    node.dataset.robot = m.robot ? m.robot.join(",") : "";
    const where = m.robot
      ? `x ${fmt(m.robot[0], 3)} m, y ${fmt(m.robot[1], 3)} m, heading ${fmt((m.robot[2] * 180) / Math.PI, 1)}° (${m.placed_by})`
      : "no pose";
    text(
      readout,
      `frame ${m.seq} (${i + 1}/${frames.length}) · +${clock(m.t_s)} / ${clock(tl.data.duration_s)} · ${where}`,
    );
    const seq = m.seq;
    imageURL(`/api/sessions/${sid}/frames/${seq}/image`).then((url) => {
      if (url && tl.data.frames[tl.index]?.seq === seq) {
        frameImg.src = url;
        frameImg.dataset.seq = String(seq);
      }
    });
    drawMap(tl);
    for (const p of tl.plots) p.redraw(false);
    onMoment?.(m, `frame ${m.seq} · +${clock(m.t_s)}`);
  };
  const stop = () => {
    clearInterval(tl.playing);
    tl.playing = null;
    text(play, "▶ Play");
    node.dataset.playing = "false";
  };
  tl.toggle = () => {
    if (tl.playing) return stop();
    if (tl.index >= tl.data.frames.length - 1) tl.show(0);
    let t = tl.data.frames[tl.index].t_s;
    let last = performance.now();
    text(play, "❚❚ Pause");
    node.dataset.playing = "true";
    let played = tl.index; // the moment playback showed last
    tl.playing = setInterval(() => {
      if (!node.isConnected) return stop();
      const now = performance.now();
      if (tl.index !== played) t = tl.data.frames[tl.index].t_s; // moved meanwhile: go on from there
      t += ((now - last) / 1000) * tl.speed;
      last = now;
      const i = momentAt(tl.data.frames, t);
      if (i !== tl.index) tl.show(i);
      played = tl.index;
      if (i >= tl.data.frames.length - 1) stop();
    }, TICK_MS);
  };
  tl.stop = stop;
  slider.addEventListener("input", () => tl.show(Number(slider.value)));
  play.addEventListener("click", () => tl.toggle());
  speed.addEventListener("change", () => {
    tl.speed = Number(speed.value);
  });

  const build = (data) => {
    tl.data = data;
    tl.defects = data.defects.filter((d) => tl.ids.has(d.id)); // the defects the page lists
    slider.max = String(Math.max(0, data.frames.length - 1));
    track.replaceChildren(slider, el("div", { class: "timeline-ticks" }, ...ticks(tl)));
    node.dataset.frames = String(data.frames.length);
    node.dataset.ticks = String(track.querySelectorAll(".timeline-tick").length);
  };
  Promise.all([apiJSON(`/api/sessions/${sid}/timeline`), preferences()])
    .then(([data, prefs]) => {
      if (!data.frames.length) {
        node.replaceChildren(el("p", { class: "muted small" }, "timeline: the session stored no frame"));
        return;
      }
      build(data);
      tl.fields = chosenFields(data.telemetry.fields, prefs.plot_fields);
      node.replaceChildren(
        el("h4", {}, "Timeline"),
        el(
          "div",
          { class: "timeline-bar" },
          play,
          speed,
          el(
            "button",
            { id: "timeline-prev", "aria-label": "previous frame", onclick: () => tl.show(tl.index - 1) },
            "◀",
          ),
          el("button", { id: "timeline-next", "aria-label": "next frame", onclick: () => tl.show(tl.index + 1) }, "▶"),
          track,
        ),
        readout,
        el(
          "p",
          { class: "muted small" },
          "Keys: ← / → or , / . frame by frame · p play / pause · defects are ticks on the timeline",
        ),
        el("div", { class: "timeline-views" }, frameImg, tl.canvas),
        fieldPicker(tl),
        tl.plotBox,
      );
      tl.show(0);
      loadPlots(tl).catch((e) => text(tl.plotBox, `plots unavailable: ${e.message}`));
      if (live) {
        // a live session: new frames join the timeline; one at its end follows them
        tl.poll = setInterval(async () => {
          if (!node.isConnected) return clearInterval(tl.poll);
          const next = await apiJSON(`/api/sessions/${sid}/timeline`).catch(() => null);
          if (!next || next.frames.length === tl.data.frames.length) return;
          const atEnd = tl.index >= tl.data.frames.length - 1;
          build(next);
          tl.show(atEnd ? next.frames.length - 1 : tl.index);
        }, LIVE_POLL_MS);
      }
    })
    .catch((e) => node.replaceChildren(el("p", { class: "muted small" }, `timeline unavailable: ${e.message}`)));
  return tl;
}

// Move the timeline to the frame a defect was first seen in (a defect selected elsewhere).
export function seekDefect(id) {
  const tl = current;
  if (!tl?.data || !tl.node.isConnected) return;
  const d = tl.data.defects.find((x) => x.id === id);
  const i = d ? tl.data.frames.findIndex((m) => m.seq === d.first_seq) : -1;
  if (i >= 0 && i !== tl.index) tl.show(i);
}

// Frame-by-frame keys on the session page (not while typing).
export function initTimeline() {
  document.addEventListener("keydown", (e) => {
    const tl = current;
    if (!tl?.data || !tl.node.isConnected || document.getElementById("view-session").hidden) return;
    if (["INPUT", "SELECT", "TEXTAREA"].includes(e.target.tagName) && e.target.id !== "timeline-slider") return;
    if (e.ctrlKey || e.metaKey || e.altKey) return;
    if (e.target.id === "timeline-slider" && e.key.startsWith("Arrow")) return; // the slider steps itself
    if (e.key === "ArrowRight" || e.key === ".") {
      e.preventDefault();
      tl.show(tl.index + 1);
    } else if (e.key === "ArrowLeft" || e.key === ",") {
      e.preventDefault();
      tl.show(tl.index - 1);
    } else if (e.key === "p") {
      e.preventDefault();
      tl.toggle();
    }
  });
}
