// armserver dashboard: live drawings, plots and operator controls for every arm, over the v1 API.
//
// The WebSocket handler only pushes samples into ring buffers; everything is drawn once per
// animation frame from the newest samples. Units on the wire are SI; the page shows mm and
// degrees, and the test hook (window.armDashboard) reports SI.

import { attachSafety, drawSafety } from "./safety.js";
import { attachClassroom, leaseFor } from "./classroom.js";

const API = "/api/v1";
const WINDOW_S = 10;            // plot and trail window, s
const WS_RATE = 30;             // telemetry messages a second asked of the server (samples are batched)
const TOKEN_KEY = "armserver.token";
const BACKOFF_MIN_S = 0.5;
const BACKOFF_MAX_S = 8;
const JOG_THROTTLE_MS = 150;    // live jog while a slider is dragged
const JOG_REST_TOLERANCE = 0.03; // rad or m: the arm still stands at the last jog's targets
const DRAWN_LOG = 600;          // tips drawn from new samples the page keeps for its tests (20 s at WS_RATE)
const COLORS = ["#4cc9f0", "#f472b6", "#a3e635", "#fbbf24", "#a78bfa", "#fb923c"];
const AXIS_COLORS = ["#f87171", "#4ade80", "#60a5fa"];
const CODE_WORDS = {
  unreachable: "Out of reach", joint_limit: "Joint limit", velocity_limit: "Too fast",
  estop_latched: "Emergency stop latched", busy: "Busy", link_down: "Link down",
  device_timeout: "Device timeout", device_error: "Device error", unauthorized: "Needs a token",
  forbidden: "Not allowed with this token", leased: "Another client holds the lease",
  keep_out: "Keep-out zone",
  no_gripper: "No gripper", invalid_request: "Invalid request", network: "No connection",
  not_found: "Not found", unknown_arm: "Unknown arm", not_supported: "Not supported",
  fault: "Servo fault", not_homed: "Not homed", torque_off: "Torque off",
};

const arms = new Map();         // name -> Arm

// ------------------------------------------------------------------ DOM helpers

const $ = (sel, root = document) => root.querySelector(sel);

function h(tag, attrs = {}, ...children) {
  const el = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (v === undefined || v === null || v === false) continue;
    if (k === "class") el.className = v;
    else if (k.startsWith("on")) el.addEventListener(k.slice(2), v);
    else el.setAttribute(k, v === true ? "" : v);
  }
  for (const c of children.flat()) if (c !== null && c !== undefined) el.append(c);
  return el;
}

function showError(el, err) {
  el.replaceChildren();
  if (!err) return;
  const words = CODE_WORDS[err.code] || (err.code ? err.code.replace(/_/g, " ") : "Error");
  let detail = err.detail || "";
  const lead = err.code ? `${err.code.replace(/_/g, " ")}: ` : "";
  if (lead && detail.toLowerCase().startsWith(lead)) detail = detail.slice(lead.length);
  el.append(h("strong", {}, words + ": "), detail);
  el.dataset.code = err.code || "";
}

function clearError(el) { el.replaceChildren(); delete el.dataset.code; }

// ------------------------------------------------------------------ access token and HTTP

let tokenWaiters = [];         // {resolve, reject} of requests waiting for a token

function token() { return sessionStorage.getItem(TOKEN_KEY) || ""; }

/** Open the token form; resolves when a token is entered, rejects if the form is dismissed. */
function askToken(reason) {
  const dlg = $("#token-dialog");
  $("#token-reason").textContent = reason || "The server asks for an access token.";
  if (!dlg.open) dlg.showModal();
  $("#token-input").focus();
  return new Promise((resolve, reject) => tokenWaiters.push({ resolve, reject }));
}

function settleTokenWaiters(ok) {
  const waiters = tokenWaiters;
  tokenWaiters = [];
  for (const w of waiters) {
    if (ok) w.resolve();
    else w.reject(new ApiError(401, "unauthorized", "no access token given"));
  }
}

function tokenChanged() {
  settleTokenWaiters(true);
  for (const arm of arms.values()) arm.reconnectNow();
}

export class ApiError extends Error {
  constructor(status, code, detail) {
    super(detail);
    this.status = status;
    this.code = code;
    this.detail = detail;
  }
}

function describe(detail) {
  if (typeof detail === "string") return detail;
  if (Array.isArray(detail)) {
    return detail.map((d) => `${(d.loc || []).filter((p) => p !== "body").join(".")}: ${d.msg}`).join("; ");
  }
  return detail ? JSON.stringify(detail) : "";
}

async function api(method, path, body) {
  for (;;) {
    const headers = {};
    const sent = token();   // the token this try carries
    if (body !== undefined) headers["Content-Type"] = "application/json";
    if (sent) headers.Authorization = `Bearer ${sent}`;
    if (leaseFor(path)) headers["X-Arm-Lease"] = leaseFor(path);
    let res;
    try {
      res = await fetch(API + path, {
        method, headers, body: body === undefined ? undefined : JSON.stringify(body),
      });
    } catch (e) {
      throw new ApiError(0, "network", `the server did not answer (${e.message})`);
    }
    let data = null;
    try { data = await res.json(); } catch { /* empty or not JSON */ }
    if (res.status === 401) {
      // sent before a token was entered (or changed): try again with it, without asking again
      if (token() !== sent) continue;
      await askToken(sent ? "The token was refused; enter another." : describe(data?.detail));
      continue;
    }
    if (!res.ok) {
      throw new ApiError(res.status, data?.code || `http_${res.status}`,
        describe(data?.detail) || res.statusText);
    }
    return data;
  }
}

// ------------------------------------------------------------------ kinematics (same formulas as the server)

/** Rotation matrix (row-major 3x3) of `angle` rad about the unit `axis` (Rodrigues). */
function rotation(axis, angle) {
  const n = Math.hypot(axis[0], axis[1], axis[2]) || 1;
  const [x, y, z] = [axis[0] / n, axis[1] / n, axis[2] / n];
  const c = Math.cos(angle), s = Math.sin(angle), t = 1 - c;
  return [
    [c + x * x * t, x * y * t - z * s, x * z * t + y * s],
    [y * x * t + z * s, c + y * y * t, y * z * t - x * s],
    [z * x * t - y * s, z * y * t + x * s, c + z * z * t],
  ];
}

function matmul(a, b) {
  return a.map((row) => [0, 1, 2].map((j) => row[0] * b[0][j] + row[1] * b[1][j] + row[2] * b[2][j]));
}

/**
 * Body points from the base to the tip, each [x, y, z] m, for joint positions q: the joint
 * chain the server describes (`ArmDetail.chain`, app/arms/model.py `chain_points` is the
 * reference). Null if the server gave no chain. Works for any arm type.
 */
function chainPoints(ch, q) {
  if (!ch) return null;
  let R = [[1, 0, 0], [0, 1, 0], [0, 0, 1]];
  let p = [0, 0, 0];
  const out = [p.slice()];
  for (const st of ch.steps) {
    const amount = st.offset + (st.joint === null || st.joint === undefined ? 0 : q[st.joint]);
    if (st.kind === "rotate") {
      R = matmul(R, rotation(st.axis, amount));
    } else {
      const v = st.axis.map((a) => a * amount);
      p = [0, 1, 2].map((i) => p[i] + R[i][0] * v[0] + R[i][1] * v[1] + R[i][2] * v[2]);
    }
    if (st.point !== null && st.point !== undefined) out.push(p.slice());
  }
  return out;
}

function bounds(detail) {
  const lo = [0, 0, 0], hi = [0, 0, 0];
  const n = detail.joints.length, steps = n > 3 ? 5 : 7;
  const q = new Array(n).fill(0);
  const visit = (j) => {
    if (j === n) {
      for (const p of chainPoints(detail.chain, q) || []) {
        for (let k = 0; k < 3; k++) { lo[k] = Math.min(lo[k], p[k]); hi[k] = Math.max(hi[k], p[k]); }
      }
      return;
    }
    const { min, max } = detail.joints[j];
    for (let i = 0; i < steps; i++) { q[j] = min + (max - min) * i / (steps - 1); visit(j + 1); }
  };
  visit(0);
  for (let k = 0; k < 3; k++) {
    const pad = Math.max(0.02, 0.08 * (hi[k] - lo[k]));
    lo[k] -= pad; hi[k] += pad;
  }
  return { lo, hi };
}

// ------------------------------------------------------------------ ring buffer of samples

class Ring {
  constructor(cap, nj) {
    this.cap = cap; this.nj = nj; this.count = 0; this.head = 0;
    this.t = new Float64Array(cap);
    this.seq = new Float64Array(cap);
    this.brk = new Uint8Array(cap);     // 1: the line breaks before this sample (gap, lost samples)
    this.pos = Array.from({ length: nj }, () => new Float32Array(cap));
    this.vel = Array.from({ length: nj }, () => new Float32Array(cap));
    this.tq = Array.from({ length: nj }, () => new Float32Array(cap));
    this.hasTq = new Uint8Array(cap);
    this.f = Array.from({ length: 3 }, () => new Float32Array(cap));
    this.hasF = new Uint8Array(cap);
    this.tip = Array.from({ length: 3 }, () => new Float64Array(cap));
  }

  push(s, brk) {
    const i = this.head;
    this.t[i] = s.time; this.seq[i] = s.seq; this.brk[i] = brk ? 1 : 0;
    for (let j = 0; j < this.nj; j++) {
      this.pos[j][i] = s.positions[j];
      this.vel[j][i] = s.velocities[j];
      this.tq[j][i] = s.torques ? s.torques[j] : 0;
    }
    this.hasTq[i] = s.torques ? 1 : 0;
    const f = s.tip_force;
    this.hasF[i] = f ? 1 : 0;
    this.f[0][i] = f ? f.x : 0; this.f[1][i] = f ? f.y : 0; this.f[2][i] = f ? f.z : 0;
    this.tip[0][i] = s.tip.x; this.tip[1][i] = s.tip.y; this.tip[2][i] = s.tip.z;
    this.head = (i + 1) % this.cap;
    this.count = Math.min(this.count + 1, this.cap);
  }

  /** Buffer index of the k-th oldest sample. */
  at(k) { return (this.head - this.count + k + this.cap) % this.cap; }

  /** Oldest k whose time is >= t0 (binary search; times ascend). */
  firstAfter(t0) {
    let lo = 0, hi = this.count;
    while (lo < hi) {
      const mid = (lo + hi) >> 1;
      if (this.t[this.at(mid)] < t0) lo = mid + 1; else hi = mid;
    }
    return lo;
  }
}

// ------------------------------------------------------------------ canvas helpers

function fitCanvas(cv) {
  const dpr = window.devicePixelRatio || 1;
  const w = Math.max(1, Math.round(cv.clientWidth * dpr)), hgt = Math.max(1, Math.round(cv.clientHeight * dpr));
  if (cv.width !== w || cv.height !== hgt) { cv.width = w; cv.height = hgt; }
  const ctx = cv.getContext("2d");
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  return { ctx, w: cv.clientWidth, h: cv.clientHeight };
}

function css(name) { return getComputedStyle(document.documentElement).getPropertyValue(name).trim(); }

let theme = null;
function loadTheme() {
  theme = {
    grid: css("--grid"), axis: css("--axis"), text: css("--muted"), fg: css("--fg"),
    link: css("--link"), joint: css("--joint"), tip: css("--tip"), trail: css("--trail"),
    plan: css("--plan"), bg: css("--canvas"),
  };
}

function niceStep(span, target) {
  const raw = span / target, p = Math.pow(10, Math.floor(Math.log10(raw)));
  const m = raw / p;
  return (m < 1.5 ? 1 : m < 3.5 ? 2 : m < 7.5 ? 5 : 10) * p;
}

// ------------------------------------------------------------------ one arm

class Arm {
  constructor(detail) {
    this.name = detail.name;
    this.detail = detail;
    this.nj = detail.joints.length;
    this.fkKnown = !!detail.chain;
    this.box = this.fkKnown ? bounds(detail) : { lo: [-0.5, -0.5, -0.1], hi: [0.5, 0.5, 0.6] };
    this.sideAxis = detail.chain?.side_axis ?? 0;
    const hz = Math.min(detail.poll_hz || 500, 2000);
    this.ring = new Ring(Math.ceil(hz * WINDOW_S * 1.3) + 64, this.nj);
    this.gapS = Math.max(0.2, 25 / hz);
    this.latest = null;
    this.lastSeq = null;
    this.lastTime = null;
    this.pendingBreak = false;
    this.gaps = 0;
    this.dropped = 0;
    this.clockOffset = null;   // server time - browser time, s
    this.estop = detail.estop;
    this.link = detail.link.state;
    this.ws = null;
    this.wsState = "connecting";
    this.backoff = BACKOFF_MIN_S;
    this.retryAt = 0;
    this.retryTimer = null;
    this.plan = null;          // {motion, request, ran}
    this.jogTarget = null;     // joint targets the jog controls stand at, while a jog is under way
    this.jogMotion = null;     // id of the last jog motion the server accepted
    this.restTarget = null;    // targets of the last jog that ended done (the next jog's base)
    this.jogInFlight = 0;
    this.breaks = [];          // the latest line breaks: {seq, prevSeq, dt}
    this.lastJogSent = 0;
    this.jogTimer = null;
    this.frames = 0;
    this.tipDrawn = null;
    this.tipDrawnSeq = null;  // the sample it was drawn from (the tests' check)
    this.drawnLog = [];       // the latest DRAWN_LOG tips drawn from new samples: [seq, x, y, z, at]
    this.plotted = { positions: [], velocities: [] };
    this.lastEvent = null;
    this.build();
    this.safety = attachSafety(this, api, h);
    this.classroom = attachClassroom(this, api, h);
    this.connect();
  }

  // ---------------------------------------------------------- DOM

  build() {
    const d = this.detail, id = (s) => `${this.name}-${s}`;
    this.el = {};
    const badge = (k, text) => (this.el[k] = h("span", { class: "badge", id: id(k) }, text));
    const canvas = (k, label) => (this.el[k] = h("canvas", { id: id(k), "aria-label": label, role: "img" }));

    const joints = d.joints.map((j, i) => {
      const rev = j.kind === "revolute";
      const step = rev ? (0.5 * Math.PI) / 180 : 0.0005;
      const slider = h("input", {
        type: "range", min: j.min, max: j.max, step, value: (j.min + j.max) / 2,
        id: id(`jog-${i}`), "aria-label": `${j.name} target`,
        oninput: () => this.onSlider(i, false), onchange: () => this.onSlider(i, true),
        onpointerdown: () => { this.dragging = i; }, onpointerup: () => { this.dragging = -1; },
        onblur: () => { if (this.dragging === i) this.dragging = -1; },
      });
      const stepBy = rev ? (5 * Math.PI) / 180 : 0.005;
      const label = rev ? "5°" : "5 mm";
      return h("div", { class: "jog-row" },
        h("span", { class: "jname", style: `color:${COLORS[i % COLORS.length]}` }, j.name),
        h("button", { type: "button", class: "step", id: id(`jog-${i}-minus`), title: `${j.name} −${label}`,
          onclick: () => this.jogStep(i, -stepBy) }, "−"),
        slider,
        h("button", { type: "button", class: "step", id: id(`jog-${i}-plus`), title: `${j.name} +${label}`,
          onclick: () => this.jogStep(i, stepBy) }, "+"),
        h("span", { class: "jval", id: id(`jog-${i}-value`) }, "–"));
    });
    this.el.sliders = d.joints.map((_, i) => joints[i].querySelector("input"));
    this.el.jogValues = d.joints.map((_, i) => joints[i].querySelector(".jval"));

    const num = (axis) => h("label", { class: "coord" }, axis,
      (this.el[axis] = h("input", { type: "number", step: "1", id: id(`target-${axis}`),
        "aria-label": `target ${axis} in mm`, oninput: () => this.planStale() })), h("span", { class: "unit" }, "mm"));

    this.el.path = h("select", { id: id("path"), "aria-label": "path", onchange: () => this.planStale() },
      ...(d.capabilities.paths || ["joint", "line"]).map((p) => h("option", { value: p }, p === "line" ? "straight line" : "joint space")));

    const gripper = d.capabilities.gripper
      ? h("section", { class: "ctl gripper" }, h("h3", {}, "Gripper"),
        h("div", { class: "row" }, h("span", { class: "muted small" }, "open"),
          (this.el.gripper = h("input", { type: "range", min: 0, max: 1, step: 0.01, value: 0, id: id("gripper"),
            "aria-label": "gripper", onchange: () => this.sendGripper() })),
          h("span", { class: "muted small" }, "closed"),
          (this.el.gripperValue = h("span", { class: "jval" }, "–"))),
        (this.el.gripperError = h("div", { class: "err", id: id("gripper-error"), role: "alert" })))
      : null;

    const force = d.capabilities.force_sensing;
    // Force: what the torques are worth (placeholder constants are labelled) and the tare.
    const forceCtl = force && d.force
      ? h("section", { class: "ctl force" }, h("h3", {}, "Force"),
        (this.el.forceText = h("div", { class: "muted small", id: id("force-note") },
          `${d.force.calibrated ? "calibrated" : "NOT calibrated"}: ${d.force.note}`)),
        h("div", { class: "row" },
          h("button", { type: "button", class: "ghost", id: id("tare"),
            title: "Make the current joint torques the zero of torques and tip force",
            onclick: () => this.tare(true) }, "Tare"),
          h("button", { type: "button", class: "ghost", id: id("tare-clear"),
            title: "Publish the torques as sensed again", onclick: () => this.tare(false) }, "Clear tare"),
          (this.el.tareText = h("span", { class: "muted small mono", id: id("tare-text") },
            d.force.tare ? "tared" : ""))),
        (this.el.tareError = h("div", { class: "err", id: id("tare-error"), role: "alert" })))
      : null;
    this.el.card = h("section", { class: "arm", "data-arm": this.name, id: id("card") },
      h("header", { class: "arm-head" },
        h("h2", {}, this.name),
        h("span", { class: "muted" }, d.description),
        h("div", { class: "spacer" }),
        badge("ws", "connecting"), badge("link", "link"), badge("estop", "estop")),
      h("div", { class: "motion-line" },
        h("span", { class: "muted" }, "Motion"),
        (this.el.motionText = h("span", { id: id("motion") }, "idle")),
        h("div", { class: "progress" }, (this.el.progress = h("div", { class: "bar", id: id("progress") }))),
        h("button", { type: "button", class: "stop", id: id("stop"), title: "Stop all motion: decelerate, hold, clear the queue",
          onclick: () => this.stop() }, "Stop motion"),
        (this.el.stopError = h("span", { class: "err inline", id: id("stop-error"), role: "alert" })),
        (this.el.eventText = h("span", { class: "muted small event", id: id("event") }, ""))),
      h("div", { class: "arm-body" },
        h("div", { class: "views" },
          h("figure", {}, canvas("top", `${this.name} top view`), h("figcaption", {}, "Top view (x right, y up)")),
          h("figure", {}, canvas("side", `${this.name} side view`),
            h("figcaption", {}, `Side view (${"xyz"[this.sideAxis]} right, z up)`)),
          (this.el.tipText = h("div", { class: "tiptext mono", id: id("tip") }, ""))),
        h("div", { class: "plots" },
          canvas("plot-pos", "joint positions"), canvas("plot-vel", "joint velocities"),
          force ? canvas("plot-tq", "joint torques") : null, force ? canvas("plot-f", "tip force") : null),
        h("div", { class: "controls" },
          h("section", { class: "ctl jog" }, h("h3", {}, "Jog joints"), ...joints,
            (this.el.jogError = h("div", { class: "err", id: id("jog-error"), role: "alert" }))),
          h("section", { class: "ctl pose" }, h("h3", {}, "Move the tip"),
            h("div", { class: "row coords" }, num("x"), num("y"), num("z")),
            h("div", { class: "row" }, this.el.path,
              h("button", { type: "button", class: "ghost", id: id("use-tip"), onclick: () => this.fillFromTip() }, "Current tip")),
            h("div", { class: "row" },
              (this.el.planBtn = h("button", { type: "button", class: "primary", id: id("plan"), onclick: () => this.planPose() }, "Plan")),
              (this.el.runBtn = h("button", { type: "button", class: "go", id: id("run"), disabled: true, onclick: () => this.runPose() }, "Run")),
              (this.el.planText = h("span", { class: "muted small", id: id("plan-text") }, "Plan to preview the path"))),
            (this.el.poseError = h("div", { class: "err", id: id("pose-error"), role: "alert" }))),
          gripper, forceCtl)));
    this.el.tq = this.el["plot-tq"];
    this.el.f = this.el["plot-f"];
    if (this.el.tq) this.el.tq.hidden = true;
    if (this.el.f) this.el.f.hidden = true;
    $("#arms").append(this.el.card);
    document.dispatchEvent(new CustomEvent("arm-card", { detail: { name: this.name, card: this.el.card, detail: d } }));  // faults.js
    // an arm scrolled out of sight is not drawn (its buffers still fill)
    this.visible = true;
    new IntersectionObserver((entries) => { this.visible = entries[entries.length - 1].isIntersecting; })
      .observe(this.el.card);
    this.renderBadges();
  }

  // ---------------------------------------------------------- telemetry

  wsUrl() {
    const proto = location.protocol === "https:" ? "wss" : "ws";
    const q = new URLSearchParams({ rate: String(WS_RATE) });
    if (token()) q.set("token", token());
    return `${proto}://${location.host}${API}/arms/${encodeURIComponent(this.name)}/telemetry?${q}`;
  }

  connect() {
    clearTimeout(this.retryTimer);
    this.retryTimer = null;
    let opened = false;
    const ws = new WebSocket(this.wsUrl());
    this.ws = ws;
    this.wsState = this.lastSeq === null ? "connecting" : "reconnecting";
    ws.onopen = () => { opened = true; this.wsState = "live"; this.backoff = BACKOFF_MIN_S; this.refresh(); };
    ws.onmessage = (ev) => this.onMessage(ev.data);
    ws.onclose = (ev) => {
      if (this.ws !== ws) return;
      this.ws = null;
      this.pendingBreak = true;
      this.wsClose = ev.code === 4401 ? "token refused" : ev.reason || "";
      // refused (4401) or never opened: a token may be needed (the probe asks), or the server is down
      if (!opened || ev.code === 4401) this.probe();
      this.scheduleReconnect();
    };
    ws.onerror = () => { /* onclose follows */ };
  }

  scheduleReconnect() {
    const delay = this.backoff * (0.8 + 0.4 * Math.random());
    this.backoff = Math.min(this.backoff * 2, BACKOFF_MAX_S);
    this.wsState = "reconnecting";
    this.retryAt = performance.now() + delay * 1000;
    this.retryTimer = setTimeout(() => this.connect(), delay * 1000);
  }

  reconnectNow() {
    if (this.ws) { const ws = this.ws; this.ws = null; ws.close(); }
    this.pendingBreak = true;
    this.backoff = BACKOFF_MIN_S;
    this.connect();
  }

  async probe() {
    try { await this.refresh(); } catch { /* shown by the badges */ }
  }

  async refresh() {
    try {
      const d = await api("GET", `/arms/${encodeURIComponent(this.name)}`);
      this.estop = d.estop;
      this.link = d.link.state;
      this.detail.link = d.link;
      updateEstopPanel();
    } catch (e) {
      if (e.code === "network") this.link = "down";
    }
  }

  onMessage(text) {
    let msg;
    try { msg = JSON.parse(text); } catch { return; }
    if (msg.type === "event") { this.onEvent(msg); return; }
    if (msg.type !== "telemetry" || !Array.isArray(msg.samples)) return;
    if (msg.dropped > 0) { this.dropped += msg.dropped; this.pendingBreak = true; }
    for (const s of msg.samples) {
      let brk = this.pendingBreak;
      if (this.lastSeq !== null) {
        if (s.seq <= this.lastSeq && s.time <= this.lastTime) continue;  // already have it
        if (s.seq !== this.lastSeq + 1 || s.time - this.lastTime > this.gapS) brk = true;
      }
      if (brk && this.lastSeq !== null) {
        this.gaps += 1;
        this.breaks.push({ seq: s.seq, prevSeq: this.lastSeq, dt: s.time - this.lastTime });
        if (this.breaks.length > 10) this.breaks.shift();
      }
      this.pendingBreak = false;
      this.ring.push(s, brk);
      this.lastSeq = s.seq;
      this.lastTime = s.time;
      this.latest = s;
    }
    if (this.latest) {
      const off = this.latest.time - Date.now() / 1000;
      this.clockOffset = this.clockOffset === null || Math.abs(off - this.clockOffset) > 1
        ? off : 0.9 * this.clockOffset + 0.1 * off;
      this.estop = this.latest.estop;
      this.link = this.latest.link;
      this.el.card.dispatchEvent(new CustomEvent("arm-sample", { detail: this.latest }));  // faults.js
    }
  }

  onEvent(msg) {
    const d = msg.data || {};
    if (msg.event === "estop") this.estop = true;
    if (msg.event === "estop_released") this.estop = false;
    if (msg.event === "link_lost") { this.link = "down"; this.pendingBreak = true; }
    if (msg.event === "link_back") this.link = "up";
    if (msg.event === "safety") this.safety?.refresh();
    if (msg.event === "torque" || msg.event === "rebooted") {
      this.el.card.dispatchEvent(new CustomEvent("arm-torque", { detail: d }));  // faults.js
    }
    this.classroom?.onEvent(msg);
    const words = {
      motion_started: "motion started", motion_ended: "motion ended", estop: "emergency stop latched",
      estop_released: "emergency stop released", link_lost: "link lost", link_back: "link back",
      lease_expired: "lease expired", watchdog: "watchdog",
    }[msg.event] || msg.event;
    const extra = [d.status, d.reason].filter(Boolean).join(": ");
    this.lastEvent = `${new Date(msg.time * 1000).toLocaleTimeString()} ${words}${extra ? ` (${extra})` : ""}`;
    updateEstopPanel();
  }

  // ---------------------------------------------------------- controls

  currentPositions() { return this.latest ? this.latest.positions.slice() : null; }

  // Where a new jog starts: the targets the last jog was sent to while the arm still stands
  // there (a shoulder sags a little below its setpoint under gravity; starting from the
  // measured positions would hand that sag on to the next setpoint, one sag per jog), else
  // the measured positions (another client moved the arm, a stop, an estop, a pose move).
  jogBase() {
    const q = this.currentPositions();
    const rest = this.restTarget;
    if (q && rest && rest.length === q.length &&
        rest.every((v, i) => Math.abs(v - q[i]) < JOG_REST_TOLERANCE)) return rest.slice();
    return q;
  }

  onSlider(i, final) {
    const v = Number(this.el.sliders[i].value);
    if (!this.jogTarget) this.jogTarget = this.jogBase();
    if (!this.jogTarget) return;
    this.jogTarget[i] = v;
    if (final) { this.dragging = -1; this.sendJog(); return; }
    this.dragging = i;
    const wait = JOG_THROTTLE_MS - (performance.now() - this.lastJogSent);
    clearTimeout(this.jogTimer);
    if (wait <= 0) this.sendJog(); else this.jogTimer = setTimeout(() => this.sendJog(), wait);
  }

  jogStep(i, delta) {
    if (!this.jogTarget) this.jogTarget = this.jogBase();
    if (!this.jogTarget) return;
    this.lastJogSent = performance.now();
    const j = this.detail.joints[i];
    this.jogTarget[i] = Math.min(j.max, Math.max(j.min, this.jogTarget[i] + delta));
    this.el.sliders[i].value = this.jogTarget[i];
    this.sendJog();
  }

  async sendJog() {
    clearTimeout(this.jogTimer);
    this.jogTimer = null;
    this.lastJogSent = performance.now();
    const positions = this.jogTarget.slice();
    this.jogInFlight += 1;
    try {
      const m = await api("POST", `/arms/${encodeURIComponent(this.name)}/move/joints`, { positions, mode: "replace" });
      this.jogMotion = m.id;
      clearError(this.el.jogError);
      if (this.plan) this.plan.ran = true;  // the preview no longer describes what will run
    } catch (e) {
      showError(this.el.jogError, e);
      this.jogTarget = null;  // resync to the arm
    } finally {
      this.jogInFlight -= 1;
    }
  }

  poseRequest() {
    const mm = (k) => Number(this.el[k].value) / 1000;
    const req = { x: mm("x"), y: mm("y"), z: mm("z"), path: this.el.path.value, mode: "replace" };
    for (const k of ["x", "y", "z"]) {
      if (this.el[k].value.trim() === "" || !Number.isFinite(req[k])) {
        throw new ApiError(0, "invalid_request", `enter ${k} in millimetres`);
      }
    }
    return req;
  }

  fillFromTip() {
    if (!this.latest) return;
    for (const k of ["x", "y", "z"]) this.el[k].value = (this.latest.tip[k] * 1000).toFixed(1);
    this.planStale();
  }

  planStale() {
    if (this.plan && !this.plan.ran) {
      this.plan = null;
      this.el.runBtn.disabled = true;
      this.el.planText.textContent = "Target changed: plan again";
    }
  }

  async planPose() {
    clearError(this.el.poseError);
    try {
      const req = this.poseRequest();
      this.el.planText.textContent = "planning…";
      const motion = await api("POST", `/arms/${encodeURIComponent(this.name)}/plan/pose`, req);
      this.plan = { motion, request: req, ran: false };
      this.el.runBtn.disabled = false;
      this.el.planText.textContent =
        `${motion.planned_duration.toFixed(2)} s, ${req.path === "line" ? "straight line" : "joint space"}`;
    } catch (e) {
      this.plan = null;
      this.el.runBtn.disabled = true;
      this.el.planText.textContent = "no plan";
      showError(this.el.poseError, e);
    }
  }

  async runPose() {
    if (!this.plan) return;
    clearError(this.el.poseError);
    const plan = this.plan;
    try {
      const motion = await api("POST", `/arms/${encodeURIComponent(this.name)}/move/pose`, plan.request);
      plan.ran = true;
      plan.motion = { ...plan.motion, ...motion, planned_path: motion.planned_path?.length ? motion.planned_path : plan.motion.planned_path };
      this.el.runBtn.disabled = true;
      this.el.planText.textContent = `running ${motion.id} (${motion.planned_duration.toFixed(2)} s)`;
      this.jogTarget = null;
      this.jogMotion = null;
      this.restTarget = null;
    } catch (e) {
      showError(this.el.poseError, e);
    }
  }

  async sendGripper() {
    try {
      await api("POST", `/arms/${encodeURIComponent(this.name)}/gripper`, { value: Number(this.el.gripper.value) });
      clearError(this.el.gripperError);
    } catch (e) {
      showError(this.el.gripperError, e);
    }
  }

  async tare(on) {
    try {
      const r = await api(on ? "POST" : "DELETE", `/arms/${encodeURIComponent(this.name)}/force/tare`);
      this.el.tareText.textContent = r.offsets
        ? `tared at ${r.offsets.map((v) => v.toFixed(3)).join(", ")}` : "";
      clearError(this.el.tareError);
    } catch (e) {
      showError(this.el.tareError, e);
    }
  }

  async stop() {
    try {
      await api("POST", `/arms/${encodeURIComponent(this.name)}/stop`);
      clearError(this.el.stopError);
      this.jogTarget = null;
      this.jogMotion = null;
      this.restTarget = null;
    } catch (e) {
      showError(this.el.stopError, e);
    }
  }

  // ---------------------------------------------------------- drawing (once per animation frame)

  renderBadges() {
    const set = (el, text, cls) => {
      if (el.textContent !== text) el.textContent = text;
      const c = `badge ${cls}`;
      if (el.className !== c) el.className = c;
    };
    let ws = "live", wsCls = "ok";
    if (this.wsState === "reconnecting") {
      const s = Math.max(0, (this.retryAt - performance.now()) / 1000);
      ws = this.ws ? "reconnecting…" : `reconnecting in ${s.toFixed(0)} s`; wsCls = "warn";
    } else if (this.wsState === "connecting") { ws = "connecting…"; wsCls = "warn"; }
    else if (this.latest && Date.now() / 1000 + (this.clockOffset ?? 0) - this.latest.time > 1) { ws = "no samples"; wsCls = "warn"; }
    set(this.el.ws, ws, wsCls);
    const stale = this.latest?.stale ? " (stale)" : "";
    set(this.el.link, `link ${this.link}${stale}`, this.link === "up" && !stale ? "ok" : this.link === "down" ? "bad" : "warn");
    set(this.el.estop, this.estop ? "E-STOP LATCHED" : "estop clear", this.estop ? "bad" : "ok");
    this.el.card.classList.toggle("latched", !!this.estop);

    const m = this.latest?.motion;
    const text = m ? `${m.id} · ${m.status}${m.status === "running" ? ` · ${Math.round(m.progress * 100)}%` : ""}` : "idle";
    if (this.el.motionText.textContent !== text) this.el.motionText.textContent = text;
    const width = `${Math.round((m ? m.progress : 0) * 100)}%`;
    if (this.el.progress.style.width !== width) this.el.progress.style.width = width;
    this.el.progress.className = `bar ${m ? m.status : ""}`;
    if (this.lastEvent && this.el.eventText.textContent !== this.lastEvent) this.el.eventText.textContent = this.lastEvent;
  }

  renderControls() {
    if (!this.latest) return;
    const q = this.latest.positions;
    const m = this.latest.motion;
    const jogging = m && m.id === this.jogMotion && (m.status === "running" || m.status === "queued");
    // between a jog's request and its first sample the target must survive, or quick clicks are lost
    const waiting = this.jogInFlight > 0 || this.jogTimer || this.dragging >= 0 ||
      (this.jogMotion && (!m || m.id !== this.jogMotion) && performance.now() - this.lastJogSent < 1000);
    if (!jogging && !waiting) {
      if (this.jogTarget && m && m.id === this.jogMotion && m.status === "done") this.restTarget = this.jogTarget;
      this.jogTarget = null; this.jogMotion = null;
    }
    const target = this.jogTarget || q;
    this.detail.joints.forEach((j, i) => {
      if (this.dragging !== i && document.activeElement !== this.el.sliders[i]) this.el.sliders[i].value = target[i];
      const show = (v) => (j.kind === "revolute" ? `${((v * 180) / Math.PI).toFixed(1)}°` : `${(v * 1000).toFixed(1)} mm`);
      const text = Math.abs(target[i] - q[i]) > 1e-3 ? `${show(q[i])} → ${show(target[i])}` : show(q[i]);
      if (this.el.jogValues[i].textContent !== text) this.el.jogValues[i].textContent = text;
    });
    if (this.el.gripperValue) {
      const g = this.latest.gripper;
      const text = g === null || g === undefined ? "not set" : g.toFixed(2);
      if (this.el.gripperValue.textContent !== text) this.el.gripperValue.textContent = text;
      if (typeof g === "number" && document.activeElement !== this.el.gripper) this.el.gripper.value = g;
    }
    if (this.el.x.value === "" && this.el.y.value === "" && this.el.z.value === "") this.fillFromTip();
    if (this.plan && this.plan.ran && this.plan.motion.id && this.latest.motion?.id === this.plan.motion.id) {
      const st = this.latest.motion.status;
      if (st !== "running" && st !== "queued") this.el.planText.textContent = `${this.plan.motion.id} ${st}`;
    }
  }

  draw() {
    this.frames += 1;
    this.renderBadges();
    this.renderControls();
    const q = this.latest?.positions;
    let pts = null;
    if (q) {
      pts = this.fkKnown ? chainPoints(this.detail.chain, q) : [[this.latest.tip.x, this.latest.tip.y, this.latest.tip.z]];
      const tip = pts[pts.length - 1];
      this.tipDrawn = { x: tip[0], y: tip[1], z: tip[2] };
      if (this.tipDrawnSeq !== this.latest.seq) {
        // what the page drew and when (the tests judge each against the server's sample)
        this.drawnLog.push([this.latest.seq, tip[0], tip[1], tip[2], Date.now() / 1000]);
        if (this.drawnLog.length > DRAWN_LOG) this.drawnLog.splice(0, this.drawnLog.length - DRAWN_LOG);
      }
      this.tipDrawnSeq = this.latest.seq;
      this.el.tipText.textContent = `tip  x ${(tip[0] * 1000).toFixed(1)}  y ${(tip[1] * 1000).toFixed(1)}  z ${(tip[2] * 1000).toFixed(1)} mm`;
    }
    if (!this.visible) return;
    this.drawView(this.el.top, 0, 1, pts, "top");
    this.drawView(this.el.side, this.sideAxis, 2, pts, "side");
    this.drawPlots();
  }

  drawView(cv, ax, ay, pts, which) {
    const { ctx, w, h: hh } = fitCanvas(cv);
    ctx.fillStyle = theme.bg; ctx.fillRect(0, 0, w, hh);
    const { lo, hi } = this.box, m = 24;
    const sx = (w - 2 * m) / (hi[ax] - lo[ax]), sy = (hh - 2 * m) / (hi[ay] - lo[ay]);
    const s = Math.min(sx, sy);
    const cx = w / 2 - s * (lo[ax] + hi[ax]) / 2, cy = hh / 2 + s * (lo[ay] + hi[ay]) / 2;
    const X = (p) => cx + s * p[ax], Y = (p) => cy - s * p[ay];

    // grid every 50 mm (or a nice step), labelled in mm
    const step = niceStep(Math.max(hi[ax] - lo[ax], hi[ay] - lo[ay]), 6);
    ctx.lineWidth = 1; ctx.font = "10px system-ui, sans-serif"; ctx.fillStyle = theme.text;
    const x0 = (0 - cx) / s, x1 = (w - cx) / s, y0 = (cy - hh) / s, y1 = cy / s;
    for (let v = Math.ceil(x0 / step) * step; v <= x1; v += step) {
      const px = cx + s * v;
      ctx.strokeStyle = Math.abs(v) < step / 2 ? theme.axis : theme.grid;
      ctx.beginPath(); ctx.moveTo(px, 0); ctx.lineTo(px, hh); ctx.stroke();
      ctx.fillText(`${Math.round(v * 1000)}`, px + 2, hh - 4);
    }
    for (let v = Math.ceil(y0 / step) * step; v <= y1; v += step) {
      const py = cy - s * v;
      ctx.strokeStyle = Math.abs(v) < step / 2 ? theme.axis : theme.grid;
      ctx.beginPath(); ctx.moveTo(0, py); ctx.lineTo(w, py); ctx.stroke();
      ctx.fillText(`${Math.round(v * 1000)}`, 2, py - 2);
    }
    ctx.fillText(`${"xyz"[ax]}, ${"xyz"[ay]} in mm`, w - 80, 12);

    this.drawFixtures(ctx, X, Y, which);
    drawSafety(this, ctx, X, Y, ax, ay, which);

    // tip trail of the last WINDOW_S seconds, fading with age; broken at gaps
    const r = this.ring;
    if (r.count > 1) {
      const stride = Math.max(1, Math.floor(r.count / 800));
      ctx.lineWidth = 1.5; ctx.strokeStyle = theme.trail;
      const chunks = 8, per = Math.ceil(r.count / chunks);
      for (let c = 0; c < chunks; c++) {
        const k0 = c * per, k1 = Math.min(r.count - 1, (c + 1) * per);
        if (k1 <= k0) continue;
        ctx.globalAlpha = 0.15 + 0.85 * ((c + 1) / chunks);
        ctx.beginPath();
        let pen = false;
        for (let k = k0; k <= k1; k++) {
          const i = r.at(k);
          if (r.brk[i] && k > k0) pen = false;
          if (k % stride && k !== k1 && !r.brk[i]) continue;
          const p = [r.tip[0][i], r.tip[1][i], r.tip[2][i]];
          if (pen) ctx.lineTo(X(p), Y(p)); else { ctx.moveTo(X(p), Y(p)); pen = true; }
        }
        ctx.stroke();
      }
      ctx.globalAlpha = 1;
    }

    // planned path, dashed, with its target
    const plan = this.plan?.motion;
    if (plan && plan.planned_path?.length) {
      const faded = this.plan.ran && this.latest?.motion?.id === plan.id && !["running", "queued"].includes(this.latest.motion.status);
      ctx.save();
      ctx.globalAlpha = faded ? 0.35 : 1;
      ctx.setLineDash([6, 4]); ctx.lineWidth = 2; ctx.strokeStyle = theme.plan;
      ctx.beginPath();
      plan.planned_path.forEach((p, k) => {
        const v = [p.x, p.y, p.z];
        if (k) ctx.lineTo(X(v), Y(v)); else ctx.moveTo(X(v), Y(v));
      });
      ctx.stroke();
      ctx.setLineDash([]);
      const t = plan.target_tip, tv = [t.x, t.y, t.z];
      ctx.beginPath();
      ctx.moveTo(X(tv) - 6, Y(tv) - 6); ctx.lineTo(X(tv) + 6, Y(tv) + 6);
      ctx.moveTo(X(tv) + 6, Y(tv) - 6); ctx.lineTo(X(tv) - 6, Y(tv) + 6);
      ctx.stroke();
      ctx.restore();
    }

    // the arm itself
    if (pts) {
      ctx.lineCap = "round"; ctx.lineJoin = "round";
      ctx.strokeStyle = this.estop ? "#ef4444" : theme.link; ctx.lineWidth = 7;
      ctx.beginPath();
      pts.forEach((p, k) => (k ? ctx.lineTo(X(p), Y(p)) : ctx.moveTo(X(p), Y(p))));
      ctx.stroke();
      ctx.fillStyle = theme.joint;
      for (const p of pts.slice(0, -1)) { ctx.beginPath(); ctx.arc(X(p), Y(p), 5, 0, 2 * Math.PI); ctx.fill(); }
      const tip = pts[pts.length - 1];
      ctx.fillStyle = theme.tip;
      ctx.beginPath(); ctx.arc(X(tip), Y(tip), 5.5, 0, 2 * Math.PI); ctx.fill();
    } else {
      ctx.fillStyle = theme.text; ctx.font = "13px system-ui, sans-serif";
      ctx.fillText("waiting for telemetry…", w / 2 - 60, hh / 2);
    }
  }

  /**
   * What does not move with the joints, for any arm type: a plate at the base origin, and the
   * travel of every prismatic joint (its rail: where its body point goes from the joint's
   * minimum to its maximum, the other joints as they are), dashed.
   */
  drawFixtures(ctx, X, Y, which) {
    ctx.strokeStyle = theme.axis; ctx.fillStyle = theme.grid; ctx.lineWidth = 2;
    const a = X([0, 0, 0]), b = Y([0, 0, 0]);
    if (which === "top") {
      ctx.beginPath(); ctx.arc(a, b, 12, 0, 2 * Math.PI); ctx.fill(); ctx.stroke();
    } else {
      ctx.fillRect(a - 18, b, 36, 6); ctx.strokeRect(a - 18, b, 36, 6);
    }
    const ch = this.detail.chain, q = this.latest?.positions;
    if (!ch || !q) return;
    ctx.setLineDash([3, 3]);
    ctx.beginPath();
    let point = 0;
    for (const st of ch.steps) {
      if (st.point !== null && st.point !== undefined) point += 1;
      const j = st.joint;
      if (st.kind !== "translate" || j === null || j === undefined || st.point === null) continue;
      const { min, max } = this.detail.joints[j];
      const lo = q.slice(), hi = q.slice();
      lo[j] = min; hi[j] = max;
      const p0 = chainPoints(ch, lo)[point], p1 = chainPoints(ch, hi)[point];
      ctx.moveTo(X(p0), Y(p0)); ctx.lineTo(X(p1), Y(p1));
    }
    ctx.stroke();
    ctx.setLineDash([]);
  }

  drawPlots() {
    const r = this.ring, nj = this.nj;
    const now = Date.now() / 1000 + (this.clockOffset ?? 0);
    const tRight = this.lastTime !== null ? Math.max(now, this.lastTime) : now;
    const k0 = Math.max(0, r.firstAfter(tRight - WINDOW_S) - 1);
    const names = this.detail.joints.map((j) => j.name);
    const rev = this.detail.joints.map((j) => j.kind === "revolute");
    const pos = rev.map((v) => (v ? 180 / Math.PI : 1000));
    const posUnit = rev.map((v) => (v ? "°" : "mm"));
    this.plotted.positions = this.drawPlot(this.el["plot-pos"], "Positions", r.pos, pos,
      names.map((n, i) => `${n} ${posUnit[i]}`), k0, tRight, null);
    this.plotted.velocities = this.drawPlot(this.el["plot-vel"], "Velocities", r.vel, pos,
      names.map((n, i) => `${n} ${posUnit[i]}/s`), k0, tRight, null);
    const newest = r.count ? r.at(r.count - 1) : -1;
    if (this.el.tq) {
      const sensed = newest >= 0 && r.hasTq[newest];
      this.el.tq.hidden = !sensed;
      if (sensed) {
        this.plotted.torques = this.drawPlot(this.el.tq, "Joint torques", r.tq, new Array(nj).fill(1),
          names.map((n, i) => `${n} ${rev[i] ? "N·m" : "N"}`), k0, tRight, r.hasTq);
      }
    }
    if (this.el.f) {
      const sensed = newest >= 0 && r.hasF[newest];
      this.el.f.hidden = !sensed;
      if (sensed) {
        this.plotted.tip_force = this.drawPlot(this.el.f, "Tip force", r.f, [1, 1, 1],
          ["x N", "y N", "z N"], k0, tRight, r.hasF, AXIS_COLORS);
      }
    }
  }

  /** One scrolling plot; returns the newest plotted value of each series (SI). */
  drawPlot(cv, title, series, scale, labels, k0, tRight, valid, colors = COLORS) {
    const { ctx, w, h: hh } = fitCanvas(cv);
    const r = this.ring, L = 46, R = 8, T = 18, B = 16;
    ctx.fillStyle = theme.bg; ctx.fillRect(0, 0, w, hh);
    const pw = w - L - R, ph = hh - T - B;
    const n = series.length, k1 = r.count - 1;
    let lo = Infinity, hi = -Infinity;
    for (let k = k0; k <= k1; k++) {
      const i = r.at(k);
      if (valid && !valid[i]) continue;
      for (let j = 0; j < n; j++) {
        const v = series[j][i] * scale[j];
        if (v < lo) lo = v;
        if (v > hi) hi = v;
      }
    }
    if (!(lo <= hi)) { lo = -1; hi = 1; }
    const minSpan = 2;
    if (hi - lo < minSpan) { const c = (hi + lo) / 2; lo = c - minSpan / 2; hi = c + minSpan / 2; }
    const pad = 0.08 * (hi - lo);
    lo -= pad; hi += pad;
    const X = (t) => L + pw * (1 - (tRight - t) / WINDOW_S);
    const Y = (v) => T + ph * (1 - (v - lo) / (hi - lo));

    ctx.font = "10px system-ui, sans-serif"; ctx.lineWidth = 1;
    const step = niceStep(hi - lo, 4);
    for (let v = Math.ceil(lo / step) * step; v <= hi; v += step) {
      ctx.strokeStyle = Math.abs(v) < step / 2 ? theme.axis : theme.grid;
      ctx.beginPath(); ctx.moveTo(L, Y(v)); ctx.lineTo(w - R, Y(v)); ctx.stroke();
      ctx.fillStyle = theme.text;
      ctx.fillText(Math.abs(v) < 1e-9 ? "0" : +v.toPrecision(3) + "", 4, Y(v) + 3);
    }
    for (let s = 0; s <= WINDOW_S; s += 2) {
      const px = L + pw * (1 - s / WINDOW_S);
      ctx.strokeStyle = theme.grid;
      ctx.beginPath(); ctx.moveTo(px, T); ctx.lineTo(px, T + ph); ctx.stroke();
      ctx.fillStyle = theme.text;
      ctx.fillText(s ? `−${s} s` : "now", px - (s ? 12 : 20), hh - 4);
    }
    ctx.fillStyle = theme.fg; ctx.font = "600 11px system-ui, sans-serif";
    ctx.fillText(title, L, 12);
    ctx.font = "11px system-ui, sans-serif";
    const room = w - R - L - ctx.measureText(title).width - 24;
    const width = (ls) => ls.reduce((acc, l) => acc + ctx.measureText(l).width + 16, 0);
    if (width(labels) > room) labels = labels.map((l) => l.split(" ")[0]);  // names only
    let lx = w - R;
    for (let j = n - 1; j >= 0; j--) {
      const tw = ctx.measureText(labels[j]).width;
      lx -= tw + 16;
      ctx.fillStyle = colors[j % colors.length];
      ctx.fillRect(lx, 5, 9, 9);
      ctx.fillStyle = theme.text;
      ctx.fillText(labels[j], lx + 12, 13);
    }

    const newest = new Array(n).fill(null);
    if (k1 < k0) return newest;
    ctx.save();
    ctx.beginPath(); ctx.rect(L, T, pw, ph); ctx.clip();
    const stride = Math.max(1, Math.floor((k1 - k0 + 1) / (pw * 1.5)));
    ctx.lineWidth = 1.6; ctx.lineJoin = "round";
    for (let j = 0; j < n; j++) {
      ctx.strokeStyle = colors[j % colors.length];
      ctx.beginPath();
      let pen = false;
      for (let k = k0; k <= k1; k++) {
        const i = r.at(k);
        if (valid && !valid[i]) { pen = false; continue; }
        if (r.brk[i]) pen = false;
        if (pen && k % stride && k !== k1) continue;
        const x = X(r.t[i]), y = Y(series[j][i] * scale[j]);
        if (pen) ctx.lineTo(x, y); else { ctx.moveTo(x, y); pen = true; }
        if (k === k1) newest[j] = series[j][i];
      }
      ctx.stroke();
    }
    // mark gaps: a faint band where samples are missing
    ctx.fillStyle = "rgba(248, 113, 113, 0.10)";
    ctx.strokeStyle = "rgba(248, 113, 113, 0.45)";
    ctx.setLineDash([2, 3]);
    for (let k = Math.max(k0 + 1, 1); k <= k1; k++) {
      const i = r.at(k);
      if (!r.brk[i]) continue;
      const a = X(r.t[r.at(k - 1)]), b = X(r.t[i]);
      ctx.fillRect(a, T, Math.max(2, b - a), ph);
      ctx.beginPath(); ctx.moveTo(a, T); ctx.lineTo(a, T + ph); ctx.stroke();
    }
    ctx.setLineDash([]);
    ctx.restore();
    return newest;
  }

  state() {
    return {
      lastSeq: this.lastSeq,
      tipDrawn: this.tipDrawn,
      tipDrawnSeq: this.tipDrawnSeq,
      drawnLog: this.drawnLog.slice(),
      plotted: this.plotted,
      frames: this.frames,
      visible: this.visible,
      ws: this.wsState,
      link: this.link,
      estop: this.estop,
      gaps: this.gaps,
      dropped: this.dropped,
      samples: this.ring.count,
      breaks: this.breaks.slice(),
      plannedPath: this.plan?.motion?.planned_path?.length ?? 0,
    };
  }
}

// ------------------------------------------------------------------ emergency stop (every arm)

function updateEstopPanel() {
  const latched = [...arms.values()].filter((a) => a.estop).map((a) => a.name);
  const st = $("#estop-status");
  const text = latched.length ? `LATCHED: ${latched.join(", ")}` : "not latched";
  if (st.textContent !== text) st.textContent = text;
  $("#estop-panel").classList.toggle("latched", latched.length > 0);
}

async function estopAll(latch) {
  const err = $("#estop-error");
  clearError(err);
  const names = [...arms.keys()];
  const results = await Promise.allSettled(
    names.map((n) => api(latch ? "POST" : "DELETE", `/arms/${encodeURIComponent(n)}/estop`)));
  const failed = [];
  results.forEach((res, k) => {
    const arm = arms.get(names[k]);
    if (res.status === "fulfilled") arm.estop = !!res.value?.estop;
    else failed.push([names[k], res.reason]);
  });
  if (failed.length) {
    const [name, e] = failed[0];
    showError(err, new ApiError(e.status, e.code, `${name}: ${e.detail}${failed.length > 1 ? ` (and ${failed.length - 1} more)` : ""}`));
  }
  updateEstopPanel();
}

// ------------------------------------------------------------------ start-up and frame loop

function frame() {
  for (const arm of arms.values()) arm.draw();
  updateEstopPanel();
  const live = [...arms.values()].filter((a) => a.wsState === "live").length;
  const st = $("#server-status");
  const text = arms.size ? `${live}/${arms.size} arms live` : st.textContent;
  if (st.textContent !== text) st.textContent = text;
  st.className = `badge ${arms.size && live === arms.size ? "ok" : "warn"}`;
  requestAnimationFrame(frame);
}

async function loadArms() {
  for (let delay = 1; ; delay = Math.min(delay * 2, BACKOFF_MAX_S)) {
    try {
      const list = await api("GET", "/arms");
      const details = await Promise.all(list.map((a) => api("GET", `/arms/${encodeURIComponent(a.name)}`)));
      $("#loading")?.remove();
      for (const d of details) if (!arms.has(d.name)) arms.set(d.name, new Arm(d));
      return;
    } catch (e) {
      $("#loading").textContent = `Cannot load the arms (${e.detail}); retrying in ${delay} s…`;
      await new Promise((r) => setTimeout(r, delay * 1000));
    }
  }
}

function setupChrome() {
  $("#estop-button").addEventListener("click", () => estopAll(true));
  $("#estop-release").addEventListener("click", () => estopAll(false));
  $("#token-button").addEventListener("click", () => askToken("Set the access token for this tab."));
  $("#token-form").addEventListener("submit", () => {
    sessionStorage.setItem(TOKEN_KEY, $("#token-input").value.trim());
    $("#token-input").value = "";
    tokenChanged();
  });
  $("#token-clear").addEventListener("click", () => {
    sessionStorage.removeItem(TOKEN_KEY);
    $("#token-dialog").close();
    tokenChanged();
  });
  $("#token-dialog").addEventListener("close", () => settleTokenWaiters(false));
}

window.armDashboard = {
  api,  // for faults.js
  arms: () => [...arms.keys()],
  state: (name) => arms.get(name)?.state() ?? null,
  safety: (name) => arms.get(name)?.safety?.state() ?? null,
  classroom: (name) => arms.get(name)?.classroom?.state() ?? null,
};

loadTheme();
setupChrome();
requestAnimationFrame(frame);
loadArms();
