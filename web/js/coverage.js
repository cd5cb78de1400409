// The Drive page's coverage map: a plan view of the surface in world coordinates (x along,
// y across) with the robot's pose and heading, its trajectory, each captured frame placed at
// its odometry pose as it arrives and then where the station's registration puts it (the
// live 3D map's while the robot drives, the mosaic's after), and what counts as imaged at
// the required resolution: footprints that do not count outlined red, holes filled red.
// The trajectory and the defects seen in frames are kept for every live session, from the
// station's coverage_state as the page connects and the live events after it, so a page
// reloaded, opened in another tab or switched between robots draws them all.
import { api, apiJSON, el, fmt, text } from "./api.js";
import { selectedSession } from "./drive.js";
import { EVENT } from "./events.js";
import { on } from "./live.js";
import { drawRobot } from "./plan_view.js";

const POLL_MS = 1500;
const THUMB_W = 160;
const state = {
  sid: null,
  camera: null,
  frames: [],
  trail: [],
  pose: null,
  cov: null,
  busy: false,
  found: [],
  sweep: null,
};
// session id -> {trail: [{x, y}], found: [{seq, defect_class, world_box, ...}], pose, sweep}
const kept = new Map();
let canvas;
let ctx;

function keep(sid) {
  if (!kept.has(sid)) kept.set(sid, { trail: [], found: [], pose: null, sweep: null });
  return kept.get(sid);
}

function reset(sid) {
  const k = sid ? keep(sid) : { trail: [], found: [], pose: null, sweep: null };
  Object.assign(state, { sid, camera: null, frames: [], cov: null, ...k });
  if (sid) {
    apiJSON(`/api/sessions/${sid}`)
      .then((s) => {
        if (state.sid === sid) state.camera = s.calibration?.camera || null;
      })
      .catch(() => {});
  }
  draw();
}

// World corners of a downward-camera image at a robot pose (the station's image_to_world).
function footprintAt(pose) {
  const cam = state.camera;
  if (!cam?.px_per_m) return null;
  const [mx, my] = cam.T_robot_camera || [0, 0];
  const c = Math.cos(pose.yaw);
  const s = Math.sin(pose.yaw);
  const cx = pose.x + c * mx - s * my;
  const cy = pose.y + s * mx + c * my;
  const w = cam.width / cam.px_per_m;
  const h = cam.height / cam.px_per_m;
  return { cx, cy, yaw: pose.yaw, w, h };
}

// Place a frame's picture: from its pose as it arrives, or from the station's footprint.
function place(seq, at, blob) {
  if (!at || state.frames.some((f) => f.seq === seq)) return;
  const entry = { seq, ...at, bmp: null };
  state.frames.push(entry);
  createImageBitmap(blob, { resizeWidth: THUMB_W, resizeQuality: "low" })
    .then((bmp) => {
      entry.bmp = bmp;
      draw();
    })
    .catch(() => {});
}

function fromFootprint([a, b, c]) {
  return {
    cx: (a[0] + c[0]) / 2,
    cy: (a[1] + c[1]) / 2,
    yaw: Math.atan2(b[1] - a[1], b[0] - a[0]),
    w: Math.hypot(b[0] - a[0], b[1] - a[1]),
    h: Math.hypot(c[0] - b[0], c[1] - b[1]),
  };
}

function onFrame(header, jpeg) {
  if (header.video || !header.pose || header.session_id !== selectedSession()) return;
  if (header.session_id !== state.sid) reset(header.session_id);
  const at = footprintAt(header.pose);
  if (at) place(header.seq, at, new Blob([jpeg], { type: "image/jpeg" }));
}

// Frames stored before this page opened (or while the calibration was unknown): fetched.
async function fetchMissing(sid) {
  const missing = (state.cov?.frames || []).filter((f) => !state.frames.some((g) => g.seq === f.seq)).slice(0, 12);
  for (const f of missing) {
    try {
      const res = await api(`/api/sessions/${sid}/frames/${f.seq}/image`);
      if (res.ok && sid === state.sid) place(f.seq, fromFootprint(f.footprint), await res.blob());
    } catch {
      return;
    }
  }
}

function onEvent(ev) {
  if (ev.type === EVENT.COVERAGE_STATE) {
    // what the station kept of this session so far: it replaces what this page has
    const k = keep(ev.session_id);
    k.trail.length = 0;
    for (const [x, y] of ev.trail) k.trail.push({ x, y });
    k.found.length = 0;
    k.found.push(...ev.found);
  } else if (ev.type === EVENT.FRAME_DEFECTS) {
    // searched as it arrived
    keep(ev.session_id).found.push(...ev.defects.map((d) => ({ seq: ev.seq, ...d })));
  } else if (ev.type === EVENT.TELEMETRY && ev.data.pose) {
    const k = keep(ev.session_id);
    const p = ev.data.pose;
    k.pose = p;
    k.sweep = ev.data.sweep || null;
    const last = k.trail[k.trail.length - 1];
    if (!last || Math.hypot(p.x - last.x, p.y - last.y) > 0.005) k.trail.push({ x: p.x, y: p.y });
    if (ev.session_id === state.sid) Object.assign(state, { pose: k.pose, sweep: k.sweep });
    return; // drawn at the next poll
  } else if (ev.type === EVENT.SESSION && ev.event === "session_end") {
    kept.delete(ev.session_id);
    return;
  } else {
    return;
  }
  if (ev.session_id !== state.sid) return;
  draw();
  summary();
}

async function poll() {
  const sid = selectedSession();
  if (sid !== state.sid) reset(sid);
  if (!sid || state.busy || document.getElementById("view-drive").hidden) {
    draw();
    return;
  }
  state.busy = true;
  try {
    const cov = await apiJSON(`/api/sessions/${sid}/coverage`);
    if (sid === state.sid) state.cov = cov;
    draw();
    summary();
    await fetchMissing(sid);
  } catch {
    // the next poll tries again
  } finally {
    state.busy = false;
  }
  draw();
}

function bounds() {
  const xs = [];
  const ys = [];
  const add = (x, y) => {
    xs.push(x);
    ys.push(y);
  };
  for (const f of state.cov?.frames || []) for (const [x, y] of f.footprint) add(x, y);
  for (const f of state.frames) {
    add(f.cx - f.w / 2, f.cy - f.w / 2);
    add(f.cx + f.w / 2, f.cy + f.w / 2);
  }
  for (const p of state.trail) add(p.x, p.y);
  if (!xs.length) return null;
  const pad = 0.1;
  return { x0: Math.min(...xs) - pad, y0: Math.min(...ys) - pad, x1: Math.max(...xs) + pad, y1: Math.max(...ys) + pad };
}

function draw() {
  if (!ctx) return;
  const W = canvas.width;
  const H = canvas.height;
  ctx.setTransform(1, 0, 0, 1, 0, 0);
  ctx.fillStyle = "#0d1014";
  ctx.fillRect(0, 0, W, H);
  const b = bounds();
  canvas.dataset.frames = String(state.cov?.frames.length ?? 0);
  canvas.dataset.found = String(state.found.length);
  canvas.dataset.trail = String(state.trail.length);
  if (!b) {
    ctx.fillStyle = "#8b96a0";
    ctx.font = "14px system-ui";
    ctx.textAlign = "center";
    ctx.fillText(state.sid ? "waiting for frames" : "no robot connected", W / 2, H / 2);
    return;
  }
  const k = Math.min(W / (b.x1 - b.x0), H / (b.y1 - b.y0));
  ctx.setTransform(k, 0, 0, k, (W - k * (b.x1 + b.x0)) / 2, (H - k * (b.y1 + b.y0)) / 2);
  const px = 1 / k;
  const grid = state.cov?.grid;
  // the live mosaic: each frame where the station placed it (the mosaic's or the live map's
  // registration), at its odometry pose until the station has placed it
  const placed = new Map((state.cov?.frames || []).map((f) => [f.seq, f.footprint]));
  for (const f of state.frames) {
    if (!f.bmp) continue;
    const at = placed.has(f.seq) ? fromFootprint(placed.get(f.seq)) : f;
    ctx.save();
    ctx.translate(at.cx, at.cy);
    ctx.rotate(at.yaw);
    ctx.drawImage(f.bmp, -at.w / 2, -at.h / 2, at.w, at.h);
    ctx.restore();
  }
  if (grid) {
    ctx.fillStyle = "rgba(217, 68, 60, 0.75)";
    grid.holes_rle.forEach((runs, r) => {
      for (let i = 0; i < runs.length; i += 2) {
        ctx.fillRect(
          grid.origin_m[0] + runs[i] * grid.cell_m,
          grid.origin_m[1] + r * grid.cell_m,
          runs[i + 1] * grid.cell_m,
          grid.cell_m,
        );
      }
    });
  }
  // footprints: green when they count, red when not
  for (const f of state.cov?.frames || []) {
    ctx.beginPath();
    f.footprint.forEach(([x, y], i) => (i ? ctx.lineTo(x, y) : ctx.moveTo(x, y)));
    ctx.closePath();
    ctx.strokeStyle = f.counts ? "rgba(63, 174, 106, 0.5)" : "#ff3b30";
    ctx.lineWidth = (f.counts ? 1 : 2.5) * px;
    ctx.stroke();
  }
  // defects seen in single frames (the detect job confirms them)
  for (const d of state.found) {
    const [x, y, w, h] = d.world_box;
    ctx.strokeStyle = d.defect_class === "crack" ? "#ff3b30" : "#ffcc00";
    ctx.lineWidth = 2 * px;
    ctx.strokeRect(x - 3 * px, y - 3 * px, w + 6 * px, h + 6 * px);
  }
  drawSweep(px);
  if (state.trail.length > 1) {
    ctx.beginPath();
    state.trail.forEach((p, i) => (i ? ctx.lineTo(p.x, p.y) : ctx.moveTo(p.x, p.y)));
    ctx.strokeStyle = "#e0a030";
    ctx.lineWidth = 2 * px;
    ctx.stroke();
  }
  // the robot: a triangle pointing along its heading
  if (state.pose) drawRobot(ctx, state.pose.x, state.pose.y, state.pose.yaw, 14 * px, px);
  scaleBar(k);
}

// The autonomous sweep's plan and progress: the plate's outline as its edges were found,
// the lanes driven (solid) and the next one planned (dashed), the edge points met.
function drawSweep(px) {
  const s = state.sweep;
  if (!s) return;
  ctx.save();
  ctx.strokeStyle = "#5ac8fa";
  ctx.lineWidth = 1.5 * px;
  if (s.plate_outline) {
    ctx.setLineDash([6 * px, 4 * px]);
    ctx.beginPath();
    s.plate_outline.forEach(([x, y], i) => (i ? ctx.lineTo(x, y) : ctx.moveTo(x, y)));
    ctx.closePath();
    ctx.stroke();
  }
  ctx.setLineDash([]);
  for (const [x0, y0, x1, y1] of s.lanes || []) {
    ctx.beginPath();
    ctx.moveTo(x0, y0);
    ctx.lineTo(x1, y1);
    ctx.stroke();
  }
  if (s.next_lane) {
    const [x0, y0, x1, y1] = s.next_lane;
    ctx.setLineDash([4 * px, 4 * px]);
    ctx.beginPath();
    ctx.moveTo(x0, y0);
    ctx.lineTo(x1, y1);
    ctx.stroke();
    ctx.setLineDash([]);
  }
  ctx.fillStyle = "#5ac8fa";
  for (const [x, y] of s.edges_found || []) ctx.fillRect(x - 3 * px, y - 3 * px, 6 * px, 6 * px);
  ctx.restore();
}

function scaleBar(k) {
  const m = [0.05, 0.1, 0.2, 0.5, 1, 2, 5].find((v) => v * k > 60) || 5;
  ctx.setTransform(1, 0, 0, 1, 0, 0);
  ctx.fillStyle = "#e4e8ec";
  ctx.fillRect(10, canvas.height - 14, m * k, 3);
  ctx.font = "12px system-ui";
  ctx.textAlign = "left";
  ctx.fillText(m < 1 ? `${m * 100} cm` : `${m} m`, 10, canvas.height - 20);
}

function summary() {
  const cov = state.cov;
  const out = document.getElementById("coverage-summary");
  const list = document.getElementById("coverage-holes");
  if (!cov?.area_surface_m2) {
    text(out, "no frame placed yet");
    list.replaceChildren();
    return;
  }
  const why = {};
  for (const f of cov.frames) if (!f.counts) why[f.why_not] = (why[f.why_not] || 0) + 1;
  const notCounted = Object.entries(why)
    .map(([r, n]) => `${n} ${r}`)
    .join(", ");
  const cracks = state.found.filter((d) => d.defect_class === "crack").length;
  const found = state.found.length
    ? ` · seen in frames: ${cracks} crack, ${state.found.length - cracks} corrosion`
    : "";
  text(
    out,
    `imaged at ≤ ${cov.required_mm_per_px} mm/px: ` +
      `${fmt(cov.area_imaged_m2, 3)} of ${fmt(cov.area_surface_m2, 3)} m² ` +
      `(${fmt(cov.fraction_imaged * 100, 1)} %) · ${cov.holes.length} hole${cov.holes.length === 1 ? "" : "s"}` +
      `${notCounted ? ` · frames not counted: ${notCounted}` : ""}${found}`,
  );
  list.replaceChildren(
    ...cov.holes
      .slice(0, 8)
      .map((h, i) =>
        el(
          "li",
          {},
          `hole ${i + 1} at x ${fmt(h.x_m, 2)} m, y ${fmt(h.y_m, 2)} m — ` +
            `${fmt(h.bbox_m[2] * 100, 0)} × ${fmt(h.bbox_m[3] * 100, 0)} cm`,
        ),
      ),
  );
}

export function initCoverage() {
  canvas = document.getElementById("coverage-map");
  ctx = canvas.getContext("2d");
  on("frame", onFrame);
  on("event", onEvent);
  setInterval(poll, POLL_MS);
  poll();
}
