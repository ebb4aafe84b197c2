"""The driver base: one asyncio task owns an arm's link (ARCHITECTURE rule 2).

Everyone else calls `submit(message)` and awaits a future. The owner task takes requests from a
bounded queue one at a time, writes, reads until the matching reply or the timeout, and resolves
the future with a typed reply or a typed error (DeviceTimeout, CorruptReply, DeviceError,
LinkDown). Between requests it polls the device at the profile's rate and publishes samples.

A lost link fails every pending request with `link_down`, is reported once (state, event, log),
and is reopened with capped exponential backoff; while it is down `submit` fails at once.

This module is the contract (state, `submit`, the motion contract, the hooks a subclass
writes); the owner task and the samples are `OwnerTask` in app/device/owner.py.
"""

from __future__ import annotations

import abc
import asyncio
import logging
import time
from collections.abc import Awaitable, Callable
from typing import Any

import numpy as np

from app.arms import model_for
from app.config import ArmProfile
from app.device.actuator import Actuator as Actuator  # the contract, re-exported
from app.device.actuator import SettleState as SettleState
from app.device.owner import (  # the owner task's tunables, re-exported
    BACKOFF_FIRST_S as BACKOFF_FIRST_S,
)
from app.device.owner import BACKOFF_MAX_S as BACKOFF_MAX_S
from app.device.owner import POLL_CATCH_UP as POLL_CATCH_UP
from app.device.owner import POLL_EARLY_S as POLL_EARLY_S
from app.device.owner import STALE_AFTER as STALE_AFTER
from app.device.owner import OwnerTask, _Request
from app.errors import (
    ArmError,
    Busy,
    CorruptReply,
    DeviceTimeout,
    LinkDown,
    NotSupported,
)
from app.links.base import Link, LinkState
from app.runtime.control_thread import on_home
from app.runtime.tasks import cancel_and_wait, retrieve
from app.telemetry.hub import TelemetryHub

log = logging.getLogger(__name__)

#: A poll's readings in joint units: positions, velocities, torques (None: not sensed).
Readings = tuple[np.ndarray, np.ndarray, np.ndarray | None]

#: Tries of each set-up exchange (`_setup_exchange`): set-up is a chain of idempotent commands,
#: so one lost or corrupt reply in it should cost a retry, not a reconnect. With 5 % of replies
#: lost, a 24-exchange chain without retries succeeds 30 % of the time; with 3 tries, 99.7 %.
SETUP_ATTEMPTS = 3
#: Reads an exchange makes once its deadline has passed, each without waiting, until one finds
#: nothing: what arrived by the time the driver looks counts. A loop held up past the
#: deadline between the write and its first read (a starved machine: 504 "no reply to SET_PID
#: within 50 ms" in a loaded run, the reply long there) finds the reply; bounded, so a port
#: that never stops talking cannot hold the exchange.
LATE_READS = 4


class ReplyWait:
    """How long an exchange may still wait for its reply, from the deadline its link gave
    (`Reply.deadline`, `time.monotonic()`) on the running loop's clock (uvloop's keeps whole
    milliseconds). Once the deadline has passed, what arrived by the time the driver looks
    counts: reads that do not wait (`left` 0), until one finds nothing or LATE_READS were made;
    then `left` is None and the timeout stands."""

    __slots__ = ("_deadline", "_late", "_loop")

    def __init__(self, deadline: float) -> None:
        self._loop = asyncio.get_running_loop()
        self._deadline = self._loop.time() + (deadline - time.monotonic())
        self._late = 0  # reads since the deadline

    def left(self) -> float | None:
        """Seconds the next read may wait (0: a late one), or None: timed out."""
        left = self._deadline - self._loop.time()
        if left > 0:
            return left
        if self._late >= LATE_READS:
            return None
        self._late += 1
        return 0.0

    def found(self, anything: bool) -> None:
        """What the last read found: a late read that found nothing ends the wait."""
        if self._late and not anything:
            self._late = LATE_READS


class Driver(OwnerTask, abc.ABC):
    """Base of the per-model drivers. Subclasses implement the protocol exchange."""

    def __init__(self, profile: ArmProfile, link: Link, hub: TelemetryHub) -> None:
        self.profile = profile
        self.link = link
        self.hub = hub
        self.model = model_for(profile)
        # tip, tip velocity and tip force at the readers' rate, batched (app/telemetry/hub.py)
        hub.derive_with(lambda: self.model)
        self.timeout = profile.link.timeout_s
        self._queue: asyncio.Queue[_Request] = asyncio.Queue(maxsize=profile.link.queue_size)
        self._task: asyncio.Task[None] | None = None
        self._idle: asyncio.Future[None] | None = None  # the owner task's idle wait
        self._poll_now = False  # a request asked for a poll next (`poll_after`)
        self._hold_until = 0.0  # loop time until which no poll goes before the hold (owner.py)
        #: (positions, velocities, torques) of the last sample and its derived (tip, tip
        #: velocity, tip force): reused while the readings do not change.
        self._derived_key: tuple[list[float], list[float], list[float] | None] | None = None
        self._derived: tuple[Any, Any, Any] | None = None
        #: The last poll's sample (from the full path), the readings its derived fields
        #: follow from, and what it was made from: published again for a reply that repeats
        #: the last poll's byte for byte (owner.py `_repeat`).
        self._template: tuple[dict[str, Any], Any, tuple[Any, ...]] | None = None
        #: Publish the last sample again for such a reply (False: every reply takes the full
        #: path: the reference tests/test_sample_repeat.py compares with).
        self.repeat_samples = True
        self._seq = 0
        self._stamp = 0.0  # the last sample's time (owner.py `_publish`: never goes back)
        self._poll_failures = 0
        self.stale = True
        #: The poll error that made the samples stale (None while polls succeed): the device
        #: stopped answering even where commands need no reply (the motion watchdog reads it).
        self.stale_error: ArmError | None = None
        self.last_error: str | None = None
        self.stats = {"requests": 0, "replies": 0, "timeouts": 0, "corrupt": 0, "stale_replies": 0,
                      "polls": 0, "poll_failures": 0, "reconnects": 0, "repeats": 0}
        self.gripper: float | None = None
        self.positions: np.ndarray | None = None
        self.velocities: np.ndarray | None = None
        #: Hardware faults (API "Faults and homing"): `{"joint", "servo", "bits", "raw",
        #: "advice"}` each; empty when healthy or for a device that reports none.
        self.faults: list[dict[str, Any]] = []
        #: The joints whose torque this server switched off and not on again (`note_torque`).
        self.torque_off: tuple[int, ...] = ()
        #: One flag per joint: False for a joint that needs homing until POST /home.
        self.homed = [not j.needs_homing or profile.link.homed_at_start for j in profile.joints]
        #: One flag per joint: False for a joint whose zero the hardware does not know
        #: (profile `zero_known = false`) until a calibration is declared or found stored for
        #: this hardware (app/calibration/book.py sets them, at connect and on request).
        self.calibrated = [True] * len(profile.joints)
        #: Joint torques (N m or N) that gravity puts on the joints at joint values q (the
        #: gravity fit, app/calibration/gravity.py), subtracted from every reading; None: none.
        self.gravity: Callable[[np.ndarray], np.ndarray] | None = None
        #: What the driver found out about the device's firmware at connect that a user
        #: must know (a build without a command the driver relies on), with what to do; None.
        self.firmware_note: str | None = None
        #: Awaited in the owner task each time the link comes up, after the device's set-up
        #: and before the first poll (the service finds the stored calibration there).
        self.on_link_ready: Callable[[], Awaitable[None]] | None = None
        #: Counts changes of the ticks <-> joint units conversion (homing moves an offset):
        #: a driver that reuses converted readings for a repeated reply checks it.
        self.units_version = 0
        self._converted_key: tuple[Any, int] | None = None
        self._converted: Readings | None = None
        #: The latest joint torques as sensed, before the tare; the tare (POST .../force/tare)
        #: is subtracted from every reading before it is published.
        self.torques_raw: np.ndarray | None = None
        self.torque_tare: np.ndarray | None = None
        #: The loop the owner task runs on (the control thread's); requests cross into it.
        self.home_loop: asyncio.AbstractEventLoop | None = None
        #: What the device was last told to go to, in encoder ticks per joint (NaN: nothing
        #: told since the link came up): the one record of the arm's commanded state. Every
        #: command that moves the arm notes it as it is written (`note_commanded`): planned
        #: setpoints, the estop's hold and pass-through commands alike. `command_seq` counts
        #: the notes, so the motion executor can tell whether its own setpoint is still the
        #: last one the arm was told.
        self._commanded_ticks: np.ndarray | None = None
        self.command_seq = 0
        #: When the last command was noted (monotonic s): a pass-through setpoint may move
        #: from the last command only as fast as the joint may (app/safety/guard.py).
        self.commanded_at = 0.0
        #: Asked in the owner task just before a gated command (one that moves the arm) is
        #: written; raises to refuse it (the service sets the estop latch's check here).
        self.motion_gate: Callable[[], None] | None = None

    # ------------------------------------------------------------ public

    @property
    def name(self) -> str:
        return self.profile.name

    @property
    def state(self) -> LinkState:
        return self.link.state

    async def start(self) -> None:
        if self._task is None:
            self.home_loop = asyncio.get_running_loop()
            self._task = asyncio.create_task(self._run(), name=f"link:{self.name}")

    async def close(self) -> None:
        await cancel_and_wait(self._task)
        self._task = None
        self._fail_pending(LinkDown(f"{self.name}: server shutting down"))
        await self.link.close()

    async def submit(self, message: Any, timeout: float | None = None, *, gated: bool = False,
                     on_send: Callable[[], None] | None = None) -> Any:
        """Runs `_submit` on the owner task's loop (the queue is the owner task's)."""
        return await on_home(self.home_loop, lambda: self._submit(
            message, timeout, gated=gated, on_send=on_send))

    async def _submit(self, message: Any, timeout: float | None = None, *, gated: bool = False,
                      on_send: Callable[[], None] | None = None) -> Any:
        """Queue `message` for the owner task and await its reply (or its typed error); from
        any loop (it runs on the owner task's loop). A `gated` message moves the arm: the
        owner task asks `motion_gate` just before writing it, and calls `on_send` as it is
        written."""
        if self.link.state is not LinkState.UP:
            raise LinkDown(f"{self.name} link is {self.link.state.value}: "
                           f"{self.link.last_error or 'not connected yet'}")
        fut: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        # A caller that gave up (cancelled, timed out) no longer reads the error the owner task
        # or close() sets later: mark it read, or asyncio logs "exception never retrieved".
        fut.add_done_callback(retrieve)
        req = _Request(message, fut, timeout if timeout is not None else self.timeout,
                       gated=gated, on_send=on_send)
        try:
            self._queue.put_nowait(req)
        except asyncio.QueueFull:
            raise Busy(f"{self.name}: {self._queue.maxsize} requests already queued") from None
        self._wake_owner()
        # Belt and braces: the owner task answers every request, but a caller never waits
        # longer than a full queue of timeouts (each may add one quiet period) plus a second.
        bound = (self._queue.maxsize + 1) * 2 * req.timeout + 1.0
        try:
            async with asyncio.timeout(bound):  # not wait_for: on 3.11 it can lose a cancel
                return await asyncio.shield(fut)
        except TimeoutError:
            fut.cancel()
            raise DeviceTimeout(f"{self.name}: the link task did not answer within "
                                f"{bound:.1f} s") from None

    def wait_connected(self, timeout: float) -> asyncio.Future[bool]:
        async def _wait() -> bool:
            deadline = time.monotonic() + timeout
            while True:
                past = time.monotonic() >= deadline  # a last look after it (a held-up loop)
                if self.link.state is LinkState.UP and not self.stale:
                    return True
                if past:
                    return False
                await asyncio.sleep(0.01)
        return asyncio.ensure_future(_wait())

    # ------------------------------------------------------------ the commanded state

    def note_commanded(self, ticks: Any, joints: Any = None) -> None:
        """The device was just told to go to `ticks` (all joints, or those in `joints`)."""
        cur = self._commanded_ticks
        if cur is None:
            cur = np.full(self.model.n, np.nan)
        else:
            cur = cur.copy()
        if joints is None:
            cur[:] = np.asarray(ticks, dtype=float)
        else:
            cur[list(joints)] = np.asarray(ticks, dtype=float)
        self._commanded_ticks = cur
        self.command_seq += 1
        self.commanded_at = time.monotonic()

    def forget_commanded(self, joints: Any = None) -> None:
        """What the device holds is no longer known from here (a servo set up again holds
        its present position): those joints count as commanded where they are."""
        if joints is None or self._commanded_ticks is None:
            self._commanded_ticks = None
        else:
            cur = self._commanded_ticks.copy()
            cur[list(joints)] = np.nan
            self._commanded_ticks = cur
        self.command_seq += 1

    def note_torque(self, joints: Any, on: bool) -> None:
        """The torque of `joints` (indices) was just switched on or off (`torque_off`)."""
        off = set(self.torque_off)
        if on:
            off.difference_update(joints)
        else:
            off.update(joints)
        self.torque_off = tuple(sorted(off))

    @property
    def commanded(self) -> np.ndarray | None:
        """Per joint, where the device was last told to go (rad or m), NaN where nothing was
        told since the link came up; None before any command."""
        ticks = self._commanded_ticks
        if ticks is None:
            return None
        return np.asarray(self.model.transmission.from_ticks(ticks), dtype=float)

    def told(self) -> np.ndarray | None:
        """Where each joint is headed: the last command where there is one, else where the
        joint is measured; None before any reading."""
        q = self.positions
        if q is None:
            return None
        cmd = self.commanded
        if cmd is None:
            return np.array(q, dtype=float)
        return np.where(np.isnan(cmd), q, cmd)

    def pace(self) -> np.ndarray | None:
        """Per joint, the speed (rad/s or m/s) at which the device itself moves to a new
        position command, where it paces itself (a Dynamixel servo's Profile Velocity); NaN
        for a joint that goes as fast as it can (a PID step). None: no joint is paced."""
        return None

    # ------------------------------------------------------------ the motion contract

    @abc.abstractmethod
    async def command_joints(self, q: np.ndarray, *, hold: bool = False) -> None:
        """Send one joint setpoint (rad or m, within the limits: the caller checked them). A
        `hold` (the estop's) is not gated by the latch; every other setpoint is."""

    @abc.abstractmethod
    async def set_gripper(self, value: float) -> None:
        """Command the end effector (0 open .. 1 closed); NoGripper where there is none."""

    async def settle_state(self) -> SettleState:
        """Torque and arrival per joint, where the device reports them (base: it does not)."""
        return SettleState()

    async def reboot(self, dxl_id: int) -> None:
        """Reboot one actuator of the arm, where the device can (base: it cannot)."""
        raise NotSupported(f"{self.name} cannot reboot servo {dxl_id}: its device has no reboot")

    async def set_torque(self, on: bool) -> None:
        """Switch the joints' torque off (the arm is free to be moved by hand: a teleoperation
        leader) or on again, holding where the joints are, where the device can (base: it
        cannot)."""
        raise NotSupported(f"{self.name} cannot switch its joints' torque off: its device "
                           "has no such command")

    def converted(self, raw: Any) -> Readings | None:
        """The readings `remember_converted` kept for an equal `raw` reading (an arm at rest
        reads the same, poll after poll), while homing has not changed the units; else None."""
        if (raw, self.units_version) == self._converted_key:
            return self._converted
        return None

    def remember_converted(self, raw: Any, readings: Readings) -> Readings:
        """Keep `readings` (positions, velocities, torques in joint units) for `raw`; they are
        made read-only, as the polls that read the same share them."""
        for a in readings:
            if a is not None:
                a.setflags(write=False)
        self._converted_key, self._converted = (raw, self.units_version), readings
        return readings

    def set_home(self, k: int, q: float) -> None:
        """Declare joint `k`'s current physical position to be `q` (rad or m): shift the
        transmission offset so the last reading and every later one agree, and mark it homed.
        The offset is kept in the server, not written to the device (see README)."""
        tr = self.model.transmission
        if self.positions is not None:
            now = float(self.positions[k])
            # a new (frozen) Transmission for the model every user of the arm shares
            self.model.transmission = tr.with_offset(
                k, float(tr.offset_ticks[k]) + (now - q) * float(tr.ticks_per_unit[k]))
            self.units_version += 1
            self.command_seq += 1  # a setpoint in the old units no longer means the same
            self.positions = self.positions.copy()
            self.positions[k] = q
        self.homed[k] = True

    def set_offset(self, k: int, offset_ticks: float) -> None:
        """Set joint `k`'s transmission offset (the device's ticks at the joint's zero) as a
        stored calibration has it; the same path as `set_home` (`Transmission.with_offset`),
        without a reading. A setpoint in the old units no longer means the same."""
        tr = self.model.transmission
        old = float(tr.offset_ticks[k])
        if old == offset_ticks:
            return
        self.model.transmission = tr.with_offset(k, offset_ticks)
        self.units_version += 1
        self.command_seq += 1
        if self.positions is not None:
            self.positions = self.positions.copy()
            self.positions[k] -= (offset_ticks - old) / float(tr.ticks_per_unit[k])

    def hardware_identity(self) -> str:
        """What tells this arm's hardware from another on the same port, for the stored
        calibration: the arm type, then the link's own identity where it has one (an HID
        serial number, a simulator's), else the link's kind and address, and the servo ids
        where the joints have them (a Dynamixel bus: the bus and its IDs)."""
        link = self.link
        ident = link.identity or f"{link.kind}:{link.address}"
        ids = [j.motor_id for j in self.profile.joints if j.motor_id is not None]
        if ids:
            ident += ":ids=" + ",".join(str(i) for i in ids)
        return f"{self.profile.model}:{ident}"

    async def _link_ready(self) -> None:
        """`on_link_ready`, in the owner task; a bug in it is logged, not the end of the link
        task (the calibration then stays as it was)."""
        if self.on_link_ready is None:
            return
        try:
            await self.on_link_ready()
        except Exception:
            log.exception("%s: on link ready", self.name)

    # ------------------------------------------------------------ for subclasses

    @abc.abstractmethod
    async def _exchange(self, message: Any, timeout: float) -> Any:
        """Write one request and read its reply, in the owner task. Raise DeviceTimeout,
        CorruptReply or DeviceError for that request, LinkError if the link is lost."""

    @abc.abstractmethod
    async def _poll(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Read the device state in the owner task: joint positions, velocities (SI) and
        joint torques (N m or N) where sensed."""

    async def _on_connected(self) -> None:  # noqa: B027 - an optional hook
        """Prepare the device after the link opens (modes, torque); in the owner task."""

    async def _setup_exchange(self, message: Any, timeout: float) -> Any:
        """`_exchange` for an idempotent set-up command, tried again after a timeout or a
        corrupt reply (up to SETUP_ATTEMPTS); a device error or a lost link is not retried."""
        for attempt in range(1, SETUP_ATTEMPTS + 1):
            try:
                return await self._exchange(message, timeout)
            except (DeviceTimeout, CorruptReply):
                if attempt == SETUP_ATTEMPTS:
                    raise
                self._reset_reader()
        raise AssertionError("unreachable")

    def _reset_reader(self) -> None:  # noqa: B027 - an optional hook
        """Forget partial input (after a timeout or reconnect)."""

    def _repeat_ok(self) -> bool:
        """A poll reply byte for byte the last poll's would leave this driver as the full
        path would and give the same readings (no partial input held, no request pending, no
        check due that a poll runs): the owner task may publish the last sample again for it
        (owner.py `_repeat`). Base: never; a driver says when."""
        return False

    def _repeated(self, at: float) -> None:  # noqa: B027 - an optional hook
        """A repeated poll reply, read at `at` (`time.time()`), was taken without the full
        path: what the full path would have changed for the same bytes (a check's clock)."""

    def read_at(self, at: float | None = None) -> float:
        """When the reading being polled was taken, on `time.monotonic()`'s clock: now, or
        for a reply the link read ahead (its `reply_time`, or `at`: `time.time()`) that long
        ago."""
        if at is None:
            at = getattr(self.link, "reply_time", None)
        now = time.monotonic()
        return now if at is None else now - max(0.0, time.time() - at)
