"""Property tests of the safety envelope on both arms, through the motion executor's own
planners (the plan a move request gets) and an independent oracle here:

- no accepted motion has any sampled point (every setpoint the executor will command, at the
  control rate) of any checked body point inside a zone, grown by that point's margin, or
  below the floor;
- every refused one names a zone (or the floor) that its path does enter, and the body point
  and time it names are the first such.

And in telemetry: with speed_override 0.25 the measured peak joint speed of a long move is at
most 0.25 of the joint's limit plus the controller's tracking error (stated below).
"""

from __future__ import annotations

import re
from typing import Any

import numpy as np
import pytest
from _wait import new_samples
from conftest import running_client
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from app import schemas as s
from app.arms.loading import load_profile
from app.config import KeepOutBox, SafetySettings
from app.errors import ArmError
from app.safety.envelope import KeepOut
from app.service import ArmService
from kinematics.trajectory import time_grid

SERVICES = {name: ArmService(load_profile(name)) for name in ("rbe3001", "angler")}
#: Where the arms reach, m (a box around each workspace, for random zones).
REACH = {"rbe3001": (np.array([-0.4, -0.4, -0.1]), np.array([0.4, 0.4, 0.6])),
         "angler": (np.array([-0.2, -0.2, -0.06]), np.array([0.2, 0.2, 0.1]))}

unit = st.floats(0.0, 1.0, allow_nan=False)


@st.composite
def scenario(draw: st.DrawFn, arm: str) -> dict[str, Any]:
    svc = SERVICES[arm]
    m = svc.model
    lo, hi = REACH[arm]
    zones = []
    for i in range(draw(st.integers(1, 3))):
        c = lo + (hi - lo) * np.array([draw(unit) for _ in range(3)])
        h = (hi - lo) * np.array([draw(st.floats(0.02, 0.2)) for _ in range(3)])
        zones.append(KeepOutBox.model_validate(
            {"name": f"z{i}", "min": dict(zip("xyz", (c - h).tolist(), strict=True)),
             "max": dict(zip("xyz", (c + h).tolist(), strict=True))}))
    floor = draw(st.none() | st.floats(float(lo[2]), float(lo[2] + 0.1)))
    q0 = m.lower + (m.upper - m.lower) * np.array([draw(unit) for _ in range(m.n)])
    q1 = m.lower + (m.upper - m.lower) * np.array([draw(unit) for _ in range(m.n)])
    return {"zones": zones, "floor": floor, "q0": q0, "q1": q1,
            "line": draw(st.booleans()), "speed": draw(st.sampled_from([1.0, 0.5]))}


def oracle(svc: ArmService, q: np.ndarray, zones: list[KeepOutBox],
           floor: float | None) -> list[tuple[int, str, str]]:
    """Every (sample index, zone or "floor", body point) with a point inside, written
    plainly: a loop over zones and body points, the box grown by each point's margin."""
    pts = svc.safety.points(q)  # (T, B, 3); chain is tested against fk in test_chain.py
    margins = svc.safety.margins
    found = []
    for b, body in enumerate(svc.safety.bodies):
        m = margins[b]
        for z in zones:
            lo = np.array([z.min.x, z.min.y, z.min.z]) - m
            hi = np.array([z.max.x, z.max.y, z.max.z]) + m
            inside = np.all((pts[:, b] >= lo) & (pts[:, b] <= hi), axis=-1)
            found += [(int(i), z.name, body) for i in np.flatnonzero(inside)]
        if floor is not None:
            found += [(int(i), "floor", body) for i in np.flatnonzero(pts[:, b, 2] < floor + m)]
    return sorted(found)


def check(arm: str, sc: dict[str, Any]) -> None:
    svc = SERVICES[arm]
    svc.safety.apply(SafetySettings(zones=sc["zones"], floor_z=sc["floor"]), "stored")
    q0 = sc["q0"]
    start = (q0, np.zeros_like(q0), np.zeros_like(q0))
    dt = 1.0 / svc.profile.link.control_hz
    try:
        if sc["line"]:
            p = svc.model.fk(sc["q1"])
            req = s.MovePose(x=p[0], y=p[1], z=p[2], path="line", speed=sc["speed"])
            plan = svc.motion._plan_pose_from(start, p, req, True)
        else:
            req = s.MoveJoints(positions=sc["q1"].tolist(), speed=sc["speed"])
            plan = svc.motion._plan_joint_from(start, sc["q1"], req, True)
    except KeepOut as exc:
        refused = exc.detail
    except ArmError:
        assume(False)  # unreachable, joint limits: not this property's business
        return
    else:
        refused = None
    if refused is None:
        t = time_grid(plan.traj.duration, dt)
        q = np.asarray(plan.traj.sample(t)[0])
        assert oracle(svc, q, sc["zones"], sc["floor"]) == [], "an accepted motion enters"
        return
    # refused: the same plan without the envelope, sampled the same way, enters what it names
    svc.safety.apply(SafetySettings(), "stored")
    if sc["line"]:
        plan = svc.motion._plan_pose_from(start, svc.model.fk(sc["q1"]), req, True)
    else:
        plan = svc.motion._plan_joint_from(start, sc["q1"], req, True)
    t = time_grid(plan.traj.duration, dt)
    hits = oracle(svc, np.asarray(plan.traj.sample(t)[0]), sc["zones"], sc["floor"])
    assert hits, f"refused, but the path enters nothing: {refused}"
    named = re.search(r"zone '([^']+)'", refused)
    zone = named.group(1) if named else ("floor" if "below the floor" in refused else None)
    body = refused.split()[1]
    at = float(re.search(r"m, ([0-9.]+) s into the motion", refused).group(1))  # type: ignore[union-attr]
    first = hits[0][0]
    assert (first, zone, body) in hits, (refused, hits[:5])
    assert at == pytest.approx(t[first], abs=0.006), (refused, t[first])


@pytest.mark.parametrize("arm", ["rbe3001", "angler"])
def test_accepted_motions_stay_out_and_refusals_name_a_zone_the_path_enters(arm: str) -> None:
    @settings(max_examples=30, deadline=None, derandomize=True,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
    @given(scenario(arm))
    def prop(sc: dict[str, Any]) -> None:
        check(arm, sc)

    prop()


#: The simulated rbe3001's tracking error in joint speed, stated: its firmware PID (P on the
#: position error, 400 Hz) follows the 100 Hz setpoint stream with a lag, static friction holds
#: a joint until the error has built up, and the simulated firmware steps its physics in bursts
#: when its thread runs late; each makes the joint move faster than commanded for a moment to
#: catch up. Measured on this move at 0.25 (limit 0.375 rad/s): base and elbow 0.05..0.12
#: rad/s over on an idle host, up to 0.25 rad/s over on a loaded one (load average 7 on 2
#: cores); the gravity-loaded shoulder least. The bound is 0.3 rad/s. The commanded speeds, which
#: speed_override governs, are held to the scaled limit exactly. The test prints both.
TRACKING_RAD_S = 0.3


# Serial (tests/conftest.py), as its twin in test_tracking.py: a measured speed; two busy
# workers hold control ticks up and the PID catching up after one overshoots.
@pytest.mark.serial
async def test_speed_override_caps_the_measured_joint_speed_in_telemetry() -> None:
    async with running_client() as (app, client):
        svc = app.state.services["rbe3001"]
        r = await client.put("/api/v1/arms/rbe3001/safety", json={"speed_override": 0.25})
        assert r.status_code == 200
        seen: list[list[float]] = []
        commanded: list[np.ndarray] = []

        def listen(sample: dict[str, Any]) -> None:
            seen.append(sample["velocities"])
            cmd = svc.motion._cmd
            if cmd is not None:
                commanded.append(np.abs(cmd[1]))

        off = svc.hub.add_listener(listen)
        try:
            q1 = [1.2, 1.0, 1.2]
            r = await client.post("/api/v1/arms/rbe3001/move/joints",
                                  json={"positions": q1, "wait": True})
            assert r.status_code == 200 and r.json()["status"] == "done", r.text
            await new_samples(svc.hub, 50)  # 0.1 s at 500 Hz: any overshoot after the plan
        finally:
            off()
        peak = np.abs(np.array(seen)).max(axis=0)
        peak_cmd = np.array(commanded).max(axis=0)
        cap = 0.25 * svc.model.vmax
        print(f"\npeak joint speed at speed_override 0.25: measured {np.round(peak, 3).tolist()}"
              f" rad/s, commanded {np.round(peak_cmd, 3).tolist()} rad/s, limit x 0.25 = "
              f"{cap.tolist()} rad/s ({len(seen)} samples)")
        assert len(seen) > 100
        assert np.all(peak_cmd <= cap * (1 + 1e-6)), (peak_cmd, cap)
        # it did run at the scaled limit, planned at the profile's tracking margin of it
        assert peak_cmd.max() >= 0.95 * svc.profile.tracking_margin * cap.max()
        assert np.all(peak <= cap + TRACKING_RAD_S), (peak, cap)
