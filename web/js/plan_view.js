// What the plan views (the Drive page's coverage map, the session timeline's) draw alike.

// The robot: a triangle ``r`` across pointing along its heading, at (x, y) world metres on
// a context scaled to metres (``px``: metres per screen pixel).
export function drawRobot(ctx, x, y, yaw, r, px) {
  ctx.save();
  ctx.translate(x, y);
  ctx.rotate(yaw);
  ctx.beginPath();
  ctx.moveTo(r, 0);
  ctx.lineTo(-r * 0.7, r * 0.6);
  ctx.lineTo(-r * 0.7, -r * 0.6);
  ctx.closePath();
  ctx.fillStyle = "#4a90d9";
  ctx.fill();
  ctx.strokeStyle = "#fff";
  ctx.lineWidth = 1.5 * px;
  ctx.stroke();
  ctx.restore();
}

// Fields grouped by their unit (one plot per unit): unit -> [field, ...], in the fields' order.
export function byUnit(fields, unitOf) {
  const groups = new Map();
  for (const f of fields) {
    const unit = unitOf(f) || "";
    if (!groups.has(unit)) groups.set(unit, []);
    groups.get(unit).push(f);
  }
  return groups;
}
