"""`ArmClient`: the blocking client, made from `AsyncArmClient` rather than written twice.

An `ArmClient` owns a private event loop on a daemon thread and an `AsyncArmClient` living on
it. Each public member of the async class becomes a blocking one here by kind, with the same
signature and docstring (`functools.wraps`) and a type mypy checks against the async one:

- a coroutine method (`health`, `move_pose`, ...) runs on the loop and returns its result;
- an async context manager (`hold_lease`, `queue_turn`) becomes a context manager: its
  background work (the lease renewals) keeps running on the loop while the block runs;
- an async iterator (`telemetry`, `telemetry_messages`) becomes an iterator; leaving the loop
  early closes the WebSocket.

The class body is one line per member naming it (that line is what gives mypy the type); a
public member of `AsyncArmClient` without its line fails at import.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import threading
from collections.abc import AsyncIterator, Callable, Coroutine, Iterator
from contextlib import AbstractAsyncContextManager
from typing import Any, Concatenate, ParamSpec, TypeVar

import httpx

from app.client.aio import AsyncArmClient

P = ParamSpec("P")
R = TypeVar("R")


def blocking(fn: Callable[Concatenate[AsyncArmClient, P], Coroutine[Any, Any, R]]
             ) -> Callable[Concatenate[ArmClient, P], R]:
    """A coroutine method of `AsyncArmClient` as a blocking method of `ArmClient`."""
    @functools.wraps(fn)
    def method(self: ArmClient, /, *args: P.args, **kwargs: P.kwargs) -> R:
        return self._run(fn(self._aio, *args, **kwargs))
    return method


def blocking_cm(fn: Callable[Concatenate[AsyncArmClient, P], AbstractAsyncContextManager[R]]
                ) -> Callable[Concatenate[ArmClient, P], contextlib.AbstractContextManager[R]]:
    """An async context manager method as a context manager method."""
    @functools.wraps(fn)
    @contextlib.contextmanager
    def method(self: ArmClient, /, *args: P.args, **kwargs: P.kwargs) -> Iterator[R]:
        cm = fn(self._aio, *args, **kwargs)
        value = self._run(cm.__aenter__())
        try:
            yield value
        except BaseException as exc:
            if not self._run(cm.__aexit__(type(exc), exc, exc.__traceback__)):
                raise
        else:
            self._run(cm.__aexit__(None, None, None))
    return method


def blocking_iter(fn: Callable[Concatenate[AsyncArmClient, P], AsyncIterator[R]]
                  ) -> Callable[Concatenate[ArmClient, P], Iterator[R]]:
    """An async generator method as a generator method."""
    @functools.wraps(fn)
    def method(self: ArmClient, /, *args: P.args, **kwargs: P.kwargs) -> Iterator[R]:
        agen = fn(self._aio, *args, **kwargs)
        try:
            while True:
                try:
                    item = self._run(_anext(agen))
                except StopAsyncIteration:
                    return
                yield item
        finally:
            aclose = getattr(agen, "aclose", None)
            if aclose is not None and not self._closed:
                self._run(aclose())
    return method


async def _anext(agen: AsyncIterator[R]) -> R:
    return await agen.__anext__()


async def _make(kwargs: dict[str, Any]) -> AsyncArmClient:
    return AsyncArmClient(**kwargs)


class ArmClient:
    """Blocking client: one method per route, returning `app.schemas` models (see
    `AsyncArmClient` for the arguments, errors and retries)."""

    def __init__(self, base_url: str = "http://127.0.0.1:8000", token: str | None = None,
                 lease: str | None = None, timeout: float = 10.0,
                 transport: httpx.AsyncBaseTransport | None = None) -> None:
        self._closed = False
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="armclient-loop",
                                        daemon=True)
        self._thread.start()
        self._aio = self._run(_make({"base_url": base_url, "token": token, "lease": lease,
                                     "timeout": timeout, "transport": transport}))

    def _run(self, coro: Coroutine[Any, Any, R]) -> R:
        if self._closed:
            coro.close()
            raise RuntimeError("this ArmClient is closed")
        future = asyncio.run_coroutine_threadsafe(coro, self._loop)
        try:
            return future.result()
        except BaseException:
            future.cancel()  # e.g. Ctrl-C while waiting: stop the request too
            raise

    # The async client's state, read and set through: one place holds it.

    @property
    def base_url(self) -> str:
        return self._aio.base_url

    @property
    def token(self) -> str | None:
        return self._aio.token

    @property
    def timeout(self) -> float:
        return self._aio.timeout

    @property
    def lease(self) -> str | None:
        return self._aio.lease

    @lease.setter
    def lease(self, value: str | None) -> None:
        self._aio.lease = value

    @property
    def leases(self) -> dict[str, str]:
        return self._aio.leases

    def __enter__(self) -> ArmClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the connections and stop the loop thread (idempotent)."""
        if self._closed:
            return
        try:
            self._run(self._aio.aclose())
        finally:
            self._closed = True
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(timeout=10.0)
            if not self._thread.is_alive():
                self._loop.close()

    send = blocking(AsyncArmClient.send)
    health = blocking(AsyncArmClient.health)
    arms = blocking(AsyncArmClient.arms)
    arm = blocking(AsyncArmClient.arm)
    state = blocking(AsyncArmClient.state)
    move_joints = blocking(AsyncArmClient.move_joints)
    move_pose = blocking(AsyncArmClient.move_pose)
    plan_joints = blocking(AsyncArmClient.plan_joints)
    plan_pose = blocking(AsyncArmClient.plan_pose)
    motion = blocking(AsyncArmClient.motion)
    cancel_motion = blocking(AsyncArmClient.cancel_motion)
    wait_motion = blocking(AsyncArmClient.wait_motion)
    stop = blocking(AsyncArmClient.stop)
    estop = blocking(AsyncArmClient.estop)
    release_estop = blocking(AsyncArmClient.release_estop)
    gripper = blocking(AsyncArmClient.gripper)
    tare_force = blocking(AsyncArmClient.tare_force)
    clear_tare = blocking(AsyncArmClient.clear_tare)
    forward = blocking(AsyncArmClient.forward)
    inverse = blocking(AsyncArmClient.inverse)
    inverse_velocity = blocking(AsyncArmClient.inverse_velocity)
    workspace = blocking(AsyncArmClient.workspace)
    rbe3001_set_pid = blocking(AsyncArmClient.rbe3001_set_pid)
    rbe3001_status = blocking(AsyncArmClient.rbe3001_status)
    rbe3001_set_gain = blocking(AsyncArmClient.rbe3001_set_gain)
    rbe3001_set_claw = blocking(AsyncArmClient.rbe3001_set_claw)
    dxl_ping = blocking(AsyncArmClient.dxl_ping)
    dxl_read_register = blocking(AsyncArmClient.dxl_read_register)
    dxl_write_register = blocking(AsyncArmClient.dxl_write_register)
    dxl_sync_read = blocking(AsyncArmClient.dxl_sync_read)
    dxl_sync_write = blocking(AsyncArmClient.dxl_sync_write)
    dxl_reboot = blocking(AsyncArmClient.dxl_reboot)
    home = blocking(AsyncArmClient.home)
    unhome = blocking(AsyncArmClient.unhome)
    set_torque = blocking(AsyncArmClient.set_torque)
    calibration = blocking(AsyncArmClient.calibration)
    calibrate = blocking(AsyncArmClient.calibrate)
    forget_calibration = blocking(AsyncArmClient.forget_calibration)
    calibrate_gravity = blocking(AsyncArmClient.calibrate_gravity)
    servo_setup = blocking(AsyncArmClient.servo_setup)
    scan_servos = blocking(AsyncArmClient.scan_servos)
    assign_servo = blocking(AsyncArmClient.assign_servo)
    start_practice_bus = blocking(AsyncArmClient.start_practice_bus)
    plug_practice_servo = blocking(AsyncArmClient.plug_practice_servo)
    stop_practice_bus = blocking(AsyncArmClient.stop_practice_bus)
    safety = blocking(AsyncArmClient.safety)
    set_safety = blocking(AsyncArmClient.set_safety)
    world = blocking(AsyncArmClient.world)
    set_world = blocking(AsyncArmClient.set_world)
    move_hand = blocking(AsyncArmClient.move_hand)
    let_go_hand = blocking(AsyncArmClient.let_go_hand)
    start_teleop = blocking(AsyncArmClient.start_teleop)
    replay = blocking(AsyncArmClient.replay)
    teleop_sessions = blocking(AsyncArmClient.teleop_sessions)
    stop_teleop = blocking(AsyncArmClient.stop_teleop)
    take_lease = blocking(AsyncArmClient.take_lease)
    renew_lease = blocking(AsyncArmClient.renew_lease)
    release_lease = blocking(AsyncArmClient.release_lease)
    me = blocking(AsyncArmClient.me)
    join_queue = blocking(AsyncArmClient.join_queue)
    queue = blocking(AsyncArmClient.queue)
    queue_entry = blocking(AsyncArmClient.queue_entry)
    leave_queue = blocking(AsyncArmClient.leave_queue)
    reorder_queue = blocking(AsyncArmClient.reorder_queue)
    clear_queue = blocking(AsyncArmClient.clear_queue)
    revoke_lease = blocking(AsyncArmClient.revoke_lease)
    audit = blocking(AsyncArmClient.audit)
    audit_csv = blocking(AsyncArmClient.audit_csv)
    recordings = blocking(AsyncArmClient.recordings)
    recording = blocking(AsyncArmClient.recording)
    create_recording = blocking(AsyncArmClient.create_recording)
    start_episode = blocking(AsyncArmClient.start_episode)
    stop_episode = blocking(AsyncArmClient.stop_episode)
    discard_episode = blocking(AsyncArmClient.discard_episode)
    recording_archive = blocking(AsyncArmClient.recording_archive)
    cameras = blocking(AsyncArmClient.cameras)
    camera = blocking(AsyncArmClient.camera)
    camera_frame = blocking(AsyncArmClient.camera_frame)
    camera_stream = blocking(AsyncArmClient.camera_stream)
    detections = blocking(AsyncArmClient.detections)
    camera_calibration = blocking(AsyncArmClient.camera_calibration)
    calibrate_camera = blocking(AsyncArmClient.calibrate_camera)
    queue_turn = blocking_cm(AsyncArmClient.queue_turn)
    hold_lease = blocking_cm(AsyncArmClient.hold_lease)
    telemetry_messages = blocking_iter(AsyncArmClient.telemetry_messages)
    telemetry = blocking_iter(AsyncArmClient.telemetry)


def missing_twins(async_cls: type, sync_cls: type) -> list[str]:
    """The public members of `async_cls` that `sync_cls` does not make from it."""
    return [name for name, fn in vars(async_cls).items()
            if not name.startswith("_") and name != "aclose" and callable(fn)
            and getattr(vars(sync_cls).get(name), "__wrapped__", None) is not fn]


if missing := missing_twins(AsyncArmClient, ArmClient):
    raise TypeError(f"AsyncArmClient members without a blocking twin in ArmClient: {missing}; "
                    "add `name = blocking(AsyncArmClient.name)` (or blocking_cm / blocking_iter)")
