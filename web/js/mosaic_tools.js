// Tools on the mosaic viewer: a legend, a scale bar, the cursor's position on the structure
// (metres), a measuring tool (mm between two clicks) and drawing a missed defect (two corners).
// World coordinates of mosaic pixel p: origin_m + p / px_per_m (the stitch job's mosaic.json).
import { el, fmt, text } from "./api.js";

const OSD = () => window.OpenSeadragon;

export function toolbar() {
  return el(
    "div",
    { class: "mosaic-tools" },
    el("button", { id: "tool-measure", "aria-pressed": "false", title: "click two points to measure (mm)" }, "Measure"),
    el(
      "button",
      { id: "tool-draw", "aria-pressed": "false", title: "click two corners of a defect the detector missed" },
      "Draw missed defect",
    ),
    el(
      "select",
      { id: "draw-class", "aria-label": "class of the drawn defect" },
      el("option", { value: "crack" }, "crack"),
      el("option", { value: "corrosion" }, "corrosion"),
    ),
    el("span", { id: "cursor-position", class: "muted mono" }, ""),
    el("span", { id: "tool-readout", class: "mono" }, ""),
  );
}

export function attachTools(viewer, box, world, { onDraw }) {
  const ppm = world?.px_per_m || null;
  const origin = world?.origin_m || [0, 0];
  const referenced = Boolean(world?.world_referenced && ppm);
  const state = { tool: null, points: [], marks: [] };
  box.append(
    el(
      "div",
      { class: "mosaic-legend small" },
      el("span", {}, el("i", { class: "swatch crack" }), "crack"),
      el("span", {}, el("i", { class: "swatch corrosion" }), "corrosion"),
      el("span", {}, el("i", { class: "swatch confirmed" }), "confirmed"),
      el("span", {}, el("i", { class: "swatch rejected" }), "rejected"),
    ),
    el("div", { id: "scale-bar", class: "scale-bar" }, el("div", { class: "bar" }), el("span", {})),
  );
  // screen pixels per mosaic pixel
  const scalePx = () => {
    const a = viewer.viewport.imageToViewerElementCoordinates(new (OSD().Point)(0, 0));
    const b = viewer.viewport.imageToViewerElementCoordinates(new (OSD().Point)(1000, 0));
    return (b.x - a.x) / 1000;
  };
  const updateScale = () => {
    const bar = document.getElementById("scale-bar");
    if (!bar || !referenced) {
      if (bar) bar.hidden = true;
      return;
    }
    const screenPerMm = (scalePx() * ppm) / 1000;
    const mm = [1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000].find((v) => v * screenPerMm >= 80) || 5000;
    bar.querySelector(".bar").style.width = `${mm * screenPerMm}px`;
    text(bar.querySelector("span"), mm >= 1000 ? `${mm / 1000} m` : mm >= 10 ? `${mm / 10} cm` : `${mm} mm`);
  };
  viewer.addHandler("animation", updateScale);
  viewer.addHandler("open", updateScale);
  viewer.addHandler("resize", updateScale);
  new (OSD().MouseTracker)({
    element: viewer.canvas,
    moveHandler: (ev) => {
      const p = viewer.viewport.viewerElementToImageCoordinates(ev.position);
      text(
        document.getElementById("cursor-position"),
        referenced
          ? `x ${fmt(origin[0] + p.x / ppm, 3)} m, y ${fmt(origin[1] + p.y / ppm, 3)} m`
          : `pixel ${Math.round(p.x)}, ${Math.round(p.y)} (no scale)`,
      );
    },
  });
  const clearMarks = () => {
    state.marks.forEach((m) => viewer.removeOverlay(m));
    state.marks = [];
    state.points = [];
  };
  const setTool = (name) => {
    state.tool = state.tool === name ? null : name;
    clearMarks();
    for (const t of ["measure", "draw"]) {
      document.getElementById(`tool-${t}`).setAttribute("aria-pressed", String(state.tool === t));
    }
    text(
      document.getElementById("tool-readout"),
      state.tool === "measure" ? "click the first point" : state.tool === "draw" ? "click the first corner" : "",
    );
  };
  document.getElementById("tool-measure").addEventListener("click", () => setTool("measure"));
  document.getElementById("tool-draw").addEventListener("click", () => setTool("draw"));
  const mark = (p) => {
    const node = el("div", { class: "tool-point" });
    viewer.addOverlay({
      element: node,
      location: viewer.viewport.imageToViewportCoordinates(p),
      placement: OSD().Placement.CENTER,
    });
    state.marks.push(node);
  };
  // an SVG line across the box of the two points
  const line = (a, b) => {
    const x = Math.min(a.x, b.x);
    const y = Math.min(a.y, b.y);
    const w = Math.max(Math.abs(b.x - a.x), 1);
    const h = Math.max(Math.abs(b.y - a.y), 1);
    const ns = "http://www.w3.org/2000/svg";
    const svg = document.createElementNS(ns, "svg");
    svg.setAttribute("viewBox", "0 0 100 100");
    svg.setAttribute("preserveAspectRatio", "none");
    svg.setAttribute("class", "tool-line");
    const l = document.createElementNS(ns, "line");
    for (const [k, v] of Object.entries({
      x1: ((a.x - x) / w) * 100,
      y1: ((a.y - y) / h) * 100,
      x2: ((b.x - x) / w) * 100,
      y2: ((b.y - y) / h) * 100,
    })) {
      l.setAttribute(k, v);
    }
    svg.appendChild(l);
    viewer.addOverlay({ element: svg, location: viewer.viewport.imageToViewportRectangle(x, y, w, h) });
    state.marks.push(svg);
  };
  // a click on the mosaic while a tool is on: true when the tool took it
  return function onClick(p) {
    if (!state.tool) return false;
    if (state.points.length === 2) clearMarks();
    state.points.push(p);
    mark(p);
    if (state.points.length === 1) {
      text(
        document.getElementById("tool-readout"),
        state.tool === "measure" ? "click the second point" : "click the opposite corner",
      );
      return true;
    }
    const [a, b] = state.points;
    if (state.tool === "measure") {
      line(a, b);
      const px = Math.hypot(b.x - a.x, b.y - a.y);
      const readout = document.getElementById("tool-readout");
      text(readout, referenced ? `${fmt((px / ppm) * 1000, 1)} mm` : `${fmt(px, 0)} px (no scale)`);
      readout.dataset.mm = referenced ? String((px / ppm) * 1000) : "";
    } else {
      const bbox = {
        bbox_x: Math.round(Math.min(a.x, b.x)),
        bbox_y: Math.round(Math.min(a.y, b.y)),
        bbox_w: Math.max(1, Math.round(Math.abs(b.x - a.x))),
        bbox_h: Math.max(1, Math.round(Math.abs(b.y - a.y))),
      };
      onDraw({ defect_class: document.getElementById("draw-class").value, ...bbox }).then((msg) => {
        setTool(null);
        text(document.getElementById("tool-readout"), msg);
      });
    }
    return true;
  };
}
