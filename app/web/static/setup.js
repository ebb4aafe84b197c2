// armserver dashboard: servo set-up from the factory state (issue 24), the dashboard's face of
// `armserver setup-servos` (routes under /api/v1/setup-servos, app/web/routes/setup_servos.py).
//
// Walks a student through it: choose the arm's profile and the port (or start the practice bus,
// a simulated bus of factory servos the server serves), scan, connect only the servo for the
// next joint (with the ones already set up), assign it, and the scan that follows verifies it;
// then the next joint. Every refusal is shown in words with its code (no_servo,
// several_servos, id_in_use, port_in_use ...). Scanning and assigning need an instructor's
// token: the set-up writes the servos' EEPROM.
import { call, el } from "./panel.js";

const FACTORY_RATE = 57600;
const fmtRate = (r) => `${r.toLocaleString("en")} bps`;

class SetupPanel {
  constructor(root) {
    this.scan = null;
    this.practice = null;
    this.busy = false;
    const id = (s) => `setup-${s}`;
    this.el = {
      profile: el("select", { id: id("profile"), "aria-label": "profile" }),
      port: el("input", { type: "text", id: id("port"), "aria-label": "port", size: 34,
        placeholder: "/dev/ttyUSB0 or /dev/serial/by-id/…" }),
      rates: el("input", { type: "text", id: id("rates"), "aria-label": "baud rates to scan", size: 18,
        placeholder: "rates: all standard" }),
      joint: el("select", { id: id("joint"), "aria-label": "joint" }),
      practice: el("div", { class: "muted small", id: id("practice") }),
      found: el("table", { class: "small", id: id("found") }),
      steps: el("ol", { class: "small", id: id("steps") }),
      said: el("pre", { class: "small", id: id("said") }),
      note: el("span", { class: "muted small", id: id("note") }, ""),
      error: el("div", { class: "err", id: id("error"), role: "alert" }),
    };
    const button = (name, text, title, onclick, cls) =>
      el("button", { type: "button", id: id(name), title, onclick, class: cls || null }, text);
    root.append(el("details", { id: id("details"), ontoggle: (ev) => { if (ev.target.open) this.load(); } },
      el("summary", {}, "Servo set-up (Dynamixel, from the factory state)"),
      el("section", { class: "ctl", id: id("panel") },
        el("div", { class: "row" }, el("label", {}, "Profile ", this.el.profile),
          el("label", {}, "Port ", this.el.port), this.el.rates,
          button("scan", "Scan", "Find the servos on the port at every standard rate (writes nothing)",
            () => this.doScan(), "primary")),
        el("div", { class: "row" },
          button("practice-start", "Practice bus", "Start a simulated bus of one factory servo (ID 1, 57,600 bps) and use its port",
            () => this.startPractice()),
          button("practice-plug", "Plug in a servo", "Plug one more factory servo into the practice bus",
            () => this.plug()),
          button("practice-stop", "Stop practice bus", "Stop the practice bus", () => this.stopPractice(), "ghost"),
          this.el.practice),
        this.el.found, this.el.steps,
        el("div", { class: "row" }, el("label", {}, "Joint ", this.el.joint),
          button("assign", "Assign", "Give the one new servo on the port this joint's ID, rate and settings (EEPROM, torque off), then verify",
            () => this.assign(), "primary")),
        this.el.said, this.el.note, this.el.error)));
  }

  async load() {   // at start, and each time the panel is opened (a token may have come since)
    try {
      const info = await call("GET", "/setup-servos");
      const keep = this.el.profile.value;
      this.el.profile.replaceChildren(...info.profiles.map((p) => el("option", { value: p }, p)));
      if (info.profiles.includes(keep)) this.el.profile.value = keep;
      this.el.error.replaceChildren();
      this.showPractice(info.practice);
      this.render();
    } catch (e) { this.showError(e); }
  }

  showPractice(bus) {
    this.practice = bus;
    this.el.practice.textContent = bus.running
      ? `practice bus at ${bus.port}: ${bus.servos.map((s) => `ID ${s.id} @ ${fmtRate(s.baudrate)}`).join(", ") || "no servo"}`
      : "no practice bus";
  }

  async startPractice() {
    const bus = await this.run("POST", "/setup-servos/practice", { servos: 1 }, "practice bus started: one factory servo plugged in");
    if (!bus) return;
    this.showPractice(bus);
    this.el.port.value = bus.port;
    this.scan = null;
    this.render();
  }

  async plug() {
    const bus = await this.run("POST", "/setup-servos/practice/servos", undefined, "one more factory servo plugged in");
    if (bus) this.showPractice(bus);
  }

  async stopPractice() {
    const bus = await this.run("DELETE", "/setup-servos/practice", undefined, "practice bus stopped");
    if (bus) this.showPractice(bus);
  }

  request(extra = {}) {
    const rates = this.el.rates.value.split(/[\s,]+/).filter(Boolean).map(Number);
    return { port: this.el.port.value.trim(), profile: this.el.profile.value,
      ...(rates.length ? { baudrates: rates } : {}), ...extra };
  }

  async doScan() {
    if (!this.el.port.value.trim()) { this.showError({ detail: "type the port the servos are on (or start the practice bus)" }); return; }
    this.el.note.textContent = "scanning every standard rate…";
    const d = await this.run("POST", "/setup-servos/scan", this.request(), "scanned");
    if (d) { this.scan = d; this.render(); }
  }

  async assign() {
    const joint = this.el.joint.value;
    if (!this.scan || !joint) { this.showError({ detail: "scan first, then choose the joint" }); return; }
    this.el.note.textContent = `setting up the servo for joint ${joint}…`;
    const d = await this.run("POST", "/setup-servos/assign", this.request({ joint }), `joint ${joint} set up`);
    if (!d) return;
    this.el.said.textContent = d.said.join("\n");
    this.el.said.dataset.joint = joint;
    if (this.practice?.running) this.showPractice(await call("GET", "/setup-servos").then((i) => i.practice).catch(() => this.practice));
    const again = await this.run("POST", "/setup-servos/scan", this.request(), `joint ${joint} set up and verified`);
    if (again) { this.scan = again; this.render(); }
  }

  render() {
    const s = this.scan;
    if (!s) {
      this.el.found.replaceChildren();
      this.el.steps.replaceChildren(el("li", {}, "Choose the arm's profile and type the port its adapter is on (or press Practice bus), then Scan."));
      this.el.joint.replaceChildren();
      return;
    }
    this.el.found.replaceChildren(
      el("tr", {}, ...["ID", "rate", "model", "torque", "is"].map((h) => el("th", {}, h))),
      ...s.servos.map((f) => el("tr", { "data-id": f.id, "data-joint": f.joint || "" },
        el("td", {}, String(f.id)), el("td", {}, fmtRate(f.baudrate)), el("td", {}, f.model_name),
        el("td", {}, f.torque ? "on" : "off"), el("td", {}, f.joint ? `joint ${f.joint}` : f.note || "not the profile's"))));
    this.el.found.dataset.servos = JSON.stringify(s.servos.map((f) => [f.id, f.baudrate, f.joint]));
    const next = s.todo[0];
    const steps = [];
    if (!s.servos.length && !s.collisions.length) steps.push("Nothing answered at any standard rate: check power, the cable and the adapter.");
    for (const c of s.collisions) steps.push(`Garbled answers: ${c}. Connect one servo at a time.`);
    if (next) {
      const fresh = s.servos.filter((f) => !f.joint);
      steps.push(`Connect only the servo for joint ${next} (ID ${s.joints[next]} when set up), with the ones already set up${fresh.length ? "" : "; power it"}.`);
      steps.push(`Press Assign: it gets ID ${s.joints[next]}, ${fmtRate(s.profile_baudrate)} and the profile's settings (torque off, EEPROM), and is read back.`);
      steps.push(`Still to set up: ${s.todo.join(", ")}.`);
    } else steps.push(`Every joint of ${s.profile} answers at its ID and ${fmtRate(s.profile_baudrate)}: the arm's link can come up (serve it on this port).`);
    if (s.servos.some((f) => f.id === 1 && f.baudrate === FACTORY_RATE)) steps.push("A servo in the factory state (ID 1, 57,600 bps) is on the bus.");
    this.el.steps.replaceChildren(...steps.map((t) => el("li", {}, t)));
    this.el.steps.dataset.next = next || "";
    const keep = this.el.joint.value;
    this.el.joint.replaceChildren(...Object.keys(s.joints).map((j) => el("option", { value: j }, `${j} (ID ${s.joints[j]})`)));
    this.el.joint.value = next || keep || Object.keys(s.joints)[0];
  }

  async run(method, path, body, done) {
    if (this.busy) return null;
    this.busy = true;
    this.el.error.replaceChildren();
    delete this.el.error.dataset.code;
    try {
      const d = await call(method, path, body);
      this.el.note.textContent = `${new Date().toLocaleTimeString()} ${done}`;
      return d;
    } catch (e) { this.showError(e); this.el.note.textContent = ""; return null; } finally { this.busy = false; }
  }

  showError(e) {
    this.el.error.dataset.code = e.code || "";
    this.el.error.textContent = `${e.detail || e.message || String(e)}${e.code ? ` (${e.code})` : ""}`;
  }

  state() {
    return { scan: this.scan, practice: this.practice, error: this.el.error.textContent,
      errorCode: this.el.error.dataset.code || null, note: this.el.note.textContent,
      said: this.el.said.textContent };
  }
}

let panel = null;
function start() {
  const root = document.getElementById("servo-setup");
  if (root && !panel) panel = new SetupPanel(root);
}
if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", start);
else start();

window.armServoSetup = { state: () => panel?.state() ?? null };
