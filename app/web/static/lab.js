// Lab view: every arm of every arm server publishing to one MQTT broker, one tile each, read
// from the broker over MQTT over WebSocket: a lab screen never connects to an arm server.
//
// Topics (API.md "Lab-wide telemetry over MQTT"): {prefix}/{arm}/state (retained sample),
// {prefix}/{arm}/online, {prefix}/{arm}/events, {prefix}/server/online. Each server has its own
// prefix under one root (`armserver`, or `armserver/bench3`...): this page subscribes to one
// and two levels under the root.
//
// URL parameters: broker (default ws://<this host>:9001), root (default armserver),
// user / pass (if the broker wants them for reading). Test hook: window.labView.
//
// The MQTT client below is subscribe-only MQTT 3.1.1 (CONNECT, SUBSCRIBE, PUBLISH in with
// PUBACK for QoS 1, PINGREQ), written here so the page has no build step and no CDN.

const params = new URLSearchParams(location.search);
const BROKER = params.get("broker") || `ws://${location.hostname || "127.0.0.1"}:9001`;
const ROOT = (params.get("root") || "armserver").replace(/\/+$/, "");
const KEEPALIVE_S = 30;
const enc = new TextEncoder();
const dec = new TextDecoder();

// ------------------------------------------------------------------ MQTT 3.1.1, subscribe only

function mqttString(s) {
  const b = enc.encode(s);
  return [b.length >> 8, b.length & 0xff, ...b];
}

function packet(type, body) {
  const out = [type];
  let n = body.length;
  do {
    let byte = n % 128;
    n = Math.floor(n / 128);
    if (n > 0) byte |= 0x80;
    out.push(byte);
  } while (n > 0);
  return new Uint8Array([...out, ...body]);
}

export class MqttSubscriber {
  constructor(url, { user = null, pass = null, topics = [], onMessage, onState }) {
    this.url = url;
    this.user = user;
    this.pass = pass;
    this.topics = topics; // [[filter, qos]]
    this.onMessage = onMessage;
    this.onState = onState;
    this.buf = new Uint8Array(0);
    this.nextId = 1;
    this.backoff = 500;
    this.received = 0;
    this.connect();
  }

  connect() {
    this.onState("connecting", this.url);
    const ws = new WebSocket(this.url, ["mqtt"]);
    ws.binaryType = "arraybuffer";
    this.ws = ws;
    ws.onopen = () => {
      let flags = 0x02; // clean session
      const payload = mqttString(`lab-${Math.random().toString(16).slice(2, 14)}`);
      if (this.user) { flags |= 0x80; payload.push(...mqttString(this.user)); }
      if (this.user && this.pass) { flags |= 0x40; payload.push(...mqttString(this.pass)); }
      ws.send(packet(0x10, [...mqttString("MQTT"), 4, flags, KEEPALIVE_S >> 8,
        KEEPALIVE_S & 0xff, ...payload]));
    };
    ws.onmessage = (ev) => this.feed(new Uint8Array(ev.data));
    ws.onclose = () => {
      clearInterval(this.pinger);
      this.onState("down", this.url);
      setTimeout(() => this.connect(), this.backoff);
      this.backoff = Math.min(this.backoff * 2, 10000);
    };
    ws.onerror = () => ws.close();
  }

  feed(bytes) {
    // a WebSocket message may carry part of a packet or several packets
    const joined = new Uint8Array(this.buf.length + bytes.length);
    joined.set(this.buf);
    joined.set(bytes, this.buf.length);
    let pos = 0;
    while (joined.length - pos >= 2) {
      let len = 0, mult = 1, i = pos + 1, byte;
      do {
        if (i >= joined.length) { this.buf = joined.slice(pos); return; }
        byte = joined[i++];
        len += (byte & 0x7f) * mult;
        mult *= 128;
      } while (byte & 0x80);
      if (joined.length - i < len) break;
      this.handle(joined[pos], joined.subarray(i, i + len));
      pos = i + len;
    }
    this.buf = joined.slice(pos);
  }

  handle(first, body) {
    const type = first >> 4;
    if (type === 2) { // CONNACK
      if (body[1] !== 0) { this.onState("refused", `CONNACK code ${body[1]}`); this.ws.close(); return; }
      this.backoff = 500;
      const id = this.nextId++;
      const subs = this.topics.flatMap(([t, q]) => [...mqttString(t), q]);
      this.ws.send(packet(0x82, [id >> 8, id & 0xff, ...subs]));
      this.pinger = setInterval(() => this.ws.send(new Uint8Array([0xc0, 0])),
        (KEEPALIVE_S * 1000) / 2);
      this.onState("up", this.url);
    } else if (type === 3) { // PUBLISH
      const qos = (first >> 1) & 3;
      const tlen = (body[0] << 8) | body[1];
      const topic = dec.decode(body.subarray(2, 2 + tlen));
      let at = 2 + tlen;
      if (qos > 0) {
        this.ws.send(new Uint8Array([0x40, 2, body[at], body[at + 1]])); // PUBACK
        at += 2;
      }
      this.received++;
      this.onMessage(topic, dec.decode(body.subarray(at)), (first & 1) === 1);
    }
    // SUBACK (9), PINGRESP (13): nothing to do
  }
}

// ------------------------------------------------------------------ tiles

const tiles = new Map(); // key: the arm's topic prefix, e.g. "armserver/rbe3001"
const servers = new Map(); // server prefix -> online
let brokerState = "connecting";
let dirty = true;

function tile(key) {
  let t = tiles.get(key);
  if (!t) {
    t = { key, online: null, sample: null, lastEvent: null, updated: 0 };
    tiles.set(key, t);
  }
  return t;
}

function onMessage(topic, text, retained) {
  const cut = topic.lastIndexOf("/");
  const key = topic.slice(0, cut);
  const kind = topic.slice(cut + 1);
  let value;
  try { value = JSON.parse(text); } catch { return; }
  if (key.endsWith("/server") && kind === "online") {
    servers.set(key.slice(0, -"/server".length), value === true);
  } else if (kind === "online") {
    tile(key).online = value === true;
  } else if (kind === "state") {
    const t = tile(key);
    t.sample = value;
    t.updated = performance.now();
    t.retained = retained;
  } else if (kind === "events") {
    tile(key).lastEvent = value;
  }
  dirty = true;
}

function serverOf(key) {
  return key.slice(0, key.lastIndexOf("/"));
}

function fmt(x, digits = 3) {
  return typeof x === "number" ? x.toFixed(digits) : "–";
}

function el(tag, cls, text) {
  const e = document.createElement(tag);
  if (cls) e.className = cls;
  if (text !== undefined) e.textContent = text;
  return e;
}

function render() {
  if (!dirty) return;
  dirty = false;
  const badge = document.getElementById("broker-status");
  badge.textContent = `${brokerState} · ${BROKER}`;
  badge.className = `badge ${brokerState === "up" ? "ok" : "bad"}`;
  const grid = document.getElementById("tiles");
  document.getElementById("empty").hidden = tiles.size > 0;
  for (const key of [...tiles.keys()].sort()) {
    const t = tiles.get(key);
    let node = grid.querySelector(`[data-key="${CSS.escape(key)}"]`);
    if (!node) {
      node = el("section", "tile");
      node.dataset.key = key;
      grid.append(node);
    }
    const s = t.sample;
    const serverUp = servers.get(serverOf(key));
    const online = t.online === true && serverUp !== false;
    node.classList.toggle("offline", !online);
    node.replaceChildren();
    const head = el("div", "row");
    head.append(el("h2", null, key.slice(ROOT.length + 1) || key));
    head.append(el("span", `badge ${online ? "ok" : "bad"} online`, online ? "online" : "offline"));
    if (s?.estop) head.append(el("span", "badge bad estop", "ESTOP"));
    const faults = Array.isArray(s?.faults) ? s.faults : [];
    if (faults.length) {
      head.append(el("span", "badge warn faults",
        faults.map((f) => `${f.joint ?? f.servo}: ${(f.bits || []).join(", ")}`).join("; ")));
    }
    node.append(head);
    if (s) {
      node.append(el("div", "mono joints", `joints ${(s.positions || []).map((q) => fmt(q)).join("  ")}`));
      node.append(el("div", "mono tip",
        `tip ${fmt(s.tip?.x * 1000, 1)} ${fmt(s.tip?.y * 1000, 1)} ${fmt(s.tip?.z * 1000, 1)} mm`));
      const motion = s.motion ? `${s.motion.status} ${Math.round(s.motion.progress * 100)} %` : "idle";
      node.append(el("div", "muted small", `link ${s.link} · ${motion} · seq ${s.seq}`));
    } else {
      node.append(el("div", "muted small", "no sample yet"));
    }
    if (t.lastEvent) {
      node.append(el("div", "muted small event", `last event: ${t.lastEvent.event}`));
    }
  }
}

function frame() {
  render();
  requestAnimationFrame(frame);
}

const topics = [];
for (const level of ["+", "+/+"]) {
  topics.push([`${ROOT}/${level}/state`, 0], [`${ROOT}/${level}/online`, 1],
    [`${ROOT}/${level}/events`, 1]);
}
const client = new MqttSubscriber(BROKER, {
  user: params.get("user"),
  pass: params.get("pass"),
  topics,
  onMessage,
  onState: (state) => { brokerState = state; dirty = true; },
});

// test hook: what the page shows, as data
window.labView = {
  get broker() { return brokerState; },
  get received() { return client.received; },
  tiles() {
    const out = {};
    for (const [key, t] of tiles) {
      const serverUp = servers.get(serverOf(key));
      out[key] = { online: t.online === true && serverUp !== false, sample: t.sample,
        lastEvent: t.lastEvent };
    }
    return out;
  },
  servers() { return Object.fromEntries(servers); },
};

document.getElementById("root").textContent = ROOT;
requestAnimationFrame(frame);
