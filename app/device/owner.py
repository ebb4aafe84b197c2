"""The owner task of one arm's link and the samples it publishes: the machinery under
`Driver` (app/device/driver.py), which holds the state it works on and the protocol exchange.

Requests from `Driver.submit` wait in a bounded queue; the owner task opens the link (capped
exponential backoff), serves requests one at a time, polls at the profile's rate between them
and publishes each sample (tip, tip velocity and tip force reused while readings repeat, or,
with a deriving hub, computed at the sample's first read: app/telemetry/hub.py).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from app.errors import ArmError, DeviceError, DeviceTimeout, LinkDown
from app.links.base import Link, LinkError, LinkState
from app.links.threaded import BATCH_S, IDLE_BATCH_S, ThreadLink
from app.runtime.gc_policy import young_if_due
from app.runtime.tasks import resolve
from app.telemetry.hub import TelemetryHub

if TYPE_CHECKING:
    from app.arms.model import KinematicsModel
    from app.config import ArmProfile

#: The driver's logger, as before the owner task had a module of its own.
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
#: The shortest idle wait, s: uvloop's clock resolution (`_idle_until`); POLL_EARLY_S covers it.
LOOP_TICK_S = 0.001
#: Longest the owner task waits for the link's thread to hand over scheduled polls, s: only
#: a thread that stopped answering makes it wait that long (app/links/threaded.py).
SCHEDULE_WAIT_MAX_S = 1.0
#: Consecutive failed polls before samples are marked stale and an event is sent.
STALE_AFTER = 3
#: After an estop latches (`hold_coming`), the longest the owner task waits for the latch's
#: hold before it polls again, s: the hold's task runs once the latch's step yields, a few
#: hundred microseconds later; a poll started meanwhile held the hold back a whole device
#: round trip (tests/test_estop_hold_first.py). Only a hold that does not come (no reading to
#: hold at) or a loop held up that long lets the polls go on without it.
HOLD_COMING_S = 0.005


@dataclass
class _Request:
    message: Any
    future: asyncio.Future[Any]
    timeout: float
    queued_at: float = field(default_factory=time.monotonic)
    #: A command that moves the arm: `motion_gate` is asked just before it is written (the
    #: estop latch wins over a command queued before it), and `on_send` notes it as sent.
    gated: bool = False
    on_send: Callable[[], None] | None = None


class OwnerTask:
    """The owner task and the samples of a `Driver`: everything here runs in the owner task,
    on the loop the driver was started on. `Driver.__init__` sets the state below; `Driver`
    (or its subclass) gives the exchange, the poll and the hooks."""

    profile: ArmProfile
    link: Link
    hub: TelemetryHub
    model: KinematicsModel
    motion_gate: Callable[[], None] | None
    _queue: asyncio.Queue[_Request]
    _idle: asyncio.Future[None] | None
    _poll_now: bool
    _hold_until: float
    _derived_key: tuple[list[float], list[float], list[float] | None] | None
    _derived: tuple[Any, Any, Any] | None
    _template: tuple[dict[str, Any], Any, tuple[Any, ...]] | None
    repeat_samples: bool
    units_version: int
    _seq: int
    _stamp: float
    _poll_failures: int
    stale: bool
    stale_error: ArmError | None
    last_error: str | None
    stats: dict[str, int]
    gripper: float | None
    positions: np.ndarray | None
    velocities: np.ndarray | None
    faults: list[dict[str, Any]]
    homed: list[bool]
    calibrated: list[bool]
    gravity: Callable[[np.ndarray], np.ndarray] | None
    torques_raw: np.ndarray | None
    torque_tare: np.ndarray | None

    if TYPE_CHECKING:  # Driver's
        @property
        def name(self) -> str: ...

        async def _exchange(self, message: Any, timeout: float) -> Any: ...

        async def _poll(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]: ...

        async def _on_connected(self) -> None: ...

        async def _link_ready(self) -> None: ...

        def _reset_reader(self) -> None: ...

        def forget_commanded(self, joints: Any = None) -> None: ...

        def _repeat_ok(self) -> bool: ...

        def _repeated(self, at: float) -> None: ...

    # ------------------------------------------------------------ owner task

    async def _run(self) -> None:
        delay = BACKOFF_FIRST_S
        was_up = False
        while True:
            self.link.state = LinkState.CONNECTING
            try:
                await self.link.open()
                self._reset_reader()
                self.forget_commanded()  # what the device holds now is its own
                await self._on_connected()
                await self._link_ready()
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
        if isinstance(self.link, ThreadLink):
            await self._session_scheduled(self.link)
            return
        period = 1.0 / self.profile.link.poll_hz
        loop = asyncio.get_running_loop()
        next_poll = loop.time()
        polled = False  # the last thing done was a poll
        while True:
            now = loop.time()
            if now < self._hold_until and self._queue.empty():
                await self._idle_until(loop, self._hold_until)  # the estop's hold first
                continue
            due = now >= next_poll - POLL_EARLY_S
            # A queued request goes between two polls even when the next one is already due:
            # polls that fall behind (a slow bus, a loaded machine) catch up back to back,
            # and a setpoint stream must not wait for the whole catch-up (it did: an executor
            # held up for hundreds of milliseconds behind its own arm's polls).
            if (self._poll_now or (due and not (polled and not self._queue.empty()))) \
                    and now >= self._hold_until:
                self._poll_now = False
                await self._do_poll()
                polled = True
                if due:  # a poll a request asked for (`poll_after`) leaves the schedule as it was
                    next_poll += period
                    if next_poll < loop.time() - POLL_CATCH_UP * period:  # far behind: skip
                        next_poll = loop.time() + period
                continue
            try:
                req = self._queue.get_nowait()
            except asyncio.QueueEmpty:
                await self._idle_until(loop, next_poll - POLL_EARLY_S)
                continue
            polled = False
            await self._serve(req)

    async def _session_scheduled(self, link: ThreadLink) -> None:
        """`_session` over a link with a thread of its own (app/links/threaded.py): while
        nothing is queued and the last poll succeeded, the link's thread polls on the schedule
        and the owner task waits, the batches of replies that repeat the last one published
        as they are handed over (`_on_replies`); woken for anything else (a reply that changed
        or failed, a request), it pauses the thread (the poll in flight ends first), serves a
        queued request, passes each reply read ahead through the driver's poll, in order
        (after a failed request the driver's quiet wait comes first, as before any exchange),
        then goes on as `_session` does."""
        period = 1.0 / self.profile.link.poll_hz
        loop = asyncio.get_running_loop()
        next_poll = loop.time()
        polled = False  # the last thing done was a poll
        ok = False  # the last poll succeeded: the thread may poll on its own

        def readers(n: int) -> None:  # repeats as often as someone takes the samples
            link.batch_repeats(BATCH_S if n else IDLE_BATCH_S)
        self.hub.on_readers = readers
        readers(self.hub.readers)
        try:
            while True:
                now = loop.time()
                due = now >= next_poll - POLL_EARLY_S
                # as `_session`: a queued request goes between two polls (replies the thread
                # read ahead are polls made: it goes before their samples, an estop's hold
                # waits for no sample), a poll a request asked for (`poll_after`) right after;
                # but not before a poll read ahead that failed: its reply may still come, and
                # would answer the request (a STATUS's reply names no poll), so the driver
                # takes the failure first and its quiet wait comes before the request
                failed_ahead = link.prefetched and not link.clean
                if (not self._queue.empty() and not self._poll_now and not failed_ahead
                        and (polled or not due or link.prefetched)):
                    polled = False
                    await self._serve(self._queue.get_nowait())
                    continue
                if link.prefetched:  # the thread's polls, before any poll made now
                    while link.prefetched:
                        if self._repeat(link):  # the last reply again: the last sample again
                            continue
                        ok = await self._do_poll(prefetched=True)
                        if not ok:  # the driver resynchronises: the rest is input it drops
                            link.drop_prefetched()
                    polled = True
                    next_poll = max(next_poll, link.next_slot)
                    continue
                # a due poll with nothing queued after a good one: the thread makes it, at once
                alone = ok and link.can_schedule  # the thread may poll on its own
                if self._poll_now or (due and not (alone and self._queue.empty())):
                    self._poll_now = False
                    ok = await self._do_poll()
                    polled = True
                    if due:  # a poll a request asked for leaves the schedule as it was
                        next_poll += period
                        if next_poll < loop.time() - POLL_CATCH_UP * period:  # far behind
                            next_poll = loop.time() + period
                    continue
                if alone:
                    if await self._idle_scheduled(loop, link, next_poll, period):
                        polled = True
                    next_poll = max(next_poll, link.next_slot)
                else:  # after a failed poll the driver polls itself (its quiet wait first)
                    await self._idle_until(loop, next_poll - POLL_EARLY_S)
        finally:
            self.hub.on_readers = None
            await link.pause()

    async def _idle_scheduled(self, loop: asyncio.AbstractEventLoop, link: ThreadLink,
                              slot: float, period: float) -> bool:
        """Let the link's thread poll from `slot` while the owner task waits for a request
        (`_wake_owner`) or for replies the thread hands over (`_on_replies`: a batch that
        only repeats the last poll's reply is published there, and the owner task waits on
        with the schedule running); anything else (a reply that changed or failed, a request,
        the thread's silence) wakes it, and the schedule is paused again before this returns.
        True if repeats were published meanwhile (polls made)."""
        fut = loop.create_future()
        self._idle = fut  # before the thread may wake it
        repeats = self.stats["repeats"]
        if not link.arm(slot, period, self._on_replies):
            timer = loop.call_at(max(slot - POLL_EARLY_S, loop.time() + LOOP_TICK_S),
                                 resolve, fut)
        else:  # the thread wakes it; the timer only bounds a thread that stopped answering
            timer = loop.call_at(loop.time() + SCHEDULE_WAIT_MAX_S, resolve, fut)
        try:
            await fut
        finally:
            self._idle = None
            timer.cancel()
            await link.pause()
        return self.stats["repeats"] != repeats

    def _on_replies(self) -> None:
        """The link's thread has replies for the owner task (called on its loop, in the
        thread's hand-over). While the owner task waits in `_idle_scheduled` (the schedule
        armed) with nothing queued, replies that all repeat the last poll's are published
        here, as the owner task would publish them (`_repeat`: no I/O, nothing else of the
        task's touched), and it is left waiting: no task step, no future, no re-arm for an
        arm at rest. Anything else wakes it."""
        link, fut = self.link, self._idle
        if (fut is not None and not fut.done() and isinstance(link, ThreadLink)
                and link.armed and self._queue.empty() and not self._poll_now
                and self._repeat(link) and not link.prefetched):
            young_if_due()  # this wake-up, not the policy's timer's (app/runtime/gc_policy.py)
            return
        self._wake_owner()

    async def _idle_until(self, loop: asyncio.AbstractEventLoop, when: float) -> None:
        """Wait for a request or loop time `when`, whichever is first: one bare future and one
        timer the loop keeps (no task: `asyncio.wait_for` makes one per call on Python 3.11,
        at every poll that was most of an idle arm's cost). `submit` resolves the future."""
        fut = loop.create_future()
        self._idle = fut
        # uvloop (the HTTP loop, which runs the arms with ARMSERVER_CONTROL_THREAD=false) keeps
        # time in whole milliseconds and runs a timer due in under half of one at once: the
        # wait would spin until its clock ticks (24 % of a core for one idle 500 Hz arm). At
        # least LOOP_TICK_S: the poll is then at most that after its early slot, never late.
        timer = loop.call_at(max(when, loop.time() + LOOP_TICK_S), resolve, fut)
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
            loop.call_soon_threadsafe(resolve, fut)

    def hold_coming(self) -> None:
        """The estop just latched on this loop (`ArmService._latch`) and its hold will be
        queued as soon as the latch's step yields: until then, or HOLD_COMING_S, the owner
        task starts no poll (`_session`; over a link with a thread of its own the schedule's
        pause does that job, app/links/threaded.py). The first command that is not gated (the
        hold) ends the wait."""
        self._hold_until = asyncio.get_running_loop().time() + HOLD_COMING_S

    async def _serve(self, req: _Request) -> None:
        if not req.gated:
            self._hold_until = 0.0
        if req.future.done():  # the caller gave up (cancelled) while queued
            return
        self.stats["requests"] += 1
        try:
            if req.gated and self.motion_gate is not None:
                self.motion_gate()  # raises (EstopLatched): nothing is written
            if req.on_send is not None:
                req.on_send()
            sent_at = asyncio.get_running_loop().time()
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
        after = getattr(req.message, "poll_after", False)
        if after:
            self._poll_now = True  # taken next, ahead of the schedule and of queued requests
        if not req.future.done():
            req.future.set_result(reply)
        if after:
            # ... once the device can show the request's effect (`poll_delay_s`: a goal's
            # first encoder tick at the servo's pace), or a request comes: a read sooner reads
            # what the last sample said, and the effect shows only a poll period later (issue
            # 23's goal tail). The caller has its answer already. Timed from the end of the
            # request's write (the link's `written_at`), not from before the exchange: a
            # process held up between the two had the poll read the sample before
            # (tests/test_passthrough_check_poll.py; from the write's start, once in a loaded
            # clean clone, the same within the write).
            loop = asyncio.get_running_loop()
            written = self.link.written_at
            start = written if written is not None and written > sent_at else sent_at
            until = start + getattr(req.message, "poll_delay_s", 0.0)
            if loop.time() < until and self._queue.empty():
                await self._idle_until(loop, until)

    async def _do_poll(self, prefetched: bool = False) -> bool:
        """One poll and its sample (or its failure counted); True if it succeeded.
        `prefetched`: the reply is the one the link's thread read ahead on the schedule."""
        self.stats["polls"] += 1
        sched = self.link if isinstance(self.link, ThreadLink) else None
        if sched is not None:
            sched.begin_poll(prefetched)
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
            return False
        if self._poll_failures >= STALE_AFTER:
            log.info("%s: device answering again", self.name)
            self.hub.event("device_back")
        self._poll_failures = 0
        self.stale = False
        self.stale_error = None
        self.positions, self.velocities = q, qd
        self.torques_raw = tau
        at = sched.reply_time if sched is not None else None
        sample, inputs = self._publish(q, qd, self._tared(tau, q), stale=False, at=at)
        self._template = (sample, inputs, (q, qd, tau, self.gravity, self.torque_tare,
                                           self.units_version))
        young_if_due()  # a moving or read arm's polls wake the loop anyway
        return True

    def _repeat(self, link: ThreadLink) -> bool:
        """The replies the link's thread read ahead, from the next on, that are byte for byte
        the last poll's (`ThreadLink.take_repeats`: an arm at rest), published as the last
        sample again, each with its reply's own time and the next seq, without parsing,
        converting and checking the same bytes again (in one step: `publish_run`); True if
        there were any. Only where nothing a sample is made from has changed since that sample
        (the readings, units, tare, gravity fit, gripper, faults, homing, calibration; the
        driver's own state: `_repeat_ok`), else False and the full path runs. What a
        subscriber sees is the same as from the full path (tests/test_sample_repeat.py)."""
        t = self._template
        if (t is None or self._poll_failures or self.stale or not self.repeat_samples
                or not self._repeat_ok()):
            return False
        sample, inputs, (q, qd, tau, gravity, tare, units) = t
        if (q is not self.positions or qd is not self.velocities or tau is not self.torques_raw
                or gravity is not self.gravity or tare is not self.torque_tare
                or units != self.units_version or sample["gripper"] != self.gripper
                or sample["faults"] != self.faults or sample["homed"] != self.homed
                or sample["calibrated"] != self.calibrated):
            return False
        ats = link.take_repeats()
        if not ats:
            return False
        self._repeated(ats[-1])  # (what it sets, each repeat would set again: the last holds)
        n = len(ats)
        self.stats["polls"] += n
        self.stats["repeats"] += n
        stamps = [self._next_stamp(at) for at in ats]  # (times never go back)
        if inputs is not None:  # derived fields from the same readings at their first read
            sample = dict(sample, tip=None, tip_velocity=None, tip_force=None)
        self.hub.publish_run(sample, stamps, inputs)
        return True

    # ------------------------------------------------------------ samples

    def _next_stamp(self, at: float | None) -> tuple[int, float]:
        """The next sample's seq and time: `at` (`time.time()` when its reading was taken; None:
        now), never before the last sample's time."""
        self._seq += 1
        stamp = time.time() if at is None else at
        if stamp < self._stamp:
            stamp = self._stamp
        self._stamp = stamp
        return self._seq, stamp

    def _publish(self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray | None, stale: bool,
                 at: float | None = None) -> tuple[dict[str, Any], Any]:
        """Publish one sample; `at`: when its reading was taken (`time.time()`), if not now.
        Sample times never go back: a reading the link's thread took before a sample published
        meanwhile (an estop's `publish_state`) is stamped with that sample's time. Answers the
        sample and the readings its derived fields wait for (None: derived already)."""
        _, stamp = self._next_stamp(at)
        positions = q.tolist()
        velocities = qd.tolist()
        torques = None if tau is None else tau.tolist()
        lazy = self.hub.deriver is not None
        # An arm at rest reads the same values poll after poll: its tip, tip velocity and tip
        # force are then those of the last sample, not worth a forward kinematics, a Jacobian
        # and a solve again (most of a sample's cost; the encoded bytes are the same). With a
        # deriving hub they wait for the sample's first reader, batched (app/telemetry/hub.py).
        key = (positions, velocities, torques)
        if lazy:
            tip = tip_v = force = None
        elif key == self._derived_key and self._derived is not None:
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
            "time": stamp,
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
            "calibrated": list(self.calibrated),
        }
        # the arm's hub adds the estop, motion, fault and homing fields
        if lazy:
            inputs = (np.array(q, dtype=float), np.array(qd, dtype=float),
                      None if tau is None else np.array(tau, dtype=float))
            self.hub.publish(sample, inputs)
            return sample, inputs
        self.hub.publish(sample)
        return sample, None

    def publish_state(self) -> None:
        """Publish the latest reading again, at once, with the arm's state as it is now: for a
        change of state a client must see without waiting for the next reading (an estop's
        latch; like `stale` when the link is lost). The next poll's reading follows as it comes.
        Nothing before the first reading; a stale arm's sample stays stale."""
        if self.stale:
            self._publish_stale()
        elif self.positions is not None and self.velocities is not None:
            self._publish(self.positions, self.velocities,
                          self._tared(self.torques_raw, self.positions), stale=False)

    def _tared(self, tau: np.ndarray | None, q: np.ndarray) -> np.ndarray | None:
        """Raw torques less gravity at `q` (where a gravity fit is made) and the tare (None:
        no torques)."""
        if tau is not None and self.gravity is not None:
            tau = tau - self.gravity(q)
        if tau is not None and self.torque_tare is not None:
            tared: np.ndarray = tau - self.torque_tare
            return tared
        return tau

    def _publish_stale(self) -> None:
        if self.positions is not None and self.velocities is not None:
            self._publish(self.positions, np.zeros_like(self.velocities), None, stale=True)



def _vec(v: np.ndarray) -> dict[str, float]:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}
