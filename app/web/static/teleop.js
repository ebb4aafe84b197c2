// armserver dashboard: teleoperation (API.md "Teleoperation (v1.2)"), a bar under the top bar.
//
// Pick the leader, the follower and the rate (30..100 Hz), and whether the leader's torque goes
// off ("by hand": a real leader's always does; a simulated one is then moved through its world,
// PUT /arms/{leader}/world/hand), then Start. The bar shows the session's state twice a second:
// running with its achieved rate and the latency from a leader sample to the follower's command
// (p50, p99), held (by the deadman: the leader's sample stale or late; or the follower refusing
// a setpoint), or stopped and why. Stop ends it: the follower holds where it is. Starting needs
// an operator token and the follower's lease where one is held (the classroom panel's, sent as
// X-Arm-Lease); any viewer sees the bar.
import { leaseFor } from "./classroom.js";
import { API, authHeaders, call, el } from "./panel.js";

const POLL_MS = 500;

let session = null;   // the id of the session this bar shows
let timer = null;

const bar = el("div", { id: "teleop-bar", class: "teleop-bar",
  style: "display:flex;flex-wrap:wrap;gap:0.5rem;align-items:center;padding:0.4rem 1rem" });
const leader = el("select", { id: "teleop-leader", title: "The arm that leads" });
const follower = el("select", { id: "teleop-follower", title: "The arm that follows" });
const rate = el("input", { id: "teleop-rate", type: "number", min: "30", max: "100", step: "1",
  value: "50", style: "width:4.5em", title: "Commands a second (30..100 Hz)" });
const byHand = el("input", { id: "teleop-by-hand", type: "checkbox",
  title: "The leader's torque off for the session, to be moved by hand" });
const holding = el("input", { id: "teleop-holding", type: "checkbox",
  title: "The leader's joints that fall without torque (an OpenManipulator-X's shoulder, " +
    "elbow and wrist; the angler's z winch) are held by hand or rest (load_supported): " +
    "without it a freed leader with such joints is refused" });
const start = el("button", { id: "teleop-start", type: "button", class: "go", disabled: true,
  title: "Start: the leader drives the follower" }, "▶ Start");
const stop = el("button", { id: "teleop-stop", type: "button", class: "primary", disabled: true,
  title: "Stop: the follower holds where it is" }, "■ Stop");
const status = el("span", { id: "teleop-status", class: "muted" }, "not running");
const err = el("span", { id: "teleop-error", class: "err", role: "alert" });
bar.append(el("strong", {}, "Teleoperation"), leader, el("span", { class: "muted" }, "→"), follower,
  el("label", {}, rate, " Hz"), el("label", { class: "small" }, byHand, " leader by hand"),
  el("label", { class: "small" }, holding, " I hold it"), start, stop, status, err);

const HELD = { deadman: "held by deadman (leader sample stale or late)",
  no_target: "held (no follower target for the leader's pose)" };

/** One line of a session's state and figures. */
export function describe(t) {
  if (t.status !== "running") return `stopped: ${t.reason || "ended"}`;
  const lat = t.latency_ms;
  const figures = `${t.achieved_hz.toFixed(1)} Hz · latency p50 ` +
    (lat ? `${lat.p50.toFixed(2)} ms · p99 ${lat.p99.toFixed(2)} ms` : "– · p99 –") +
    ` · ${t.commands} commands · ${t.holds} holds`;
  const held = !t.held ? "running"
    : HELD[t.held] || `held (the follower refused: ${t.held.replace(/^refused:/, "")})`;
  return `${held} · ${figures}`;
}

function show(t) {
  const running = t?.status === "running";
  status.textContent = t ? describe(t) : "not running";
  status.className = running ? `badge ${t.held ? "warn" : "ok"}` : "muted";
  stop.disabled = !running;
  start.disabled = running || !leader.value || !follower.value;
  for (const c of [leader, follower, rate, byHand, holding]) c.disabled = running;
}

let polling = null;    // the refresh under way (one at a time: a 401 waits for the token dialog)

function refresh() {
  if (!polling) polling = poll().finally(() => { polling = null; });
  return polling;
}

async function poll() {
  try {
    const list = await call("GET", "/teleop");
    let t = session ? list.find(x => x.id === session) : null;
    if (!t) t = list.find(x => x.status === "running") || null;  // one started elsewhere
    if (t) session = t.id;
    show(t);
  } catch (e) {
    err.textContent = e.message;
  }
}

/** POST /teleop with the follower's lease, where this dashboard holds one. */
async function begin(body) {
  const lease = leaseFor(`/arms/${encodeURIComponent(body.follower)}/`);
  if (!lease) return call("POST", "/teleop", body);
  const res = await fetch(API + "/teleop", { method: "POST", body: JSON.stringify(body),
    headers: { ...authHeaders(), "Content-Type": "application/json", "X-Arm-Lease": lease } });
  const data = await res.json().catch(() => null);
  if (!res.ok) throw Object.assign(new Error(data?.detail || res.statusText), { code: data?.code });
  return data;
}

async function act(fn) {
  err.textContent = "";
  start.disabled = stop.disabled = true;
  try { await fn(); } catch (e) { err.textContent = e.message; }
  await refresh();
}

start.addEventListener("click", () => act(async () => {
  const body = { leader: leader.value, follower: follower.value, rate_hz: Number(rate.value) };
  if (byHand.checked) body.free_leader = true;
  if (holding.checked) body.load_supported = true;
  session = (await begin(body)).id;
}));
stop.addEventListener("click", () => act(() =>
  call("DELETE", `/teleop/${encodeURIComponent(session)}`)));

async function load() {
  const arms = (await call("GET", "/arms")).map(a => a.name);
  leader.replaceChildren(...arms.map(n => el("option", { value: n }, n)));
  follower.replaceChildren(...arms.map(n => el("option", { value: n }, n)));
  if (arms.length > 1) follower.value = arms[1];
  await refresh();
}

function attach() {
  const host = document.getElementById("teleop-panel");
  if (host) host.append(bar);
  else document.querySelector("header.topbar")?.after(bar);
  load().catch(e => { err.textContent = e.message; });
  timer = setInterval(refresh, POLL_MS);
}

if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", attach);
else attach();
window.addEventListener("pagehide", () => clearInterval(timer));
