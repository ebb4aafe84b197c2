// armserver dashboard: joint calibration (API.md "Calibration (v1.2)"), one panel per arm.
//
// Leads a student through the day-one step: which joints are not calibrated on this hardware
// (from each sample's `calibrated`), the calibration poses the profile names (e.g. a jig),
// and a button that declares the pose the arm is in (nothing moves). Then the
// gravity fit: a motion through a few poses (the arm moves: lease holder), its progress, its
// residual. The firmware note of the arm's detail (a board without STATUS) is shown first.
// Calls go through app.js's `api` (window.armDashboard.api), so tokens and leases work as
// everywhere.
import { CardPanel, call, el, panelPerCard } from "./panel.js";

const fmt = (v) => (Math.abs(v) < 1e-9 ? "0" : v.toFixed(3));

class Panel extends CardPanel {
  constructor(name, card, detail) {
    super();
    this.name = name;
    this.detail = detail;
    this.calibrated = detail.calibrated || [];
    this.cal = null;
    const id = (s) => `${name}-cal-${s}`;
    this.path = `/arms/${encodeURIComponent(name)}/calibration`;
    this.el = {
      firmware: el("div", { class: "err", id: id("firmware"), role: "alert" }),
      joints: el("div", { class: "row", id: id("joints") }),
      steps: el("ol", { class: "small", id: id("steps") }),
      pose: el("select", { id: id("pose"), "aria-label": "calibration pose" }),
      positions: el("input", { type: "text", id: id("positions"), "aria-label": "joint values (rad, m)",
        placeholder: "or joint values: a, b, … (rad, m)" }),
      gravity: el("div", { class: "muted small", id: id("gravity") }),
      note: el("span", { class: "muted small", id: id("note") }, ""),
      error: el("div", { class: "err", id: id("error"), role: "alert" }),
    };
    this.el.section = el("section", { class: "ctl calibration", id: id("panel") },
      el("h3", {}, "Calibration"),
      this.el.firmware, this.el.joints, this.el.steps,
      el("div", { class: "row" }, this.el.pose, this.el.positions,
        el("button", { type: "button", class: "primary", id: id("declare"),
          title: "The arm is in this pose now: set the joints' zeros (nothing moves)",
          onclick: () => this.declare() }, "Declare pose")),
      el("div", { class: "row" },
        el("button", { type: "button", id: id("gravity-run"),
          title: "Move through a few poses and fit the gravity torques (the arm moves)",
          onclick: () => this.fitGravity() }, "Fit gravity"),
        el("button", { type: "button", class: "ghost", id: id("forget"),
          title: "Forget this hardware's stored calibration (instructor)",
          onclick: () => this.forget() }, "Forget")),
      this.el.gravity, this.el.note, this.el.error);
    (card.querySelector(".controls") || card).append(this.el.section);
    card.addEventListener("arm-sample", (ev) => this.update(ev.detail));
    this.el.firmware.textContent = detail.firmware || "";
    this.refresh();
  }

  update(sample) {
    const c = sample.calibrated || [];
    if (JSON.stringify(c) === JSON.stringify(this.calibrated)) return;
    this.calibrated = c;
    this.refresh();
  }

  async refresh() {
    try { this.cal = await call("GET", this.path); } catch (e) { this.showError(e); }
    this.render();
  }

  render() {
    const names = this.detail.joints.map((j) => j.name);
    const joints = this.cal?.joints || names.map((n, i) => ({ name: n, calibrated: this.calibrated[i] !== false }));
    this.el.joints.replaceChildren(el("span", { class: "muted small" }, "calibrated:"),
      ...joints.map((j) => el("span", { class: `badge ${j.calibrated ? "ok" : "warn"}`, "data-joint": j.name,
        title: j.calibrated ? `${j.source}: zero at ${fmt(j.offset)}` : "zero not known on this hardware" },
        `${j.name} ${j.calibrated ? "✓" : "✗"}`)));
    this.el.joints.dataset.calibrated = JSON.stringify(joints.map((j) => j.calibrated));
    const poses = this.cal?.poses || {};
    this.el.pose.replaceChildren(el("option", { value: "" }, "joint values →"),
      ...Object.entries(poses).map(([n, q]) => el("option", { value: n }, `${n} (${q.map(fmt).join(", ")})`)));
    if (Object.keys(poses).length) this.el.pose.value = Object.keys(poses)[0];
    const missing = joints.filter((j) => !j.calibrated).map((j) => j.name);
    const steps = missing.length ? [
      `Not calibrated on this hardware: ${missing.join(", ")}. Moves that would move them are refused.`,
      Object.keys(poses).length
        ? `Put the arm in a calibration pose (${Object.keys(poses).join(", ")}; README "On real hardware").`
        : "Put the arm in a pose whose joint values you know.",
      "Choose that pose (or type its joint values) and press Declare pose. Nothing moves.",
      "Check the arm drawn above matches the real one, then move it.",
    ] : ["Every joint's zero is known. Fit gravity to have the tip force read zero at every pose."];
    this.el.steps.replaceChildren(...steps.map((t) => el("li", {}, t)));
    const g = this.cal?.gravity, run = this.cal?.gravity_run;
    this.el.gravity.textContent = run && run.status === "running"
      ? `gravity fit: pose ${run.done + 1} of ${run.poses.length}…`
      : g ? `gravity fit: residual ${g.rms.toFixed(4)} (worst ${g.worst.toFixed(4)})${this.cal.stored ? ", stored" : ""}`
        : run && run.status === "failed" ? `gravity fit failed: ${run.reason}` : "no gravity fit";
  }

  async declare() {
    const text = this.el.positions.value.trim();
    let body;
    if (text) {
      const positions = text.split(/[\s,]+/).filter(Boolean).map(Number);
      if (positions.some((v) => !Number.isFinite(v))) { this.showError({ detail: "joint values must be numbers" }); return; }
      body = { positions };
    } else if (this.el.pose.value) body = { pose: this.el.pose.value };
    else { this.showError({ detail: "choose a pose or type joint values" }); return; }
    const d = await this.run("POST", this.path, body, "calibrated");
    if (d) { this.cal = d; this.render(); }
  }

  async fitGravity() {
    const d = await this.run("POST", `${this.path}/gravity`, {}, "gravity fit started");
    if (!d) return;
    for (let i = 0; i < 600; i++) {   // follow the run (at most 5 minutes of it)
      await new Promise((r) => setTimeout(r, 500));
      await this.refresh();
      if (!this.cal?.gravity_run || this.cal.gravity_run.status !== "running") break;
    }
  }

  async forget() {
    const d = await this.run("DELETE", this.path, undefined, "calibration forgotten");
    if (d) { this.cal = d; this.render(); }
  }

  state() {
    return { calibration: this.cal, calibrated: this.calibrated, ...this.shown() };
  }
}

panelPerCard(Panel, "armCalibration");
