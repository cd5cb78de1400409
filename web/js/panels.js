// The Drive page's panels (plots, coverage, edge events) opened or closed as each user left
// them, kept with their preferences on the station.
import { keep, preferences } from "./preferences.js";

function layout() {
  const out = {};
  for (const d of document.querySelectorAll("details.panel[data-panel]"))
    out[d.dataset.panel] = d.open ? "open" : "closed";
  return out;
}

export async function initPanels() {
  const kept = (await preferences()).drive_panels || {};
  for (const d of document.querySelectorAll("details.panel[data-panel]")) {
    if (kept[d.dataset.panel]) d.open = kept[d.dataset.panel] !== "closed";
  }
  let saved = JSON.stringify(layout());
  document.body.dataset.panels = saved;
  for (const d of document.querySelectorAll("details.panel[data-panel]")) {
    d.addEventListener("toggle", () => {
      const now = JSON.stringify(layout());
      if (now === saved) return;
      saved = now;
      document.body.dataset.panels = now;
      keep({ drive_panels: JSON.parse(now) });
    });
  }
}
