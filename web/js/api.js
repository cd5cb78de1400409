// REST helpers: the bearer token of this tab, authenticated fetch and downloads.
export let token = sessionStorage.getItem("steelscan-token");
const listeners = [];

export function setToken(value) {
  token = value || null;
  if (token) sessionStorage.setItem("steelscan-token", token);
  else sessionStorage.removeItem("steelscan-token");
}
export function onSignedOut(fn) {
  listeners.push(fn);
}
export function authHeaders() {
  return token ? { Authorization: `Bearer ${token}` } : {};
}

export async function api(path, options = {}) {
  const res = await fetch(path, { ...options, headers: { ...authHeaders(), ...(options.headers || {}) } });
  if (res.status === 401) {
    listeners.forEach((fn) => fn());
    throw new Error("signed out");
  }
  return res;
}

export async function apiJSON(path, options = {}) {
  const res = await api(path, options);
  if (!res.ok) throw new Error(`${path}: HTTP ${res.status}`);
  return res.json();
}

export function patchJSON(path, body) {
  return api(path, { method: "PATCH", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) });
}

export function text(el, value) {
  if (el) el.textContent = value;
}

export function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") node.className = v;
    else if (k === "dataset") Object.assign(node.dataset, v);
    else if (k.startsWith("on")) node.addEventListener(k.slice(2), v);
    else if (v !== undefined && v !== null && v !== false) node.setAttribute(k, v === true ? "" : v);
  }
  node.append(...children.filter((c) => c !== null && c !== undefined));
  return node;
}

// A duration as people say it: "12 min 05 s", "1 h 02 min".
export function duration(seconds) {
  if (typeof seconds !== "number" || !Number.isFinite(seconds)) return "–";
  const t = Math.round(seconds);
  const h = Math.floor(t / 3600);
  const m = Math.floor((t % 3600) / 60);
  const s = t % 60;
  const two = (n) => String(n).padStart(2, "0");
  return h ? `${h} h ${two(m)} min` : m ? `${m} min ${two(s)} s` : `${s} s`;
}

export function fmt(v, digits = 2) {
  return typeof v === "number" && Number.isFinite(v) ? v.toFixed(digits) : "–";
}

// Authenticated download; an export still being made (202 + job) is waited for.
export async function download(path, filename, status) {
  for (let attempt = 0; attempt < 900; attempt++) {
    const res = await api(path);
    if (res.status === 202) {
      const job = await res.json();
      text(status, `preparing ${filename}… ${Math.round(job.progress * 100)}%`);
      await new Promise((r) => setTimeout(r, 1000));
      continue;
    }
    if (!res.ok) {
      text(status, `${filename}: failed (HTTP ${res.status})`);
      return;
    }
    const url = URL.createObjectURL(await res.blob());
    const a = el("a", { href: url, download: filename });
    document.body.appendChild(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 60000);
    text(status, "");
    return;
  }
}
