// The admin page: accounts (add, role, new password, remove) and robots (register with a
// token shown once, revoke). Only admins see it; the station refuses others anyway.
import { api, apiJSON, el, text } from "./api.js";

const ROLES = ["viewer", "operator", "admin"];

async function send(method, path, body) {
  const res = await api(path, {
    method,
    headers: { "Content-Type": "application/json" },
    body: body ? JSON.stringify(body) : undefined,
  });
  if (res.ok) return "";
  let detail = "";
  try {
    const j = await res.json();
    detail = typeof j.detail === "string" ? j.detail : j.detail?.[0]?.msg || "";
  } catch {
    // not JSON
  }
  return `HTTP ${res.status}${detail ? `: ${detail}` : ""}`;
}

function status(id) {
  return el("p", { id, class: "small", role: "status" });
}

function usersTable(users, refresh) {
  const result = (msg) => {
    text(document.getElementById("users-status"), msg);
    if (!msg.startsWith("HTTP")) refresh();
  };
  const rows = users.map((u) =>
    el(
      "tr",
      { dataset: { user: u.name } },
      el("td", {}, u.name),
      el(
        "td",
        {},
        el(
          "select",
          {
            "aria-label": `role of ${u.name}`,
            onchange: async (e) => {
              const err = await send("PATCH", `/api/users/${encodeURIComponent(u.name)}`, { role: e.target.value });
              result(err || `${u.name} is now ${e.target.value}`);
            },
          },
          ...ROLES.map((r) => {
            const o = el("option", { value: r }, r);
            o.selected = r === u.role;
            return o;
          }),
        ),
      ),
      el("td", {}, new Date(u.created_at).toLocaleDateString()),
      el(
        "td",
        {},
        el(
          "button",
          {
            onclick: async () => {
              const password = prompt(`New password for ${u.name} (at least 8 characters):`);
              if (!password) return;
              const err = await send("PATCH", `/api/users/${encodeURIComponent(u.name)}`, { password });
              result(err || `${u.name} has a new password and is signed out everywhere`);
            },
          },
          "New password",
        ),
        " ",
        el(
          "button",
          {
            class: "danger",
            onclick: async () => {
              if (!confirm(`Remove the account ${u.name}?`)) return;
              const err = await send("DELETE", `/api/users/${encodeURIComponent(u.name)}`);
              result(err || `${u.name} removed`);
            },
          },
          "Remove",
        ),
      ),
    ),
  );
  const form = el(
    "form",
    {
      id: "add-user",
      class: "row",
      onsubmit: async (e) => {
        e.preventDefault();
        const f = new FormData(e.target);
        const err = await send("POST", "/api/users", {
          name: f.get("name"),
          password: f.get("password"),
          role: f.get("role"),
        });
        if (!err) e.target.reset();
        result(err || `${f.get("name")} added`);
      },
    },
    el("input", { name: "name", placeholder: "user name", required: true, "aria-label": "new user's name" }),
    el("input", {
      name: "password",
      type: "password",
      placeholder: "password (8+ characters)",
      minlength: "8",
      required: true,
      autocomplete: "new-password",
      "aria-label": "new user's password",
    }),
    el("select", { name: "role", "aria-label": "new user's role" }, ...ROLES.map((r) => el("option", { value: r }, r))),
    el("button", { type: "submit" }, "Add user"),
  );
  return [
    el("h2", {}, "Users"),
    el("table", { id: "users" }, el("tr", {}, ...["name", "role", "since", ""].map((h) => el("th", {}, h))), ...rows),
    form,
    status("users-status"),
  ];
}

function robotsTable(robots, refresh) {
  const rows = robots.map((r) =>
    el(
      "tr",
      { dataset: { robot: r.name }, class: r.revoked ? "muted" : "" },
      el("td", {}, r.name),
      el("td", {}, r.revoked ? "revoked" : "active"),
      el("td", { class: "num" }, String(r.sessions)),
      el("td", {}, r.last_session_at ? new Date(r.last_session_at).toLocaleString() : "–"),
      el(
        "td",
        {},
        r.revoked
          ? ""
          : el(
              "button",
              {
                class: "danger",
                onclick: async () => {
                  if (!confirm(`Revoke ${r.name}'s token? It will not be able to connect again.`)) return;
                  const err = await send("DELETE", `/api/robots/${encodeURIComponent(r.name)}`);
                  text(document.getElementById("robots-status"), err || `${r.name} revoked`);
                  if (!err) refresh();
                },
              },
              "Revoke",
            ),
      ),
    ),
  );
  const form = el(
    "form",
    {
      id: "add-robot",
      class: "row",
      onsubmit: async (e) => {
        e.preventDefault();
        const name = new FormData(e.target).get("name");
        const res = await api("/api/robots", {
          method: "POST",
          headers: { "Content-Type": "application/json" },
          body: JSON.stringify({ name }),
        });
        const out = document.getElementById("robots-status");
        if (!res.ok) {
          text(out, `HTTP ${res.status}: ${(await res.json().catch(() => ({}))).detail || ""}`);
          return;
        }
        const { token } = await res.json();
        e.target.reset();
        await refresh();
        document
          .getElementById("robots-status")
          .replaceChildren(
            `Token of ${name} (shown once; set it as the robot's STEELSCAN token): `,
            el("code", { id: "new-robot-token", class: "mono" }, token),
          );
      },
    },
    el("input", { name: "name", placeholder: "robot name", required: true, "aria-label": "new robot's name" }),
    el("button", { type: "submit" }, "Register robot"),
  );
  return [
    el("h2", {}, "Robots"),
    el(
      "table",
      { id: "robots" },
      el("tr", {}, ...["name", "token", "sessions", "last session", ""].map((h) => el("th", {}, h))),
      ...rows,
    ),
    form,
    status("robots-status"),
  ];
}

// Opening the page drops what it showed last time (stale lists, forms about to be replaced)
// until the station answers; a refresh after an action keeps it meanwhile.
export async function loadAdmin({ opening = false } = {}) {
  const root = document.getElementById("admin");
  if (opening) root.replaceChildren(el("p", { class: "small" }, "loading accounts and robots…"));
  const keep = {
    users: document.getElementById("users-status")?.textContent || "",
    robots: document.getElementById("robots-status")?.cloneNode(true),
  };
  const [users, robots] = await Promise.all([apiJSON("/api/users"), apiJSON("/api/robots")]);
  root.replaceChildren(
    el("section", {}, ...usersTable(users, loadAdmin)),
    el("section", {}, ...robotsTable(robots, loadAdmin)),
  );
  text(document.getElementById("users-status"), keep.users);
  if (keep.robots) document.getElementById("robots-status").replaceWith(keep.robots);
}
