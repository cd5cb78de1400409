// The replay of a defect: the frames it was seen in (thumbnails), and a timeline over every
// frame of the session, the way Foxglove's is, with those frames marked: each position shows
// the frame, the robot's pose and the telemetry of that moment, all from the stored data.
import { apiJSON, el, fmt, text } from "./api.js";
import { imageURL } from "./images.js";

const timelines = new Map(); // session id -> its frames (seq, timestamp, pose), loaded once

async function sessionFrames(sid) {
  if (!timelines.has(sid)) {
    timelines.set(
      sid,
      (async () => {
        const out = [];
        for (let skip = 0; ; skip += 1000) {
          const page = await apiJSON(`/api/sessions/${sid}/frames?skip=${skip}&limit=1000`);
          out.push(...page.data);
          if (out.length >= page.count || !page.data.length) return out;
        }
      })(),
    );
  }
  return timelines.get(sid);
}

// The telemetry sample nearest time t (robot clock), from a window around it.
async function telemetryAt(sid, t) {
  const body = await apiJSON(`/api/sessions/${sid}/telemetry?since=${t - 2}&until=${t + 2}&limit=400`);
  let best = null;
  for (const s of body.data) if (!best || Math.abs(s.timestamp - t) < Math.abs(best.timestamp - t)) best = s;
  return best ? { dt_s: best.timestamp - t, data: best.data } : null;
}

function clock(seconds) {
  const t = Math.max(0, Math.round(seconds));
  return `${String(Math.floor(t / 60)).padStart(2, "0")}:${String(t % 60).padStart(2, "0")}`;
}

function caption(f, start, telemetry) {
  const t = telemetry?.data || {};
  const wheels = t.wheel_speed_mps || [];
  return [
    `frame ${f.seq}`,
    `+${clock(f.timestamp - start)}`,
    f.pose_x !== null && f.pose_x !== undefined
      ? `x ${fmt(f.pose_x, 3)} m, y ${fmt(f.pose_y, 3)} m, heading ${fmt(((f.pose_yaw || 0) * 180) / Math.PI, 1)}°`
      : "no pose",
    t.battery_v ? `battery ${fmt(t.battery_v.main)} V` : null,
    wheels.length ? `speed ${fmt(wheels.reduce((a, v) => a + v, 0) / wheels.length)} m/s` : null,
    typeof t.adhesion_margin === "number" ? `adhesion ${fmt(t.adhesion_margin)}×` : null,
    telemetry ? `telemetry ${fmt(telemetry.dt_s, 2)} s from the frame` : "no telemetry",
  ]
    .filter(Boolean)
    .join(" · ");
}

export function replay(sid, defectId) {
  const node = el(
    "div",
    { id: "replay", class: "replay" },
    el("p", { class: "muted small" }, "finding the frames it was seen in…"),
  );
  Promise.all([apiJSON(`/api/sessions/${sid}/defects/${defectId}/sightings`), sessionFrames(sid)])
    .then(([seen, frames]) => {
      if (!frames.length) {
        node.replaceChildren(el("p", { class: "muted small" }, "the session stored no frame"));
        return;
      }
      const index = new Map(frames.map((f, i) => [f.seq, i]));
      const start = frames[0].timestamp;
      const big = el("img", { class: "replay-frame", alt: "frame" });
      const line = el("p", { class: "small replay-caption" });
      const marks = el(
        "datalist",
        { id: `sightings-${defectId}` },
        ...seen.map((s) => el("option", { value: String(index.get(s.seq) ?? 0) })),
      );
      const timeline = el("input", {
        type: "range",
        min: "0",
        max: String(frames.length - 1),
        step: "1",
        list: marks.id,
        "aria-label": "session timeline: every frame, the defect's marked",
      });
      const thumbs = seen.map((s) => {
        const img = el("img", { alt: `frame ${s.seq}`, loading: "lazy" });
        imageURL(s.image_url).then((url) => {
          if (url) img.src = url;
        });
        return el(
          "button",
          {
            class: "replay-thumb",
            dataset: { seq: s.seq },
            title: `frame ${s.seq}`,
            onclick: () => show(index.get(s.seq) ?? 0),
          },
          img,
        );
      });
      let shown = -1;
      const show = async (i) => {
        const f = frames[i];
        shown = i;
        timeline.value = String(i);
        thumbs.forEach((t) => t.classList.toggle("selected", Number(t.dataset.seq) === f.seq));
        node.dataset.shown = String(f.seq);
        node.dataset.seen = String(seen.some((s) => s.seq === f.seq));
        text(line, caption(f, start, null));
        const [url, telemetry] = await Promise.all([
          imageURL(`/api/sessions/${sid}/frames/${f.seq}/image`),
          telemetryAt(sid, f.timestamp).catch(() => null),
        ]);
        if (shown !== i) return; // scrubbed on meanwhile
        if (url) big.src = url;
        text(line, caption(f, start, telemetry));
      };
      timeline.addEventListener("input", () => show(Number(timeline.value)));
      node.replaceChildren(
        el(
          "h4",
          {},
          seen.length ? `Seen in ${seen.length} frame${seen.length === 1 ? "" : "s"}` : "Not seen in any stored frame",
        ),
        el("div", { class: "replay-strip" }, ...thumbs),
        marks,
        el(
          "label",
          { class: "small muted" },
          `session timeline (${frames.length} frames, ${clock(frames[frames.length - 1].timestamp - start)})`,
          timeline,
        ),
        big,
        line,
      );
      show(seen.length ? (index.get(seen[0].seq) ?? 0) : 0);
    })
    .catch((e) => node.replaceChildren(el("p", { class: "muted small" }, `frames unavailable: ${e.message}`)));
  return node;
}
