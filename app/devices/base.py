"""The driver base: one asyncio task owns an arm's link (ARCHITECTURE rule 2).

Everyone else calls `submit(message)` and awaits a future. The owner task takes requests from a
bounded queue one at a time, writes, reads until the matching reply or the timeout, and resolves
the future with a typed reply or a typed error (DeviceTimeout, CorruptReply, DeviceError,
LinkDown). Between requests it polls the device at the profile's rate and publishes samples.

A lost link fails every pending request with `link_down`, is reported once (state, event, log),
and is reopened with capped exponential backoff; while it is down `submit` fails at once.
"""

from __future__ import annotations

import abc
import asyncio
import logging
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from app.actuator import Actuator as Actuator  # the contract, re-exported
from app.actuator import SettleState as SettleState
from app.arm_model import model_for
from app.config import ArmProfile
from app.control import on_control
from app.errors import (
    ArmError,
    Busy,
    CorruptReply,
    DeviceError,
    DeviceTimeout,
    LinkDown,
    NotSupported,
)
from app.links.base import Link, LinkError, LinkState
from app.tasks import cancel_and_wait
from app.telemetry import TelemetryHub

log = logging.getLogger(__name__)

#: First and last reconnect delay, s: quick enough to recover a replugged cable within a second,
#: slow enough not to spin on a port that is gone.
BACKOFF_FIRST_S = 0.1
BACKOFF_MAX_S = 2.0
#: A poll may run this much before its slot: epoll rounds waits up to whole milliseconds, so
#: waiting for the exact slot would stretch a 2 ms period to 3. The schedule stays absolute.
POLL_EARLY_S = 0.001
#: Polls a stalled loop may catch up on back to back (10 periods: 20 ms at 500 Hz) before
#: it skips ahead instead; a short stall then costs no sample, a long one no burst.
POLL_CATCH_UP = 10
#: Consecutive failed polls before samples are marked stale and an event is sent.
STALE_AFTER = 3
#: Tries of each set-up exchange (`_setup_exchange`): set-up is a chain of idempotent commands,
#: so one lost or corrupt reply in it should cost a retry, not a reconnect. With 5 % of replies
#: lost, a 24-exchange chain without retries succeeds 30 % of the time; with 3 tries, 99.7 %.
SETUP_ATTEMPTS = 3


@dataclass
class _Request:
    message: Any
    future: asyncio.Future[Any]
    timeout: float
    queued_at: float = field(default_factory=time.monotonic)


class Driver(abc.ABC):
    """Base of the per-model drivers. Subclasses implement the protocol exchange."""

    def __init__(self, profile: ArmProfile, link: Link, hub: TelemetryHub) -> None:
        self.profile = profile
        self.link = link
        self.hub = hub
        self.model = model_for(profile)
        self.timeout = profile.link.timeout_s
        self._queue: asyncio.Queue[_Request] = asyncio.Queue(maxsize=profile.link.queue_size)
        self._task: asyncio.Task[None] | None = None
        self._idle: asyncio.Future[None] | None = None  # the owner task's idle wait
        self._poll_now = False  # poll_soon() was called
        #: (positions, velocities, torques) of the last sample and its derived (tip, tip
        #: velocity, tip force): reused while the readings do not change.
        self._derived_key: tuple[list[float], list[float], list[float] | None] | None = None
        self._derived: tuple[Any, Any, Any] | None = None
        self._seq = 0
        self._poll_failures = 0
        self.stale = True
        #: The poll error that made the samples stale (None while polls succeed): the device
        #: stopped answering even where commands need no reply (the motion watchdog reads it).
        self.stale_error: ArmError | None = None
        self.last_error: str | None = None
        self.stats = {"requests": 0, "replies": 0, "timeouts": 0, "corrupt": 0, "stale_replies": 0,
                      "polls": 0, "poll_failures": 0, "reconnects": 0}
        self.gripper: float | None = None
        self.positions: np.ndarray | None = None
        self.velocities: np.ndarray | None = None
        #: Hardware faults (API "Faults and homing"): `{"joint", "servo", "bits", "raw",
        #: "advice"}` each; empty when healthy or for a device that reports none.
        self.faults: list[dict[str, Any]] = []
        #: One flag per joint: False for a joint that needs homing until POST /home.
        self.homed = [not j.needs_homing or profile.link.homed_at_start for j in profile.joints]
        #: The latest joint torques as sensed, before the tare; the tare (POST .../force/tare)
        #: is subtracted from every reading before it is published.
        self.torques_raw: np.ndarray | None = None
        self.torque_tare: np.ndarray | None = None
        #: The loop the owner task runs on (the control thread's); requests cross into it.
        self.home_loop: asyncio.AbstractEventLoop | None = None

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

    @on_control
    async def submit(self, message: Any, timeout: float | None = None) -> Any:
        """Queue `message` for the owner task and await its reply (or its typed error); from
        any loop (it runs on the owner task's loop)."""
        if self.link.state is not LinkState.UP:
            raise LinkDown(f"{self.name} link is {self.link.state.value}: "
                           f"{self.link.last_error or 'not connected yet'}")
        fut: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        # A caller that gave up (cancelled, timed out) no longer reads the error the owner task
        # or close() sets later: mark it read, or asyncio logs "exception never retrieved".
        fut.add_done_callback(_retrieve)
        req = _Request(message, fut, timeout if timeout is not None else self.timeout)
        try:
            self._queue.put_nowait(req)
        except asyncio.QueueFull:
            raise Busy(f"{self.name}: {self._queue.maxsize} requests already queued") from None
        self._wake_owner()
        # Belt and braces: the owner task answers every request, but a caller never waits
        # longer than a full queue of timeouts (each may add one quiet period) plus a second.
        bound = (self._queue.maxsize + 1) * 2 * req.timeout + 1.0
        try:
            return await asyncio.wait_for(asyncio.shield(fut), bound)
        except TimeoutError:
            fut.cancel()
            raise DeviceTimeout(f"{self.name}: the link task did not answer within "
                                f"{bound:.1f} s") from None

    def poll_soon(self) -> None:
        """Poll now, ahead of the schedule: a state change the samples must show at once
        (an emergency stop) gets a fresh sample within one device round trip."""
        self._poll_now = True
        self._wake_owner()

    def wait_connected(self, timeout: float) -> asyncio.Future[bool]:
        async def _wait() -> bool:
            deadline = time.monotonic() + timeout
            while time.monotonic() < deadline:
                if self.link.state is LinkState.UP and not self.stale:
                    return True
                await asyncio.sleep(0.01)
            return False
        return asyncio.ensure_future(_wait())

    # ------------------------------------------------------------ the motion contract

    @abc.abstractmethod
    async def command_joints(self, q: np.ndarray) -> None:
        """Send one joint setpoint (rad or m, within the limits: the caller checked them)."""

    @abc.abstractmethod
    async def set_gripper(self, value: float) -> None:
        """Command the end effector (0 open .. 1 closed); NoGripper where there is none."""

    async def settle_state(self) -> SettleState:
        """Torque and arrival per joint, where the device reports them (base: it does not)."""
        return SettleState()

    async def reboot(self, dxl_id: int) -> None:
        """Reboot one actuator of the arm, where the device can (base: it cannot)."""
        raise NotSupported(f"{self.name} cannot reboot servo {dxl_id}: its device has no reboot")

    def set_home(self, k: int, q: float) -> None:
        """Declare joint `k`'s current physical position to be `q` (rad or m): shift the
        transmission offset so the last reading and every later one agree, and mark it homed.
        The offset is kept in the server, not written to the device (see README)."""
        tr = self.model.transmission
        if self.positions is not None:
            now = float(self.positions[k])
            # the arrays of the (frozen) Transmission are shared by every user of the model
            tr.offset_ticks[k] += (now - q) * float(tr.ticks_per_unit[k])
            self.positions = self.positions.copy()
            self.positions[k] = q
        self.homed[k] = True

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

    # ------------------------------------------------------------ owner task

    async def _run(self) -> None:
        delay = BACKOFF_FIRST_S
        was_up = False
        while True:
            self.link.state = LinkState.CONNECTING
            try:
                await self.link.open()
                self._reset_reader()
                await self._on_connected()
            except LinkError as exc:
                self._lost(str(exc), was_up)
                was_up = False
                await self.link.close()
                await asyncio.sleep(delay)
                delay = min(delay * 2, BACKOFF_MAX_S)
                continue
            except ArmError as exc:  # device did not answer its set-up: retry like a lost link
                self.link.state = LinkState.DOWN
                self.link.last_error = f"device set-up failed: {exc.detail}"
                self._lost(self.link.last_error, was_up)
                was_up = False
                await self.link.close()
                await asyncio.sleep(delay)
                delay = min(delay * 2, BACKOFF_MAX_S)
                continue
            delay = BACKOFF_FIRST_S
            self.link.state = LinkState.UP
            self.link.last_error = None
            self.last_error = None
            log.info("%s: link up (%s %s)", self.name, self.link.kind, self.link.address)
            if self.stats["reconnects"] or was_up:
                self.hub.event("link_back", kind=self.link.kind)
            was_up = True
            try:
                await self._session()
            except LinkError as exc:
                self.stats["reconnects"] += 1
                self._lost(str(exc), True)
                await self.link.close()
                await asyncio.sleep(delay)
            except Exception as exc:  # a bug must not end the link task: start the link afresh
                log.exception("%s: link session failed", self.name)
                self.stats["reconnects"] += 1
                self._lost(f"internal error: {type(exc).__name__}: {exc}", True)
                await self.link.close()
                await asyncio.sleep(delay)

    def _lost(self, reason: str, announce: bool) -> None:
        self.link.state = LinkState.DOWN
        self.link.last_error = reason
        changed = self.last_error != reason
        self.last_error = reason
        self.stale = True
        self._fail_pending(LinkDown(f"{self.name} link lost: {reason}"))
        if announce:
            log.warning("%s: link lost: %s", self.name, reason)
            self.hub.event("link_lost", reason=reason)
        elif changed:
            log.warning("%s: cannot open link: %s", self.name, reason)
        self._publish_stale()

    def _fail_pending(self, exc: ArmError) -> None:
        while not self._queue.empty():
            req = self._queue.get_nowait()
            if not req.future.done():
                req.future.set_exception(exc)

    async def _session(self) -> None:
        period = 1.0 / self.profile.link.poll_hz
        loop = asyncio.get_running_loop()
        next_poll = loop.time()
        while True:
            now = loop.time()
            due = now >= next_poll - POLL_EARLY_S
            if due or self._poll_now:
                self._poll_now = False
                await self._do_poll()
                if due:  # a poll asked for by poll_soon() leaves the schedule as it was
                    next_poll += period
                    if next_poll < loop.time() - POLL_CATCH_UP * period:  # far behind: skip
                        next_poll = loop.time() + period
                continue
            try:
                req = self._queue.get_nowait()
            except asyncio.QueueEmpty:
                await self._idle_until(loop, next_poll - POLL_EARLY_S)
                continue
            await self._serve(req)

    async def _idle_until(self, loop: asyncio.AbstractEventLoop, when: float) -> None:
        """Wait for a request or loop time `when`, whichever is first: one bare future and one
        timer the loop keeps (no task: `asyncio.wait_for` makes one per call on Python 3.11,
        at every poll that was most of an idle arm's cost). `submit` resolves the future."""
        fut = loop.create_future()
        self._idle = fut
        timer = loop.call_at(when, _resolve, fut)
        try:
            await fut
        finally:
            self._idle = None
            timer.cancel()

    def _wake_owner(self) -> None:
        """A request was queued: end the owner task's idle wait (from any thread)."""
        fut = self._idle
        if fut is None or fut.done():
            return
        loop = fut.get_loop()
        try:
            same = asyncio.get_running_loop() is loop
        except RuntimeError:
            same = False
        if same:
            fut.set_result(None)
        else:
            loop.call_soon_threadsafe(_resolve, fut)

    async def _serve(self, req: _Request) -> None:
        if req.future.done():  # the caller gave up (cancelled) while queued
            return
        self.stats["requests"] += 1
        try:
            reply = await self._exchange(req.message, req.timeout)
        except LinkError:
            if not req.future.done():
                req.future.set_exception(LinkDown(f"{self.name} link lost during the request"))
            raise
        except asyncio.CancelledError:
            if not req.future.done():
                req.future.set_exception(LinkDown(f"{self.name}: driver stopping"))
            raise
        except Exception as exc:  # a bug or unencodable request: fail it, keep the link task
            if isinstance(exc, ArmError):
                err: ArmError = exc
                if isinstance(exc, DeviceTimeout):
                    self.stats["timeouts"] += 1
                    self._reset_reader()
            else:
                log.exception("%s: request %r failed", self.name, req.message)
                err = DeviceError(f"{self.name}: cannot send the request: {exc}")
            if not req.future.done():
                req.future.set_exception(err)
            return
        self.stats["replies"] += 1
        if not req.future.done():
            req.future.set_result(reply)

    async def _do_poll(self) -> None:
        self.stats["polls"] += 1
        try:
            q, qd, tau = await self._poll()
        except LinkError:
            raise
        except (ArmError, ValueError, ArithmeticError) as exc:
            if not isinstance(exc, ArmError):  # a reply our conversions could not take
                log.warning("%s: poll reply not usable: %s", self.name, exc)
                exc = DeviceError(f"{self.name}: poll reply not usable: {exc}")
            self.stats["poll_failures"] += 1
            if isinstance(exc, DeviceTimeout):
                self._reset_reader()
            self._poll_failures += 1
            if self._poll_failures == STALE_AFTER:
                self.stale = True
                self.stale_error = exc
                self.last_error = exc.detail
                log.warning("%s: device not answering polls: %s", self.name, exc.detail)
                self.hub.event("device_stale", reason=exc.detail, code=exc.code)
                self._publish_stale()
            return
        if self._poll_failures >= STALE_AFTER:
            log.info("%s: device answering again", self.name)
            self.hub.event("device_back")
        self._poll_failures = 0
        self.stale = False
        self.stale_error = None
        self.positions, self.velocities = q, qd
        self.torques_raw = tau
        if tau is not None and self.torque_tare is not None:
            tau = tau - self.torque_tare
        self._publish(q, qd, tau, stale=False)

    # ------------------------------------------------------------ samples

    def _publish(self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray | None, stale: bool) -> None:
        self._seq += 1
        positions = q.tolist()
        velocities = qd.tolist()
        torques = None if tau is None else tau.tolist()
        # An arm at rest reads the same values poll after poll: its tip, tip velocity and tip
        # force are then those of the last sample, not worth a forward kinematics, a Jacobian
        # and a solve again (most of a sample's cost; the encoded bytes are the same).
        key = (positions, velocities, torques)
        if key == self._derived_key and self._derived is not None:
            tip, tip_v, force = self._derived
        else:
            m = self.model
            J = m.jacobian(q)
            tip, tip_v, force = m.tip(q), _vec(J @ qd), None  # tip: with pitch for a wrist
            if tau is not None:
                f = m.tip_force(q, tau, J)
                if f is not None and np.all(np.isfinite(f)):
                    force = _vec(f)
            self._derived_key, self._derived = key, (tip, tip_v, force)
        sample: dict[str, Any] = {
            "seq": self._seq,
            "time": time.time(),
            "positions": positions,
            "velocities": velocities,
            "torques": torques,
            "tip": tip,
            "tip_velocity": tip_v,
            "tip_force": force,
            "gripper": self.gripper,
            "motion": None,
            "estop": False,
            "link": self.link.state.value,
            "stale": stale,
            "faults": list(self.faults),
            "homed": list(self.homed),
        }
        self.hub.publish(sample)  # the arm's hub adds the estop, motion, fault and homing fields

    def _publish_stale(self) -> None:
        if self.positions is not None and self.velocities is not None:
            self._publish(self.positions, np.zeros_like(self.velocities), None, stale=True)


def _resolve(fut: asyncio.Future[None]) -> None:
    if not fut.done():
        fut.set_result(None)


def _retrieve(fut: asyncio.Future[Any]) -> None:
    if not fut.cancelled():
        fut.exception()


def _vec(v: np.ndarray) -> dict[str, float]:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}
