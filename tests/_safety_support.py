"""What the pass-through safety tests share (tests/test_passthrough_safety.py, the state
machine of tests/test_safety_machine.py): servers over the simulated arms (in process, or a
real uvicorn on loopback, with or without `raw_access` and tokens), a recorder of every
telemetry sample with the simulated device's own setpoint beside it, and the three safety
invariants of issue 22, judged from those records:

(a) after a latch the device's setpoint never moves further than `estop_tolerance` (8 encoder
    ticks, or 30 ms at the joint's velocity limit, whichever is more) from where the arm was
    when the estop latched;
(b) no sample puts a body point (the envelope's own point model, `ArmSafety.points` and
    `first_hit`) inside a keep-out zone accepted before it;
(c) no joint's measured speed exceeds its velocity limit by more than SPEED_TOLERANCE.

Nothing here is mocked: the device setpoint is read from the simulated firmware (the rbe3001's
SET_PID setpoint) and the simulated MX-28s (each servo's Goal Position register), in the
control thread, in the same listener call as the sample it goes with.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import httpx
import numpy as np
from _wait import wait_for, wait_until
from conftest import LiveServer, make_settings, running_client
from conftest import serve_live as conftest_serve_live
from fastapi import FastAPI

from app.arms.loading import load_profile
from app.config import ArmProfile, KeepOutBox, SafetySettings, Settings, homed_at_start
from app.safety.envelope import ArmSafety

API = "/api/v1"
ARMS = ("rbe3001", "angler")

#: Tokens of the servers that have them (`tokens=True`).
OPERATOR, INSTRUCTOR, VIEWER = "op-safety-1", "instr-safety-1", "view-safety-1"

#: The measured speed may exceed the limit by this factor (the tracking tests' bound: the
#: simulated firmware's PID catching up after a late tick; the servos cap at the limit).
SPEED_TOLERANCE = 1.1
#: The longest step of motion the executor commands at once, s (app/motion_stream
#: MAX_STEP_S); the estop's hold may be this far from the latch at the joint's limit.
STEP_S = 0.03
#: Encoder ticks the hold may be off where a joint's 30 ms step is shorter.
HOLD_TICKS = 8.0
#: How long after the first latched sample the hold must be on the device, s: the latch
#: publishes its sample before the hold is written (one device round trip; generous).
HOLD_GRACE_S = 0.06
#: A measured body point may graze a zone by this much (m) before it counts as inside: the
#: envelope checks the commanded path, and the measured one trails it (the rbe3001's PID,
#: gravity droop of a few ticks at 0.37 m; the servos follow their profile within a tick).
ZONE_SLACK = {"rbe3001": 0.005, "angler": 0.0015}


def profiles(raw: bool = False) -> list[ArmProfile]:
    """The default server's two simulated arms (homed at start), optionally with raw access."""
    return [homed_at_start(load_profile(n)).model_copy(update={"raw_access": raw})
            for n in ARMS]


def token_settings(**over: Any) -> Settings:
    return make_settings(operator_tokens=OPERATOR, instructor_tokens=INSTRUCTOR,
                         viewer_tokens=VIEWER, **over)


def auth(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


# ---------------------------------------------------------------- servers


@contextlib.asynccontextmanager
async def served(profiles_: list[ArmProfile] | None = None, settings: Settings | None = None,
                 headers: dict[str, str] | None = None
                 ) -> AsyncIterator[tuple[FastAPI, httpx.AsyncClient]]:
    """conftest's in-process app and client, over `profiles_`."""
    async with running_client(settings, headers, profiles_) as pair:
        yield pair


@contextlib.contextmanager
def serve_live(profiles_: list[ArmProfile] | None = None,
               settings: Settings | None = None) -> Iterator[LiveServer]:
    """conftest's live uvicorn server, over `profiles_`."""
    with conftest_serve_live(settings, profiles=profiles_) as live:
        yield live


# ---------------------------------------------------------------- the device's own state


def device_setpoint(svc: Any) -> np.ndarray:
    """The simulated device's setpoint in joint units (rad, m): the rbe3001 firmware's SET_PID
    setpoint, or each MX-28's Goal Position, through the arm's transmission (homing offsets
    included). Read it on the control thread (a listener) or between polls."""
    dev = svc.driver.link.device
    if hasattr(dev, "setpoint"):
        ticks = np.asarray(dev.setpoint, dtype=float)
    else:
        ticks = np.array([dev.servo(j.motor_id).get("goal_position")
                          for j in svc.profile.joints], dtype=float)
    return np.asarray(svc.model.transmission.from_ticks(ticks), dtype=float)


def estop_tolerance(svc: Any) -> np.ndarray:
    """Per joint: max(8 encoder ticks, the joint's velocity limit x 30 ms)."""
    ticks = np.abs(HOLD_TICKS / np.asarray(svc.model.transmission.ticks_per_unit, dtype=float))
    return np.maximum(ticks, np.asarray(svc.model.vmax, dtype=float) * STEP_S)


def to_ticks(svc: Any, q: Any) -> np.ndarray:
    return np.asarray(svc.model.transmission.to_ticks(np.asarray(q, dtype=float)), dtype=float)


def set_pid_body(svc: Any, q: Any) -> dict[str, Any]:
    return {"joints": [{"position_ticks": float(t), "velocity_ticks_s": 0.0}
                       for t in to_ticks(svc, q)]}


def goal_raw(svc: Any, k: int, q: Any) -> int:
    """goal_position (raw) of joint k's servo for joint vector q."""
    return int(round(float(to_ticks(svc, q)[k])))


def motor_of(svc: Any, k: int) -> int:
    return int(svc.profile.joints[k].motor_id)


def box(name: str, centre: Any, half: float | list[float]) -> dict[str, Any]:
    c = np.asarray(centre, dtype=float)
    h = np.broadcast_to(np.asarray(half, dtype=float), (3,))
    lo, hi = c - h, c + h
    return {"name": name, "min": dict(zip("xyz", lo.tolist(), strict=True)),
            "max": dict(zip("xyz", hi.tolist(), strict=True))}


# ---------------------------------------------------------------- samples


@dataclass
class Rec:
    mono: float  # time.monotonic() when the sample was published
    seq: int
    q: np.ndarray | None
    qd: np.ndarray | None
    estop: bool
    setpoint: np.ndarray
    motion: dict[str, Any] | None


@dataclass
class Recorder:
    """Every sample of one arm, as published (a hub listener, on the control thread), with the
    simulated device's setpoint read in the same call."""

    svc: Any
    samples: list[Rec] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    _off: Callable[[], None] | None = None

    def __post_init__(self) -> None:
        self._off = self.svc.hub.add_listener(self._on)

    def _on(self, sample: dict[str, Any]) -> None:
        try:
            q, qd = sample.get("positions"), sample.get("velocities")
            self.samples.append(Rec(
                time.monotonic(), int(sample.get("seq", -1)),
                None if q is None else np.asarray(q, dtype=float),
                None if qd is None else np.asarray(qd, dtype=float),
                bool(sample.get("estop")), device_setpoint(self.svc), sample.get("motion")))
        except Exception as exc:  # noqa: BLE001 - a listener must not break the publisher
            self.errors.append(f"{type(exc).__name__}: {exc}")

    def close(self) -> None:
        if self._off is not None:
            self._off()
            self._off = None

    def __len__(self) -> int:
        return len(self.samples)

    def since(self, n: int) -> list[Rec]:
        return self.samples[n:]

    def latest(self) -> Rec:
        return self.samples[-1]


def _samples_when(rec: Recorder, pred: Callable[[list[Rec]], bool],
                  start: int) -> Callable[[], list[list[Rec]] | None]:
    """A condition for tests/_wait.py: the samples since `start`, boxed (an empty list may
    satisfy `pred`), once pred(them) holds."""
    def ready() -> list[list[Rec]] | None:
        got = rec.since(start)
        return [got] if pred(got) else None
    return ready


async def wait_samples(rec: Recorder, pred: Callable[[list[Rec]], bool],
                       timeout: float = 10.0, start: int = 0) -> list[Rec]:
    """Poll (bounded) until pred(samples since `start`) holds; those samples."""
    box: list[list[Rec]] = await wait_for(_samples_when(rec, pred, start), timeout,
                                          "samples", every=0.01)
    return box[0]


def wait_samples_sync(rec: Recorder, pred: Callable[[list[Rec]], bool],
                      timeout: float = 10.0, start: int = 0) -> list[Rec]:
    """`wait_samples` for a plain thread (blocking)."""
    box: list[list[Rec]] = wait_until(_samples_when(rec, pred, start), timeout, "samples",
                                      every=0.01)
    return box[0]


def positions(recs: list[Rec]) -> np.ndarray:
    return np.array([r.q for r in recs if r.q is not None])


def peak_speed(recs: list[Rec]) -> np.ndarray:
    qd = np.array([np.abs(r.qd) for r in recs if r.qd is not None])
    return qd.max(axis=0) if len(qd) else np.zeros(0)


# ---------------------------------------------------------------- the invariants


def speed_violations(svc: Any, recs: list[Rec]) -> list[str]:
    """(c): samples with a joint faster than SPEED_TOLERANCE x its limit (the first few)."""
    vmax = np.asarray(svc.model.vmax, dtype=float)
    out = []
    for r in recs:
        if r.qd is None:
            continue
        over = np.flatnonzero(np.abs(r.qd) > SPEED_TOLERANCE * vmax)
        for k in over:
            out.append(f"seq {r.seq}: {svc.model.names[k]} at {abs(r.qd[k]):.4g} "
                       f"(limit {vmax[k]:g}, x{SPEED_TOLERANCE} = {SPEED_TOLERANCE * vmax[k]:.4g}"
                       f"; estop {r.estop})")
        if len(out) >= 5:
            break
    return out


@dataclass
class LatchTracker:
    """(a), incrementally: for each run of latched samples, the position of its first sample
    (the latch publishes the latest reading at once) and, from HOLD_GRACE_S after it, every
    device setpoint against it."""

    svc: Any
    ref: np.ndarray | None = None
    t_latch: float = 0.0
    worst: np.ndarray | None = None  # largest |setpoint - ref| per joint over every latch

    def feed(self, recs: list[Rec]) -> list[str]:
        tol = estop_tolerance(self.svc)
        out: list[str] = []
        for r in recs:
            if not r.estop:
                self.ref = None
                continue
            if self.ref is None:
                if r.q is None:
                    continue
                self.ref, self.t_latch = r.q.copy(), r.mono
                continue
            if r.mono - self.t_latch < HOLD_GRACE_S:
                continue
            off = np.abs(r.setpoint - self.ref)
            self.worst = off if self.worst is None else np.maximum(self.worst, off)
            bad = np.flatnonzero(off > tol * 1.0001)
            if bad.size and len(out) < 5:
                out.append(
                    f"seq {r.seq}, {r.mono - self.t_latch:.3f} s after the latch: device "
                    f"setpoint {np.round(r.setpoint, 5).tolist()} vs where the arm was "
                    f"{np.round(self.ref, 5).tolist()}: "
                    + ", ".join(f"{self.svc.model.names[k]} off by {off[k]:.4g} "
                                f"(tolerance {tol[k]:.4g})" for k in bad))
        return out


def shrunk(zones: list[dict[str, Any]], slack: float) -> list[KeepOutBox]:
    out = []
    for z in zones:
        lo = np.array([z["min"][a] for a in "xyz"]) + slack
        hi = np.array([z["max"][a] for a in "xyz"]) - slack
        if np.all(hi > lo):
            out.append(KeepOutBox.model_validate(
                {"name": z["name"], "min": dict(zip("xyz", lo.tolist(), strict=True)),
                 "max": dict(zip("xyz", hi.tolist(), strict=True))}))
    return out


def zone_hits(svc: Any, recs: list[Rec], zones: list[dict[str, Any]],
              floor_z: float | None = None, slack: float | None = None) -> str | None:
    """(b): the first sample of `recs` with a body point inside one of `zones` (each grown by
    its point's margin, as the envelope does, less `slack` for the measured path's tracking),
    as the envelope's own `first_hit` finds it; None if none."""
    slack = ZONE_SLACK.get(svc.name, 0.003) if slack is None else slack
    boxes = shrunk(zones, slack)
    if not boxes and floor_z is None:
        return None
    env: ArmSafety = svc.safety.preview(SafetySettings(
        zones=boxes, floor_z=None if floor_z is None else floor_z - slack))
    got = [r for r in recs if r.q is not None]
    if not got:
        return None
    q = np.array([r.q for r in got])
    hit = env.first_hit(q, np.array([r.mono for r in got]))
    if hit is None:
        return None
    r = got[hit.index]
    return (f"seq {r.seq}: the {hit.body} at {np.round(hit.point, 4).tolist()} m is inside "
            f"'{hit.zone}' (less {slack} m of tracking slack) at joints "
            f"{np.round(r.q, 4).tolist()} (estop {r.estop}, motion {r.motion})")


def documented(r: httpx.Response, ok: tuple[int, ...], codes: set[str]) -> str | None:
    """None if the answer is a success in `ok` or an error with one of `codes`; else what is
    wrong (a 500 is never acceptable)."""
    if r.status_code in ok:
        return None
    try:
        code = r.json().get("code")
    except ValueError:
        code = None
    if r.status_code >= 500 and code not in ("link_down", "device_timeout"):
        return f"{r.request.method} {r.request.url.path}: {r.status_code} {r.text[:300]}"
    if code in codes:
        return None
    return (f"{r.request.method} {r.request.url.path}: {r.status_code} code {code!r} is not "
            f"one of {sorted(codes)}: {r.text[:300]}")
