// The browser's live link (/ws/live): JSON events and binary camera frames in, commands out.
import { text, token } from "./api.js";
import { EVENT } from "./events.js";

const handlers = { event: [], frame: [] };
let socket = null;
export const link = { watcherId: null, open: false };

export function on(kind, fn) {
  handlers[kind].push(fn);
}

export function connect() {
  const proto = location.protocol === "https:" ? "wss" : "ws";
  const query = token ? `?token=${encodeURIComponent(token)}` : "";
  socket = new WebSocket(`${proto}://${location.host}/ws/live${query}`);
  socket.binaryType = "arraybuffer";
  const state = document.getElementById("link-state");
  socket.onopen = () => {
    link.open = true;
    text(state, "live link up");
    state.classList.add("ok");
  };
  socket.onclose = () => {
    link.open = false;
    text(state, "reconnecting…");
    state.classList.remove("ok");
    handlers.event.forEach((fn) => fn({ type: "link", open: false }));
    setTimeout(connect, 1000);
  };
  socket.onmessage = (ev) => {
    if (typeof ev.data === "string") {
      const event = JSON.parse(ev.data);
      if (event.type === EVENT.HELLO) link.watcherId = event.watcher_id;
      handlers.event.forEach((fn) => fn(event));
    } else {
      const view = new DataView(ev.data);
      const headLen = view.getUint32(0, true);
      const header = JSON.parse(new TextDecoder().decode(new Uint8Array(ev.data, 4, headLen)));
      const jpeg = new Uint8Array(ev.data, 4 + headLen);
      handlers.frame.forEach((fn) => fn(header, jpeg));
    }
  };
}

export function send(message) {
  if (!socket || socket.readyState !== WebSocket.OPEN) return false;
  socket.send(JSON.stringify(message));
  return true;
}
