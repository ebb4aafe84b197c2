"""Kinematics routes against the arm's own model (`service.model`)."""

from __future__ import annotations

import httpx
import numpy as np
import pytest
from fastapi import FastAPI

from app.schemas import ForwardResult, InverseResult, Workspace

API = "/api/v1"


@pytest.mark.parametrize("arm,q", [("rbe3001", [0.3, 0.7, -0.4]),
                                   ("angler", [0.02, 0.01, 0.5, 0.03])])
async def test_forward_matches_the_model(app_and_client: tuple[FastAPI, httpx.AsyncClient],
                                         arm: str, q: list[float]) -> None:
    app, client = app_and_client
    r = await client.post(f"{API}/arms/{arm}/kinematics/forward", json={"positions": q})
    assert r.status_code == 200, r.text
    res = ForwardResult.model_validate(r.json())
    model = app.state.services[arm].model
    assert np.allclose([res.tip.x, res.tip.y, res.tip.z], model.fk(np.array(q)), atol=1e-12)
    assert np.allclose(res.jacobian, model.jacobian(np.array(q)), atol=1e-12)
    assert np.array(res.jacobian).shape == (3, len(q))


async def test_forward_checks_the_joint_count(app_client: httpx.AsyncClient) -> None:
    r = await app_client.post(f"{API}/arms/rbe3001/kinematics/forward", json={"positions": [0, 0]})
    assert r.status_code == 422 and r.json()["code"] == "invalid_request"
    assert "base, shoulder, elbow" in r.json()["detail"]
    r = await app_client.post(f"{API}/arms/rbe3001/kinematics/forward",
                              json={"positions": [1e308, 1e308, 1e308]})
    assert r.status_code in (200, 422)  # finite answer or a 422, never a 500


async def test_inverse_answers_every_branch_flagged(
        app_and_client: tuple[FastAPI, httpx.AsyncClient]) -> None:
    app, client = app_and_client
    p = [0.2, 0.05, 0.15]
    r = await client.post(f"{API}/arms/rbe3001/kinematics/inverse",
                          json={"x": p[0], "y": p[1], "z": p[2]})
    assert r.status_code == 200, r.text
    res = InverseResult.model_validate(r.json())
    assert len(res.solutions) >= 2
    assert [s.branch for s in res.solutions] == list(range(len(res.solutions)))
    assert any(s.within_limits for s in res.solutions)
    model = app.state.services["rbe3001"].model
    for s in res.solutions:
        assert np.allclose(model.fk(np.array(s.positions)), p, atol=1e-9)
        assert s.within_limits == (not s.violations)


async def test_inverse_angler_cases(app_client: httpx.AsyncClient) -> None:
    r = await app_client.post(f"{API}/arms/angler/kinematics/inverse",
                              json={"x": 0.05, "y": 0.1, "z": 0.0, "ik_case": "dx_zero"})
    assert r.status_code == 200, r.text
    assert r.json()["solutions"]


async def test_inverse_unreachable_is_422(app_client: httpx.AsyncClient) -> None:
    r = await app_client.post(f"{API}/arms/rbe3001/kinematics/inverse",
                              json={"x": 1.0, "y": 0, "z": 0.2})
    assert r.status_code == 422
    assert r.json()["code"] == "unreachable" and "reach" in r.json()["detail"]


async def test_workspace_bounds_contain_the_points(app_client: httpx.AsyncClient) -> None:
    for arm in ("rbe3001", "angler"):
        r = await app_client.get(f"{API}/arms/{arm}/workspace", params={"n": 200})
        assert r.status_code == 200
        w = Workspace.model_validate(r.json())
        assert len(w.points) == 200
        pts = np.array([[p.x, p.y, p.z] for p in w.points])
        lo = np.array([w.lower.x, w.lower.y, w.lower.z])
        hi = np.array([w.upper.x, w.upper.y, w.upper.z])
        assert np.all(pts >= lo - 0.01) and np.all(pts <= hi + 0.01)
    r = await app_client.get(f"{API}/arms/rbe3001/workspace")
    assert len(r.json()["points"]) == 500
    for bad in ("0", "5001", "x"):
        r = await app_client.get(f"{API}/arms/rbe3001/workspace", params={"n": bad})
        assert r.status_code == 422 and r.json()["code"] == "invalid_request"
