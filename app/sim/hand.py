"""A hand in a simulated arm's world: it moves the arm's joints as a person moves an arm whose
servos' torque is off (a teleoperation leader, API.md "Teleoperation"; the issue's "a
simulated arm moved through its world").

It acts on the simulated device, never on the server: each joint servo of a simulated
Dynamixel bus (app/arms/dynamixel/sim_bus.py) whose Torque Enable (64) is 0 has its Present
Position and Present Velocity set to where the hand has it, and the server reads them over the
link as it reads hardware. The ROBOTIS e-manual's X-series control table, Torque Enable (64):
0 is "Torque OFF (Free-run) and the motor does not generate torque", so a hand turns the horn;
with torque on, a position-mode servo drives to its Goal Position and holds it, so the hand
does not move it: a move is refused at the start with 409 `conflict` when a joint it would
move (further than `STILL_TICKS` from where it is) holds torque, and a joint whose torque comes
on during a move (the session that freed it has ended) is let go. A joint held where the goal
has it (the angler's z winch, whose torque stays on: it falls without) stays held.

The hand stays on the arm from its first move until it lets go (`let_go`, `DELETE
/arms/{arm}/world/hand`): it holds the joints where it left them. A joint that falls without
torque (the profile's `falls_without_torque`) falls on the simulated bus once its servo's
torque is off and nothing holds it (app/arms/dynamixel/sim_gravity.py), as a real one does:
take hold of a leader first (a move to where it is, `here`, moves nothing and is allowed with
its torque on), then free it.

The hand goes in a straight line in joint space from where the joints are when the device
next runs (the simulated clock of its link) to the goal, at `speed` (rad/s or m/s) on the
joint with the longest way, every joint arriving together. Units: joint units at this
module's surface (rad, m), ticks only where the servo's registers are set (through the
world's model's transmission, as the world reads them back).

Threads: `move_to` is called on a request's thread, `apply` by the device's tap on the
control thread; a move crosses as one attribute assignment (`_asked`), the tap's progress as
another (`_done`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from app.errors import Conflict, InvalidRequest, JointLimit
from app.sim.world import World

#: The hand's default speed on the joint with the longest way (rad/s or m/s): unhurried.
DEFAULT_SPEED = 0.5
#: The fastest the hand goes (rad/s or m/s): an XM430's no-load speed is about 4.8 rad/s.
MAX_SPEED = 4.0
#: Encoder ticks within which a goal leaves a joint where it is (a joint the hand does not move
#: may hold torque).
STILL_TICKS = 8.0


@dataclass(frozen=True)
class HandMove:
    """A move asked for: the goal (rad, m) and the speed; `serial` counts the moves."""

    goal: tuple[float, ...]
    speed: float
    serial: int


@dataclass(frozen=True)
class _Under:
    """A move under way on the device's clock: from `start` at `t0`, `duration` s long."""

    move: HandMove
    start: np.ndarray
    t0: float
    duration: float


class Hand:
    """The hand on `device`'s joint servos (by the profile's `motor_id`), in `world`'s
    joint units."""

    def __init__(self, world: World, device: Any) -> None:
        if not hasattr(device, "servo"):
            raise TypeError(f"a {type(device).__name__} has no servos a hand could move")
        self.world = world
        self.device = device
        self.ids = [int(j.motor_id or 0) for j in world.profile.joints]
        self._asked: HandMove | None = None
        self._under: _Under | None = None
        self._done = 0  # the serial of the last move ended (arrived, or let go)
        self._serial = 0
        #: The hand is on the arm (from its first move until `let_go`): it holds the joints
        #: it moved where it left them, against gravity (the bus's `gravity`, if any).
        self._grip = False
        self._gravity = getattr(device, "gravity", None)

    # --- a request's side --------------------------------------------------------------

    def holding(self, goal: np.ndarray | None = None) -> list[str]:
        """The joints whose servo holds torque now (or does not answer: a hand cannot move
        what is not there); with `goal` (rad, m), only those it would move."""
        names = [j.name for j in self.world.profile.joints]
        ticks = None if goal is None else self.world.model.transmission.to_ticks(goal)
        out = []
        for k, (name, i) in enumerate(zip(names, self.ids, strict=True)):
            s = self.device.servo(i)
            if s is None or (s.torque and (ticks is None or abs(
                    float(ticks[k]) - float(s.get("present_position"))) > STILL_TICKS)):
                out.append(name)
        return out

    def move_to(self, goal: list[float], speed: float = DEFAULT_SPEED) -> HandMove:
        """Ask for a move to `goal` (rad, m, the arm's joint order) at `speed`. 422
        `invalid_request` for a goal of the wrong width or a speed out of (0, MAX_SPEED];
        422 `joint_limit` for a goal beyond the arm's joint limits (the hand moves the arm
        within its mechanical range); 409 `conflict` while a joint's servo holds torque.
        A new move replaces one under way, from where the joints are then."""
        m = self.world.model
        q = np.asarray(goal, dtype=float)
        if q.shape != (m.n,) or not np.all(np.isfinite(q)):
            raise InvalidRequest(f"{self.world.profile.name}: the hand takes {m.n} joint "
                                 f"positions ({', '.join(m.names)}), got {goal!r}")
        if not (np.isfinite(speed) and 0.0 < speed <= MAX_SPEED):
            raise InvalidRequest(f"the hand's speed {speed!r} is outside (0, {MAX_SPEED:g}]")
        if np.any((q < m.lower) | (q > m.upper)):
            raise JointLimit(f"the hand cannot take {self.world.profile.name} there: "
                             + "; ".join(m.violations(q) or [f"outside {q.tolist()}"]))
        held = self.holding(q)
        if held:
            raise Conflict(f"{self.world.profile.name}: {', '.join(held)} hold torque: a servo "
                           "with torque on keeps its goal against a hand (switch it off: a "
                           "teleoperation session with free_leader, or Torque Enable 0)")
        self._serial += 1
        move = HandMove(tuple(float(x) for x in q), float(speed), self._serial)
        self._hold(True)
        self._asked = move
        return move

    def here(self) -> list[float]:
        """Where the joints are now (rad, m): a goal that moves nothing (`move_to` it to take
        hold of the arm where it is, its torque on or off). Within the joint limits: a joint
        on its stop reads up to half a tick beyond it (the OpenManipulator-X's shoulder, fallen
        onto its stop, 3,072 ticks: 1.5707963 rad against its limit 1.570796)."""
        ticks = self._present_ticks()
        if ticks is None:
            i = next((i for i in self.ids if self.device.servo(i) is None), "of a joint")
            raise Conflict(f"{self.world.profile.name}: servo {i} does not answer: a hand "
                           "cannot hold what is not there")
        m = self.world.model
        q = np.clip(m.transmission.from_ticks(ticks), m.lower, m.upper)
        return [float(x) for x in q]

    def let_go(self) -> None:
        """Take the hand off the arm: a move under way ends where it is, and a joint whose
        servo's torque is off and that falls without it (the bus's gravity) falls."""
        self._asked = None
        self._hold(False)

    def _hold(self, on: bool) -> None:
        self._grip = on
        if self._gravity is not None:
            self._gravity.held = on

    @property
    def active(self) -> bool:
        """A move is asked for or under way (the tap then runs the device up to now first)."""
        return self._asked is not None or self._under is not None

    def busy(self, serial: int) -> bool:
        """Move `serial` has not ended yet (neither arrived nor let go)."""
        return self._done < serial

    # --- the device's side (the tap, on the control thread) -----------------------------

    def apply(self, now: float) -> None:
        """Set each free joint servo where the hand has it at `now` (device clock, s)."""
        asked = self._asked
        under = self._under
        if not self._grip:  # let go: a move under way ends here
            if under is not None:
                self._under = None
                self._done = under.move.serial
            return
        if asked is not None and (under is None or under.move is not asked):
            if under is not None:  # replaced: the earlier move ends here
                self._done = under.move.serial
            under = self._begin(asked, now)
        if under is None:
            return
        tr = self.world.model.transmission
        t = min(max(now - under.t0, 0.0), under.duration)
        frac = t / under.duration if under.duration > 0 else 1.0
        goal = np.asarray(under.move.goal, dtype=float)
        q = under.start + frac * (goal - under.start)
        qd = ((goal - under.start) / under.duration if 0 < t < under.duration
              else np.zeros_like(q))
        ticks, tps = tr.to_ticks(q), tr.velocity_to_ticks(qd)
        free = 0
        for k, i in enumerate(self.ids):
            s = self.device.servo(i)
            if s is None or s.torque:
                continue  # holds its goal: the hand lets this joint go
            free += 1
            s.carry(ticks[k], tps[k], now)  # there, turning as the hand turns it
        if t >= under.duration or free == 0:
            self._under = None
            self._done = under.move.serial
            if self._asked is under.move:
                self._asked = None

    def _present_ticks(self) -> list[float] | None:
        """Every joint servo's Present Position, ticks (None: one does not answer)."""
        ticks = []
        for i in self.ids:
            s = self.device.servo(i)
            if s is None:
                return None
            ticks.append(float(s.get("present_position")))
        return ticks

    def _begin(self, move: HandMove, now: float) -> _Under | None:
        ticks = self._present_ticks()
        if ticks is None:  # a servo that does not answer: nothing to hold on to
            self._done, self._asked, self._under = move.serial, None, None
            return None
        start = np.asarray(self.world.model.transmission.from_ticks(ticks), dtype=float)
        way = float(np.max(np.abs(np.asarray(move.goal) - start)))
        self._under = _Under(move, start, now, way / move.speed)
        return self._under
