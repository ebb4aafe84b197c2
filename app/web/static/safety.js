// Safety envelope on the dashboard: keep-out zones and the floor drawn in both views, and a
// speed-override slider for the instructor (GET/PUT /api/v1/arms/{arm}/safety).
//
// app.js hooks in three places: attachSafety() after an arm's card is built, drawSafety() in
// each view after the fixtures, and refresh() on a "safety" event from the telemetry socket.

const ZONE_FILL = "rgba(239, 68, 68, 0.18)";
const ZONE_EDGE = "#ef4444";

class SafetyPanel {
  constructor(arm, api, h) {
    this.arm = arm;
    this.api = api;
    this.data = null;
    this.drawn = { top: 0, side: 0, floor: false };
    const id = (s) => `${arm.name}-${s}`;
    this.el = {};
    this.el.summary = h("span", { class: "muted small", id: id("safety-summary") }, "…");
    this.el.slider = h("input", {
      type: "range", min: 0.05, max: 1, step: 0.05, value: 1, id: id("speed-override"),
      "aria-label": "speed override", disabled: true,
      oninput: () => { this.el.value.textContent = pct(this.el.slider.value); },
      onchange: () => this.setSpeed(Number(this.el.slider.value)),
    });
    this.el.value = h("span", { class: "jval", id: id("speed-override-value") }, "–");
    this.el.error = h("div", { class: "err", id: id("safety-error"), role: "alert" });
    this.el.section = h("section", { class: "ctl safety", id: id("safety") },
      h("h3", {}, "Safety envelope"),
      h("div", { class: "row" }, this.el.summary),
      h("div", { class: "row" }, h("span", { class: "muted small" }, "speed"), this.el.slider,
        this.el.value),
      this.el.error);
    const controls = arm.el.card.querySelector(".controls") || arm.el.card;
    controls.append(this.el.section);
    this.refresh();
  }

  path() { return `/arms/${encodeURIComponent(this.arm.name)}/safety`; }

  async refresh() {
    try {
      this.show(await this.api("GET", this.path()));
    } catch (e) {
      this.el.summary.textContent = `cannot read the envelope (${e.detail || e})`;
    }
  }

  async setSpeed(v) {
    this.el.error.replaceChildren();
    try {
      this.show(await this.api("PUT", this.path(), { speed_override: v }));
    } catch (e) {
      this.el.error.textContent = e.code === "forbidden"
        ? "Only an instructor may change the speed override" : `${e.detail || e}`;
      if (this.data) this.show(this.data);  // the slider goes back to what the server has
    }
  }

  show(d) {
    this.data = d;
    const floor = d.floor_z === null ? "no floor" : `floor ${(d.floor_z * 1000).toFixed(0)} mm`;
    const zones = d.zones.length === 1 ? "1 zone" : `${d.zones.length} zones`;
    const stored = d.persisted ? "" : " (not yet saved: see health)";
    this.el.summary.textContent = `${zones}, ${floor}, speed ${pct(d.speed_override)}${stored}`;
    this.el.slider.value = String(d.speed_override);
    this.el.slider.disabled = !d.editable;
    this.el.slider.title = d.editable ? "Scales the limits of moves planned from now on"
      : "Only an instructor may change this";
    this.el.value.textContent = pct(d.speed_override);
  }

  state() {
    const d = this.data;
    return d && { zones: d.zones.map((z) => z.name), floor_z: d.floor_z,
      speed_override: d.speed_override, editable: d.editable, drawn: { ...this.drawn },
      slider: Number(this.el.slider.value), sliderDisabled: this.el.slider.disabled };
  }
}

function pct(v) { return `${Math.round(Number(v) * 100)}%`; }

export function attachSafety(arm, api, h) {
  return new SafetyPanel(arm, api, h);
}

/** Zones as rectangles (their projection on the view's plane) and the floor in the side view. */
export function drawSafety(arm, ctx, X, Y, ax, ay, which) {
  const panel = arm.safety, d = panel?.data;
  if (!d) return;
  const at = (p, a, b) => { const v = [0, 0, 0]; v[ax] = p[a]; v[ay] = p[b]; return v; };
  ctx.save();
  ctx.lineWidth = 1.5; ctx.font = "11px system-ui, sans-serif";
  let n = 0;
  for (const z of d.zones) {
    const lo = [z.min.x, z.min.y, z.min.z], hi = [z.max.x, z.max.y, z.max.z];
    const p0 = at([lo[ax], lo[ay]], 0, 1), p1 = at([hi[ax], hi[ay]], 0, 1);
    const x0 = X(p0), y0 = Y(p0), x1 = X(p1), y1 = Y(p1);
    ctx.fillStyle = ZONE_FILL; ctx.strokeStyle = ZONE_EDGE;
    ctx.fillRect(Math.min(x0, x1), Math.min(y0, y1), Math.abs(x1 - x0), Math.abs(y1 - y0));
    ctx.strokeRect(Math.min(x0, x1), Math.min(y0, y1), Math.abs(x1 - x0), Math.abs(y1 - y0));
    ctx.fillStyle = ZONE_EDGE;
    ctx.fillText(z.name, Math.min(x0, x1) + 3, Math.min(y0, y1) + 12);
    n += 1;
  }
  let floor = false;
  if (which === "side" && d.floor_z !== null) {
    const v = [0, 0, 0]; v[ay] = d.floor_z;
    const y = Y(v);
    ctx.strokeStyle = ZONE_EDGE; ctx.setLineDash([8, 4]);
    ctx.beginPath(); ctx.moveTo(0, y); ctx.lineTo(ctx.canvas.width, y); ctx.stroke();
    ctx.setLineDash([]); ctx.fillStyle = ZONE_EDGE;
    ctx.fillText("floor", 4, y - 4);
    floor = true;
  }
  ctx.restore();
  panel.drawn[which] = n;
  if (which === "side") panel.drawn.floor = floor;
}
