"""A teleoperation leader on another worker process of a lab (`armserver serve --workers N`,
app/lab): its samples read over that worker's telemetry WebSocket, on its Unix socket.

The session runs where it always does, on the follower's control loop in the follower's worker
(app/teleop/session.py), and reads the leader through `subscribe()` as it reads a local one. A
reader task on this worker's HTTP loop holds the WebSocket (`?rate=RATE_HZ`: each batch as
soon as it is due, API.md "Telemetry") and keeps the newest sample of each message; the
session takes them under a lock, from its own thread. Only the newest sample counts for a tick,
so the others of a batch are not kept. The latency the session reports (leader sample time to
follower command) then includes the hop: the leader worker's sender, the socket, this reader.

The leader's estop latch is its samples' `estop` stamp (app/telemetry/arm_hub.py). A lost
socket (the leader's worker restarting: close 1012) is opened again with a backoff; meanwhile
no sample comes, and the session's deadman holds the follower.

A leader freed for the session (a real arm's default, `free_leader`) has its torque switched
in its own worker, where its lease and its state are: `PUT /api/v1/arms/{leader}/torque` on
that worker's socket, with the caller's token, the leader's lease (X-Leader-Lease) and the
body's `load_supported`, on this worker's HTTP loop (the session's end asks from the
follower's control loop). That worker's answer is the refusal: its lease, a motion it runs,
a device without a torque switch.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import orjson
from websockets.asyncio.client import unix_connect
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidStatus

from app import schemas as s
from app.arms import model_for
from app.arms.model import KinematicsModel
from app.config import ArmProfile
from app.errors import CODES, ArmError, DeviceTimeout, LinkDown
from app.runtime.control_thread import on_home
from app.runtime.tasks import soon_on

log = logging.getLogger(__name__)

#: The leader's telemetry rate asked of its worker, Hz: at 100 Hz and up a batch goes as soon
#: as it is due, so a sample waits at most 1/RATE_HZ (5 ms) for its message.
RATE_HZ = 200.0
#: How long opening the leader's socket and its first sample may take, s.
OPEN_TIMEOUT_S = 5.0
#: Wait before opening a lost socket again, s; doubles to RECONNECT_MAX_S.
RECONNECT_S = 0.1
RECONNECT_MAX_S = 2.0
#: Newest samples kept between two takes (the session reads only the last).
KEEP = 8
#: How long the leader's worker may take to switch its torque, s (its reply timeouts, a
#: read of the servos' positions before torque on).
TORQUE_TIMEOUT_S = 5.0


@dataclass(frozen=True)
class Peer:
    """An arm on another worker: its profile and that worker's Unix socket."""

    profile: ArmProfile
    uds: Path


class RemoteFeed:
    """The session's view of the remote leader's samples (`LeaderFeed`)."""

    def __init__(self, leader: RemoteLeader, initial: str | None) -> None:
        self._leader = leader
        self._initial = initial

    @property
    def initial(self) -> str | None:
        return self._initial

    def take(self) -> tuple[list[str], list[str], int]:
        return self._leader._take(), [], 0

    def close(self) -> None:
        self._leader.close()


class RemoteLeader:
    """An arm of another worker as a teleoperation leader (`Leader`); `open()` it first (on the
    HTTP loop), `close()` it from any thread."""

    def __init__(self, peer: Peer, headers: list[tuple[str, str]], lease: str | None = None,
                 load_supported: bool = False) -> None:
        """`headers`: the caller's (its token); `lease`: the leader's lease id, where one is
        held, and `load_supported`, for its torque (`set_torque`)."""
        self.profile = peer.profile
        self._uds = peer.uds
        self._headers = headers
        self._lease = lease
        self._load_supported = load_supported
        self._model = model_for(peer.profile)
        self._lock = threading.Lock()
        self._pending: deque[str] = deque(maxlen=KEEP)
        self._latest: dict[str, Any] | None = None
        self._latest_raw: str | None = None
        self._connected = False
        self.last_error: str | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._task: asyncio.Task[None] | None = None
        self._first = asyncio.Event()

    @property
    def name(self) -> str:
        return self.profile.name

    @property
    def model(self) -> KinematicsModel:
        return self._model

    @property
    def estop(self) -> bool:
        latest = self._latest
        return bool(latest is not None and latest.get("estop"))

    def link_status(self) -> s.LinkStatus:
        up = self._connected and self._latest is not None and not self._latest.get("stale")
        return s.LinkStatus(kind=self.profile.link.kind, address=self.profile.link.address,
                            state="up" if up else "down", connected=up,
                            last_error=None if up else self.last_error)

    async def set_torque(self, on: bool) -> None:
        """Switch the leader's torque in its own worker (on this worker's HTTP loop, from any
        loop): that worker's refusal is raised as its code says; 504 `device_timeout` where
        it does not answer within TORQUE_TIMEOUT_S, 503 `link_down` where its socket
        refuses."""
        await on_home(self._loop, lambda: self._put_torque(on))

    async def _put_torque(self, on: bool) -> None:
        headers = dict(self._headers)
        if self._lease is not None:
            headers["X-Arm-Lease"] = self._lease
        body = {"on": on, "load_supported": self._load_supported}
        try:
            async with httpx.AsyncClient(transport=httpx.AsyncHTTPTransport(uds=str(self._uds)),
                                         base_url="http://localhost",
                                         timeout=TORQUE_TIMEOUT_S) as client:
                r = await client.put(f"/api/v1/arms/{self.name}/torque", json=body,
                                     headers=headers)
        except httpx.TimeoutException:
            raise DeviceTimeout(f"{self.name}'s worker did not switch its torque within "
                                f"{TORQUE_TIMEOUT_S:g} s") from None
        except httpx.HTTPError as exc:
            raise LinkDown(f"{self.name}'s worker: {exc!r}") from None
        if r.status_code == 200:
            return
        try:
            err = r.json()
            detail, code = str(err["detail"]), str(err["code"])
        except (ValueError, KeyError, TypeError):
            detail, code = f"HTTP {r.status_code}: {r.text[:200]}", "device_error"
        row = CODES.get(code)
        if row is None or row.status is None:  # not an answer of the table: the worker's fault
            code = "device_error"
        raise ArmError(f"{self.name}'s worker: {detail}", code=code)

    def subscribe(self, backlog: int | None = None) -> RemoteFeed:
        with self._lock:
            self._pending.clear()
            return RemoteFeed(self, self._latest_raw)

    def _take(self) -> list[str]:
        with self._lock:
            out = list(self._pending)
            self._pending.clear()
        return out

    async def open(self) -> None:
        """Start reading; answers once the first sample came. 503 `link_down` when the leader's
        worker does not answer within OPEN_TIMEOUT_S or refuses the socket."""
        self._loop = asyncio.get_running_loop()
        self._task = asyncio.create_task(self._run(), name=f"teleop-leader:{self.name}")
        try:
            async with asyncio.timeout(OPEN_TIMEOUT_S):
                await self._first.wait()
        except TimeoutError:
            self.close()
            raise LinkDown(f"{self.name}'s worker sent no sample within {OPEN_TIMEOUT_S:g} s "
                           f"({self.last_error or 'no answer'})") from None

    def close(self) -> None:
        """Stop reading (from any thread; again is nothing)."""
        task, loop = self._task, self._loop
        if task is None or loop is None or task.done():
            return
        with contextlib.suppress(RuntimeError):  # its loop closed: the task is gone
            soon_on(loop, task.cancel)

    async def _run(self) -> None:
        uri = f"ws://localhost/api/v1/arms/{self.name}/telemetry?rate={RATE_HZ:g}"
        wait = RECONNECT_S
        while True:
            try:
                async with unix_connect(str(self._uds), uri, additional_headers=self._headers,
                                        compression=None, max_size=None, ping_interval=None,
                                        open_timeout=OPEN_TIMEOUT_S) as ws:
                    if wait != RECONNECT_S:
                        log.info("teleop leader %s: its socket is open again", self.name)
                    self._connected, wait = True, RECONNECT_S
                    async for message in ws:
                        self._received(message)
                    self.last_error = f"the leader's socket closed ({ws.close_code})"
            except InvalidStatus as exc:
                self.last_error = f"the leader's worker refused: {exc.response.status_code}"
            except (OSError, InvalidHandshake, TimeoutError, ConnectionClosed) as exc:
                self.last_error = f"the leader's worker: {exc!r}"
            if self._connected or wait == RECONNECT_S:  # once per outage, not per try
                log.warning("teleop leader %s: %s; opening it again", self.name,
                            self.last_error)
            self._connected = False
            await asyncio.sleep(wait)
            wait = min(wait * 2, RECONNECT_MAX_S)

    def _received(self, message: str | bytes) -> None:
        try:
            data = orjson.loads(message)
            latest = data["samples"][-1] if data.get("type") == "telemetry" else None
        except (orjson.JSONDecodeError, AttributeError, KeyError, IndexError, TypeError):
            log.warning("teleop leader %s: a message that is no telemetry: %.80r", self.name,
                        message)
            return
        if not isinstance(latest, dict):  # an event, or a batch with no sample
            return
        raw = orjson.dumps(latest).decode()
        with self._lock:
            self._latest, self._latest_raw = latest, raw
            self._pending.append(raw)
        self._first.set()


def peer_of(peers: Mapping[str, Peer] | None, name: str) -> Peer | None:
    """`name`'s peer, where the lab gave this worker the arms of the others."""
    return None if peers is None else peers.get(name)

