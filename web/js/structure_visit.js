// One visit of a structure: its element condition table, the changes since the visit before
// (how the two were registered, each defect new / grown / unchanged / gone, the elements whose
// condition worsened), and for a selected defect the two visits side by side and in a swipe
// view, with the defect's history across every visit.
import { api, apiJSON, el, fmt, text } from "./api.js";
import { historyChart } from "./structure_chart.js";

const UNITS = { m: "m", m2: "m²", each: "each" };
const CROP_PX = 384;

function badge(status) {
  return el("span", { class: `badge ${status}` }, status);
}

// Each element's quantity in CS1-CS4 as a stacked bar.
function csBar(e) {
  const total = Object.values(e.cs).reduce((a, b) => a + b, 0) || 1;
  return el(
    "span",
    { class: "cs-bar", title: [1, 2, 3, 4].map((k) => `CS${k} ${fmt(e.cs[`cs${k}`], 3)}`).join(", ") },
    ...[1, 2, 3, 4].map((k) => {
      const part = el("i", { class: `cs${k}` });
      part.style.width = `${(100 * e.cs[`cs${k}`]) / total}%`;
      return part;
    }),
  );
}

function conditionTable(condition, worsened) {
  const heads = ["element", "unit", "quantity", "CS1", "CS2", "CS3", "CS4", "", "defects"];
  return el(
    "table",
    { id: "condition" },
    el("tr", {}, ...heads.map((h) => el("th", {}, h))),
    ...condition.elements.map((e) =>
      el(
        "tr",
        { dataset: { element: e.element_id }, class: worsened.has(e.element_id) ? "worsened" : "" },
        el(
          "td",
          {},
          `${e.number} ${e.name}`,
          worsened.has(e.element_id) ? el("span", { class: "badge worsened" }, "worsened") : null,
        ),
        el("td", {}, UNITS[e.unit] || e.unit),
        el("td", { class: "num" }, fmt(e.quantity, 2)),
        ...[1, 2, 3, 4].map((k) => el("td", { class: "num" }, fmt(e.cs[`cs${k}`], 3))),
        el("td", {}, csBar(e)),
        el("td", { class: "num" }, String(e.defects.length)),
      ),
    ),
  );
}

function registrationNote(changes) {
  if (!changes.previous_session_id) return "The first visit on record: nothing to compare with.";
  const r = changes.registration;
  const since = `Since the visit of ${changes.previous_date}`;
  if (!r) return `${since}: placed by its marked datum (the two mosaics could not be aligned).`;
  return (
    `${since}: mosaics aligned to ${fmt(r.residual_mm, 2)} mm (rigid fit ${fmt(r.rigid_rms_mm, 2)} mm, ` +
    `overlap ${fmt(r.overlap * 100, 0)} %); this visit placed at x ${fmt(r.datum.x, 3)} m, ` +
    `y ${fmt(r.datum.y, 3)} m, yaw ${fmt((r.datum.yaw * 180) / Math.PI, 2)}°.`
  );
}

const number = (side) => (side ? `#${side.number ?? side.defect_id}` : "–");
const delta = (v, digits) => (v === null || v === undefined ? "–" : `${v > 0 ? "+" : ""}${fmt(v, digits)}`);

function changesTable(changes, onSelect) {
  const heads = ["status", "class", "before", "after", "length (mm)", "Δ length", "Δ width", "Δ area (mm²)"];
  return el(
    "table",
    { id: "changes" },
    el("tr", {}, ...heads.map((h) => el("th", {}, h))),
    ...changes.changes.map((c, i) => {
      const length = c.after?.length_mm ?? c.before?.length_mm;
      const row = el(
        "tr",
        { dataset: { change: i, status: c.status }, tabindex: "0" },
        el("td", {}, badge(c.status)),
        el("td", {}, c.class),
        el("td", {}, number(c.before)),
        el("td", {}, number(c.after)),
        el("td", { class: "num" }, fmt(length, 1)),
        el("td", { class: "num" }, delta(c.length_change_mm, 1)),
        el("td", { class: "num" }, delta(c.width_change_mm, 2)),
        el("td", { class: "num" }, delta(c.area_change_mm2, 0)),
      );
      const pick = () => {
        row.parentNode.querySelectorAll("tr.selected").forEach((r) => r.classList.remove("selected"));
        row.classList.add("selected");
        onSelect(c);
      };
      row.addEventListener("click", pick);
      row.addEventListener("keydown", (e) => {
        if (e.key === "Enter") pick();
      });
      return row;
    }),
  );
}

// A square around both visits' boxes of a defect, with room to see where it lies.
function cropBox(change) {
  const boxes = [change.before?.box_m, change.after?.box_m].filter(Boolean);
  const x0 = Math.min(...boxes.map((b) => b[0]));
  const y0 = Math.min(...boxes.map((b) => b[1]));
  const x1 = Math.max(...boxes.map((b) => b[2]));
  const y1 = Math.max(...boxes.map((b) => b[3]));
  const side = Math.max(0.06, 1.6 * Math.max(x1 - x0, y1 - y0));
  const cx = (x0 + x1) / 2;
  const cy = (y0 + y1) / 2;
  return [cx - side / 2, cy - side / 2, cx + side / 2, cy + side / 2];
}

async function crop(sessionId, box) {
  const [x0, y0, x1, y1] = box.map((v) => v.toFixed(4));
  const res = await api(`/api/sessions/${sessionId}/mosaic/crop?x0=${x0}&y0=${y0}&x1=${x1}&y1=${y1}&size=${CROP_PX}`);
  return res.ok ? URL.createObjectURL(await res.blob()) : null;
}

// The defect's box outlined on a crop of `box`.
function outline(box, side) {
  if (!side?.box_m) return null;
  const w = box[2] - box[0];
  const node = el("div", { class: "crop-box" });
  node.style.left = `${(100 * (side.box_m[0] - box[0])) / w}%`;
  node.style.top = `${(100 * (side.box_m[1] - box[1])) / w}%`;
  node.style.width = `${(100 * (side.box_m[2] - side.box_m[0])) / w}%`;
  node.style.height = `${(100 * (side.box_m[3] - side.box_m[1])) / w}%`;
  return node;
}

function picture(url, alt, box, side) {
  return el(
    "div",
    { class: "crop" },
    url ? el("img", { src: url, alt }) : el("p", { class: "muted" }, "no mosaic here"),
    outline(box, side),
  );
}

// Two pictures of one place stacked; the slider reveals the later over the earlier.
function swipe(before, after, labels) {
  const top = el("div", { class: "swipe-top" }, after);
  const line = el("div", { class: "swipe-line" });
  const slider = el("input", {
    type: "range",
    min: "0",
    max: "100",
    value: "50",
    id: "swipe-slider",
    "aria-label": `swipe between ${labels[0]} and ${labels[1]}`,
  });
  const set = () => {
    top.style.clipPath = `inset(0 ${100 - slider.value}% 0 0)`;
    line.style.left = `${slider.value}%`;
  };
  slider.addEventListener("input", set);
  set();
  return el(
    "div",
    { class: "swipe-view" },
    el("div", { class: "swipe", id: "swipe" }, before, top, line),
    el("div", { class: "swipe-labels small" }, el("span", {}, `◀ ${labels[1]}`), el("span", {}, `${labels[0]} ▶`)),
    slider,
  );
}

// The track of the history holding this change's defect at this visit.
function trackOf(history, visitId, change) {
  const at = (t, id) => t.entries.some((e) => e.session_id === visitId && e.defect_id === id);
  if (change.after) return history.tracks.find((t) => at(t, change.after.defect_id));
  return history.tracks.find((t) => {
    const i = t.entries.findIndex((e) => e.session_id === visitId && e.status === "gone");
    return i > 0 && t.entries[i - 1].defect_id === change.before.defect_id;
  });
}

async function compare(node, visit, changes, change, history) {
  const box = cropBox(change);
  const labels = [changes.previous_date, visit.date];
  node.replaceChildren(el("p", { class: "muted" }, "loading the two visits…"));
  const [then, now] = await Promise.all([crop(changes.previous_session_id, box), crop(visit.session_id, box)]);
  const title = `${change.class} ${number(change.after || change.before)}: ${change.status}`;
  node.replaceChildren(
    el("h4", {}, title),
    el(
      "div",
      { class: "compare" },
      el(
        "figure",
        {},
        picture(then, `the defect on ${labels[0]}`, box, change.before),
        el("figcaption", {}, `${labels[0]} ${number(change.before)}`),
      ),
      el(
        "figure",
        {},
        picture(now, `the defect on ${labels[1]}`, box, change.after),
        el("figcaption", {}, `${labels[1]} ${number(change.after)}`),
      ),
      swipe(picture(then, `before, ${labels[0]}`, box, null), picture(now, `after, ${labels[1]}`, box, null), labels),
    ),
    el("div", { id: "defect-history" }, el("p", { class: "muted" }, "loading its history…")),
  );
  node.dataset.ready = "true";
  const track = trackOf(await history(), visit.session_id, change);
  document
    .getElementById("defect-history")
    ?.replaceChildren(track ? historyChart(track, visit.session_id) : el("p", { class: "muted" }, "no history"));
}

// The panel of one visit in `root`; `previous` is the visit before it (or null), `history`
// gives the structure's defect history (loaded once).
export async function showVisit(root, structure, visit, history) {
  root.replaceChildren(el("p", { class: "muted" }, "loading the visit…"));
  const [condition, changes] = await Promise.all([
    apiJSON(`/api/structures/${structure.id}/condition?session_id=${encodeURIComponent(visit.session_id)}`),
    apiJSON(`/api/sessions/${visit.session_id}/changes`),
  ]);
  const worsened = new Set(changes.worsened_elements.map((w) => w.element_id));
  const compareNode = el("div", { id: "defect-compare" });
  const counts = {};
  for (const c of changes.changes) counts[c.status] = (counts[c.status] || 0) + 1;
  const csv = el("a", { href: "#", class: "small" }, "condition CSV");
  csv.addEventListener("click", async (e) => {
    e.preventDefault();
    const res = await api(`/api/structures/${structure.id}/condition.csv?session_id=${visit.session_id}`);
    if (!res.ok) return;
    const url = URL.createObjectURL(await res.blob());
    const a = el("a", { href: url, download: `condition-${structure.id}-${visit.date}.csv` });
    document.body.appendChild(a);
    a.click();
    a.remove();
  });
  root.replaceChildren(
    el(
      "h3",
      {},
      `Visit of ${visit.date} `,
      el("a", { href: `#/session/${visit.session_id}`, class: "small" }, "open the session"),
    ),
    el("h4", {}, "Element condition ", csv),
    condition.elements.length
      ? conditionTable(condition, worsened)
      : el("p", { class: "muted" }, "No elements yet: draw them on a mosaic above."),
    condition.unplaced_defects.length
      ? el("p", { class: "small muted" }, `${condition.unplaced_defects.length} defects on no element`)
      : null,
    el("h4", {}, "Changes since the visit before"),
    el("p", { id: "registration", class: "small" }, registrationNote(changes)),
    changes.changes.length
      ? el(
          "p",
          { class: "small" },
          ...Object.entries(counts).flatMap(([s, n]) => [badge(s), ` ${n} `]),
          worsened.size ? el("span", { class: "badge worsened" }, `${worsened.size} elements worsened`) : null,
        )
      : null,
    changes.changes.length ? changesTable(changes, (c) => compare(compareNode, visit, changes, c, history)) : null,
    compareNode,
  );
  text(compareNode, changes.changes.length ? "Select a defect to compare the two visits." : "");
}
