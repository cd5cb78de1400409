// Images the API serves (frames), fetched with the page's token once and kept as object URLs
// while the page lives.
import { api } from "./api.js";

const urls = new Map(); // API path -> promise of an object URL (null: not available)

export function imageURL(path) {
  if (!urls.has(path)) {
    urls.set(
      path,
      api(path)
        .then((r) => (r.ok ? r.blob() : null))
        .then((b) => (b ? URL.createObjectURL(b) : null))
        .catch(() => null),
    );
  }
  return urls.get(path);
}
