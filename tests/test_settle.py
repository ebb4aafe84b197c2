"""The settle check (app/motion/settle.py) ends a motion `done` on the joints in tolerance at
SETTLE_CONFIRM checks in a row, not on one reading: a reading the link corrupted into the
tolerance (the rbe3001's packets carry no checksum) must not end a motion with the arm still
on its way. The device here is a scripted `Actuator` (its protocol is what motion reads of a
device: app/device/actuator.py), each look at `positions` the next reading of the script."""

from __future__ import annotations

import asyncio
from collections.abc import Sequence

import numpy as np
import pytest

from app.device.actuator import SettleState
from app.links.base import LinkState
from app.motion import settle
from app.motion.settle import SETTLE_CONFIRM, Settle

TARGET = np.array([0.5, 0.6, 0.3])
TOL = np.full(3, 0.01)
FAR = TARGET + np.array([0.2, 0.0, 0.0])  # on its way
NEAR = TARGET + 0.002  # in tolerance


class _Link:
    state = LinkState.UP
    last_error = None


class ScriptedArm:
    """A device whose readings are `script`, one per look; the last one repeats."""

    def __init__(self, script: Sequence[np.ndarray]) -> None:
        self.script = list(script)
        self.looks = 0
        self.asked = 0  # settle_state calls
        self.link = _Link()
        self.stale = False
        self.stale_error = None
        self.faults: list[dict[str, object]] = []

    @property
    def positions(self) -> np.ndarray:
        k = min(self.looks, len(self.script) - 1)
        self.looks += 1
        return self.script[k]

    async def settle_state(self) -> SettleState:
        self.asked += 1
        return SettleState()


class LateArm(ScriptedArm):
    """The same, whose first `settle_state` answers after the settle timeout (a process held
    up before the settle loop's first look)."""

    async def settle_state(self) -> SettleState:
        if self.asked == 0:
            await asyncio.sleep(settle.SETTLE_TIMEOUT_S + 0.1)
        return await super().settle_state()


def test_two_checks_in_a_row_are_the_rule() -> None:
    assert SETTLE_CONFIRM == 2


async def test_one_reading_in_tolerance_among_far_ones_does_not_end_the_motion() -> None:
    # far, one corrupted reading near the target, far again, then the arm arrives
    arm = ScriptedArm([FAR, NEAR, FAR, FAR, NEAR, NEAR, NEAR])
    verdict, err = await Settle("rbe3001", ["base", "shoulder", "elbow"], arm).wait(
        TARGET, TOL, lambda: False)
    assert (verdict, err) == ("done", None)
    # done at the second of the two readings in a row (the 6th look), not at the 2nd
    assert arm.looks == 6
    assert arm.asked == 2  # once before the loop (torque), once when it settled


async def test_an_arm_at_the_target_is_done_on_its_second_check() -> None:
    arm = ScriptedArm([NEAR])
    verdict, _ = await Settle("rbe3001", ["base", "shoulder", "elbow"], arm).wait(
        TARGET, TOL, lambda: False)
    assert verdict == "done" and arm.looks == SETTLE_CONFIRM


async def test_a_settle_held_up_past_its_deadline_still_looks_before_its_verdict(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Held up past the settle timeout before its first look, the check still takes
    SETTLE_CONFIRM readings: an arm at the target is done, one on its way fails naming how
    far off it is (it had failed on no reading, "inf off", in a loaded clean clone)."""
    monkeypatch.setattr(settle, "SETTLE_TIMEOUT_S", 0.2)
    arm = LateArm([NEAR])
    verdict, err = await Settle("rbe3001", ["base", "shoulder", "elbow"], arm).wait(
        TARGET, TOL, lambda: False)
    assert (verdict, err) == ("done", None) and arm.looks == SETTLE_CONFIRM
    arm = LateArm([FAR])
    verdict, err = await Settle("rbe3001", ["base", "shoulder", "elbow"], arm).wait(
        TARGET, TOL, lambda: False)
    assert verdict == "failed" and err is not None and "base is 0.200000 off" in str(err)
    assert arm.looks == SETTLE_CONFIRM


@pytest.mark.parametrize("far_first", [True, False])
async def test_readings_that_only_flicker_into_tolerance_fail_the_motion(
        monkeypatch: pytest.MonkeyPatch, far_first: bool) -> None:
    # the reason names the worse of the last two checks, whichever came last
    monkeypatch.setattr(settle, "SETTLE_TIMEOUT_S", 0.3)
    arm = ScriptedArm([FAR, NEAR] * 200 if far_first else [NEAR, FAR] * 200)
    verdict, err = await Settle("rbe3001", ["base", "shoulder", "elbow"], arm).wait(
        TARGET, TOL, lambda: False)
    assert verdict == "failed" and err is not None
    assert err.code == "not_settled"
    assert "base is 0.200000 off" in str(err)
    assert arm.asked == 1  # never asked whether it arrived: never two in a row
