// The coverage map of a session's timeline: every frame's footprint (those imaged by the
// moment shown filled), the path driven so far, the defects (coloured once seen), the
// camera's footprint now and the robot, in world metres: x right, y down, as the mosaic.
import { drawRobot } from "./plan_view.js";

const CLASS_COLOURS = { crack: "#ff3b30", corrosion: "#ffcc00" };

// ``tl``: {canvas, data: the timeline, index: the moment shown, defects, places: id -> box}
export function drawMap(tl) {
  const canvas = tl.canvas;
  const ctx = canvas.getContext("2d");
  const W = canvas.width;
  const H = canvas.height;
  ctx.setTransform(1, 0, 0, 1, 0, 0);
  ctx.fillStyle = "#0d1014";
  ctx.fillRect(0, 0, W, H);
  const placed = tl.data.frames.filter((m) => m.footprint);
  if (!placed.length) {
    ctx.fillStyle = "#8b96a0";
    ctx.font = "14px system-ui";
    ctx.textAlign = "center";
    ctx.fillText("no frame placed on the structure", W / 2, H / 2);
    return;
  }
  const xs = placed.flatMap((m) => m.footprint.map((p) => p[0]));
  const ys = placed.flatMap((m) => m.footprint.map((p) => p[1]));
  const b = {
    x0: Math.min(...xs) - 0.05,
    y0: Math.min(...ys) - 0.05,
    x1: Math.max(...xs) + 0.05,
    y1: Math.max(...ys) + 0.05,
  };
  const k = Math.min(W / (b.x1 - b.x0), H / (b.y1 - b.y0));
  // x right, y down: the mosaic's orientation, so the two read alike
  ctx.setTransform(k, 0, 0, k, (W - k * (b.x1 + b.x0)) / 2, (H - k * (b.y1 + b.y0)) / 2);
  const px = 1 / k;
  const poly = (pts) => {
    ctx.beginPath();
    pts.forEach(([x, y], i) => (i ? ctx.lineTo(x, y) : ctx.moveTo(x, y)));
    ctx.closePath();
  };
  const now = tl.data.frames[tl.index];
  for (const m of placed) {
    poly(m.footprint);
    ctx.fillStyle = m.t_s <= now.t_s ? "rgba(63, 174, 106, 0.16)" : "rgba(139, 150, 160, 0.06)";
    ctx.fill();
  }
  const path = tl.data.frames.filter((m) => m.robot && m.t_s <= now.t_s);
  if (path.length > 1) {
    ctx.beginPath();
    path.forEach((m, i) => (i ? ctx.lineTo(m.robot[0], m.robot[1]) : ctx.moveTo(m.robot[0], m.robot[1])));
    ctx.strokeStyle = "#e0a030";
    ctx.lineWidth = 2 * px;
    ctx.stroke();
  }
  for (const d of tl.defects) {
    const at = tl.places.get(d.id);
    if (!at) continue;
    const seen = d.t_s !== null && d.t_s <= now.t_s;
    ctx.strokeStyle = seen ? CLASS_COLOURS[d.defect_class] || "#fff" : "rgba(139, 150, 160, 0.5)";
    ctx.lineWidth = (seen ? 2 : 1) * px;
    ctx.strokeRect(at[0] - 3 * px, at[1] - 3 * px, at[2] + 6 * px, at[3] + 6 * px);
  }
  if (now.footprint) {
    poly(now.footprint);
    ctx.strokeStyle = "#ffd60a";
    ctx.lineWidth = 2 * px;
    ctx.stroke();
  }
  if (now.robot) drawRobot(ctx, now.robot[0], now.robot[1], now.robot[2], 12 * px, px);
}
