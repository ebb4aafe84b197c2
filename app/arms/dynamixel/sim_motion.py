"""The motion of one simulated MX-28: a profile generator and a motor that follows it.

In the position modes the profile generator turns Goal Position, Profile Velocity and
Profile Acceleration into a trajectory as the e-manual's Profile Velocity(112) section
describes (Profile Velocity 0: step, no profile; Profile Acceleration 0: rectangular;
otherwise triangular or trapezoidal by the travel distance). The motor follows that
trajectory exactly while it can, and never turns faster than `cap` (the no-load speed at the
supply voltage, given by the servo): a trajectory faster than that leaves the motor behind
and sets the Following Error bit. In velocity mode the generator ramps to the goal velocity
under Profile Acceleration (0: step) and the motor follows within the same cap.

Everything is in ticks and seconds, integrated in steps of at most `STEP_S`; deterministic.
"""

from __future__ import annotations

import math

from protocol import mx28

#: integration step, s
STEP_S = 0.001
#: lag behind the trajectory (ticks) beyond which Moving Status reports a following error;
#: the e-manual gives no figure: 20 ticks is 1.8 deg, well above tracking noise of a real servo
FOLLOWING_ERROR_TICKS = 20.0


def profile_type(pv_raw: float, pa_raw: float, distance: float) -> int:
    """Moving Status profile-type bits for a move of `distance` ticks (e-manual table)."""
    if pv_raw <= 0:
        return mx28.PROFILE_STEP
    if pa_raw <= 0:
        return mx28.PROFILE_RECTANGULAR
    v_tri = math.sqrt(pa_raw * mx28.ACC_TICKS_PER_UNIT * abs(distance))
    if v_tri <= pv_raw * mx28.VEL_TICKS_PER_UNIT:
        return mx28.PROFILE_TRIANGULAR
    return mx28.PROFILE_TRAPEZOIDAL


class Motion:
    """Present (pos, vel, acc) and trajectory (traj_pos, traj_vel) of one servo, ticks."""

    def __init__(self) -> None:
        self.pos = self.vel = self.acc = 0.0
        self.traj_pos = self.traj_vel = 0.0
        self.goal = 0.0
        self.profile_bits = 0
        self.lag = 0.0

    def reset(self, pos: float) -> None:
        """The motor is at `pos`, at rest, with no trajectory under way."""
        self.pos = self.traj_pos = self.goal = pos
        self.stop()

    def stop(self) -> None:
        """Torque off (or held): at rest where it stands."""
        self.vel = self.acc = self.traj_vel = self.lag = 0.0
        self.traj_pos = self.pos

    def new_goal(self, goal: float, pv_raw: float, pa_raw: float) -> None:
        self.goal = float(goal)
        self.profile_bits = profile_type(pv_raw, pa_raw, goal - self.traj_pos)

    # position modes -----------------------------------------------------------------------
    @property
    def at_rest(self) -> bool:
        """On the goal with no trajectory under way and the motor still: a step changes
        nothing (every integration step would write back the same values)."""
        return (self.traj_pos == self.goal == self.pos and self.traj_vel == 0.0
                and self.vel == 0.0 and self.acc == 0.0 and self.lag == 0.0)

    def step_position(self, dt: float, cap: float, pv_raw: float, pa_raw: float) -> None:
        if self.at_rest:  # the same state out, without 1,000 integration steps a second
            return
        vmax = pv_raw * mx28.VEL_TICKS_PER_UNIT if pv_raw > 0 else math.inf
        amax = pa_raw * mx28.ACC_TICKS_PER_UNIT if pa_raw > 0 else math.inf
        t_left = dt
        while t_left > 1e-12:
            h = min(STEP_S, t_left)
            t_left -= h
            self._trajectory(h, vmax, amax)
            self._follow(h, cap)

    def _trajectory(self, h: float, vmax: float, amax: float) -> None:
        goal, v = self.goal, self.traj_vel
        err = goal - self.traj_pos
        if math.isinf(vmax) or (abs(err) < 1e-9 and abs(v) <= amax * h):
            self.traj_pos, self.traj_vel = goal, 0.0
            return
        # fastest velocity from which the goal can still be reached without overshoot
        v_des = math.copysign(min(vmax, math.sqrt(2.0 * amax * abs(err))), err)
        v_new = v + max(-amax * h, min(amax * h, v_des - v))
        p_new = self.traj_pos + 0.5 * (v + v_new) * h
        if (goal - p_new) * err <= 0.0:
            p_new, v_new = goal, 0.0
        self.traj_pos, self.traj_vel = p_new, v_new

    def _follow(self, h: float, cap: float) -> None:
        want = (self.traj_pos - self.pos) / h
        if abs(want) <= cap:
            v_new, self.pos = want, self.traj_pos
        else:
            v_new = math.copysign(cap, want)
            self.pos += v_new * h
        self.acc = (v_new - self.vel) / h
        self.vel = v_new
        self.lag = abs(self.traj_pos - self.pos)

    def moving_status(self, goal: int) -> int:
        """Moving Status (123) in a position mode with torque on."""
        ongoing = self.traj_pos != self.goal or self.traj_vel != 0.0
        arrived = not ongoing and abs(goal - self.pos) < 1.0
        return (self.profile_bits
                | (mx28.IN_POSITION if arrived else 0)
                | (mx28.PROFILE_ONGOING if ongoing else 0)
                | (mx28.FOLLOWING_ERROR if self.lag > FOLLOWING_ERROR_TICKS else 0))

    # velocity and PWM modes ---------------------------------------------------------------
    def step_velocity(self, dt: float, target_raw: float, acc_raw: float, cap: float) -> None:
        target = target_raw * mx28.VEL_TICKS_PER_UNIT
        amax = acc_raw * mx28.ACC_TICKS_PER_UNIT if acc_raw > 0 else math.inf
        t_left = dt
        while t_left > 1e-12:
            h = min(STEP_S, t_left)
            t_left -= h
            self.traj_vel += max(-amax * h, min(amax * h, target - self.traj_vel))
            v_new = max(-cap, min(cap, self.traj_vel))
            self.pos += 0.5 * (self.vel + v_new) * h
            self.acc = (v_new - self.vel) / h
            self.vel = v_new
            self.traj_pos = self.goal = self.pos
        self.lag = 0.0
