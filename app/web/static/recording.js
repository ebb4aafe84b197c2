// armserver dashboard: recordings (API.md "Recordings (v1.2)"), a bar under the top bar.
//
// Pick a dataset (or make one of every arm and the first camera), then Record / Stop: the bar
// shows the dataset's episode count and, while an episode records, its length (polled twice a
// second). Discard throws the current episode away. Recording moves nothing; an operator token
// is needed to start and stop, any viewer sees the bar.
import { call, el } from "./panel.js";

const POLL_MS = 500;

let current = null;   // the chosen dataset's id
let timer = null;

const bar = el("section", { id: "recording-bar", class: "recording-bar", "aria-label": "Recording",
  style: "display:flex;flex-wrap:wrap;gap:0.5rem;align-items:center;padding:0.4rem 1rem" });
const pick = el("select", { id: "recording-pick", title: "The dataset episodes go into" });
const status = el("span", { id: "recording-status", class: "muted" }, "no dataset");
const record = el("button", { id: "recording-record", type: "button", class: "go", disabled: true,
  title: "Start an episode" }, "● Record");
const discard = el("button", { id: "recording-discard", type: "button", class: "ghost", disabled: true,
  title: "Throw the current episode away" }, "Discard");
const make = el("button", { id: "recording-new", type: "button", class: "ghost",
  title: "A new dataset of every arm and the first camera" }, "New dataset…");
const err = el("span", { id: "recording-error", class: "err", role: "alert" });
bar.append(el("strong", {}, "Recording"), pick, make, record, discard, status, err);

function show(d) {
  if (!d) {
    status.textContent = "no dataset";
    record.disabled = discard.disabled = true;
    return;
  }
  const cur = d.current;
  const n = `${d.episodes} episode${d.episodes === 1 ? "" : "s"}`;
  status.textContent = cur ? `${n} · recording ${cur.length_s.toFixed(1)} s (${cur.frames} frames)`
    : n + (d.last_error ? ` · last: ${d.last_error}` : "");
  record.textContent = cur ? "■ Stop" : "● Record";
  record.className = cur ? "primary" : "go";
  record.title = cur ? "End the episode and write it" : "Start an episode";
  record.disabled = false;
  discard.disabled = !cur;
}

async function refresh() {
  if (!current) return show(null);
  try {
    show(await call("GET", `/recordings/${encodeURIComponent(current)}`));
  } catch (e) {
    err.textContent = e.message;
  }
}

async function load(select) {
  const list = await call("GET", "/recordings");
  pick.replaceChildren(...list.map(r => el("option", { value: r.id }, r.name)));
  if (select) current = select;
  if (!list.some(r => r.id === current)) current = list.length ? list[0].id : null;
  if (current) pick.value = current;
  await refresh();
}

async function act(fn) {
  err.textContent = "";
  record.disabled = true;
  try { await fn(); } catch (e) { err.textContent = e.message; }
  await refresh();
}

record.addEventListener("click", () => act(async () => {
  const d = await call("GET", `/recordings/${encodeURIComponent(current)}`);
  const path = `/recordings/${encodeURIComponent(current)}/episodes`;
  if (d.current) await call("POST", path + "/stop");
  else await call("POST", path, {});
}));
discard.addEventListener("click", () => act(() =>
  call("DELETE", `/recordings/${encodeURIComponent(current)}/episodes/current`)));
pick.addEventListener("change", () => { current = pick.value; act(async () => {}); });
make.addEventListener("click", () => act(async () => {
  const name = prompt("Dataset name (letters, digits, _ - .)", `demo-${Date.now() % 100000}`);
  if (!name) return;
  const task = prompt("What do the episodes show?", "demonstration") || "demonstration";
  const arms = (await call("GET", "/arms")).map(a => a.name);
  const cams = (await call("GET", "/cameras").catch(() => [])).map(c => c.name).slice(0, 1);
  const d = await call("POST", "/recordings", { name, arms, cameras: cams, fps: 30, task });
  await load(d.id);
}));

function start() {
  document.querySelector("header.topbar")?.after(bar);
  load().catch(e => { err.textContent = e.message; });
  timer = setInterval(refresh, POLL_MS);
}

if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", start);
else start();
window.addEventListener("pagehide", () => clearInterval(timer));
