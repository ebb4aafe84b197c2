"""The cheaper sample (issue 27): derived fields (tip, tip velocity, tip force) computed at the
first read, batched, equal to the single-sample maths; nothing derived when nobody reads."""

from __future__ import annotations

import json

import numpy as np
import pytest
from _wait import wait_for

from app.arms import model_for
from app.arms.loading import load_profile
from app.config import homed_at_start
from app.service import ArmService
from app.telemetry.derive import Derivation, derive
from app.telemetry.hub import TelemetryHub

ARMS = ["rbe3001", "angler", "openmanipulator_x"]


def _single(model, q, qd, tau):
    """What owner.py computed for every sample before issue 27."""
    J = model.jacobian(q)
    v = J @ qd
    force = None
    if tau is not None:
        f = model.tip_force(q, tau, J)
        if f is not None and np.all(np.isfinite(f)):
            force = {"x": float(f[0]), "y": float(f[1]), "z": float(f[2])}
    return model.tip(q), {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}, force


@pytest.mark.parametrize("name", ARMS)
def test_a_batch_derives_what_one_sample_at_a_time_did(name: str) -> None:
    model = model_for(load_profile(name))
    rng = np.random.default_rng(27)
    q = rng.uniform(model.lower, model.upper, size=(40, model.n))
    q[5] = np.clip(np.zeros(model.n), model.lower, model.upper)  # near singular poses too
    q[6] = model.lower
    qd = rng.normal(0.0, 0.5, size=q.shape)
    tau = rng.normal(0.0, 0.3, size=q.shape)
    items = [({}, (q[i], qd[i], tau[i] if i % 3 else None)) for i in range(len(q))]
    derive(model, items)
    nones = 0
    for sample, (qi, qdi, taui) in items:
        tip, tip_v, force = _single(model, qi, qdi, taui)
        assert sample["tip"].keys() == tip.keys()
        for k in tip:
            assert sample["tip"][k] == pytest.approx(tip[k], abs=1e-12)
        for k in "xyz":
            assert sample["tip_velocity"][k] == pytest.approx(tip_v[k], abs=1e-12)
        if force is None:
            nones += 1
            assert sample["tip_force"] is None
        else:
            for k in "xyz":
                assert sample["tip_force"][k] == pytest.approx(force[k], rel=1e-9, abs=1e-9)
    assert nones >= len(items) // 3  # the samples without torques at least


def test_readings_at_rest_reuse_the_last_values() -> None:
    model = model_for(load_profile("rbe3001"))
    calls = []
    derivation = Derivation(lambda: calls.append(1) or model)  # type: ignore[func-returns-value]
    q, qd, tau = np.array([0.1, 0.6, 0.3]), np.zeros(3), np.array([0.01, -0.2, 0.05])
    a: dict[str, object] = {}
    b: dict[str, object] = {}
    derivation([(a, (q, qd, tau))])
    derivation([(b, (q.copy(), qd.copy(), tau.copy()))])
    assert a["tip"] is b["tip"] and a["tip_force"] is b["tip_force"]
    c: dict[str, object] = {}
    derivation([(c, (q + 0.01, qd, tau))])
    assert c["tip"] != a["tip"]


class _Counting:
    """The hub's real deriver, counting the samples it derives."""

    def __init__(self, hub: TelemetryHub) -> None:
        assert hub.deriver is not None
        self.inner, self.count = hub.deriver, 0
        hub.deriver = self

    def __call__(self, items):  # type: ignore[no-untyped-def]
        self.count += len(items)
        self.inner(items)


@pytest.mark.parametrize("name", ARMS)
async def test_nothing_is_derived_that_nobody_reads_and_every_read_sample_is_whole(
        name: str) -> None:
    svc = ArmService(homed_at_start(load_profile(name)))
    await svc.start()
    try:
        await wait_for(lambda: svc.hub.published >= 5, what="samples")
        counting = _Counting(svc.hub)
        start = svc.hub.published
        await wait_for(lambda: svc.hub.published >= start + 20, what="20 more samples")
        assert counting.count == 0  # nobody read them: no kinematics at all
        latest = json.loads(svc.hub.latest_bytes or b"null")
        assert counting.count == 1
        q = np.array(latest["positions"])
        tip = svc.model.tip(q)
        assert latest["tip"] == pytest.approx(tip)
        sub = svc.hub.subscribe()
        try:
            first = svc.hub.published
            await wait_for(lambda: svc.hub.published >= first + 10, what="10 more samples")
            samples, _, dropped = sub.take()
            assert dropped == 0 and len(samples) >= 10
            for text in samples:
                s = json.loads(text)
                assert s["tip"] == pytest.approx(svc.model.tip(np.array(s["positions"])))
                assert set(s["tip_velocity"]) == {"x", "y", "z"}
            assert counting.count <= 1 + len(samples)  # each sample derived once at most
        finally:
            sub.close()
    finally:
        await svc.close()
