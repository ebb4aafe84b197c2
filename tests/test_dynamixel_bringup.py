"""Issue 24's day-one items on the simulated hardware: the inverse-velocity route (design
document section 4.2) checked against finite differences of the forward kinematics, and its
422 near a singularity."""

from __future__ import annotations

import httpx
import numpy as np
import pytest

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
