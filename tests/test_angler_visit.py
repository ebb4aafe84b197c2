"""examples/angler_visit.py as the design document has it (issue 24, item 9). It runs in the
suite against a live server in tests/test_examples.py (`--quick`, beside the other examples,
whose assertions say the origin is every joint at 0 and dx_used takes theta3 = -90 deg);
here, its data and the design's rule, and each target solvable as the design says."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

from app.arms import model_for
from app.arms.loading import load_profile
from kinematics import pprp

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def _visit():  # type: ignore[no-untyped-def]
    sys.path.insert(0, str(EXAMPLES))
    try:
        import angler_visit
    finally:
        sys.path.remove(str(EXAMPLES))
    return angler_visit


def test_origin_is_every_joint_at_zero_and_dx_used_takes_the_design_theta3() -> None:
    v = _visit()
    assert v.ORIGIN == [0.0, 0.0, 0.0, 0.0]
    for x in (0.03, 0.12, 0.0, -0.03, -0.12):
        assert v.design_theta3(x) == float(pprp.design_theta3(x))
    assert v.design_theta3(0.03) == -math.pi / 2 and v.design_theta3(-0.03) == math.pi / 2


def test_every_target_has_a_solution_within_limits_in_its_case() -> None:
    v = _visit()
    model = model_for(load_profile("angler"))
    for target, case in v.TARGETS:
        opts = model.ik(np.array(target), None, _opts(case, target))
        ok = [s for s in opts if s.within_limits]
        assert ok, (target, case, [s.violations for s in opts])
        if case == "dx_used":
            assert all(abs(s.positions[2] - v.design_theta3(target[0])) < 1e-9 for s in ok)


def test_no_claim_above_the_mx28_no_load_speed() -> None:
    text = (EXAMPLES / "angler_visit.py").read_text()
    assert "0.01 m/s" not in text
    profile = load_profile("angler")
    for j in profile.joints[:2]:  # the x and y carriages
        assert j.max_velocity <= 55.0 / 60.0 * (j.lead_m or 0.0)  # 55 rpm at 12 V, no load


def _opts(case: str, target: tuple[float, float, float]):  # type: ignore[no-untyped-def]
    from app.arms.angler.model import AnglerIK

    theta3 = None if case == "dx_zero" else float(pprp.design_theta3(target[0]))
    return AnglerIK(ik_case=case, theta3=theta3)  # type: ignore[arg-type]
