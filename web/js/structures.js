// The structures an inspection team visits (#/structures) and one structure's page
// (#/structure/<id>[/visit/<session>]): its AASHTO elements, drawn on a visit's mosaic; its
// visits on a timeline; per visit the element condition and the changes since the visit
// before, with a defect's two visits side by side, in a swipe view and its history.
import { api, apiJSON, el, fmt, text } from "./api.js";
import { elementViewer } from "./structure_mosaic.js";
import { showVisit } from "./structure_visit.js";

const page = { structure: null, visits: [], elements: [], aashto: [], mosaic: null, box: null, history: null };

async function failure(res) {
  let detail = "";
  try {
    detail = (await res.json()).detail;
  } catch {
    // not JSON
  }
  if (Array.isArray(detail)) detail = detail.map((d) => d.msg).join("; ");
  return `HTTP ${res.status}${detail ? `: ${detail}` : ""}`;
}

function send(path, method, body) {
  return api(path, {
    method,
    headers: { "Content-Type": "application/json" },
    body: body === undefined ? undefined : JSON.stringify(body),
  });
}

// --- the list ---

function createForm() {
  const status = el("span", { class: "small", role: "status" });
  const form = el(
    "form",
    { id: "new-structure", class: "row" },
    el("label", {}, "Name ", el("input", { name: "name", required: true, maxlength: "200", size: "24" })),
    el("label", {}, "Owner's id ", el("input", { name: "owner_id", maxlength: "100", placeholder: "e.g. NBI number" })),
    el("label", {}, "Location ", el("input", { name: "location", maxlength: "2000", size: "24" })),
    el("button", { type: "submit" }, "Add structure"),
    status,
  );
  form.addEventListener("submit", async (e) => {
    e.preventDefault();
    const res = await send("/api/structures", "POST", Object.fromEntries(new FormData(form)));
    if (!res.ok) {
      text(status, `not added (${await failure(res)})`);
      return;
    }
    location.hash = `#/structure/${(await res.json()).id}`;
  });
  return form;
}

export async function showStructures() {
  const root = document.getElementById("structures-page");
  destroyViewer();
  const structures = await apiJSON("/api/structures");
  const open = (s) => {
    location.hash = `#/structure/${s.id}`;
  };
  root.replaceChildren(
    el("h2", {}, "Structures"),
    createForm(),
    // a narrow screen scrolls the table, not the page
    el(
      "div",
      { class: "table-scroll" },
      el(
        "table",
        { id: "structures" },
        el("tr", {}, ...["Name", "Owner's id", "Location", "Visits", "Added"].map((h) => el("th", {}, h))),
        ...structures.map((s) =>
          el(
            "tr",
            {
              dataset: { structure: s.id },
              tabindex: "0",
              onclick: () => open(s),
              onkeydown: (e) => {
                if (e.key === "Enter") open(s);
              },
            },
            el("td", {}, s.name),
            el("td", {}, s.owner_id || "–"),
            el("td", {}, s.location || "–"),
            el("td", { class: "num" }, String(s.sessions)),
            el("td", {}, new Date(s.created_at).toLocaleDateString()),
          ),
        ),
      ),
    ),
    structures.length ? null : el("p", { class: "muted" }, "No structure yet."),
  );
}

// --- one structure ---

function destroyViewer() {
  page.mosaic?.destroy();
  page.mosaic = null;
}

// A session attached to the structure, with the pose of its world frame on the structure's.
function attachForm(s) {
  const sessions = el("select", { id: "attach-session", "aria-label": "session to attach" });
  apiJSON("/api/sessions?limit=200")
    .then((body) =>
      sessions.replaceChildren(
        ...body.data.map((x) =>
          el(
            "option",
            { value: x.id },
            `${new Date(x.started_at).toLocaleDateString()} ${x.structure} (${x.id.slice(0, 8)})`,
          ),
        ),
      ),
    )
    .catch(() => {});
  const number = (name, label) => el("input", { name, type: "number", step: "any", value: "0", "aria-label": label });
  const x = number("x", "datum x (m)");
  const y = number("y", "datum y (m)");
  const yaw = number("yaw", "datum yaw (degrees)");
  const status = el("span", { class: "small", role: "status" });
  const button = el("button", { id: "attach", type: "button" }, "Attach");
  button.addEventListener("click", async () => {
    const datum = { x: Number(x.value), y: Number(y.value), yaw: (Number(yaw.value) * Math.PI) / 180 };
    const res = await send(`/api/sessions/${sessions.value}/structure`, "PUT", { structure_id: s.id, datum });
    if (!res.ok) {
      text(status, `not attached (${await failure(res)})`);
      return;
    }
    showStructure(s.id, sessions.value);
  });
  return el(
    "div",
    { class: "row attach" },
    el("span", {}, "Add a visit: session "),
    sessions,
    el("span", { class: "muted", title: "where the robot started, on the structure's frame" }, "started at x"),
    x,
    el("span", { class: "muted" }, "m, y"),
    y,
    el("span", { class: "muted" }, "m, yaw"),
    yaw,
    el("span", { class: "muted" }, "°"),
    button,
    status,
  );
}

// The visits along a line of dates, each with its defects; one is selected.
function timeline(visits, selected, onSelect) {
  const t = visits.map((v) => Date.parse(v.date));
  const t0 = Math.min(...t);
  const span = Math.max(...t) - t0;
  return el(
    "div",
    { class: "timeline", id: "timeline" },
    el("div", { class: "timeline-line" }),
    ...visits.map((v, i) => {
      const b = el(
        "button",
        {
          class: `visit${v.session_id === selected ? " selected" : ""}`,
          dataset: { session: v.session_id },
          "aria-pressed": String(v.session_id === selected),
          title: `${v.operator || "–"} · ${v.status}${v.mosaic ? "" : " · no mosaic"}`,
          onclick: () => onSelect(v),
        },
        el("b", {}, v.date),
        el("span", { class: "small" }, `${v.defects} defect${v.defects === 1 ? "" : "s"}`),
      );
      b.style.left = `${visits.length === 1 ? 50 : 6 + (88 * (t[i] - t0)) / (span || 1)}%`;
      return b;
    }),
  );
}

function elementsTable(s) {
  return el(
    "table",
    { id: "elements" },
    el("tr", {}, ...["element", "name", "quantity", "box (m)", ""].map((h) => el("th", {}, h))),
    ...page.elements.map((e) => {
      const remove = el("button", { class: "danger", "aria-label": `delete element ${e.number} ${e.name}` }, "Delete");
      remove.addEventListener("click", async () => {
        if ((await api(`/api/structures/${s.id}/elements/${e.id}`, { method: "DELETE" })).ok) await reloadElements(s);
      });
      return el(
        "tr",
        { dataset: { element: e.id } },
        el("td", {}, String(e.number)),
        el("td", {}, e.name),
        el("td", { class: "num" }, `${fmt(e.quantity, 2)} ${e.unit === "m2" ? "m²" : e.unit}`),
        el("td", { class: "mono small" }, e.box.map((c) => fmt(c, 3)).join(", ")),
        el("td", {}, remove),
      );
    }),
  );
}

async function reloadElements(s) {
  page.elements = await apiJSON(`/api/structures/${s.id}/elements`);
  document.getElementById("elements")?.replaceWith(elementsTable(s));
  page.mosaic?.show(page.elements);
}

// The quantity an element of `unit` has over a box: its length along the longer side (m), its
// area (m²), or one.
function quantityOf(unit, box) {
  const w = box[2] - box[0];
  const h = box[3] - box[1];
  return unit === "m" ? Math.max(w, h) : unit === "m2" ? w * h : 1;
}

// Define an element: a box drawn on a visit's mosaic, its AASHTO number, quantity and name.
function elementTools(s) {
  const visits = page.visits.filter((v) => v.mosaic);
  const which = el(
    "select",
    { id: "element-visit", "aria-label": "visit whose mosaic to draw on" },
    ...visits.map((v) => el("option", { value: v.session_id }, v.date)),
  );
  const drawButton = el("button", { id: "draw-element", type: "button", "aria-pressed": "false" }, "Draw element");
  const numberSelect = el(
    "select",
    { id: "element-number", "aria-label": "AASHTO element" },
    ...page.aashto.map((t) => el("option", { value: t.number }, `${t.number} ${t.name} (${t.unit})`)),
  );
  const quantity = el("input", {
    id: "element-quantity",
    type: "number",
    step: "any",
    min: "0",
    "aria-label": "quantity",
  });
  const unit = el("span", { class: "muted" });
  const name = el("input", {
    id: "element-name",
    maxlength: "200",
    placeholder: "name (optional)",
    "aria-label": "name",
  });
  const status = el("span", { class: "small", role: "status", id: "element-status" });
  const add = el("button", { id: "add-element", type: "button" }, "Add element");
  const form = el(
    "div",
    { class: "row", id: "element-form", hidden: true },
    numberSelect,
    quantity,
    unit,
    name,
    add,
    status,
  );
  const viewerBox = el("div", { id: "element-viewer", class: "mosaic-viewer element-viewer" });
  const readout = el("span");
  const prefill = () => {
    const t = page.aashto.find((x) => String(x.number) === numberSelect.value);
    text(unit, t ? (t.unit === "m2" ? "m²" : t.unit) : "");
    if (t && page.box) quantity.value = quantityOf(t.unit, page.box).toFixed(t.unit === "each" ? 0 : 3);
  };
  numberSelect.addEventListener("change", prefill);
  const setDrawing = (on) => {
    drawButton.setAttribute("aria-pressed", String(on));
    page.mosaic?.draw(on);
  };
  drawButton.addEventListener("click", () => setDrawing(drawButton.getAttribute("aria-pressed") !== "true"));
  add.addEventListener("click", async () => {
    const body = {
      number: Number(numberSelect.value),
      quantity: Number(quantity.value),
      box: page.box,
      name: name.value,
    };
    const res = await send(`/api/structures/${s.id}/elements`, "POST", body);
    if (!res.ok) {
      text(status, `not added (${await failure(res)})`);
      return;
    }
    text(status, "added");
    form.hidden = true;
    page.box = null;
    setDrawing(false);
    await reloadElements(s);
  });
  const open = async () => {
    destroyViewer();
    const visit = page.visits.find((v) => v.session_id === which.value);
    if (!visit) return;
    const onBox = (box) => {
      page.box = box;
      form.hidden = false;
      text(status, "");
      prefill();
    };
    page.mosaic = await elementViewer(viewerBox, visit, onBox);
    page.mosaic?.show(page.elements);
    if (page.mosaic) readout.replaceChildren(page.mosaic.readout);
  };
  which.addEventListener("change", open);
  return {
    node: el(
      "div",
      { class: "element-tools" },
      visits.length
        ? el("div", { class: "row" }, el("span", {}, "On the mosaic of the visit of "), which, drawButton, readout)
        : el("p", { class: "muted" }, "Elements are drawn on a visit's mosaic: attach a processed session first."),
      form,
      visits.length ? viewerBox : null,
    ),
    open: (sessionId) => {
      if (!visits.length) return;
      if (visits.some((v) => v.session_id === sessionId)) which.value = sessionId;
      open().catch((e) => text(viewerBox, `cannot show the mosaic: ${e.message}`));
    },
  };
}

// The structure's defect history, asked for once per page (it registers every visit).
function defectHistory(s) {
  if (!page.history) {
    page.history = apiJSON(`/api/structures/${s.id}/history`).catch((e) => {
      page.history = null;
      throw e;
    });
  }
  return page.history;
}

export async function showStructure(id, sessionId = null) {
  const root = document.getElementById("structures-page");
  destroyViewer();
  root.replaceChildren(el("p", { class: "muted" }, "loading…"));
  const [s, aashto] = await Promise.all([apiJSON(`/api/structures/${id}`), apiJSON("/api/aashto")]);
  Object.assign(page, { structure: s, aashto: aashto.elements, history: null, box: null });
  [page.elements, page.visits] = await Promise.all([
    apiJSON(`/api/structures/${id}/elements`),
    apiJSON(`/api/structures/${id}/visits`),
  ]);
  const visit = page.visits.find((v) => v.session_id === sessionId) || page.visits.at(-1) || null;
  const panel = el("section", { id: "visit-panel" });
  const tools = elementTools(s);
  const select = (v) => {
    history.replaceState(null, "", `#/structure/${s.id}/visit/${v.session_id}`);
    document.querySelectorAll("#timeline .visit").forEach((b) => {
      b.classList.toggle("selected", b.dataset.session === v.session_id);
      b.setAttribute("aria-pressed", String(b.dataset.session === v.session_id));
    });
    showVisit(panel, s, v, () => defectHistory(s)).catch((e) => text(panel, `cannot show the visit: ${e.message}`));
  };
  root.replaceChildren(
    el("p", { class: "small" }, el("a", { href: "#/structures" }, "◀ all structures")),
    el(
      "h2",
      { id: "structure-name" },
      s.name,
      " ",
      el("small", {}, [s.owner_id, s.location].filter(Boolean).join(" · ")),
    ),
    el(
      "section",
      {},
      el("h3", {}, `Visits (${page.visits.length})`),
      page.visits.length
        ? timeline(page.visits, visit?.session_id, select)
        : el("p", { class: "muted" }, "No visit yet."),
      attachForm(s),
    ),
    el("section", {}, el("h3", {}, "Elements"), elementsTable(s), tools.node),
    panel,
  );
  tools.open(visit?.session_id);
  if (visit) select(visit);
}
