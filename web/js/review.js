// One session: cover details, downloads, the mosaic in a pan-and-zoom viewer (OpenSeadragon
// over the Deep Zoom pyramid) with the defects drawn on it, the defect table with filters,
// sorting and review (confirm / reject, CS1–CS4, comment; keyboard shortcuts), the 3D view.
import { api, apiJSON, authHeaders, download, duration, el, fmt, patchJSON, text, token } from "./api.js";
import { EVENT } from "./events.js";
import { jobsBar } from "./jobs.js";
import { on } from "./live.js";
import { mosaicCursor, robotIn3d } from "./moment_views.js";
import { attachTools, toolbar } from "./mosaic_tools.js";
import { replay } from "./replay.js";
import { seekDefect, sessionTimeline } from "./timeline.js";

// column, heading, decimals: one format per quantity wherever it is shown
const COLUMNS = [
  ["number", "#", 0],
  ["defect_class", "class", null],
  ["length_mm", "length (mm)", 1],
  ["max_width_mm", "max width (mm)", 2],
  ["area_mm2", "area (mm²)", 0],
  ["world_x_m", "x (m)", 3],
  ["world_y_m", "y (m)", 3],
  ["confidence", "confidence", 2],
];
// A defect's one position, in the table, the panel, the 3D view, the PDF and the CSV
// (world_x_m, world_y_m); world_w_m, world_h_m are its box's size.
const POSITION_MEANING = "the corner of the defect's box nearest the structure's origin";
const HEADING_TITLE = {
  world_x_m: `x of ${POSITION_MEANING}`,
  world_y_m: `y of ${POSITION_MEANING}`,
};
const view = {
  session: null,
  defects: [],
  sort: "number",
  desc: false,
  selected: null,
  viewer: null,
  overlays: new Map(),
};

// The defect's number in its session, as the PDF, CSV and 3D view show it (frame defects: F).
export function label(d) {
  return `${d.source === "frame" ? "F" : "#"}${d.number ?? d.id}`;
}

function visible() {
  const cls = document.getElementById("filter-class")?.value || "";
  const review = document.getElementById("filter-review")?.value || "";
  const cs = document.getElementById("filter-cs")?.value || "";
  const below = document.getElementById("filter-confidence")?.value || "";
  const rows = view.defects.filter(
    (d) =>
      (!cls || d.defect_class === cls) &&
      (!review || d.review_status === review) &&
      (!cs || (cs === "none" ? !d.condition_state : d.condition_state === cs)) &&
      (!below || (d.confidence !== null && d.confidence !== undefined && d.confidence < Number(below))),
  );
  const key = view.sort;
  rows.sort((a, b) => {
    const x = a[key];
    const y = b[key];
    if (x === y) return (a.number ?? a.id) - (b.number ?? b.id);
    if (x === null || x === undefined) return 1;
    if (y === null || y === undefined) return -1;
    return (x < y ? -1 : 1) * (view.desc ? -1 : 1);
  });
  return rows;
}

async function save(d, body, input) {
  const res = await patchJSON(`/api/sessions/${view.session.id}/defects/${d.id}`, body);
  if (input) {
    input.classList.toggle("saved", res.ok);
    input.classList.toggle("failed", !res.ok);
    input.title = res.ok ? "saved" : `not saved (HTTP ${res.status})`;
  }
  if (res.ok) {
    Object.assign(d, await res.json());
    styleOverlay(d);
    if (d.id === view.selected) showDetail(d);
  }
  return res.ok;
}

function reviewInput(d, field, options) {
  const input = options
    ? el(
        "select",
        { name: field, "aria-label": `${field} of defect ${label(d)}` },
        ...options.map((o) => el("option", { value: o }, o || "–")),
      )
    : el("input", {
        name: field,
        "aria-label": `comment on defect ${label(d)}`,
        placeholder: "comment",
        maxlength: "2000",
      });
  input.value = d[field] ?? "";
  input.addEventListener("change", () => {
    const body =
      field === "condition_state" && !input.value ? { clear_condition_state: true } : { [field]: input.value };
    save(d, body, input);
  });
  return el("td", {}, input);
}

function renderTable() {
  const table = document.getElementById("defects");
  const rows = visible();
  const head = el(
    "tr",
    {},
    ...COLUMNS.map(([key, label]) =>
      el(
        "th",
        {
          class: "sortable",
          title: HEADING_TITLE[key],
          "aria-sort": view.sort === key ? (view.desc ? "descending" : "ascending") : "none",
          onclick: () => {
            view.desc = view.sort === key ? !view.desc : false;
            view.sort = key;
            renderTable();
          },
        },
        label + (view.sort === key ? (view.desc ? " ▼" : " ▲") : ""),
      ),
    ),
    el("th", {}, "review"),
    el("th", {}, "CS"),
    el("th", {}, "comment"),
  );
  table.replaceChildren(
    head,
    ...rows.map((d) => {
      const tr = el(
        "tr",
        {
          dataset: { defect: d.id },
          class: d.id === view.selected ? "selected" : "",
          onclick: (e) => {
            if (!["SELECT", "INPUT", "OPTION"].includes(e.target.tagName)) select(d.id);
          },
        },
        ...COLUMNS.map(([key, , digits]) =>
          el("td", {}, key === "number" ? label(d) : digits === null ? d[key] : fmt(d[key], digits)),
        ),
        reviewInput(d, "review_status", ["unreviewed", "confirmed", "rejected"]),
        reviewInput(d, "condition_state", ["", "CS1", "CS2", "CS3", "CS4"]),
        reviewInput(d, "comment", null),
      );
      return tr;
    }),
  );
  text(document.getElementById("defect-count"), `${rows.length} of ${view.defects.length} defects`);
  const shown = new Set(rows.map((d) => d.id));
  view.defects.forEach((d) => styleOverlay(d, shown.has(d.id)));
}

function styleOverlay(d, shown = true) {
  const box = view.overlays.get(d.id);
  if (!box) return;
  box.className = `defect-box ${d.defect_class} ${d.review_status}${d.id === view.selected ? " selected" : ""}`;
  box.hidden = !shown;
}

function select(id, { pan = true, focus3d = true } = {}) {
  view.selected = id;
  document
    .querySelectorAll("#defects tr[data-defect]")
    .forEach((tr) => tr.classList.toggle("selected", Number(tr.dataset.defect) === id));
  const row = document.querySelector(`#defects tr[data-defect='${id}']`);
  row?.scrollIntoView({ block: "nearest" });
  const shown = new Set(visible().map((x) => x.id));
  view.defects.forEach((x) => styleOverlay(x, shown.has(x.id)));
  const d = view.defects.find((x) => x.id === id);
  if (!d) return;
  seekDefect(id); // the timeline moves to the frame it was first seen in
  const img = el("img", { alt: `defect ${label(d)}`, width: "192", height: "192" });
  api(`/api/sessions/${view.session.id}/defects/${d.id}/thumbnail.jpg?size=192`)
    .then((r) => (r.ok ? r.blob() : null))
    .then((b) => {
      if (b) img.src = URL.createObjectURL(b);
    })
    .catch(() => {});
  view.thumbnail = img;
  showDetail(d);
  // the 3D view flies to its marker
  if (focus3d && document.getElementById("view3d")) {
    api(`/api/sessions/${view.session.id}/view3d/focus/${d.id}`, { method: "POST" }).catch(() => {});
  }
  if (pan && view.viewer && d.source === "mosaic") {
    const pad = Math.max(d.bbox_w, d.bbox_h) * 1.5 + 60;
    const rect = view.viewer.viewport.imageToViewportRectangle(
      d.bbox_x + d.bbox_w / 2 - pad / 2,
      d.bbox_y + d.bbox_h / 2 - pad / 2,
      pad,
      pad,
    );
    view.viewer.viewport.fitBoundsWithConstraints(rect);
  }
}

// The selected defect's panel: picture, measurements, place, and its review as stored now.
function showDetail(d) {
  const detail = document.getElementById("defect-detail");
  detail.dataset.defect = String(d.id);
  detail.replaceChildren(
    view.thumbnail,
    el(
      "dl",
      {},
      el("dt", {}, "defect"),
      el("dd", {}, `${label(d)} ${d.defect_class} (${d.source === "frame" ? `frame ${d.frame_seq}` : "mosaic"})`),
      el("dt", {}, "size"),
      el(
        "dd",
        {},
        `${fmt(d.length_mm, 1)} mm long, ` +
          `${d.max_width_mm === null ? "width not measured" : `up to ${fmt(d.max_width_mm, 2)} mm wide`}` +
          `${d.area_mm2 === null ? "" : `, ${fmt(d.area_mm2, 0)} mm²`}`,
      ),
      ...(d.drawn_by ? [el("dt", {}, "drawn by"), el("dd", {}, d.drawn_by)] : []),
      el("dt", {}, "confidence"),
      el(
        "dd",
        { class: "defect-confidence" },
        d.confidence === null || d.confidence === undefined
          ? "not given"
          : `${fmt(d.confidence, 2)} (the detector's: about ${Math.round(d.confidence * 10)} in 10 like it are true)`,
      ),
      ...placement(d),
      el("dt", {}, "review"),
      el("dd", { class: "review-state" }, d.review_status),
      el("dt", {}, "condition state"),
      el("dd", { class: "review-cs" }, d.condition_state || "not rated"),
      el("dt", {}, "comment"),
      el("dd", { class: "review-comment" }, d.comment || "–"),
      el("dt", {}, "reviewed by"),
      el("dd", {}, d.reviewed_by ? `${d.reviewed_by}, ${new Date(d.reviewed_at).toLocaleString()}` : "–"),
    ),
    replayFor(d),
  );
}

// Where the defect is on the structure: its position (the box's corner, as in the table)
// and the box it spans.
function placement(d) {
  if (d.world_x_m === null) return [el("dt", {}, "on the structure"), el("dd", {}, "not placed")];
  const x0 = d.world_x_m;
  const y0 = d.world_y_m;
  return [
    el("dt", {}, "on the structure"),
    el("dd", { class: "defect-position" }, `x ${fmt(x0, 3)} m, y ${fmt(y0, 3)} m (${POSITION_MEANING})`),
    el("dt", {}, "box"),
    el(
      "dd",
      { class: "defect-box-m" },
      `x ${fmt(x0, 3)}–${fmt(x0 + (d.world_w_m ?? 0), 3)} m, y ${fmt(y0, 3)}–${fmt(y0 + (d.world_h_m ?? 0), 3)} m`,
    ),
  ];
}

// The replay strip and timeline, kept while the same defect stays selected.
function replayFor(d) {
  if (view.replay?.id !== d.id) view.replay = { id: d.id, node: replay(view.session.id, d.id) };
  return view.replay.node;
}

function onKey(e) {
  if (document.getElementById("view-session").hidden) return;
  if (["INPUT", "SELECT", "TEXTAREA"].includes(e.target.tagName)) return;
  if (e.target.tagName === "BUTTON" && (e.key === "Enter" || e.key === " ")) return; // the button's own
  const rows = visible();
  const i = rows.findIndex((d) => d.id === view.selected);
  const d = rows[i];
  const input = (name) => document.querySelector(`#defects tr[data-defect='${view.selected}'] [name=${name}]`);
  const set = (field, value, body) => {
    if (!d) return;
    const inp = input(field);
    if (inp) inp.value = value;
    save(d, body || { [field]: value }, inp);
  };
  if (e.key === "j" || e.key === "ArrowDown") {
    e.preventDefault();
    if (rows.length) select(rows[Math.min(rows.length - 1, i + 1)].id);
  } else if (e.key === "k" || e.key === "ArrowUp") {
    e.preventDefault();
    if (rows.length) select(rows[Math.max(0, i - 1)].id);
  } else if (e.key === "c") set("review_status", "confirmed");
  else if (e.key === "x") set("review_status", "rejected");
  else if (e.key === "u") set("review_status", "unreviewed");
  else if (["1", "2", "3", "4"].includes(e.key)) set("condition_state", `CS${e.key}`);
  else if (e.key === "0") set("condition_state", "", { clear_condition_state: true });
  else if (e.key === "/" || e.key === "Enter") {
    if (d) {
      e.preventDefault();
      input("comment")?.focus();
    }
  }
}

async function openViewer(s, stitch) {
  const box = document.getElementById("mosaic-viewer");
  const dzi = await api(`/api/sessions/${s.id}/results/mosaic.dzi`);
  if (!dzi.ok || !window.OpenSeadragon) {
    // no pyramid (or no viewer library): the overview image
    const res = await api(`/api/sessions/${s.id}/results/mosaic_overview.png`);
    if (res.ok) {
      box.replaceChildren(
        el("img", { src: URL.createObjectURL(await res.blob()), alt: "mosaic overview", class: "overview" }),
      );
    }
    return;
  }
  const xml = new DOMParser().parseFromString(await dzi.text(), "application/xml").documentElement;
  const size = xml.getElementsByTagName("Size")[0];
  const source = {
    Image: {
      xmlns: "http://schemas.microsoft.com/deepzoom/2008",
      Url: `/api/sessions/${s.id}/mosaic_files/`,
      Format: xml.getAttribute("Format"),
      Overlap: xml.getAttribute("Overlap"),
      TileSize: xml.getAttribute("TileSize"),
      Size: { Width: size.getAttribute("Width"), Height: size.getAttribute("Height") },
    },
  };
  const world = await apiJSON(`/api/sessions/${s.id}/results/mosaic.json`).catch(() => null);
  const viewer = window.OpenSeadragon({
    element: box,
    tileSources: source,
    prefixUrl: "/vendor/openseadragon/images/",
    loadTilesWithAjax: true,
    ajaxHeaders: authHeaders(),
    showNavigator: true,
    navigatorPosition: "BOTTOM_RIGHT",
    maxZoomPixelRatio: 4,
    gestureSettingsMouse: { clickToZoom: false },
    crossOriginPolicy: false,
  });
  view.viewer = viewer;
  const toolClick = attachTools(viewer, box, world, { onDraw: drawDefect });
  viewer.addHandler("open", () => {
    for (const d of view.defects.filter((x) => x.source === "mosaic")) addOverlay(d);
    renderTable(); // the filters hide boxes too
    view.cursor.attach(viewer, world);
    box.dataset.ready = "true";
  });
  viewer.addHandler("canvas-click", (ev) => {
    if (!ev.quick) return;
    const p = viewer.viewport.viewerElementToImageCoordinates(ev.position);
    if (toolClick(p)) return;
    const hit = view.defects.find(
      (d) =>
        d.source === "mosaic" &&
        p.x >= d.bbox_x - 6 &&
        p.x <= d.bbox_x + d.bbox_w + 6 &&
        p.y >= d.bbox_y - 6 &&
        p.y <= d.bbox_y + d.bbox_h + 6,
    );
    if (hit) select(hit.id, { pan: false });
  });
  void stitch;
}

function addOverlay(d) {
  const node = el(
    "div",
    { class: "defect-box", dataset: { defect: d.id }, title: `${label(d)} ${d.defect_class}` },
    el("span", { class: "defect-number" }, String(d.number ?? d.id)),
  );
  view.overlays.set(d.id, node);
  styleOverlay(d);
  view.viewer.addOverlay({
    element: node,
    location: view.viewer.viewport.imageToViewportRectangle(d.bbox_x - 4, d.bbox_y - 4, d.bbox_w + 8, d.bbox_h + 8),
  });
}

// A defect the detector missed, drawn on the mosaic: stored, numbered, selected.
async function drawDefect(body) {
  const res = await api(`/api/sessions/${view.session.id}/defects`, {
    method: "POST",
    headers: { "Content-Type": "application/json" },
    body: JSON.stringify(body),
  });
  if (!res.ok) {
    let detail = "";
    try {
      detail = (await res.json()).detail;
    } catch {
      // not JSON
    }
    return `not stored (HTTP ${res.status}${detail ? `: ${detail}` : ""})`;
  }
  const d = await res.json();
  view.defects.push(d);
  addOverlay(d);
  renderTable();
  select(d.id, { pan: false });
  return `${label(d)} drawn`;
}

// How much of the surface in view the camera imaged well enough, and the holes left.
function coverageNote(s) {
  const node = el("p", { id: "session-coverage", class: "small" }, "coverage: …");
  apiJSON(`/api/sessions/${s.id}/coverage?grid=false`)
    .then((c) => {
      if (!c.area_surface_m2) {
        text(node, "coverage: no frame with a pose and a camera scale");
        return;
      }
      const holes = c.holes
        .slice(0, 5)
        .map((h) => `(${fmt(h.x_m, 2)}, ${fmt(h.y_m, 2)}) m ${fmt(h.area_m2 * 1e4, 0)} cm²`)
        .join("; ");
      text(
        node,
        `coverage at ≤ ${c.required_mm_per_px} mm/px: ` +
          `${fmt(c.area_imaged_m2, 3)} of ${fmt(c.area_surface_m2, 3)} m² imaged ` +
          `(${fmt(c.fraction_imaged * 100, 1)} %), ${c.frames_not_counted} frames not counted, ` +
          `${c.holes.length} holes${holes ? `: ${holes}` : ""}`,
      );
    })
    .catch(() => text(node, "coverage unavailable"));
  return node;
}

function exportsBar(s) {
  const status = el("span", { class: "muted" });
  const done = (kind) => s.jobs.some((j) => j.kind === kind && j.state === "done");
  const items = [
    ["PDF report", "report.pdf", "report.pdf", true],
    ["Defects CSV", "defects.csv", "defects.csv", true],
    ["Report JSON", "report.json", "report.json", true],
    ["Session MCAP (Foxglove)", "export.mcap", "session.mcap", true],
    ["Mosaic overview PNG", "results/mosaic_overview.png", "mosaic.png", done("stitch")],
    ["Map PLY", "results/map.ply", "map.ply", done("map")],
    ["Trajectory TUM", "results/trajectory.tum", "trajectory.tum", done("map")],
  ];
  return el(
    "div",
    { class: "exports", id: "exports" },
    ...items
      .filter((i) => i[3])
      .map(([label, path, name]) =>
        el(
          "button",
          {
            dataset: { export: path },
            onclick: () => download(`/api/sessions/${s.id}/${path}`, `${s.id.slice(0, 8)}-${name}`, status),
          },
          label,
        ),
      ),
    status,
  );
}

function detailsForm(s) {
  const field = (name, label, value) => {
    const input = el("input", { name, value: value || "", "aria-label": label, placeholder: label });
    input.addEventListener("change", async () => {
      const res = await patchJSON(`/api/sessions/${s.id}`, { [name]: input.value });
      input.classList.toggle("saved", res.ok);
      input.classList.toggle("failed", !res.ok);
    });
    return el("label", {}, `${label} `, input);
  };
  return el("div", { class: "details" }, field("location", "Location", s.location), field("notes", "Notes", s.notes));
}

function view3dButton(s, root) {
  const button = el("button", { id: "show-3d" }, "Show 3D map");
  button.addEventListener("click", async () => {
    const res = await api(`/api/sessions/${s.id}/view3d`, { method: "POST" });
    if (!res.ok) {
      text(button, `3D view unavailable (HTTP ${res.status})`);
      return;
    }
    const { url } = await res.json(); // this session's own view: live robots never take it over
    const frame = document.getElementById("view3d") || el("iframe", { id: "view3d", title: "3D map" });
    frame.src = `${url}${token ? `?token=${encodeURIComponent(token)}` : ""}`;
    root.appendChild(frame);
    view.robot3d.resend();
  });
  return button;
}

// which data the results were made from; a warning when data came after them
function resultsCover(s) {
  const c = s.results_cover;
  if (!c) return el("p", { id: "results-cover", class: "muted" }, "Not processed yet.");
  const of = (n, total, what) => (n === total ? `${n} ${what}` : `${n} of ${total} ${what}`);
  const text =
    `Results made from ${of(c.frames, s.frames, "frames")}, ${of(c.clouds, s.clouds, "clouds")}, ` +
    `${of(c.telemetry, s.telemetry, "telemetry samples")}`;
  return el(
    "p",
    { id: "results-cover", class: c.current ? "muted" : "warning", dataset: { current: String(c.current) } },
    c.current ? `${text}: everything the session holds.` : `${text}: data stored after them is being processed.`,
  );
}

export async function showSession(id, defectNumber = null) {
  const root = document.getElementById("session-detail");
  root.replaceChildren(el("p", { class: "muted" }, "loading…"));
  const s = await apiJSON(`/api/sessions/${id}`);
  view.session = s;
  view.selected = null;
  view.overlays.clear();
  view.thumbnail = null;
  view.replay = null;
  view.cursor = mosaicCursor();
  view.robot3d = robotIn3d(id);
  if (view.viewer) {
    view.viewer.destroy();
    view.viewer = null;
  }
  const stitch = s.jobs.filter((j) => j.kind === "stitch" && j.state === "done").pop();
  const source = stitch ? "mosaic" : "frame";
  const jobs =
    s.jobs.map((j) => `${j.kind}: ${j.state}${j.error ? ` (${j.error})` : ""}`).join(" · ") || "no processing yet";
  root.replaceChildren(
    el("h3", {}, `${s.structure} — ${s.id}`),
    el(
      "p",
      { class: "muted" },
      `${new Date(s.started_at).toLocaleString()} · ${duration(s.duration_s)} · ` +
        `operator ${s.operator || "–"} · robot ${s.robot_name || "–"} · ${s.status}` +
        ` · ${s.frames} frames, ${s.clouds} clouds · ${jobs}`,
    ),
    resultsCover(s),
    detailsForm(s),
    exportsBar(s),
    jobsBar(s, () => showSession(s.id)),
    coverageNote(s),
    el(
      "div",
      { class: "review" },
      el("div", {}, toolbar(), el("div", { id: "mosaic-viewer", class: "mosaic-viewer" })),
      el(
        "aside",
        { id: "defect-detail", class: "defect-detail" },
        el("p", { class: "muted" }, "Select a defect (click it, or j / k)."),
      ),
    ),
    el("div", { id: "session-timeline" }),
    el(
      "div",
      { class: "filters" },
      el(
        "label",
        {},
        "class ",
        el(
          "select",
          { id: "filter-class", onchange: renderTable },
          ...["", "crack", "corrosion"].map((v) => el("option", { value: v }, v || "all")),
        ),
      ),
      el(
        "label",
        {},
        "review ",
        el(
          "select",
          { id: "filter-review", onchange: renderTable },
          ...["", "unreviewed", "confirmed", "rejected"].map((v) => el("option", { value: v }, v || "all")),
        ),
      ),
      el(
        "label",
        {},
        "CS ",
        el(
          "select",
          { id: "filter-cs", onchange: renderTable },
          ...["", "CS1", "CS2", "CS3", "CS4", "none"].map((v) => el("option", { value: v }, v || "all")),
        ),
      ),
      el(
        "label",
        { title: "the detector's calibrated confidence: check the doubtful ones first" },
        "confidence ",
        el(
          "select",
          { id: "filter-confidence", onchange: renderTable },
          ...[
            ["", "all"],
            ["0.5", "low (below 0.5)"],
            ["0.8", "below 0.8"],
          ].map(([v, t]) => el("option", { value: v }, t)),
        ),
      ),
      el("span", { id: "defect-count", class: "muted" }),
      el(
        "span",
        { class: "muted small" },
        "Keys: j/k next/previous · c confirm · x reject · u unreviewed · 1–4 condition state · 0 clear · / comment",
      ),
    ),
    el("p", { id: "defects-position", class: "muted small" }, `x, y: ${POSITION_MEANING} (m)`),
    el("div", { class: "table-scroll" }, el("table", { id: "defects" })),
  );
  const mapDone = s.jobs.some((j) => j.kind === "map" && j.state === "done");
  if (mapDone) root.appendChild(view3dButton(s, root));
  view.defects = (await apiJSON(`/api/sessions/${id}/defects?source=${source}&limit=5000`)).data;
  renderTable();
  const timeline = sessionTimeline(s.id, {
    defects: view.defects,
    live: s.status === "live",
    onMoment: (m, words) => {
      view.cursor.move(m);
      view.robot3d.move(m, words);
    },
    onDefect: (defectId) => select(defectId),
  });
  document.getElementById("session-timeline").replaceChildren(timeline.node);
  const wanted = defectNumber === null ? null : view.defects.find((d) => String(d.number) === String(defectNumber));
  if (stitch) {
    await openViewer(s, stitch);
  } else {
    const message = el("p", { class: "muted" }, "No mosaic yet: the stitch job has not finished.");
    document.getElementById("mosaic-viewer").replaceChildren(message);
  }
  // a link to one defect (the PDF's numbers): select it once the viewer is open
  if (wanted) {
    if (view.viewer && !view.viewer.world.getItemCount()) view.viewer.addOnceHandler("open", () => select(wanted.id));
    else select(wanted.id);
  }
}

export function initReview() {
  document.addEventListener("keydown", onKey);
  // a marker clicked in this session's 3D view selects its defect here
  on("event", (ev) => {
    if (
      ev.type === EVENT.DEFECT_SELECTED &&
      ev.session_id === view.session?.id &&
      !document.getElementById("view-session").hidden
    ) {
      select(ev.defect_id, { focus3d: false });
    }
  });
}
