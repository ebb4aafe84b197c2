// armserver dashboard: cameras (API.md "Cameras (v1.2)"), a panel on the card of each camera's arm.
//
// The panel shows the camera's MJPEG stream (read with fetch, so that the access token goes in
// the Authorization header as everywhere; the parts are drawn on a canvas) with the latest
// detections drawn over it (polled twice a second while the panel is open). Click-to-reach: a
// click on the table, once the camera is calibrated, moves the tip above that point through the
// normal move route (POST /arms/{arm}/move/pose, so the planner, the guard, the envelope and the
// lease apply; a viewer sees the refusal). Calibrate: jog the tip onto a marker, click the
// marker in the picture (the tip's position is taken from the arm's latest sample), four or
// more times, then Fit.
import { API, authHeaders, call, el } from "./panel.js";

import { leaseFor } from "./classroom.js";

//: How high above the table a click-to-reach puts the tip, m.
const HOVER_M = 0.05;
const DETECT_MS = 500;
const DRAW = { red: "#e53935", green: "#43a047", blue: "#1e88e5", yellow: "#fdd835" };
let cameras = null;   // GET /cameras, once
const panels = new Map();   // camera name -> CameraPanel

// table (x, y) -> pixel with H; pixel -> table with its inverse
function apply(h, a, b) {
  const w = h[2][0] * a + h[2][1] * b + h[2][2];
  return [(h[0][0] * a + h[0][1] * b + h[0][2]) / w, (h[1][0] * a + h[1][1] * b + h[1][2]) / w];
}
function inverse(m) {
  const [[a, b, c], [d, e, f], [g, h, i]] = m;
  const A = e * i - f * h, B = -(d * i - f * g), C = d * h - e * g;
  const det = a * A + b * B + c * C;
  return [[A / det, -(b * i - c * h) / det, (b * f - c * e) / det],
    [B / det, (a * i - c * g) / det, -(a * f - c * d) / det],
    [C / det, -(a * h - b * g) / det, (a * e - b * d) / det]];
}

// the JPEG parts of a multipart/x-mixed-replace body, by their Content-Length
async function* mjpeg(reader) {
  let buf = new Uint8Array(0);
  const dec = new TextDecoder("latin1");
  for (;;) {
    const { value, done } = await reader.read();
    if (done) return;
    const next = new Uint8Array(buf.length + value.length);
    next.set(buf); next.set(value, buf.length); buf = next;
    for (;;) {
      const text = dec.decode(buf.subarray(0, Math.min(buf.length, 1024)));
      const end = text.indexOf("\r\n\r\n");
      if (end < 0) break;
      const m = /content-length:\s*(\d+)/i.exec(text.slice(0, end));
      if (!m) throw new Error("an MJPEG part without Content-Length");
      const start = end + 4, len = Number(m[1]);
      if (buf.length < start + len) break;
      yield buf.slice(start, start + len);
      let rest = start + len;
      while (rest < buf.length && (buf[rest] === 13 || buf[rest] === 10)) rest++;
      buf = buf.slice(rest);
    }
  }
}

class CameraPanel {
  constructor(cam, card) {
    this.cam = cam;
    this.tip = null;
    this.detections = [];
    this.calibration = null;
    this.points = [];
    this.calibrating = false;
    const id = (s) => `camera-${cam.name}-${s}`;
    this.canvas = el("canvas", { id: id("view"), class: "camera-view", width: cam.width, height: cam.height,
      title: "Click on the table: move the tip above that point" , onclick: (ev) => this.click(ev) });
    this.color = el("select", { id: id("color"), "aria-label": "colour to detect" }, el("option", { value: "" }, "all colours"));
    this.status = el("span", { class: "muted small", id: id("status") }, "");
    this.error = el("div", { class: "err", id: id("error"), role: "alert" });
    this.calButton = el("button", { type: "button", class: "ghost", id: id("calibrate"),
      onclick: () => this.toggleCalibration() }, "Calibrate");
    this.fitButton = el("button", { type: "button", class: "primary", id: id("fit"), hidden: true,
      onclick: () => this.fit() }, "Fit");
    this.section = el("section", { class: "ctl camera-panel", id: id("panel") },
      el("h3", {}, `Camera ${cam.name}`), this.canvas,
      el("div", { class: "row" }, this.color, this.calButton, this.fitButton, this.status), this.error);
    (card.querySelector(".controls") || card).append(this.section);
    card.addEventListener("arm-sample", (ev) => { this.tip = ev.detail?.tip || null; });
    this.load().then(() => { this.stream(); this.poll(); });
  }

  async load() {
    try {
      const d = await call("GET", `/cameras/${encodeURIComponent(this.cam.name)}`);
      for (const c of d.colors) this.color.append(el("option", { value: c }, c));
      const cal = await call("GET", `/cameras/${encodeURIComponent(this.cam.name)}/calibration`);
      this.setCalibration(cal);
    } catch (e) { this.error.textContent = e.message; }
  }

  setCalibration(cal) {
    this.calibration = cal.calibrated ? { h: cal.homography, inv: inverse(cal.homography), z: cal.z } : null;
    this.status.textContent = cal.calibrated ? `calibrated (${cal.points} points, ${cal.rms_px.toFixed(2)} px rms)` : "not calibrated";
  }

  async stream() {
    const ctx = this.canvas.getContext("2d");
    for (;;) {
      try {
        const res = await fetch(`${API}/cameras/${encodeURIComponent(this.cam.name)}/stream`, { headers: authHeaders() });
        if (!res.ok) {
          const data = await res.json().catch(() => null);
          throw new Error(data?.detail || res.statusText);
        }
        this.error.textContent = "";
        for await (const jpeg of mjpeg(res.body.getReader())) {
          const bitmap = await createImageBitmap(new Blob([jpeg], { type: "image/jpeg" }));
          ctx.drawImage(bitmap, 0, 0, this.canvas.width, this.canvas.height);
          bitmap.close();
          this.overlay(ctx);
        }
      } catch (e) { this.error.textContent = `camera: ${e.message}`; }
      await new Promise((r) => setTimeout(r, 2000));  // down: try again
    }
  }

  overlay(ctx) {
    ctx.lineWidth = 2;
    ctx.font = "12px sans-serif";
    for (const d of this.detections) {
      const [u0, v0, u1, v1] = d.bbox;
      ctx.strokeStyle = DRAW[d.color] || "#fff";
      ctx.strokeRect(u0, v0, u1 - u0, v1 - v0);
      ctx.fillStyle = ctx.strokeStyle;
      const where = d.position ? ` ${(d.position.x * 1000).toFixed(0)}, ${(d.position.y * 1000).toFixed(0)} mm` : "";
      ctx.fillText(`${d.color}${where}`, u0, Math.max(10, v0 - 3));
    }
    ctx.strokeStyle = "#fff";
    for (const p of this.points) { ctx.beginPath(); ctx.arc(p.pixel.u, p.pixel.v, 5, 0, 2 * Math.PI); ctx.stroke(); }
  }

  async poll() {
    for (;;) {
      if (this.section.isConnected && !document.hidden) {
        try {
          const q = this.color.value ? `?color=${encodeURIComponent(this.color.value)}` : "";
          const r = await call("GET", `/cameras/${encodeURIComponent(this.cam.name)}/detections${q}`);
          this.detections = r.detections;
        } catch { this.detections = []; }
      }
      await new Promise((r) => setTimeout(r, DETECT_MS));
    }
  }

  pixel(ev) {
    const r = this.canvas.getBoundingClientRect();
    return { u: (ev.clientX - r.left) * this.canvas.width / r.width, v: (ev.clientY - r.top) * this.canvas.height / r.height };
  }

  async click(ev) {
    const px = this.pixel(ev);
    this.error.textContent = "";
    if (this.calibrating) {
      if (!this.tip) { this.error.textContent = "no tip position yet"; return; }
      this.points.push({ pixel: px, position: { x: this.tip.x, y: this.tip.y, z: this.tip.z } });
      this.status.textContent = `${this.points.length} point(s): jog the tip to the next marker and click it`;
      return;
    }
    if (!this.calibration) { this.error.textContent = "calibrate the camera first"; return; }
    const [x, y] = apply(this.calibration.inv, px.u, px.v);
    try {
      await call("POST", `/arms/${encodeURIComponent(this.cam.arm)}/move/pose`,
        { x, y, z: this.calibration.z + HOVER_M, path: "joint" });
      this.status.textContent = `moving above ${(x * 1000).toFixed(0)}, ${(y * 1000).toFixed(0)} mm`;
    } catch (e) { this.error.textContent = `${e.code ? e.code + ": " : ""}${e.message}`; }
  }

  toggleCalibration() {
    this.calibrating = !this.calibrating;
    this.points = [];
    this.fitButton.hidden = !this.calibrating;
    this.calButton.textContent = this.calibrating ? "Cancel" : "Calibrate";
    this.status.textContent = this.calibrating ? "jog the tip onto a marker on the table, then click the marker" : "";
  }

  async fit() {
    // the camera's arm's lease goes with it (api() sends a lease only on /arms/... paths)
    const lease = leaseFor(`/arms/${encodeURIComponent(this.cam.arm)}/`);
    const res = await fetch(`${API}/cameras/${encodeURIComponent(this.cam.name)}/calibration`, {
      method: "POST", body: JSON.stringify({ points: this.points }),
      headers: { ...authHeaders(), "Content-Type": "application/json", ...(lease ? { "X-Arm-Lease": lease } : {}) } });
    const data = await res.json().catch(() => null);
    if (!res.ok) { this.error.textContent = `${data?.code ? data.code + ": " : ""}${data?.detail || res.statusText}`; return; }
    this.toggleCalibration();
    this.setCalibration(data);
  }

  state() {
    return { name: this.cam.name, calibrated: !!this.calibration, detections: this.detections, points: this.points.length,
      tip: this.tip, status: this.status.textContent, error: this.error.textContent };
  }
}

document.addEventListener("arm-card", async (ev) => {
  const { name, card } = ev.detail;
  try {
    cameras = cameras || call("GET", "/cameras");
    for (const cam of await cameras) {
      if (cam.arm === name && !panels.has(cam.name)) panels.set(cam.name, new CameraPanel(cam, card));
    }
  } catch { cameras = null; /* no cameras, or no token yet: no panel */ }
});

window.armCameras = { state: (name) => panels.get(name)?.state() ?? null, panels: () => [...panels.keys()] };
