// armserver dashboard: faults and homing (API.md "Faults and homing"), one panel per arm.
//
// app.js announces each arm card ("arm-card" on document) and its newest sample ("arm-sample"
// on the card); this module adds a panel that shows the servos' hardware faults with their
// advice, which joints are homed, and offers reboot (per faulted servo), home, and the joints'
// torque off and on (a Dynamixel arm; the tare is in app.js's Force panel). The
// calls go through app.js's `api` (window.armDashboard.api), so tokens work as everywhere.
import { call, CardPanel, el, panelPerCard } from "./panel.js";

class Panel extends CardPanel {
  constructor(name, card, detail) {
    super();
    this.name = name;
    this.detail = detail;
    this.faults = detail.faults || [];
    this.homed = detail.homed || [];
    const id = (s) => `${name}-${s}`;
    this.el = {
      faults: el("ul", { class: "faults", id: id("faults"), "aria-live": "polite" }),
      homed: el("div", { class: "homed row", id: id("homed") }),
      positions: el("input", { type: "text", id: id("home-positions"), "aria-label": "home positions (rad, m)",
        placeholder: "x, y, … (rad, m) or empty: the profile's home pose" }),
      error: el("div", { class: "err", id: id("faults-error"), role: "alert" }),
      note: el("span", { class: "muted small", id: id("faults-note") }, ""),
    };
    this.el.section = el("section", { class: "ctl faults-homing", id: id("faults-panel") },
      el("h3", {}, "Faults and homing"),
      this.el.faults, this.el.homed,
      el("div", { class: "row" }, this.el.positions,
        el("button", { type: "button", class: "primary", id: id("home"), title: "Declare the arm's current pose (nothing moves)",
          onclick: () => this.home() }, "Home")),
      this.torqueRow(id),
      this.el.note, this.el.error);
    (card.querySelector(".controls") || card).append(this.el.section);
    card.addEventListener("arm-sample", (ev) => this.update(ev.detail));
    card.addEventListener("arm-torque", () => this.refreshTorque());  // app.js: any client's
    this.showTorque(detail.torque);
    this.render();
  }

  update(sample) {
    const f = sample.faults || [], hm = sample.homed || [];
    if (JSON.stringify(f) === JSON.stringify(this.faults) && JSON.stringify(hm) === JSON.stringify(this.homed)) return;
    this.faults = f;
    this.homed = hm;
    this.render();
  }

  // The joints' torque (PUT /arms/{arm}/torque): off to move the arm by hand, on again to hold
  // where the hand left it; only on an arm whose servos have a torque switch (Dynamixel).
  torqueRow(id) {
    if (this.detail.capabilities?.protocol !== "dynamixel") return null;
    this.el.torque = el("span", { class: "muted small", id: id("torque"), "data-on": "true" }, "torque on");
    return el("div", { class: "row" },
      el("button", { type: "button", id: id("torque-off"), title: "Switch every joint's torque off: the arm is moved by hand",
        onclick: () => this.setTorque(false) }, "Torque off (by hand)"),
      el("button", { type: "button", id: id("torque-on"), title: "Switch the torque on again: each joint holds where it is",
        onclick: () => this.setTorque(true) }, "Torque on (hold)"),
      this.el.torque);
  }

  // Torque off lets a joint that falls without torque fall: the server asks whether its load
  // rests or is held (409 in_use naming load_supported), as for a reboot.
  async setTorque(on) {
    const path = `/arms/${encodeURIComponent(this.name)}/torque`;
    let d = await this.run("PUT", path, { on }, on ? "torque on" : "torque off");
    if (d === null && !on && this.el.error.dataset.code === "in_use"
        && this.el.error.textContent.includes("load_supported")
        && window.confirm(`${this.el.error.textContent}\n\nIs the load held or resting? OK switches the torque off.`)) {
      d = await this.run("PUT", path, { on, load_supported: true }, "torque off (load supported)");
    }
    if (d && typeof d.on === "boolean") this.showTorque(this.detail.joints.map(() => d.on));
  }

  // Which joints hold torque (the arm's detail: false where it was switched off through the
  // server, by this page, another client or a pass-through write; moves are refused then).
  showTorque(flags) {
    if (!this.el.torque || !Array.isArray(flags)) return;
    const off = this.detail.joints.map((j) => j.name).filter((n, i) => flags[i] === false);
    this.el.torque.dataset.on = String(off.length === 0);
    this.el.torque.textContent = off.length === 0 ? "torque on"
      : `torque off (${off.join(", ")}): move it by hand; moves are refused`;
  }

  // A `torque` or `rebooted` event (any client's): the detail says which joints hold torque.
  async refreshTorque() {
    if (!this.el.torque) return;
    try { this.showTorque((await call("GET", `/arms/${encodeURIComponent(this.name)}`)).torque); }
    catch (e) { /* the next event or the page's own request shows it */ }
  }

  render() {
    const rows = this.faults.map((f) => el("li", { class: "fault", "data-servo": f.servo },
      el("strong", {}, `Servo ${f.servo} (${f.joint}): ${f.bits.join(", ") || "alert"}`), " ",
      el("span", { class: "muted small" }, f.advice), " ",
      el("button", { type: "button", class: "stop", id: `${this.name}-reboot-${f.servo}`,
        onclick: () => this.reboot(f.servo) }, `Reboot servo ${f.servo}`)));
    this.el.faults.replaceChildren(...(rows.length ? rows : [el("li", { class: "muted small ok" }, "no faults")]));
    this.el.faults.dataset.count = String(this.faults.length);
    const names = this.detail.joints.map((j) => j.name);
    this.el.homed.replaceChildren(el("span", { class: "muted small" }, "homed:"),
      ...names.map((n, i) => el("span", { class: `badge ${this.homed[i] === false ? "warn" : "ok"}`, "data-joint": n },
        `${n} ${this.homed[i] === false ? "✗" : "✓"}`)));
    this.el.homed.dataset.homed = JSON.stringify(this.homed);
  }

  // A reboot switches the servo's torque off until it is set up again: for a joint that falls
  // without torque (the profile's falls_without_torque) the server asks whether its load rests
  // or is held (409 in_use naming load_supported); the operator's yes sends it again saying so.
  async reboot(servo) {
    const path = `/arms/${encodeURIComponent(this.name)}/dynamixel/${servo}/reboot`;
    const d = await this.run("POST", path, undefined, `servo ${servo} rebooted`);
    if (d === null && this.el.error.dataset.code === "in_use"
        && this.el.error.textContent.includes("load_supported")
        && window.confirm(`${this.el.error.textContent}\n\nIs the load resting or held? OK reboots servo ${servo}.`)) {
      await this.run("POST", path, { load_supported: true }, `servo ${servo} rebooted (load supported)`);
    }
  }

  async home() {
    const text = this.el.positions.value.trim();
    let body;
    if (text) {
      const positions = text.split(/[\s,]+/).filter(Boolean).map(Number);
      if (positions.some((v) => !Number.isFinite(v))) { this.showError({ detail: "positions must be numbers" }); return; }
      body = { positions };
    }
    const d = await this.run("POST", `/arms/${encodeURIComponent(this.name)}/home`, body, "homed");
    if (d && Array.isArray(d.homed)) { this.homed = d.homed; this.faults = d.faults || this.faults; this.render(); }
  }

  state() {
    return { faults: this.faults, homed: this.homed, ...this.shown() };
  }
}

panelPerCard(Panel, "armFaults");
