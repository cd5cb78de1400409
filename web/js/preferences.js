// What the signed-in user keeps of the dashboard, on the station (so it follows them to
// any browser): GET / PATCH /api/auth/me/preferences, merged key by key.
import { api, apiJSON } from "./api.js";

let kept = null; // a promise of the preferences as last read or written

export function preferences() {
  if (!kept) kept = apiJSON("/api/auth/me/preferences").catch(() => ({}));
  return kept;
}

// Keep some preferences (a value of null forgets one); the rest stay as they are.
export async function keep(changes) {
  const res = await api("/api/auth/me/preferences", {
    method: "PATCH",
    headers: { "Content-Type": "application/json" },
    body: JSON.stringify(changes),
  });
  if (res.ok) kept = Promise.resolve(await res.json());
  return res.ok;
}
