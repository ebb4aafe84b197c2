"""Issue 24's day-one items on the simulated hardware: the inverse-velocity route (design
document section 4.2) checked against finite differences of the forward kinematics, and its
422 near a singularity; stale queue entries dropped at start."""

from __future__ import annotations

import logging
from pathlib import Path

import httpx
import numpy as np
import pytest

from tests.conftest import make_settings, running_client

API = "/api/v1"

STEP = 1e-6  # joint step of the finite differences, rad or m


async def _fk(client: httpx.AsyncClient, arm: str, q: np.ndarray) -> np.ndarray:
    r = await client.post(f"{API}/arms/{arm}/kinematics/forward",
                          json={"positions": [float(v) for v in q]})
    assert r.status_code == 200, r.text
    tip = r.json()["tip"]
    return np.array([tip["x"], tip["y"], tip["z"]])


@pytest.mark.parametrize(("arm", "q", "v"), [
    ("rbe3001", [0.3, 0.6, -0.4], [0.01, -0.02, 0.015]),
    ("angler", [0.01, -0.02, 0.5, 0.05], [0.002, -0.001, 0.003]),
])
async def test_inverse_velocity_matches_finite_differences_of_fk(
        app_client: httpx.AsyncClient, arm: str, q: list[float], v: list[float]) -> None:
    r = await app_client.post(f"{API}/arms/{arm}/kinematics/inverse-velocity",
                              json={"positions": q, "velocity": dict(zip("xyz", v, strict=True))})
    assert r.status_code == 200, r.text
    body = r.json()
    qd = np.array(body["velocities"])
    assert qd.shape == (len(q),)
    # the tip moves at v when the joints move at qd: (fk(q + h qd) - fk(q - h qd)) / 2h
    q0 = np.array(q)
    dt = STEP / max(float(np.max(np.abs(qd))), 1e-9)
    tip_rate = (await _fk(app_client, arm, q0 + dt * qd)
                - await _fk(app_client, arm, q0 - dt * qd)) / (2 * dt)
    np.testing.assert_allclose(tip_rate, v, atol=1e-6)
    assert body["condition"] >= 1.0
    tv = body["tip_velocity"]
    np.testing.assert_allclose([tv["x"], tv["y"], tv["z"]], v, atol=1e-12)
    if arm == "angler":  # four joints, three tip coordinates: the least-norm solution
        jac = np.array((await app_client.post(
            f"{API}/arms/{arm}/kinematics/forward", json={"positions": q})).json()["jacobian"])
        np.testing.assert_allclose(qd, jac.T @ np.linalg.solve(jac @ jac.T, v), atol=1e-12)


async def test_inverse_velocity_near_a_singularity_is_422_with_the_reason(
        app_client: httpx.AsyncClient) -> None:
    # rbe3001 stretched out (q3 = 90 deg: links 2 and 3 in line): the Jacobian loses rank
    r = await app_client.post(f"{API}/arms/rbe3001/kinematics/inverse-velocity",
                              json={"positions": [0.0, 0.5, 1.5707963267948966],
                                    "velocity": {"x": 0.01, "y": 0.0, "z": 0.0}})
    assert r.status_code == 422, r.text
    assert r.json()["code"] == "unreachable"
    assert "near a singularity" in r.json()["detail"]
    r = await app_client.post(f"{API}/arms/rbe3001/kinematics/inverse-velocity",
                              json={"positions": [0.0, 0.5], "velocity": {"x": 0, "y": 0, "z": 0}})
    assert r.status_code == 422, r.text


# ------------------------------------------------------------------ stale queue (item 11)

ALICE, BOB, TEACH = "tok-alice-1", "tok-bob-2", "tok-teach-4"


def _h(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


async def test_queue_entries_of_names_no_token_has_are_dropped_at_start(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A data folder left by a server with tokens: on start, an entry of a name no current
    token has is dropped and logged; an open server keeps none, and answers a move, not 409
    `leased`."""
    data = str(tmp_path / "data")
    tokened = {"operator_tokens": f"alice:{ALICE},bob:{BOB}", "instructor_tokens":
               f"teach:{TEACH}", "claim_s": 30.0, "slot_s": 60.0, "data_dir": data}
    arm = "rbe3001"
    async with running_client(make_settings(**tokened)) as (_, c):
        a = (await c.post(f"{API}/arms/{arm}/queue", headers=_h(ALICE))).json()
        b = (await c.post(f"{API}/arms/{arm}/queue", headers=_h(BOB))).json()
        assert a["name"] == "alice" and b["name"] == "bob"
    # alice's token is gone: her entry is dropped, bob's kept
    bob_only = {**tokened, "operator_tokens": f"bob:{BOB}"}
    with caplog.at_level(logging.WARNING, logger="app.classroom.queue"):
        async with running_client(make_settings(**bob_only)) as (_, c):
            q = (await c.get(f"{API}/arms/{arm}/queue", headers=_h(TEACH))).json()
            assert [e["name"] for e in q["entries"]] == ["bob"]
    assert any("'alice' dropped" in r.getMessage() and "no current token" in r.getMessage()
               for r in caplog.records)
    # an open server (the same data folder, `make run`): no queue, and a move is answered
    async with running_client(make_settings(data_dir=data, claim_s=30.0)) as (app, c):
        q = (await c.get(f"{API}/arms/{arm}/queue")).json()
        assert q["entries"] == []
        here = [float(v) for v in app.state.services[arm].driver.positions]
        r = await c.post(f"{API}/arms/{arm}/move/joints", json={"positions": here, "wait": True})
        assert r.status_code == 200, r.text
        assert r.json()["status"] == "done"
