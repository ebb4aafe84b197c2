"""Gravity on a simulated arm's joints whose servos' torque is off.

A real joint the profile says falls without torque (`falls_without_torque`: the angler's z
winch pays its load out, an OpenManipulator-X folds at the shoulder, elbow and wrist) moves
once its servo's Torque Enable (64) is 0: the e-manual's "Torque OFF (Free-run) and the motor
does not generate torque", and nothing else holds a geared servo's horn against the load. The
simulated bus of such an arm (`app.arms.dynamixel.simulated_bus`) moves those joints too, so
a simulated arm with its torque off is not a safer arm than a real one.

The model is the heaviest damping there is (a geared motor back-driven: no momentum): each
free falling joint moves down the slope of the arm's potential at a speed proportional to
the slope, capped (`MAX_SPEED`), until a joint limit stops it (the arm against its stop, the
load on the floor) or the slope is too small to overcome the gearbox's friction (`FRICTION`:
an arm balanced over its shoulder stays). The potential is that of equal weights at every
body point after the base (`KinematicsModel.joint_origins`), the gravity fit's basis
(app/calibration/gravity.py): a direction and a rough size, not a fitted arm. A joint the
profile does not mark (a base turning about the vertical, a carriage on a horizontal screw)
does not move; neither does one whose servo holds torque, or any while something holds the
arm (`held`: the world's hand on it, app/sim/hand.py).

The simulated arm starts at rest where it is (its start pose is taken as where it came to
rest before power-up: on its stops, a stand, the load on the floor), so a joint falls only
once its servo has held torque since: lifted off its rest by its own motor, it falls when
that torque goes off (torque off, a shutdown, a reboot, the bus's power cut).

Units: joint units (rad, m) for the slope and the speeds, servo ticks on the bus (through the
arm's transmission). Runs in the bus's `advance`, on the device's clock.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from app.arms import model_for
from app.calibration.gravity import basis
from app.config import ArmProfile

#: Joint speed per unit of slope (1/s: rad/s per m/rad of the summed body points' height).
GAIN = 4.0
#: The fastest a joint falls: rad/s for a revolute joint, m/s for a prismatic one.
MAX_SPEED = {"revolute": 1.0, "prismatic": 0.1}
#: The slope (m/rad or m/m) below which the gearbox's friction holds the joint.
FRICTION = 0.005


class Gravity:
    """Gravity on `bus`'s servos of `profile`'s falling joints (by their `motor_id`)."""

    def __init__(self, profile: ArmProfile, bus: Any) -> None:
        self.model = model_for(profile)
        self.bus = bus
        self.ids = [None if j.motor_id is None else int(j.motor_id) for j in profile.joints]
        self.falls = [k for k, j in enumerate(profile.joints)
                      if j.falls_without_torque and j.motor_id is not None]
        self.cap = np.array([MAX_SPEED[j.kind] for j in profile.joints])
        #: Something holds the arm (the world's hand): nothing falls.
        self.held = False
        #: Per joint: its servo has held torque since the start (lifted off its rest).
        self._lifted = [False] * len(self.ids)
        self._last: float | None = None  # device time of the last step with a joint free

    def free(self) -> list[int]:
        """The falling joints whose servo answers with its torque off now, having held it
        since the start."""
        out = []
        lifted = self._lifted
        for k in self.falls:
            s = self.bus.servo(self.ids[k])
            if s is None:
                continue
            if s.torque:
                lifted[k] = True
            elif lifted[k]:
                out.append(k)
        return out

    def step(self, now: float) -> None:
        """Move the free falling joints from the last step to `now` (device clock, s)."""
        free = self.free()  # (each call notes the servos' torque)
        if self.held or not free:
            self._last = None
            return
        last, self._last = self._last, now
        found = [None if i is None else self.bus.servo(i) for i in self.ids]
        servos: list[Any] = [x for x in found if x is not None]
        if last is None or now <= last or len(servos) != len(found):
            return
        m = self.model
        tr = m.transmission
        dt = now - last
        q = np.array(tr.from_ticks([x.pos for x in servos]), dtype=np.float64)
        slope = basis(m, q).sum(axis=1)  # d(height summed over the body points)/dq
        v = np.zeros_like(q)
        for k in free:
            if abs(slope[k]) > FRICTION:
                v[k] = -float(np.clip(GAIN * slope[k], -self.cap[k], self.cap[k]))
        unbound = q + v * dt
        target = np.clip(unbound, m.lower, m.upper)
        v = np.where(target == unbound, v, 0.0)  # against a stop: at rest there
        ticks, tps = tr.to_ticks(target), tr.velocity_to_ticks(v)
        for k in free:
            if v[k] == 0.0 and target[k] == q[k]:
                continue  # at rest already: its items as they are
            servos[k].carry(ticks[k], tps[k], now)
