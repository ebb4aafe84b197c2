"""What spans workers in a lab (issue 27): a real front with two real workers (the lab of
tests/test_lab_workers.py: left on worker 0, right on worker 1, rails on worker 0).

- Teleoperation whose leader and follower live on different workers runs in the follower's
  worker, reading the leader over its worker's telemetry socket: the follower follows.
- A recording of arms (or cameras) on different workers is refused, 409 `different_workers`;
  one of the second worker's arm and camera records through the front.
- The simulated world of an arm on the second worker is that arm's.
- A leader freed for a session has its torque switched in its own worker.
- A cross-worker session outlives a restart of its leader's worker (last: it kills worker 0).
"""

from __future__ import annotations

import json
import math
import os
import signal
from pathlib import Path
from typing import Any

import httpx
import pytest
from _wait import wait_until
from test_lab_workers import AUTH, INSTRUCTOR, OP, Lab, lab  # noqa: F401 - the fixture

INSTR = {"Authorization": f"Bearer {INSTRUCTOR}"}


def _positions(c: httpx.Client, arm: str) -> list[float]:
    r = c.get(f"/api/v1/arms/{arm}/state")
    assert r.status_code == 200, r.text
    return list(r.json()["positions"])


def test_teleoperation_across_workers(lab: Lab) -> None:  # noqa: F811 - the fixture
    with httpx.Client(base_url=lab.url, headers=OP, timeout=30) as c:
        lease = c.post("/api/v1/arms/right/lease")
        assert lease.status_code in (200, 201), lease.text
        held = {"X-Arm-Lease": lease.json()["id"]}
        try:
            started = c.post("/api/v1/teleop", headers=held, json={
                "leader": "left", "follower": "right", "rate_hz": 50})
            assert started.status_code == 201, started.text
            session = started.json()
            assert (session["leader"], session["follower"]) == ("left", "right")
            # the config's [[teleop]] default for the pair, applied in the follower's worker
            assert session["deadman_s"] == 0.5 and session["rate_hz"] == 50
            target = [0.3, 0.2, 0.1]
            move = c.post("/api/v1/arms/left/move/joints", json={"positions": target})
            assert move.status_code in (200, 202), move.text

            def follows() -> bool:
                return all(math.isclose(a, b, abs_tol=0.02)
                           for a, b in zip(_positions(c, "right"), target, strict=True))

            wait_until(follows, timeout=20, what="the right arm (worker 1) follows the left "
                       "(worker 0)")
            # the lab-wide list has it (from the follower's worker), with its figures
            listed = c.get("/api/v1/teleop", headers=AUTH)
            assert listed.status_code == 200, listed.text
            mine = [t for t in listed.json() if t["id"] == session["id"]]
            assert len(mine) == 1 and mine[0]["status"] == "running"
            assert mine[0]["commands"] > 0 and mine[0]["latency_ms"] is not None
            print("cross-worker teleop latency, ms:", mine[0]["latency_ms"])
            # a second session for the follower is its worker's refusal, as on one server
            other = c.post("/api/v1/teleop", headers=held, json={
                "leader": "rails", "follower": "right"})
            assert other.status_code in (409, 422), other.text
            stopped = c.delete(f"/api/v1/teleop/{session['id']}")
            assert stopped.status_code == 200, stopped.text
            assert stopped.json()["status"] == "ended"
            nobody = c.post("/api/v1/teleop", headers=held, json={
                "leader": "nobody", "follower": "right"})
            assert nobody.status_code == 404, nobody.text
            assert nobody.json() == {"detail": "no arm 'nobody'; this server hosts left, "
                                     "right, rails", "code": "unknown_arm"}
            unknown = c.delete("/api/v1/teleop/t999-nobody")
            assert unknown.status_code == 404 and unknown.json()["code"] == "not_found"
            # the leader's emergency stop, latched in its own worker, ends the session in the
            # follower's (the leader's samples carry the latch)
            again = c.post("/api/v1/teleop", headers=held, json={
                "leader": "left", "follower": "right", "rate_hz": 50})
            assert again.status_code == 201, again.text
            assert c.post("/api/v1/arms/left/estop").status_code == 200
            try:
                def ended() -> Any:
                    listed = c.get("/api/v1/teleop").json()
                    t = next(t for t in listed if t["id"] == again.json()["id"])
                    return t["status"] == "ended" and t["reason"]

                reason = wait_until(ended, what="the session ended by the leader's estop")
                assert "emergency stop on left" in reason
            finally:
                assert c.delete("/api/v1/arms/left/estop").status_code == 200
        finally:
            c.delete(f"/api/v1/arms/right/lease/{held['X-Arm-Lease']}")


def test_a_recording_across_workers_is_refused_one_worker_records(lab: Lab) -> None:  # noqa: F811
    with httpx.Client(base_url=lab.url, headers=OP, timeout=60) as c:
        for arms, cameras in ((["left", "right"], []), (["right"], ["table-left"])):
            r = c.post("/api/v1/recordings", json={"name": "split", "arms": arms,
                                                   "cameras": cameras, "fps": 10})
            assert r.status_code == 409, r.text
            assert r.json()["code"] == "different_workers"
            assert "worker 0" in r.json()["detail"] and "worker 1" in r.json()["detail"]
        assert c.get("/api/v1/recordings/split").status_code == 404  # nothing was made
        made = c.post("/api/v1/recordings", json={"name": "right-demo", "arms": ["right"],
                                                  "cameras": ["table-right"], "fps": 10})
        assert made.status_code == 201, made.text
        assert made.json()["arms"] == ["right"]
        assert c.post("/api/v1/recordings/right-demo/episodes").status_code == 201

        def frames() -> Any:
            current = c.get("/api/v1/recordings/right-demo").json()["current"]
            return current is not None and current.get("frames", 0) >= 5

        wait_until(frames, timeout=20, what="the episode's first frames")
        stopped = c.post("/api/v1/recordings/right-demo/episodes/stop")
        assert stopped.status_code == 200, stopped.text
        assert stopped.json()["episodes"] == 1
        listed = c.get("/api/v1/recordings", headers=AUTH)
        assert listed.status_code == 200
        ours = [r for r in listed.json() if r["id"] == "right-demo"]
        assert len(ours) == 1 and ours[0]["episodes"] == 1 and not ours[0]["recording"]


def test_the_world_of_an_arm_on_the_second_worker(lab: Lab) -> None:  # noqa: F811
    with httpx.Client(base_url=lab.url, headers=INSTR, timeout=30) as c:
        left = c.get("/api/v1/arms/left/world")
        right = c.get("/api/v1/arms/right/world")
        assert left.status_code == 200 and right.status_code == 200, right.text
        scene = {"objects": [{"id": "only-right", "kind": "ball", "color": "red",
                              "position": {"x": 0.15, "y": 0.0, "z": 0.0}}],
                 "bins": right.json()["bins"]}
        put = c.put("/api/v1/arms/right/world", json=scene)
        assert put.status_code == 200, put.text
        assert [o["id"] for o in c.get("/api/v1/arms/right/world").json()["objects"]] == [
            "only-right"]
        assert c.get("/api/v1/arms/left/world").json()["objects"] == left.json()["objects"]
        assert "only-right" not in [o["id"] for o in left.json()["objects"]]


def _torque(c: httpx.Client, arm: str, ids: range, lease: str | None = None) -> list[int]:
    """Torque Enable (64) of `arm`'s servos `ids`, read through the front from its worker
    (with `lease`, the arm's lease id, while one is held)."""
    out = []
    headers = {} if lease is None else {"X-Arm-Lease": lease}
    for i in ids:
        r = c.get(f"/api/v1/arms/{arm}/dynamixel/{i}/registers/torque_enable",
                  headers=headers)
        assert r.status_code == 200, r.text
        out.append(r.json()["raw"])
    return out


def test_a_leader_on_another_worker_is_freed_there_and_given_its_torque_back(
        lab: Lab) -> None:  # noqa: F811 - the fixture
    """A session that frees its leader (`free_leader`) switches the leader's torque in the
    leader's own worker (rails, an angler, on worker 0; the follower right on worker 1): off
    for the session once the body says its winch is held, on again when it ends. That worker
    judges the request: its lease, the winch that falls without torque."""
    servos = range(1, 5)
    body = {"leader": "rails", "follower": "right", "rate_hz": 50, "mapping": "tip",
            "free_leader": True}
    with httpx.Client(base_url=lab.url, headers=OP, timeout=30) as c:
        assert _torque(c, "rails", servos) == [1, 1, 1, 1]
        # the winch falls without torque: refused in the follower's worker, nothing switched
        refused = c.post("/api/v1/teleop", json=body)
        assert refused.status_code == 409 and refused.json()["code"] == "in_use", refused.text
        assert "z falls without torque" in refused.json()["detail"]
        assert _torque(c, "rails", servos) == [1, 1, 1, 1]
        # the leader's lease, held by this client: its worker wants it (X-Leader-Lease)
        lease = c.post("/api/v1/arms/rails/lease")
        assert lease.status_code in (200, 201), lease.text
        lid = lease.json()["id"]
        try:
            leased = c.post("/api/v1/teleop", json={**body, "load_supported": True})
            assert leased.status_code == 409 and leased.json()["code"] == "leased", leased.text
            assert "rails's worker" in leased.json()["detail"]
            assert _torque(c, "rails", servos, lid) == [1, 1, 1, 1]
            assert [t for t in c.get("/api/v1/teleop").json() if t["status"] == "running"] == []
            started = c.post("/api/v1/teleop", headers={"X-Leader-Lease": lid},
                             json={**body, "load_supported": True})
            assert started.status_code == 201, started.text
            sid = started.json()["id"]
            assert started.json()["free_leader"] is True
            try:
                assert _torque(c, "rails", servos, lid) == [0, 0, 0, 0]
                # the leader's lease given up mid-session: its torque still comes back at the
                # end (torque on, holding, needs no lease)
                released = c.delete(f"/api/v1/arms/rails/lease/{lid}")
                assert released.status_code in (200, 204), released.text
            finally:
                stopped = c.delete(f"/api/v1/teleop/{sid}")
            assert stopped.status_code == 200 and stopped.json()["status"] == "ended"
            # given back as the session ended (the follower's worker asked the leader's)
            wait_until(lambda: _torque(c, "rails", servos) == [1, 1, 1, 1],
                       what="the leader's torque on again in its own worker")
        finally:
            c.delete(f"/api/v1/arms/rails/lease/{lid}")


def test_a_cross_worker_session_outlives_its_leaders_worker(lab: Lab) -> None:  # noqa: F811
    """The leader's worker killed mid-session: the follower holds (the deadman: no sample
    comes), the session goes on, and once the worker is back its socket is opened again and
    the follower follows the restarted leader."""
    with httpx.Client(base_url=lab.url, headers=OP, timeout=30) as c:
        started = c.post("/api/v1/teleop", json={"leader": "left", "follower": "right",
                                                 "rate_hz": 50})
        assert started.status_code == 201, started.text
        sid = started.json()["id"]

        def session() -> dict[str, Any]:
            listed = c.get("/api/v1/teleop").json()
            return next(t for t in listed if t["id"] == sid)

        try:
            wait_until(lambda: session()["commands"] > 10, what="the session commanding")
            before = lab.workers()
            os.kill(before[0], signal.SIGKILL)  # the left arm's worker
            holds = session()["holds"]
            wait_until(lambda: session()["holds"] > holds + 10, timeout=20,
                       what="the follower holding while its leader is gone")
            wait_until(lambda: lab.workers().get(0) not in (None, before[0])
                       and c.get("/api/v1/arms/left/state").status_code == 200,
                       timeout=30, what="the left arm back on a new worker 0")
            assert session()["status"] == "running"
            target = [-0.25, 0.15, 0.2]
            move = c.post("/api/v1/arms/left/move/joints", json={"positions": target})
            assert move.status_code in (200, 202), move.text
            wait_until(lambda: all(math.isclose(a, b, abs_tol=0.02) for a, b in zip(
                _positions(c, "right"), target, strict=True)), timeout=30,
                what="the right arm following the restarted left arm")
        finally:
            c.delete(f"/api/v1/teleop/{sid}")


async def test_the_front_places_by_the_arms_named(tmp_path: Path) -> None:
    """app/lab/across.py on its own: the plan of the lab's config, a data folder of its own."""
    from conftest import make_settings
    from test_lab_workers import CONFIG

    from app.errors import DifferentWorkers
    from app.lab.across import Across
    from app.lab.placement import plan_lab

    config = tmp_path / "lab.toml"
    config.write_text(CONFIG)
    across = Across(plan_lab(make_settings(config=str(config)), 2), str(tmp_path / "data"))
    assert await across.place("POST", "/api/v1/teleop", b'{"follower": "right"}') == 1
    assert await across.place("POST", "/api/v1/teleop", b'{"follower": "rails"}') == 0
    for body in (b"not json", b"[1]", b'{"follower": 3}', b'{"follower": "nobody"}'):
        assert await across.place("POST", "/api/v1/teleop", body) is None  # a worker's 4xx
    rec = b'{"name": "x", "arms": ["right"], "cameras": ["table-right"]}'
    assert await across.place("POST", "/api/v1/recordings", rec) == 1
    with pytest.raises(DifferentWorkers, match="worker 0: arm left; worker 1: arm right"):
        await across.place("POST", "/api/v1/recordings", b'{"arms": ["left", "right"]}')
    # a dataset's worker from its settings file; an id that is no dataset name reads nothing
    folder = tmp_path / "data" / "recordings" / "demo"
    folder.mkdir(parents=True)
    (folder / "armserver.json").write_text(json.dumps({"arms": ["right"]}))
    (tmp_path / "data" / "armserver.json").write_text(json.dumps({"arms": ["right"]}))
    assert await across.place("GET", "/api/v1/recordings/demo/archive", b"") == 1
    for rid in ("..", ".hidden", "nobody"):
        assert await across.dataset_owner(rid) is None
    # a dataset made across today's workers (by a single server): read anywhere, recorded nowhere
    split = tmp_path / "data" / "recordings" / "both"
    split.mkdir()
    (split / "armserver.json").write_text(json.dumps({"arms": ["left"],
                                                      "cameras": ["table-right"]}))
    assert await across.place("GET", "/api/v1/recordings/both", b"") == 0
    with pytest.raises(DifferentWorkers, match="worker 0: arm left; worker 1: camera table-r"):
        await across.place("POST", "/api/v1/recordings/both/episodes", b"")
    # each dataset once, as its arms' worker lists it
    stale = {"id": "demo", "arms": ["right"], "episodes": 0}
    fresh = {"id": "demo", "arms": ["right"], "episodes": 2}
    mine = {"id": "a", "arms": ["left"], "episodes": 1}
    assert across.merge_recordings({0: [stale, mine], 1: [fresh]}) == [mine, fresh]
    sessions = {0: [{"id": "e", "status": "ended", "started": 1.0}],
                1: [{"id": "r", "status": "running", "started": 2.0}]}
    assert [t["id"] for t in across.merge_teleop(sessions)] == ["r", "e"]
