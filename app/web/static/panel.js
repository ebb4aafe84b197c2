// What the dashboard's panel modules share (faults.js, calibration.js, camera.js,
// recording.js, setup.js): a DOM builder and a call of the API, through app.js's own api()
// (token, lease, errors) once the dashboard is up, and straight to the server before; and for
// the panels of an arm's card (faults.js, calibration.js), their base class and one panel made
// for each card.

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

// A panel on an arm's card. Its subclass makes `this.el.error` and `this.el.note`: `run` says
// there what a request did (the note, with the time) or why it failed (the error and its code).
export class CardPanel {
  async run(method, path, body, done) {
    this.el.error.replaceChildren();
    try {
      const d = await call(method, path, body);
      this.el.note.textContent = `${new Date().toLocaleTimeString()} ${done}`;
      return d;
    } catch (e) { this.showError(e); return null; }
  }

  showError(e) {
    this.el.error.dataset.code = e.code || "";
    this.el.error.textContent = e.detail || e.message || String(e);
  }

  // What the panel shows of its last request, for `state()` (the tests read it).
  shown() {
    return { error: this.el.error.textContent, errorCode: this.el.error.dataset.code || null,
      note: this.el.note.textContent };
  }
}

// One `Panel` for each arm card app.js announces ("arm-card" on document: the arm's name, its
// card and detail), and `window[global].state(arm)` for the tests.
export function panelPerCard(Panel, global) {
  const panels = new Map();   // arm name -> panel
  document.addEventListener("arm-card", (ev) => {
    const { name, card, detail } = ev.detail;
    if (!panels.has(name)) panels.set(name, new Panel(name, card, detail));
  });
  window[global] = { state: (name) => panels.get(name)?.state() ?? null };
}
