// The session page's views of one moment of the timeline, beside the timeline's own: the
// mosaic cursor (the camera's footprint drawn on the mosaic) and the robot in the 3D view.
import { api, el } from "./api.js";

// The camera's footprint at the moment, where the mosaic's own placement (mosaic.json) puts
// it: world metres to mosaic pixels, an OpenSeadragon overlay turned with the frame.
export function mosaicCursor() {
  let viewer = null;
  let world = null;
  let node = null;
  let moment = null;
  const move = (m) => {
    moment = m;
    if (!viewer || !world?.world_referenced || !world.px_per_m || !m?.footprint) return;
    const k = world.px_per_m;
    const p = m.footprint.map(([x, y]) => [(x - world.origin_m[0]) * k, (y - world.origin_m[1]) * k]);
    const cx = p.reduce((a, q) => a + q[0], 0) / 4;
    const cy = p.reduce((a, q) => a + q[1], 0) / 4;
    const fw = Math.hypot(p[1][0] - p[0][0], p[1][1] - p[0][1]);
    const fh = Math.hypot(p[2][0] - p[1][0], p[2][1] - p[1][1]);
    const angle = Math.atan2(p[1][1] - p[0][1], p[1][0] - p[0][0]);
    const rect = viewer.viewport.imageToViewportRectangle(cx - fw / 2, cy - fh / 2, fw, fh);
    if (!node) {
      node = el("div", { id: "mosaic-cursor", class: "mosaic-cursor" }, el("div", { class: "mosaic-cursor-frame" }));
      viewer.addOverlay({ element: node, location: rect });
    } else {
      viewer.updateOverlay(node, rect);
    }
    node.firstChild.style.transform = `rotate(${angle}rad)`;
    Object.assign(node.dataset, { seq: String(m.seq), cx: cx.toFixed(1), cy: cy.toFixed(1) });
  };
  return {
    move,
    // the viewer has opened its mosaic: draw the moment shown so far
    attach(v, w) {
      viewer = v;
      world = w;
      node = null;
      if (moment) move(moment);
    },
    get moment() {
      return moment;
    },
  };
}

// The robot at the moment in the session's 3D view (when it is open): one request at a
// time, the latest moment wins.
export function robotIn3d(sid) {
  let busy = false;
  let next = null;
  let last = null;
  const send = (body) => {
    busy = true;
    api(`/api/sessions/${sid}/view3d/moment`, {
      method: "POST",
      headers: { "Content-Type": "application/json" },
      body: JSON.stringify(body),
    })
      .catch(() => {})
      .finally(() => {
        busy = false;
        const queued = next;
        next = null;
        if (queued) send(queued);
      });
  };
  const move = (m, words) => {
    if (!m?.robot) return;
    last = { x: m.robot[0], y: m.robot[1], yaw: m.robot[2], label: words };
    if (!document.getElementById("view3d")) return;
    if (busy) next = last;
    else send(last);
  };
  return {
    move,
    // the 3D view has just opened: show it the moment on view
    resend() {
      if (last && document.getElementById("view3d")) send(last);
    },
  };
}
