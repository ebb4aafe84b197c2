// What the dashboard's panel modules share (faults.js, calibration.js, camera.js,
// recording.js): a DOM builder and a call of the API, through app.js's own api() (token,
// lease, errors) once the dashboard is up, and straight to the server before.

export const API = "/api/v1";
export const TOKEN_KEY = "armserver.token";

export function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k.startsWith("on")) e.addEventListener(k.slice(2), v);
    else if (v !== null && v !== undefined && v !== false) e.setAttribute(k, v === true ? "" : v);
  }
  for (const c of children) if (c !== null && c !== undefined) e.append(c);
  return e;
}

export function authHeaders() {
  const t = sessionStorage.getItem(TOKEN_KEY);
  return t ? { Authorization: `Bearer ${t}` } : {};
}

export async function call(method, path, body) {
  const api = window.armDashboard?.api;
  if (api) return api(method, path, body);
  const res = await fetch(API + path, { method, headers: { ...authHeaders(), ...(body ? { "Content-Type": "application/json" } : {}) },
    body: body ? JSON.stringify(body) : undefined });
  const data = await res.json().catch(() => null);
  if (!res.ok) throw Object.assign(new Error(data?.detail || res.statusText), { code: data?.code, detail: data?.detail });
  return data;
}
