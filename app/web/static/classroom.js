// Classroom on the dashboard: who holds each arm and for how long, the queue, Join / Leave, the
// lease the dashboard claims and renews while a person uses the page, and the instructor's
// controls (revoke, move up, remove, clear). API.md "People and roles", "Queue and hand-off".
//
// app.js hooks in: attachClassroom() after an arm's card is built, onEvent() for the queue's
// telemetry events, and leaseFor(path) in api() to send X-Arm-Lease on the arm's requests.

const leases = new Map();     // arm name -> lease id the dashboard holds
let me = null;                // {name, role} from GET /me
let lastActivity = Date.now();
//: The dashboard renews its lease only while the person used the page this recently, ms.
const IDLE_MS = 60000;

["pointerdown", "keydown", "input", "wheel"].forEach((t) =>
  window.addEventListener(t, () => { lastActivity = Date.now(); }, { capture: true, passive: true }));

/** The lease id to send on a request to `path`, if the dashboard holds the arm's lease. */
export function leaseFor(path) {
  const m = /^\/arms\/([^/]+)\//.exec(path);
  return m ? leases.get(decodeURIComponent(m[1])) || null : null;
}

class ClassroomPanel {
  constructor(arm, api, h) {
    this.arm = arm;
    this.api = api;
    this.h = h;
    this.data = null;
    this.mine = null;        // my entry id
    this.renewTimer = null;
    const id = (s) => `${arm.name}-${s}`;
    this.el = {};
    this.el.holder = h("span", { id: id("holder"), class: "small" }, "…");
    this.el.join = h("button", { type: "button", id: id("queue-join"), onclick: () => this.join() }, "Join queue");
    this.el.leave = h("button", { type: "button", class: "ghost", id: id("queue-leave"), onclick: () => this.leave() }, "Leave");
    this.el.claim = h("button", { type: "button", class: "primary", id: id("queue-claim"), onclick: () => this.claim() }, "Take my turn");
    this.el.list = h("ol", { id: id("queue-list"), class: "small queue" });
    this.el.teach = h("div", { class: "row", id: id("queue-instructor") },
      h("button", { type: "button", class: "ghost", id: id("queue-revoke"), onclick: () => this.act("DELETE", "lease") }, "Revoke lease"),
      h("button", { type: "button", class: "ghost", id: id("queue-clear"), onclick: () => this.act("DELETE", "queue") }, "Clear queue"));
    this.el.error = h("div", { class: "err", id: id("queue-error"), role: "alert" });
    this.el.section = h("section", { class: "ctl classroom", id: id("classroom") },
      h("h3", {}, "Queue"),
      h("div", { class: "row" }, this.el.holder),
      h("div", { class: "row" }, this.el.join, this.el.claim, this.el.leave),
      this.el.list, this.el.teach, this.el.error);
    const controls = arm.el.card.querySelector(".controls") || arm.el.card;
    controls.append(this.el.section);
    this.refresh();
    this.tick = setInterval(() => this.refresh(), 1000);
  }

  path(...parts) { return `/arms/${encodeURIComponent(this.arm.name)}/${parts.join("/")}`; }

  async whoami() {
    if (!me) {
      try { me = await this.api("GET", "/me"); } catch { me = null; }
    }
    return me;
  }

  async refresh() {
    try {
      await this.whoami();
      this.show(await this.api("GET", this.path("queue")));
    } catch (e) {
      this.el.holder.textContent = `cannot read the queue (${e.detail || e})`;
    }
  }

  show(d) {
    this.data = d;
    const h = this.h;
    const left = d.slot_left != null ? ` · ${Math.ceil(d.slot_left)} s left` : "";
    this.el.holder.textContent = d.holder ? `held by ${d.holder}${left}`
      : d.handing_off ? "handing off…" : d.blocked ? `nobody: ${d.blocked}` : "free";
    const mine = me ? d.entries.find((e) => e.name === me.name) : null;
    this.mine = mine ? mine.id : null;
    const teach = me && me.role === "instructor";
    this.el.list.replaceChildren(...d.entries.map((e, k) => h("li", { "data-status": e.status },
      `${e.name} (${e.status})`,
      teach && e.status === "waiting" && k > 0 && d.entries[k - 1].status === "waiting"
        ? h("button", { type: "button", class: "ghost small", title: "move up", onclick: () => this.up(e.id) }, "↑") : "",
      teach || (me && e.name === me.name)
        ? h("button", { type: "button", class: "ghost small", title: "remove", onclick: () => this.remove(e.id) }, "✕") : "")));
    hide(this.el.join, !!mine || (me && me.role === "viewer"));
    hide(this.el.leave, !mine);
    hide(this.el.claim, !(mine && mine.status === "offered"));
    hide(this.el.teach, !teach);
    if (mine && mine.status === "offered" && mine.lease_id) this.offered = mine.lease_id;
    if (!mine || (mine.status !== "holding" && mine.status !== "offered")) this.dropLease();
  }

  async join() { await this.call(() => this.api("POST", this.path("queue"))); }

  async leave() { if (this.mine) await this.remove(this.mine); }

  async remove(id) {
    if (id === this.mine) this.dropLease();
    await this.call(() => this.api("DELETE", this.path("queue", encodeURIComponent(id))));
  }

  async up(id) {
    const waiting = this.data.entries.filter((e) => e.status === "waiting").map((e) => e.id);
    const k = waiting.indexOf(id);
    if (k > 0) [waiting[k - 1], waiting[k]] = [waiting[k], waiting[k - 1]];
    await this.call(() => this.api("PUT", this.path("queue"), { order: waiting }));
  }

  async act(method, what) { await this.call(() => this.api(method, this.path(what))); }

  /** Claim the offered lease (its first renewal) and keep renewing it while the page is used. */
  async claim() {
    const id = this.offered;
    if (!id) return;
    await this.call(async () => {
      const lease = await this.api("PUT", this.path("lease", id));
      leases.set(this.arm.name, id);
      lastActivity = Date.now();
      clearInterval(this.renewTimer);
      this.renewTimer = setInterval(() => this.renew(id), Math.max(200, lease.ttl * 1000 / 3));
    });
  }

  async renew(id) {
    if (Date.now() - lastActivity > IDLE_MS) return;  // nobody at the page: let it lapse
    try {
      await this.api("PUT", this.path("lease", id));
    } catch {
      this.dropLease();
      this.refresh();
    }
  }

  dropLease() {
    clearInterval(this.renewTimer);
    this.renewTimer = null;
    leases.delete(this.arm.name);
  }

  async call(fn) {
    this.el.error.replaceChildren();
    try {
      await fn();
    } catch (e) {
      this.el.error.textContent = e.code === "forbidden"
        ? "Not allowed with this token" : `${e.detail || e}`;
    }
    await this.refresh();
  }

  onEvent(msg) {
    if (["queue", "lease_offered", "lease_granted", "lease_ended", "handoff", "lease_expired"]
      .includes(msg.event)) this.refresh();
  }

  state() {
    return { data: this.data, me, lease: leases.get(this.arm.name) || null, mine: this.mine };
  }
}

// (style, not the `hidden` attribute: a `.row` is display: flex, which overrides `hidden`)
function hide(el, yes) { el.style.display = yes ? "none" : ""; }

export function attachClassroom(arm, api, h) {
  return new ClassroomPanel(arm, api, h);
}
