// A visit's mosaic in a pan-and-zoom viewer with the structure's elements outlined on it,
// and an element's extent drawn as a box (two corners) in the structure's frame. Mosaic pixel
// p lies at origin_m + p / px_per_m in the visit's world frame; the visit's datum (x, y, yaw)
// is that frame's pose on the structure.
import { api, apiJSON, authHeaders, el, fmt, text } from "./api.js";

const OSD = () => window.OpenSeadragon;

// Structure (m) <-> full-resolution mosaic pixel, through a visit's stitch result and datum.
export function placement(stitch, datum) {
  const ppm = stitch.px_per_m;
  const [ox, oy] = stitch.origin_m;
  const { x = 0, y = 0, yaw = 0 } = datum || {};
  const c = Math.cos(yaw);
  const s = Math.sin(yaw);
  return {
    toStructure(u, v) {
      const wx = ox + u / ppm;
      const wy = oy + v / ppm;
      return [x + c * wx - s * wy, y + s * wx + c * wy];
    },
    toMosaic(sx, sy) {
      const dx = sx - x;
      const dy = sy - y;
      return [(c * dx + s * dy - ox) * ppm, (-s * dx + c * dy - oy) * ppm];
    },
  };
}

// An axis-aligned box in one frame from the corners of a box in the other.
function hull(corners) {
  const xs = corners.map((p) => p[0]);
  const ys = corners.map((p) => p[1]);
  return [Math.min(...xs), Math.min(...ys), Math.max(...xs), Math.max(...ys)];
}

async function tileSource(sid, stitch) {
  const dzi = await api(`/api/sessions/${sid}/results/mosaic.dzi`);
  if (dzi.ok) {
    const xml = new DOMParser().parseFromString(await dzi.text(), "application/xml").documentElement;
    const size = xml.getElementsByTagName("Size")[0];
    const source = {
      Image: {
        xmlns: "http://schemas.microsoft.com/deepzoom/2008",
        Url: `/api/sessions/${sid}/mosaic_files/`,
        Format: xml.getAttribute("Format"),
        Overlap: xml.getAttribute("Overlap"),
        TileSize: xml.getAttribute("TileSize"),
        Size: { Width: size.getAttribute("Width"), Height: size.getAttribute("Height") },
      },
    };
    return { source, scale: 1, ajax: true };
  }
  // no tile pyramid: the overview, its pixels overview_scale of the mosaic's
  const res = await api(`/api/sessions/${sid}/results/mosaic_overview.png`);
  if (!res.ok) return null;
  const url = URL.createObjectURL(await res.blob());
  return { source: { type: "image", url }, scale: stitch.overview_scale || 1, ajax: false };
}

// The viewer of one visit's mosaic in `box`: `show(elements)` outlines elements, and while
// `draw(true)` two clicks give `onBox([x0, y0, x1, y1])` in the structure's frame (m).
export async function elementViewer(box, visit, onBox) {
  box.replaceChildren(el("p", { class: "muted" }, "loading the mosaic…"));
  const jobs = await apiJSON(`/api/sessions/${visit.session_id}/jobs`);
  const stitch = jobs.filter((j) => j.kind === "stitch" && j.state === "done").pop()?.result;
  const tiles = stitch && window.OpenSeadragon ? await tileSource(visit.session_id, stitch) : null;
  if (!tiles) {
    box.replaceChildren(el("p", { class: "muted" }, "This visit has no mosaic to draw on."));
    return null;
  }
  box.replaceChildren();
  const place = placement(stitch, visit.datum);
  const k = tiles.scale; // viewer image pixels per mosaic pixel
  const viewer = OSD()({
    element: box,
    tileSources: tiles.source,
    prefixUrl: "/vendor/openseadragon/images/",
    loadTilesWithAjax: tiles.ajax,
    ajaxHeaders: tiles.ajax ? authHeaders() : {},
    showNavigator: false,
    maxZoomPixelRatio: 4,
    gestureSettingsMouse: { clickToZoom: false },
    crossOriginPolicy: false,
  });
  const state = { drawing: false, points: [], marks: [], outlines: [], elements: [] };
  const readout = el("span", { class: "mono small", id: "element-readout" });
  const rect = (b) => {
    const [u0, v0, u1, v1] = hull([
      place.toMosaic(b[0], b[1]),
      place.toMosaic(b[2], b[1]),
      place.toMosaic(b[0], b[3]),
      place.toMosaic(b[2], b[3]),
    ]).map((c) => c * k);
    return viewer.viewport.imageToViewportRectangle(u0, v0, u1 - u0, v1 - v0);
  };
  const outline = () => {
    state.outlines.forEach((o) => viewer.removeOverlay(o));
    state.outlines = state.elements.map((e) => {
      const node = el(
        "div",
        { class: "element-box", dataset: { element: e.id } },
        el("span", {}, `${e.number} ${e.name}`),
      );
      viewer.addOverlay({ element: node, location: rect(e.box) });
      return node;
    });
  };
  const clear = () => {
    state.marks.forEach((m) => viewer.removeOverlay(m));
    state.marks = [];
    state.points = [];
  };
  viewer.addHandler("open", () => {
    outline();
    box.dataset.ready = "true";
  });
  viewer.addHandler("canvas-click", (ev) => {
    if (!ev.quick || !state.drawing) return;
    const p = viewer.viewport.viewerElementToImageCoordinates(ev.position);
    if (state.points.length === 2) clear();
    state.points.push([p.x / k, p.y / k]);
    const mark = el("div", { class: "tool-point" });
    viewer.addOverlay({
      element: mark,
      location: viewer.viewport.imageToViewportCoordinates(p),
      placement: OSD().Placement.CENTER,
    });
    state.marks.push(mark);
    if (state.points.length === 1) {
      text(readout, "click the opposite corner");
      return;
    }
    const [a, b] = state.points;
    const corners = [a, [b[0], a[1]], b, [a[0], b[1]]].map(([u, v]) => place.toStructure(u, v));
    const got = hull(corners);
    const node = el("div", { class: "element-box drawn" });
    viewer.addOverlay({ element: node, location: rect(got) });
    state.marks.push(node);
    text(readout, `x ${fmt(got[0], 3)}–${fmt(got[2], 3)} m, y ${fmt(got[1], 3)}–${fmt(got[3], 3)} m`);
    onBox(got);
  });
  return {
    readout,
    show(elements) {
      state.elements = elements;
      if (viewer.world.getItemCount()) outline();
    },
    draw(on) {
      state.drawing = on;
      clear();
      text(readout, on ? "click the first corner" : "");
    },
    destroy() {
      viewer.destroy();
      if (!tiles.ajax) URL.revokeObjectURL(tiles.source.url);
    },
  };
}
