"""When a motion is done: the measured joints settle at the target and the actuators say they
have arrived, or the device tells why they cannot (a hardware fault, torque off, a silent
device, a lost link). Reads the arm only through its `Actuator`; the executor acts on the
verdict (finish the motion, or the watchdog: fail it and hold the arm).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Sequence
from typing import Literal

import numpy as np

from app.device.actuator import Actuator
from app.errors import ArmError, Fault, LinkDown, NotSettled, TorqueOff
from app.links.base import LinkState

#: How long a finished trajectory may take to settle before the motion fails, s.
SETTLE_TIMEOUT_S = 2.0
#: How often the joints are looked at while they settle, s (every arm type polls faster).
SETTLE_CHECK_S = 0.01
#: Checks in a row, SETTLE_CHECK_S apart, that must find every joint in tolerance before the
#: actuators are asked: an arm in position for a dwell, not one reading that says so. A reading
#: the link corrupted (the rbe3001's packets carry no checksum; a byte changed within the
#: driver's jump bound is published) could otherwise end a motion `done` a poll early, with
#: the arm still on its way (bench/soak.py's 2 % corruption showed such a reading).
SETTLE_CONFIRM = 2

#: done; halted (stopped meanwhile: nothing to do); watchdog (the device says the motion
#: cannot end well: fail it and hold); failed (it did not settle in time: fail it).
Verdict = tuple[Literal["done", "halted", "watchdog", "failed"], ArmError | None]


class Settle:
    """Waits for one arm's joints to settle."""

    def __init__(self, arm: str, names: Sequence[str], device: Actuator) -> None:
        self.arm = arm
        self.names = list(names)
        self.device = device

    async def wait(self, target: np.ndarray, tol: np.ndarray,
                   halted: Callable[[], bool]) -> Verdict:
        """`done` only when every joint is within its settle tolerance of where it was sent
        at SETTLE_CONFIRM checks in a row and its actuator holds torque and says it has
        arrived (where it tells: Dynamixel Moving / Moving Status); a joint without torque
        fails the motion at once."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + SETTLE_TIMEOUT_S
        err = np.full(len(self.names), np.inf)
        moving = await self._arrived()  # a joint without torque fails at once
        if isinstance(moving, ArmError):
            return "watchdog", moving
        inside = 0  # checks in a row that found every joint in tolerance
        worst = err  # per joint, the larger error of the last two checks (for the reason)
        looks = 0
        # (at least SETTLE_CONFIRM looks, however late: a process held up past the deadline
        # before its first look had failed the motion on no reading at all, "inf off")
        while loop.time() < deadline or looks < SETTLE_CONFIRM:
            looks += 1
            if halted():
                return "halted", None
            fault = self.device_fault()
            if fault is not None:  # silent device or lost link: say so, not "did not settle"
                return "watchdog", fault
            q = self.device.positions
            if q is None or self.device.stale:
                inside = 0
            else:
                last, err = err, np.abs(q - target)
                worst = np.maximum(last, err) if np.all(np.isfinite(last)) else err
                inside = inside + 1 if np.all(err <= tol) else 0
            if inside >= SETTLE_CONFIRM:
                verdict = await self._arrived()
                if isinstance(verdict, ArmError):
                    return "watchdog", verdict
                moving = verdict
                if not moving:
                    return "done", None
            await asyncio.sleep(SETTLE_CHECK_S)
        if moving and np.all(worst <= tol):
            names = ", ".join(self.names[k] for k in moving)
            reason = f"{names} within tolerance but its servo still reports moving"
        else:  # the worse of the last two checks: a joint that only flickers into tolerance
            k = int(np.argmax(worst / tol))
            reason = f"{self.names[k]} is {worst[k]:.6f} off (tolerance {tol[k]:.6f})"
        return "failed", NotSettled(f"did not settle at the target within {SETTLE_TIMEOUT_S} s: "
                                    f"{reason}")

    async def _arrived(self) -> tuple[int, ...] | ArmError:
        """The joints whose actuator still says it is moving; or why the motion must fail
        (a hardware fault, or a joint whose servo holds no torque: it can never be done)."""
        dev = self.device
        if dev.faults:
            f = dev.faults[0]
            return Fault(f"servo {f['servo']} ({f['joint']}) reports a hardware fault: "
                         f"{', '.join(f['bits']) or 'alert'}; {f['advice']}")
        try:
            st = await dev.settle_state()
        except ArmError:
            return tuple(range(len(self.names)))  # not known now: ask again on the next round
        if st.torque_off:
            names = ", ".join(self.names[k] for k in st.torque_off)
            return TorqueOff(
                f"{names}: the servo holds no torque (torque off after a reboot or a fault, or "
                f"switched off), so the joint cannot be at its target; switch it on with PUT "
                f'/api/v1/arms/{self.arm}/torque {{"on": true}} or reboot it with POST '
                f"/api/v1/arms/{self.arm}/dynamixel/{{id}}/reboot, either holding where the "
                f"joint is")
        return st.moving

    def device_fault(self) -> ArmError | None:
        """Why the device cannot be followed now (lost link, stale polls), or None."""
        drv = self.device
        if drv.link.state is not LinkState.UP:
            return LinkDown(f"{self.arm} link lost: {drv.link.last_error or 'down'}")
        return drv.stale_error
