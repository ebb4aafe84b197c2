"""The pass-through check made cheaper (issue 23's goal latency tail) gives the verdicts it gave.

`SafetyGuard.check_passthrough` runs on the control thread before every pass-through goal; it
now decides on whole arrays, builds no path while the envelope is inactive (no zone, no floor)
and writes the reasons only for a refusal. `reference_check` below is the check as it was
before (commit c7f4815, app/safety/guard.py and app/safety/envelope.py), kept here verbatim as
the oracle. Over many random states of real arms' guards and drivers (positions, the last
command and its age, the servos' pace, homing, calibration, zones, floor, speed override, raw
access) both must accept the same commands and refuse the others with the same error, code
and message. `reference_first_hit` is the envelope's `first_hit` as it was (commit d753f31),
one (body point, zone) pair at a time; the new one, its overlapping pairs found at once, must
find the same first hit on random paths.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import app.safety.guard as guard_module
from app.arms.loading import load_profile
from app.config import SafetySettings, homed_at_start
from app.errors import ArmError, InvalidRequest, JointLimit, LinkDown, VelocityLimit
from app.safety.guard import PASSTHROUGH_STEP_S, SafetyGuard, require_finite
from app.service import ArmService

ARMS = ("rbe3001", "angler", "openmanipulator_x")
NOW = 1000.0  # the frozen monotonic clock of both checks, s

# ------------------------------------------------------------------ the check as it was

PATH_STEP = {"revolute": 0.002, "prismatic": 0.0005}
MAX_PATH_POINTS = 4000


def _path_fractions(delta: np.ndarray, kinds: Sequence[str]) -> np.ndarray:
    step = np.array([PATH_STEP[k] for k in kinds])
    n = int(np.clip(np.ceil(np.max(np.abs(delta) / step)), 1, MAX_PATH_POINTS - 1))
    return np.linspace(0.0, 1.0, n + 1)[:, None]


def _passthrough_path(here: np.ndarray, target: np.ndarray, speed: np.ndarray,
                      paced: np.ndarray, kinds: Sequence[str]) -> np.ndarray:
    delta = target - here
    s = _path_fractions(delta, kinds)
    if not np.any(paced):
        return np.asarray(here + s * delta, dtype=float)
    t_each = np.where(paced, np.abs(delta) / np.maximum(speed, 1e-12), 0.0)
    total = float(np.max(t_each))
    if total <= 0.0:
        return np.asarray(here + s * delta, dtype=float)
    frac = np.where(paced, np.minimum(1.0, s * total / np.where(t_each > 0, t_each, 1.0)), s)
    return np.asarray(here + frac * delta, dtype=float)


def _unit(kind: str) -> str:
    return "rad" if kind == "revolute" else "m"


def _reference_step(g: SafetyGuard, target: np.ndarray, here: np.ndarray, speed: np.ndarray,
                    paced: np.ndarray) -> None:
    m = g.model
    eps = np.abs(1.0 / m.transmission.ticks_per_unit)
    step = np.abs(target - here)
    cap = speed * PASSTHROUGH_STEP_S + eps
    over = [f"{name} {step[k]:.4g} {_unit(kind)} from where it is (at most {cap[k]:.4g}: "
            f"{PASSTHROUGH_STEP_S:g} s at its velocity limit {speed[k]:g} {_unit(kind)}/s)"
            for k, (name, kind) in enumerate(zip(m.names, m.kinds, strict=True))
            if not paced[k] and step[k] > cap[k]]
    told = g.device.commanded
    if told is not None:
        since = min(max(0.0, NOW - g.device.commanded_at), PASSTHROUGH_STEP_S)
        rate = speed * m.profile.tracking_margin
        moved = np.abs(target - told)
        allowed = rate * since + eps
        over += [f"{name} moved {moved[k]:.4g} {_unit(kind)} from its last command "
                 f"{since * 1e3:.1f} ms after it (at most {allowed[k]:.4g}: "
                 f"{rate[k]:.3g} {_unit(kind)}/s)"
                 for k, (name, kind) in enumerate(zip(m.names, m.kinds, strict=True))
                 if not paced[k] and np.isfinite(told[k]) and moved[k] > allowed[k]
                 and step[k] <= cap[k]]
    if over:
        raise VelocityLimit(
            "pass-through step the device would take faster than the joint's velocity "
            "limit: " + "; ".join(over) + f". Send a planned move (POST /api/v1/arms/"
            f"{g.name}/move/joints), or setpoints at most {PASSTHROUGH_STEP_S:g} s of "
            "motion at the limit from where the joint is, and from the last command no "
            "further than the limit allows in the time since it")


def reference_check(g: SafetyGuard, target: np.ndarray, pace: np.ndarray | None) -> None:
    g.require_motion_allowed()
    g.require_no_fault()
    target = np.asarray(target, dtype=float)
    require_finite(target, "pass-through positions")
    here = g.device.positions
    if here is None or g.device.stale:
        raise LinkDown(f"{g.name}: no fresh joint positions from the device to check a "
                       "pass-through command against")
    g.check_homed(here, target)
    m = g.model
    v = [] if g.profile.raw_access else m.violations(target)
    if v:
        raise JointLimit("pass-through position outside the joint limits (the profile does "
                         "not allow raw access): " + "; ".join(v))
    paced = np.zeros(m.n, dtype=bool)
    speed = np.asarray(g.scaled(m.vmax)[0], dtype=float)
    if pace is not None:
        p = np.asarray(pace, dtype=float)
        paced = np.isfinite(p) & (p > 0) & (p <= m.vmax * (1 + 1e-6))
        speed = np.where(paced, p, speed)
    g.safety.check_path(_passthrough_path(here, target, speed, paced, m.kinds),
                        "along the path from where the arm is to the commanded position")
    _reference_step(g, target, here, speed, paced)

def reference_first_hit(env: Any, q: np.ndarray, t: np.ndarray) -> Any:
    """ArmSafety.first_hit as it was (one (body, zone) pair at a time), on `env`'s settings."""
    c = env._c
    if not c.active:
        return None
    p = env.points(np.asarray(q, dtype=float).reshape(-1, env.model.n))
    lo_all, hi_all = p.min(axis=0), p.max(axis=0)
    best: tuple[int, int, str] | None = None
    for b in range(p.shape[1]):
        x, y, z = p[:, b, 0], p[:, b, 1], p[:, b, 2]
        if c.floor is not None and lo_all[b, 2] < c.floor[b]:
            i = int(np.argmax(z < c.floor[b]))
            best = min(best, (i, b, "floor")) if best else (i, b, "floor")
        for j, name in enumerate(c.names):
            lo, hi = c.lo[b, j], c.hi[b, j]
            if np.any(lo_all[b] > hi) or np.any(hi_all[b] < lo):
                continue
            cand = np.flatnonzero((x >= lo[0]) & (x <= hi[0]))
            for k, axis in ((1, y), (2, z)):
                if cand.size:
                    v = axis[cand]
                    cand = cand[(v >= lo[k]) & (v <= hi[k])]
            if cand.size:
                i = int(cand[0])
                if best is None or (i, b) < best[:2]:
                    best = (i, b, name)
    if best is None:
        return None
    i, b, zone = best
    return (zone, env.bodies[b], p[i, b].tolist(), i, float(np.asarray(t)[i]))

# ------------------------------------------------------------------ random states


_SERVICES: dict[tuple[str, bool], ArmService] = {}


def service(arm: str, raw: bool) -> ArmService:
    """A real arm's service (guard, driver, model), not started: its state is set by hand."""
    key = (arm, raw)
    if key not in _SERVICES:
        p = homed_at_start(load_profile(arm))
        _SERVICES[key] = ArmService(p.model_copy(update={"raw_access": raw}))
    return _SERVICES[key]


@st.composite
def states(draw: Any) -> tuple[ArmService, np.ndarray, np.ndarray | None]:
    svc = service(draw(st.sampled_from(ARMS)), draw(st.booleans()))
    m, drv = svc.model, svc.driver
    n = m.n
    unit = st.floats(0.0, 1.0)
    span = m.upper - m.lower
    here = m.lower + span * np.array([draw(unit) for _ in range(n)])
    # steps from a tick to the whole range, each joint its own size and sign
    scale = 10.0 ** np.array([draw(st.floats(-5.0, 0.3)) for _ in range(n)])
    moved = np.array([draw(st.sampled_from((0.0, 1.0, -1.0))) for _ in range(n)])
    target = here + moved * scale * span * 0.5
    if draw(st.integers(0, 30)) == 0:
        target[draw(st.integers(0, n - 1))] = draw(st.sampled_from((math.nan, math.inf)))
    drv.positions = here
    drv.stale = draw(st.integers(0, 7)) == 0  # often enough that 400 examples hold some
    drv.homed = [draw(st.integers(0, 8)) > 0 for _ in range(n)]
    drv.calibrated = [draw(st.integers(0, 8)) > 0 for _ in range(n)]
    drv.faults = []
    drv.forget_commanded()
    if draw(st.booleans()):
        told = here + span * np.array([draw(st.floats(-0.02, 0.02)) for _ in range(n)])
        joints = [k for k in range(n) if draw(st.integers(0, 4)) > 0]
        if joints:
            drv.note_commanded(m.transmission.to_ticks(told)[joints], joints)
        drv.commanded_at = NOW - draw(st.sampled_from((0.0, 0.001, 0.004, 0.01, 0.029, 5.0)))
    pace: np.ndarray | None = None
    if draw(st.booleans()):
        pace = m.vmax * np.array([draw(st.sampled_from((math.nan, 0.0, 0.3, 1.0, 1.2)))
                                  for _ in range(n)])
    zones = []
    reach = float(np.max(np.abs(m.joint_origins(here))))
    for i in range(draw(st.integers(0, 2))):
        c = m.joint_origins(m.lower + span * np.array([draw(unit) for _ in range(n)]))[-1]
        half = draw(st.floats(0.005, 0.1))
        zones.append({"name": f"zone{i}",
                      "min": {"x": float(c[0]) - half, "y": float(c[1]) - half,
                              "z": float(c[2]) - half},
                      "max": {"x": float(c[0]) + half, "y": float(c[1]) + half,
                              "z": float(c[2]) + half}})
    floor = draw(st.sampled_from((None, None, -reach, 0.0)))
    svc.safety.apply(SafetySettings.model_validate(
        {"zones": zones, "floor_z": floor,
         "speed_override": draw(st.sampled_from((1.0, 0.5, 0.05)))}), "stored")
    return svc, target, pace


def outcome(check: Any) -> tuple[str, str, str] | None:
    try:
        check()
    except (ArmError, InvalidRequest) as exc:
        return type(exc).__name__, exc.code, exc.detail
    return None


@settings(max_examples=600, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(states())
def test_the_check_gives_the_reference_verdict(state: Any) -> None:
    svc, target, pace = state
    g = svc.guard
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(guard_module, "time", SimpleNamespace(monotonic=lambda: NOW))
        got = outcome(lambda: g.check_passthrough(target, pace))
    assert got == outcome(lambda: reference_check(g, target, pace))


def test_the_random_states_reach_every_verdict() -> None:
    """The strategy is no vacuous pass: accepted commands and each refusal show up."""
    seen: set[str] = set()

    @settings(max_examples=400, deadline=None, derandomize=True,
              suppress_health_check=[HealthCheck.too_slow])
    @given(states())
    def collect(state: Any) -> None:
        svc, target, pace = state
        got = outcome(lambda: reference_check(svc.guard, target, pace))
        seen.add("accepted" if got is None else got[1])

    collect()
    assert {"accepted", "joint_limit", "keep_out", "velocity_limit", "not_homed",
            "invalid_request", "link_down"} <= seen, seen


@settings(max_examples=400, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(states(), st.integers(1, 60), st.integers(0, 2**31 - 1))
def test_the_envelope_finds_the_hit_it_found(state: Any, steps: int, seed: int) -> None:
    """`ArmSafety.first_hit`, its overlapping pairs now found all at once, finds the first hit
    it found (zone, body point, where, when) on random paths, planned-move and pass-through
    shapes alike: a straight path, and one through random poses."""
    svc, target, _pace = state
    env, m = svc.safety, svc.model
    here = np.asarray(svc.driver.positions, dtype=float)
    end = np.where(np.isfinite(target), target, here)
    rng = np.random.default_rng(seed)
    paths = [here + np.linspace(0.0, 1.0, steps)[:, None] * (end - here),
             m.lower + (m.upper - m.lower) * rng.random((steps, m.n))]
    for q in paths:
        t = np.linspace(0.0, 1.0, len(q))
        hit = env.first_hit(q, t)
        got = None if hit is None else (hit.zone, hit.body, hit.point.tolist(), hit.index, hit.t)
        assert got == reference_first_hit(env, q, t)
