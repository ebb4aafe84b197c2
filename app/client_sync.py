"""Blocking twin of `app.client.AsyncArmClient`: the same methods, on `httpx.Client` and the
`websockets` sync client, for scripts and the command line. See `app.client` for errors and
the retry policy.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from typing import Any, Literal, TypeVar

import httpx

from app import schemas as s
from app.client import (
    LEASE_HEADER,
    TERMINAL,
    ArmServerError,
    Call,
    LeaseKeeper,
    Requests,
    backoff,
    move_joints_model,
    move_pose_model,
    parse_answer,
    parse_ws_message,
    should_retry,
    transport_error,
    turn_pending,
    ws_close_error,
    ws_handshake_error,
    ws_url,
)

log = logging.getLogger(__name__)

T = TypeVar("T")


class ArmClient:
    """Blocking client: one method per route, returning `app.schemas` models."""

    def __init__(self, base_url: str = "http://127.0.0.1:8000", token: str | None = None,
                 lease: str | None = None, timeout: float = 10.0,
                 transport: httpx.BaseTransport | None = None) -> None:
        self.base_url = base_url.rstrip("/")
        self.token = token
        self.lease = lease
        self.leases: dict[str, str] = {}
        self.timeout = timeout
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self._http = httpx.Client(base_url=self.base_url, headers=headers, timeout=timeout,
                                  transport=transport)

    def __enter__(self) -> ArmClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def _headers(self, call: Call[Any]) -> dict[str, str]:
        headers = dict(call.headers)
        lease = self.leases.get(call.arm or "", self.lease)
        if lease and LEASE_HEADER not in headers:
            headers[LEASE_HEADER] = lease
        return headers

    def send(self, call: Call[T]) -> T:
        timeout = self.timeout if call.timeout is None else max(call.timeout, self.timeout)
        attempt = 0
        while True:
            try:
                resp = self._http.request(call.method, call.path, json=call.body,
                                          params=call.params, headers=self._headers(call),
                                          timeout=timeout)
            except httpx.HTTPError as exc:
                if should_retry(call, attempt, exc, None):
                    time.sleep(backoff(attempt))
                    attempt += 1
                    continue
                raise transport_error(exc, call) from exc
            if should_retry(call, attempt, None, resp):
                time.sleep(backoff(attempt))
                attempt += 1
                continue
            return parse_answer(call, resp)

    # --------------------------------------------------------- arms

    def health(self) -> s.Health:
        return self.send(Requests.health())

    def arms(self) -> list[s.ArmSummary]:
        return self.send(Requests.arms())

    def arm(self, arm: str) -> s.ArmDetail:
        return self.send(Requests.arm(arm))

    def state(self, arm: str) -> s.Sample:
        return self.send(Requests.state(arm))

    # --------------------------------------------------------- motion

    def move_joints(self, arm: str, positions: Sequence[float], *, duration: float | None = None,
                    speed: float = 1.0, mode: s.QueueMode = "queue",
                    wait: bool = False) -> s.Motion:
        req = move_joints_model(positions, duration, speed, mode, wait)
        return self.send(Requests.joints_request("move", arm, req, safe=False))

    def move_pose(self, arm: str, x: float, y: float, z: float, *,
                  path: Literal["joint", "line"] = "joint", branch: int | None = None,
                  ik_case: Literal["dx_zero", "dx_used"] | None = None,
                  duration: float | None = None, speed: float = 1.0,
                  mode: s.QueueMode = "queue", wait: bool = False) -> s.Motion:
        req = move_pose_model(x, y, z, path, branch, ik_case, duration, speed, mode, wait)
        return self.send(Requests.pose_request("move", arm, req, safe=False))

    def plan_joints(self, arm: str, positions: Sequence[float], *, duration: float | None = None,
                    speed: float = 1.0, mode: s.QueueMode = "queue") -> s.Motion:
        req = move_joints_model(positions, duration, speed, mode, False)
        return self.send(Requests.joints_request("plan", arm, req, safe=True))

    def plan_pose(self, arm: str, x: float, y: float, z: float, *,
                  path: Literal["joint", "line"] = "joint", branch: int | None = None,
                  ik_case: Literal["dx_zero", "dx_used"] | None = None,
                  duration: float | None = None, speed: float = 1.0,
                  mode: s.QueueMode = "queue") -> s.Motion:
        req = move_pose_model(x, y, z, path, branch, ik_case, duration, speed, mode, False)
        return self.send(Requests.pose_request("plan", arm, req, safe=True))

    def motion(self, arm: str, motion_id: str) -> s.Motion:
        return self.send(Requests.motion(arm, motion_id))

    def cancel_motion(self, arm: str, motion_id: str) -> s.Motion:
        return self.send(Requests.cancel_motion(arm, motion_id))

    def wait_motion(self, arm: str, motion_id: str, timeout: float = 120.0,
                    poll: float = 0.05) -> s.Motion:
        deadline = time.monotonic() + timeout
        while True:
            m = self.motion(arm, motion_id)
            if m.status in TERMINAL:
                return m
            if time.monotonic() > deadline:
                raise TimeoutError(f"motion {motion_id} still {m.status} after {timeout} s")
            time.sleep(poll)

    def stop(self, arm: str) -> s.StopResult:
        return self.send(Requests.stop(arm))

    def estop(self, arm: str) -> s.EstopState:
        return self.send(Requests.estop(arm))

    def release_estop(self, arm: str) -> s.EstopState:
        return self.send(Requests.release_estop(arm))

    def gripper(self, arm: str, value: float) -> s.GripperState:
        return self.send(Requests.gripper(arm, value))

    def tare_force(self, arm: str) -> s.ForceTare:
        return self.send(Requests.tare_force(arm))

    def clear_tare(self, arm: str) -> s.ForceTare:
        return self.send(Requests.clear_tare(arm))

    # --------------------------------------------------------- kinematics

    def forward(self, arm: str, positions: Sequence[float]) -> s.ForwardResult:
        return self.send(Requests.forward(arm, positions))

    def inverse(self, arm: str, x: float, y: float, z: float, *,
                ik_case: Literal["dx_zero", "dx_used"] | None = None,
                theta3: float | None = None) -> s.InverseResult:
        req = s.InverseRequest(x=x, y=y, z=z, ik_case=ik_case, theta3=theta3)
        return self.send(Requests.inverse(arm, req))

    def workspace(self, arm: str, **params: Any) -> s.Workspace:
        return self.send(Requests.workspace(arm, params))

    # --------------------------------------------------------- rbe3001 pass-through

    def rbe3001_set_pid(self, arm: str, joints: Sequence[Any]) -> s.SetPidReply:
        return self.send(Requests.rbe3001_set_pid(arm, joints))

    def rbe3001_status(self, arm: str) -> s.Rbe3001Status:
        return self.send(Requests.rbe3001_status(arm))

    def rbe3001_set_gain(self, arm: str, axis: int, kp: float, ki: float, kd: float) -> s.Ack:
        return self.send(Requests.rbe3001_set_gain(arm, axis, kp, ki, kd))

    def rbe3001_set_claw(self, arm: str, value: float) -> s.Ack:
        return self.send(Requests.rbe3001_set_claw(arm, value))

    # --------------------------------------------------------- dynamixel pass-through

    def dxl_ping(self, arm: str, dxl_id: int | None = None) -> s.PingResult:
        return self.send(Requests.dxl_ping(arm, dxl_id))

    def dxl_read_register(self, arm: str, dxl_id: int, name: str) -> s.RegisterValue:
        return self.send(Requests.dxl_read_register(arm, dxl_id, name))

    def dxl_write_register(self, arm: str, dxl_id: int, name: str,
                           raw: int) -> s.RegisterValue:
        return self.send(Requests.dxl_write_register(arm, dxl_id, name, raw))

    def dxl_sync_read(self, arm: str, name: str, ids: Sequence[int]) -> s.SyncReadResult:
        return self.send(Requests.dxl_sync_read(arm, name, ids))

    def dxl_sync_write(self, arm: str, name: str, values: Mapping[int, int]) -> s.Ack:
        return self.send(Requests.dxl_sync_write(arm, name, values))

    def dxl_reboot(self, arm: str, dxl_id: int) -> s.Ack:
        return self.send(Requests.dxl_reboot(arm, dxl_id))

    def home(self, arm: str, positions: Sequence[float] | None = None) -> s.ArmDetail:
        return self.send(Requests.home(arm, positions))

    # --------------------------------------------------------- lease

    def safety(self, arm: str) -> s.Safety:
        return self.send(Requests.safety(arm))

    def set_safety(self, arm: str, **fields: Any) -> s.Safety:
        return self.send(Requests.set_safety(arm, s.SafetyUpdate(**fields)))

    def take_lease(self, arm: str) -> s.Lease:
        return self.send(Requests.take_lease(arm))

    def renew_lease(self, arm: str, lease_id: str) -> s.Lease:
        return self.send(Requests.renew_lease(arm, lease_id))

    def release_lease(self, arm: str, lease_id: str) -> None:
        return self.send(Requests.release_lease(arm, lease_id))

    # --------------------------------------------------------- classroom

    def me(self) -> s.Me:
        return self.send(Requests.me())

    def join_queue(self, arm: str) -> s.QueueEntry:
        return self.send(Requests.join_queue(arm))

    def queue(self, arm: str) -> s.QueueStatus:
        return self.send(Requests.queue(arm))

    def queue_entry(self, arm: str, entry_id: str) -> s.QueueEntry:
        return self.send(Requests.queue_entry(arm, entry_id))

    def leave_queue(self, arm: str, entry_id: str) -> s.QueueEntry:
        return self.send(Requests.leave_queue(arm, entry_id))

    def reorder_queue(self, arm: str, order: Sequence[str]) -> s.QueueStatus:
        return self.send(Requests.reorder_queue(arm, order))

    def clear_queue(self, arm: str) -> s.QueueStatus:
        return self.send(Requests.clear_queue(arm))

    def revoke_lease(self, arm: str) -> None:
        return self.send(Requests.revoke_lease(arm))

    def audit(self, arm: str | None = None, who: str | None = None, since: float | None = None,
              until: float | None = None, limit: int = 100) -> list[s.AuditRecord]:
        return self.send(Requests.audit(  # type: ignore[no-any-return]
            {"arm": arm, "who": who, "since": since, "until": until, "limit": limit}))

    def audit_csv(self, arm: str | None = None, who: str | None = None,
                  since: float | None = None, until: float | None = None,
                  limit: int = 100) -> str:
        return self.send(Requests.audit(  # type: ignore[no-any-return]
            {"arm": arm, "who": who, "since": since, "until": until, "limit": limit}, csv=True))

    @contextlib.contextmanager
    def queue_turn(self, arm: str, poll: float = 0.25, every: float | None = None,
                   timeout: float | None = None) -> Iterator[LeaseKeeper]:
        """Join the queue, wait for the offer, claim and renew the lease for the block (see
        `AsyncArmClient.queue_turn`)."""
        entry = self.join_queue(arm)
        deadline = None if timeout is None else time.monotonic() + timeout
        try:
            while turn_pending(arm, entry, deadline, timeout):
                time.sleep(poll)
                entry = self.queue_entry(arm, entry.id)
            lease = self.renew_lease(arm, entry.lease_id or "")
        except BaseException:
            with contextlib.suppress(ArmServerError):
                self.leave_queue(arm, entry.id)
            raise
        with self._keep(arm, lease, every) as keeper:
            yield keeper

    @contextlib.contextmanager
    def hold_lease(self, arm: str, every: float | None = None) -> Iterator[LeaseKeeper]:
        """Take the lease, renew it from a background thread, release it on exit."""
        lease = self.take_lease(arm)
        with self._keep(arm, lease, every) as keeper:
            yield keeper

    @contextlib.contextmanager
    def _keep(self, arm: str, lease: s.Lease, every: float | None) -> Iterator[LeaseKeeper]:
        keeper = LeaseKeeper(lease)
        previous = self.leases.get(arm)
        self.leases[arm] = lease.id
        period = every if every is not None else max(lease.ttl / 3.0, 0.05)
        done = threading.Event()

        def beat() -> None:
            while not done.wait(period):
                try:
                    keeper.lease = self.renew_lease(arm, lease.id)
                    keeper.renewals += 1
                except ArmServerError as exc:
                    keeper.error = exc
                    log.warning("%s: lease %s not renewed: %s", arm, lease.id, exc)
                    if exc.status != 0:
                        return

        thread = threading.Thread(target=beat, name=f"lease:{arm}", daemon=True)
        thread.start()
        try:
            yield keeper
        finally:
            done.set()
            thread.join(timeout=self.timeout)
            if previous is None:
                self.leases.pop(arm, None)
            else:
                self.leases[arm] = previous
            with contextlib.suppress(ArmServerError):
                self.release_lease(arm, lease.id)

    # --------------------------------------------------------- telemetry

    def telemetry_messages(self, arm: str, rate: float | None = None
                           ) -> Iterator[s.TelemetryMessage | s.EventMessage]:
        from websockets.exceptions import ConnectionClosed, InvalidHandshake
        from websockets.sync.client import connect

        headers = {"Authorization": f"Bearer {self.token}"} if self.token else None
        try:
            ws = connect(ws_url(self.base_url, arm, rate, None), additional_headers=headers,
                         open_timeout=self.timeout, max_size=2 ** 24)
        except (InvalidHandshake, OSError, TimeoutError) as exc:
            raise ws_handshake_error(exc) from exc
        with ws:
            while True:
                try:
                    raw = ws.recv()
                except ConnectionClosed as exc:
                    err = ws_close_error(exc)
                    if err is not None:
                        raise err from exc
                    return
                yield parse_ws_message(raw)

    def telemetry(self, arm: str, rate: float | None = None, events: bool = False
                  ) -> Iterator[s.Sample | s.EventMessage]:
        last = -1
        for msg in self.telemetry_messages(arm, rate):
            if isinstance(msg, s.EventMessage):
                if events:
                    yield msg
                continue
            for sample in msg.samples:
                if sample.seq > last:
                    last = sample.seq
                    yield sample
