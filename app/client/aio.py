"""`AsyncArmClient`: the asyncio client, one method per route of the contract, returning the
contract's own pydantic models (`app.schemas`). Request bodies are built from those models
too, so a bad request (a NaN, a speed above 1) is refused before it leaves the process.

Errors: every non-2xx answer raises `ArmServerError` (or its subclass for the `code`, from the
server's table: `app.client.errors`) carrying `code`, `detail` and HTTP `status`. A transport
failure raises `ConnectionFailed` (code "connection_failed", status 0). Retries: see
`app.client.core`. The blocking `ArmClient` (`app.client.sync`) is made from this class.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator, Mapping, Sequence
from typing import Any, Literal, TypeVar

import httpx

from app import schemas as s
from app.client.core import (
    TERMINAL,
    LeaseKeeper,
    auth_headers,
    backoff,
    parse_answer,
    parse_ws_message,
    should_retry,
    transport_error,
    turn_pending,
    ws_close_error,
    ws_handshake_error,
    ws_url,
)
from app.client.errors import ArmServerError, error_from_body
from app.client.lease import keep_lease
from app.client.mjpeg import mjpeg_parts
from app.client.routes import (
    LEASE_HEADER,
    Call,
    Requests,
    move_joints_model,
    move_pose_model,
    url_path,
)

log = logging.getLogger(__name__)

T = TypeVar("T")


class AsyncArmClient:
    """Asyncio client: one method per route, returning `app.schemas` models.

    `token` is sent as `Authorization: Bearer`; `lease` (a lease id) as `X-Arm-Lease` on every
    request, unless the arm has its own lease taken with `hold_lease`.
    """

    def __init__(self, base_url: str = "http://127.0.0.1:8000", token: str | None = None,
                 lease: str | None = None, timeout: float = 10.0,
                 transport: httpx.AsyncBaseTransport | None = None) -> None:
        self.base_url = base_url.rstrip("/")
        self.token = token
        self.lease = lease
        self.leases: dict[str, str] = {}
        self.timeout = timeout
        self._http = httpx.AsyncClient(base_url=self.base_url, headers=auth_headers(token),
                                       timeout=timeout, transport=transport)

    async def __aenter__(self) -> AsyncArmClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        await self._http.aclose()

    def _headers(self, call: Call[Any]) -> dict[str, str]:
        headers = dict(call.headers)
        lease = self.leases.get(call.arm or "", self.lease)
        if lease and LEASE_HEADER not in headers:
            headers[LEASE_HEADER] = lease
        return headers

    async def send(self, call: Call[T]) -> T:
        """Send one request, retrying only where `should_retry` says it is safe."""
        timeout = self.timeout if call.timeout is None else max(call.timeout, self.timeout)
        attempt = 0
        while True:
            try:
                resp = await self._http.request(call.method, call.path, json=call.body,
                                                params=call.params, headers=self._headers(call),
                                                timeout=timeout)
            except httpx.HTTPError as exc:
                if should_retry(call, attempt, exc, None):
                    await asyncio.sleep(backoff(attempt))
                    attempt += 1
                    continue
                raise transport_error(exc, call) from exc
            if should_retry(call, attempt, None, resp):
                await asyncio.sleep(backoff(attempt))
                attempt += 1
                continue
            return parse_answer(call, resp)

    # --------------------------------------------------------- arms

    async def health(self) -> s.Health:
        return await self.send(Requests.health())

    async def arms(self) -> list[s.ArmSummary]:
        return await self.send(Requests.arms())

    async def arm(self, arm: str) -> s.ArmDetail:
        return await self.send(Requests.arm(arm))

    async def state(self, arm: str) -> s.Sample:
        return await self.send(Requests.state(arm))

    # --------------------------------------------------------- motion

    async def move_joints(self, arm: str, positions: Sequence[float], *,
                          duration: float | None = None, speed: float = 1.0,
                          mode: s.QueueMode = "queue", wait: bool = False) -> s.Motion:
        """Joint-space move (rad / m). 202 with the queued motion, or the final one if `wait`."""
        req = move_joints_model(positions, duration, speed, mode, wait)
        return await self.send(Requests.joints_request("move", arm, req, safe=False))

    async def move_pose(self, arm: str, x: float, y: float, z: float, *,
                        path: Literal["joint", "line"] = "joint", branch: int | None = None,
                        ik_case: Literal["dx_zero", "dx_used"] | None = None,
                        duration: float | None = None, speed: float = 1.0,
                        mode: s.QueueMode = "queue", wait: bool = False) -> s.Motion:
        """Move the tip to (x, y, z) m along a joint-space or straight-line path."""
        req = move_pose_model(x, y, z, path, branch, ik_case, duration, speed, mode, wait)
        return await self.send(Requests.pose_request("move", arm, req, safe=False))

    async def plan_joints(self, arm: str, positions: Sequence[float], *,
                          duration: float | None = None, speed: float = 1.0,
                          mode: s.QueueMode = "queue") -> s.Motion:
        """Preview a joint move: the motion it would be, nothing moves."""
        req = move_joints_model(positions, duration, speed, mode, False)
        return await self.send(Requests.joints_request("plan", arm, req, safe=True))

    async def plan_pose(self, arm: str, x: float, y: float, z: float, *,
                        path: Literal["joint", "line"] = "joint", branch: int | None = None,
                        ik_case: Literal["dx_zero", "dx_used"] | None = None,
                        duration: float | None = None, speed: float = 1.0,
                        mode: s.QueueMode = "queue") -> s.Motion:
        """Preview a pose move (planned duration, target joints, tip path); nothing moves."""
        req = move_pose_model(x, y, z, path, branch, ik_case, duration, speed, mode, False)
        return await self.send(Requests.pose_request("plan", arm, req, safe=True))

    async def motion(self, arm: str, motion_id: str) -> s.Motion:
        return await self.send(Requests.motion(arm, motion_id))

    async def cancel_motion(self, arm: str, motion_id: str) -> s.Motion:
        return await self.send(Requests.cancel_motion(arm, motion_id))

    async def wait_motion(self, arm: str, motion_id: str, timeout: float = 120.0,
                          poll: float = 0.05) -> s.Motion:
        """Poll a motion until it is done, stopped or failed; TimeoutError after `timeout` s."""
        deadline = time.monotonic() + timeout
        while True:
            m = await self.motion(arm, motion_id)
            if m.status in TERMINAL:
                return m
            if time.monotonic() > deadline:
                raise TimeoutError(f"motion {motion_id} still {m.status} after {timeout} s")
            await asyncio.sleep(poll)

    async def stop(self, arm: str) -> s.StopResult:
        return await self.send(Requests.stop(arm))

    async def estop(self, arm: str) -> s.EstopState:
        return await self.send(Requests.estop(arm))

    async def release_estop(self, arm: str) -> s.EstopState:
        return await self.send(Requests.release_estop(arm))

    async def gripper(self, arm: str, value: float) -> s.GripperState:
        """0.0 open .. 1.0 closed; `NoGripper` on an arm without an actuated gripper."""
        return await self.send(Requests.gripper(arm, value))

    async def tare_force(self, arm: str) -> s.ForceTare:
        """The current joint torques become the zero of `torques` and `tip_force`."""
        return await self.send(Requests.tare_force(arm))

    async def clear_tare(self, arm: str) -> s.ForceTare:
        return await self.send(Requests.clear_tare(arm))

    # --------------------------------------------------------- kinematics

    async def forward(self, arm: str, positions: Sequence[float]) -> s.ForwardResult:
        return await self.send(Requests.forward(arm, positions))

    async def inverse(self, arm: str, x: float, y: float, z: float, *,
                      ik_case: Literal["dx_zero", "dx_used"] | None = None,
                      theta3: float | None = None) -> s.InverseResult:
        req = s.InverseRequest(x=x, y=y, z=z, ik_case=ik_case, theta3=theta3)
        return await self.send(Requests.inverse(arm, req))

    async def inverse_velocity(self, arm: str, positions: Sequence[float],
                               velocity: Sequence[float]) -> s.InverseVelocityResult:
        """Joint velocities giving tip velocity (vx, vy, vz) m/s at `positions`."""
        vx, vy, vz = velocity
        req = s.InverseVelocityRequest(positions=list(positions),
                                       velocity=s.Vec3(x=vx, y=vy, z=vz))
        return await self.send(Requests.inverse_velocity(arm, req))

    async def workspace(self, /, arm: str, **params: Any) -> s.Workspace:
        return await self.send(Requests.workspace(arm, params))

    # --------------------------------------------------------- rbe3001 pass-through

    async def rbe3001_set_pid(self, arm: str, joints: Sequence[Any]) -> s.SetPidReply:
        """Three setpoints: `PidSetpoint`s, dicts, or bare position ticks."""
        return await self.send(Requests.rbe3001_set_pid(arm, joints))

    async def rbe3001_status(self, arm: str) -> s.Rbe3001Status:
        return await self.send(Requests.rbe3001_status(arm))

    async def rbe3001_set_gain(self, arm: str, axis: int, kp: float, ki: float,
                               kd: float) -> s.Ack:
        return await self.send(Requests.rbe3001_set_gain(arm, axis, kp, ki, kd))

    async def rbe3001_set_claw(self, arm: str, value: float) -> s.Ack:
        return await self.send(Requests.rbe3001_set_claw(arm, value))

    # --------------------------------------------------------- dynamixel pass-through

    async def dxl_ping(self, arm: str, dxl_id: int | None = None) -> s.PingResult:
        return await self.send(Requests.dxl_ping(arm, dxl_id))

    async def dxl_read_register(self, arm: str, dxl_id: int, name: str) -> s.RegisterValue:
        return await self.send(Requests.dxl_read_register(arm, dxl_id, name))

    async def dxl_write_register(self, arm: str, dxl_id: int, name: str,
                                 raw: int) -> s.RegisterValue:
        return await self.send(Requests.dxl_write_register(arm, dxl_id, name, raw))

    async def dxl_sync_read(self, arm: str, name: str, ids: Sequence[int]) -> s.SyncReadResult:
        return await self.send(Requests.dxl_sync_read(arm, name, ids))

    async def dxl_sync_write(self, arm: str, name: str, values: Mapping[int, int]) -> s.Ack:
        return await self.send(Requests.dxl_sync_write(arm, name, values))

    async def dxl_reboot(self, arm: str, dxl_id: int, load_supported: bool = False) -> s.Ack:
        """REBOOT one servo; `load_supported` where its joint falls without torque and its
        load rests or is held (409 `in_use` otherwise while the servo holds torque)."""
        return await self.send(Requests.dxl_reboot(arm, dxl_id, load_supported))

    async def home(self, arm: str, positions: Sequence[float] | None = None) -> s.ArmDetail:
        """Declare the arm's current pose (the profile's home pose without positions)."""
        return await self.send(Requests.home(arm, positions))

    async def unhome(self, arm: str) -> s.ArmDetail:
        """Un-home the arm on purpose (before declaring a new home pose)."""
        return await self.send(Requests.unhome(arm))

    async def set_torque(self, arm: str, on: bool,
                         load_supported: bool = False) -> s.TorqueState:
        """The joints' torque off (the arm moved by hand) or on again, holding where it is;
        `load_supported`: its joints that fall without torque are held (else 409 `in_use`)."""
        return await self.send(Requests.set_torque(arm, on, load_supported))

    async def calibration(self, arm: str) -> s.ArmCalibration:
        """The joints' calibration on this hardware and the gravity fit."""
        return await self.send(Requests.calibration(arm))

    async def calibrate(self, arm: str, positions: Sequence[float] | None = None,
                        pose: str | None = None) -> s.ArmCalibration:
        """Declare the pose the arm is in (joint values, or a calibration pose's name)."""
        return await self.send(Requests.calibrate(arm, positions, pose))

    async def forget_calibration(self, arm: str) -> s.ArmCalibration:
        """Drop the stored calibration of the arm's hardware (instructor)."""
        return await self.send(Requests.forget_calibration(arm))

    async def calibrate_gravity(self, arm: str, poses: Sequence[Sequence[float]] | None = None,
                                wait: bool = False) -> s.GravityRun:
        """The gravity fit's motion through `poses` (default: the server's choice)."""
        return await self.send(Requests.calibrate_gravity(arm, poses, wait))

    async def servo_setup(self) -> s.ServoSetupInfo:
        """What servo set-up can do on this server: profiles, ports in use, the practice bus."""
        return await self.send(Requests.servo_setup())

    async def scan_servos(self, port: str, profile: str, baudrates: Sequence[int] | None = None,
                          scan_timeout: float | None = None) -> s.ServoScan:
        """The servos answering on `port` and whose each is against `profile` (instructor);
        `scan_timeout`: how long each rate's broadcast PING waits, s."""
        return await self.send(Requests.scan_servos(port, profile, baudrates, scan_timeout))

    async def assign_servo(self, port: str, profile: str, joint: str,
                           baudrates: Sequence[int] | None = None,
                           scan_timeout: float | None = None) -> s.ServoAssigned:
        """Set up the one new servo on `port` as `joint`'s, EEPROM (instructor)."""
        return await self.send(Requests.assign_servo(port, profile, joint, baudrates,
                                                     scan_timeout))

    async def start_practice_bus(self, servos: int = 1) -> s.PracticeBus:
        """Start a simulated factory-state bus on a loopback port (instructor)."""
        return await self.send(Requests.start_practice_bus(servos))

    async def plug_practice_servo(self) -> s.PracticeBus:
        """Plug one more factory servo into the practice bus (instructor)."""
        return await self.send(Requests.plug_practice_servo())

    async def stop_practice_bus(self) -> s.PracticeBus:
        """Stop the practice bus (instructor)."""
        return await self.send(Requests.stop_practice_bus())

    # --------------------------------------------------------- lease

    async def safety(self, arm: str) -> s.Safety:
        """The arm's safety envelope: keep-out zones, floor, speed override."""
        return await self.send(Requests.safety(arm))

    async def set_safety(self, /, arm: str, **fields: Any) -> s.Safety:
        """Change the envelope (instructor): `zones=[...]`, `floor_z=` (None removes the
        floor), `speed_override=`; fields not given are kept."""
        return await self.send(Requests.set_safety(arm, s.SafetyUpdate(**fields)))

    async def world(self, arm: str) -> s.WorldScene:
        """A simulated arm's world: objects, bins, the table and the simulated tip."""
        return await self.send(Requests.world(arm))

    async def set_world(self, arm: str, scene: s.WorldScene | dict[str, Any]) -> s.WorldScene:
        """Lay out a new scene on a simulated arm (lease holder or instructor): objects
        (`id`, `kind`, `color`, `position`) and bins (`name`, `color`, `min`, `max`)."""
        body = scene if isinstance(scene, s.WorldScene) else s.WorldScene.model_validate(scene)
        return await self.send(Requests.set_world(arm, body))

    async def move_hand(self, arm: str, positions: Sequence[float] | None = None, *,
                        speed: float = 0.5, wait: bool = False) -> s.HandState:
        """Move a simulated arm's joints by the hand in its world (rad or m), as a person
        moves an arm whose torque is off (a `free_leader` of a teleoperation session); at
        `speed` on the longest way; `wait`: answer when the hand has arrived. `positions`
        None: take hold where the arm is (moving nothing; allowed with its torque on). The
        hand holds the arm until `let_go_hand`."""
        req = s.HandMoveRequest(positions=None if positions is None else list(positions),
                                speed=speed, wait=wait)
        return await self.send(Requests.move_hand(arm, req))

    async def let_go_hand(self, arm: str) -> None:
        """Take the hand off a simulated arm: a joint that falls without torque and whose
        servo's torque is off falls, as on hardware."""
        return await self.send(Requests.let_go_hand(arm))

    async def start_teleop(self, leader: str, follower: str, *, rate_hz: float = 50.0,
                           mapping: Literal["joints", "tip"] = "joints",
                           deadman_s: float = 0.2, scale: Sequence[float] | None = None,
                           offset: Sequence[float] | None = None, tip_scale: float = 1.0,
                           tip_offset: Sequence[float] | None = None,
                           clamp_margin: float = 0.0,
                           free_leader: bool | None = None,
                           load_supported: bool = False) -> s.TeleopSession:
        """Start teleoperation: `leader` drives `follower` (whose lease this client must
        hold) at `rate_hz` (30..100), mapping `joints` (one to one: `scale`, `offset` per
        joint) or `tip` (`tip_scale`, `tip_offset` m); targets clamped `clamp_margin` inside
        the follower's limits; a leader sample older than `deadman_s` holds the follower.
        `free_leader`: the leader's torque off for the session (default: a real leader's);
        `load_supported`: its joints that fall without torque are held (else 409 `in_use`
        for such a leader freed)."""
        req = s.TeleopStart(leader=leader, follower=follower, rate_hz=rate_hz, mapping=mapping,
                            deadman_s=deadman_s, tip_scale=tip_scale, clamp_margin=clamp_margin,
                            free_leader=free_leader, load_supported=load_supported,
                            scale=None if scale is None else list(scale),
                            offset=None if offset is None else list(offset),
                            tip_offset=None if tip_offset is None else list(tip_offset))
        return await self.send(Requests.start_teleop(req, self.leases.get(leader)))

    async def replay(self, arm: str, recording: str, episode: int, *,
                     wait: bool = False) -> s.Motion:
        """Play a recorded episode's actions back on `arm` (a soft start to the first, then
        the dataset's fps) as one motion; 202 with it, or its final state if `wait`."""
        req = s.ReplayRequest(recording=recording, episode=episode, wait=wait)
        return await self.send(Requests.replay(arm, req))

    async def teleop_sessions(self) -> list[s.TeleopSession]:
        """Teleoperation sessions, running then recently ended, with their figures."""
        return await self.send(Requests.teleop_sessions())

    async def stop_teleop(self, session_id: str) -> s.TeleopSession:
        """Stop a teleoperation session; the follower holds where it is."""
        return await self.send(Requests.stop_teleop(session_id))

    async def take_lease(self, arm: str) -> s.Lease:
        return await self.send(Requests.take_lease(arm))

    async def renew_lease(self, arm: str, lease_id: str) -> s.Lease:
        return await self.send(Requests.renew_lease(arm, lease_id))

    async def release_lease(self, arm: str, lease_id: str) -> None:
        return await self.send(Requests.release_lease(arm, lease_id))

    # --------------------------------------------------------- classroom

    async def me(self) -> s.Me:
        return await self.send(Requests.me())

    async def join_queue(self, arm: str) -> s.QueueEntry:
        return await self.send(Requests.join_queue(arm))

    async def queue(self, arm: str) -> s.QueueStatus:
        return await self.send(Requests.queue(arm))

    async def queue_entry(self, arm: str, entry_id: str) -> s.QueueEntry:
        return await self.send(Requests.queue_entry(arm, entry_id))

    async def leave_queue(self, arm: str, entry_id: str) -> s.QueueEntry:
        return await self.send(Requests.leave_queue(arm, entry_id))

    async def reorder_queue(self, arm: str, order: Sequence[str]) -> s.QueueStatus:
        """Instructor: every waiting entry's id, in the new order."""
        return await self.send(Requests.reorder_queue(arm, order))

    async def clear_queue(self, arm: str) -> s.QueueStatus:
        return await self.send(Requests.clear_queue(arm))

    async def revoke_lease(self, arm: str) -> None:
        """Instructor: end the arm's lease whoever holds it (and retry a failed hand-off)."""
        return await self.send(Requests.revoke_lease(arm))

    async def audit(self, arm: str | None = None, who: str | None = None,
                    since: float | None = None, until: float | None = None,
                    limit: int = 100) -> list[s.AuditRecord]:
        """Instructor: audit records, newest first."""
        return await self.send(Requests.audit(
            {"arm": arm, "who": who, "since": since, "until": until, "limit": limit}))

    async def audit_csv(self, arm: str | None = None, who: str | None = None,
                        since: float | None = None, until: float | None = None,
                        limit: int = 100) -> str:
        """The same as CSV text (a header row, then one row per record)."""
        return await self.send(Requests.audit_csv(
            {"arm": arm, "who": who, "since": since, "until": until, "limit": limit}))

    # --------------------------------------------------------- recordings

    async def recordings(self) -> list[s.RecordingSummary]:
        return await self.send(Requests.recordings())

    async def recording(self, rid: str) -> s.RecordingDetail:
        return await self.send(Requests.recording(rid))

    async def create_recording(self, name: str, arms: Sequence[str],
                               cameras: Sequence[str] = (), fps: int = 30,
                               task: str = "demonstration") -> s.RecordingDetail:
        """Operator: a LeRobot v3.0 dataset of `arms` (and `cameras`) at `fps`."""
        req = s.RecordingCreate(name=name, arms=list(arms), cameras=list(cameras), fps=fps,
                                task=task)
        return await self.send(Requests.create_recording(req))

    async def start_episode(self, rid: str, task: str | None = None) -> s.RecordingDetail:
        """Operator: start recording an episode (409 `busy` while one records)."""
        return await self.send(Requests.start_episode(rid, task))

    async def stop_episode(self, rid: str) -> s.RecordingDetail:
        """Operator: end the episode; answers once it is written."""
        return await self.send(Requests.stop_episode(rid))

    async def discard_episode(self, rid: str) -> s.RecordingDetail:
        return await self.send(Requests.discard_episode(rid))

    async def recording_archive(self, rid: str) -> bytes:
        """The dataset's folder as tar bytes."""
        return await self.send(Requests.recording_archive(rid))

    # --------------------------------------------------------- cameras

    async def cameras(self) -> list[s.CameraSummary]:
        return await self.send(Requests.cameras())

    async def camera(self, cam: str) -> s.CameraDetail:
        return await self.send(Requests.camera(cam))

    async def camera_frame(self, cam: str) -> bytes:
        """The camera's latest frame, JPEG bytes."""
        return await self.send(Requests.camera_frame(cam))

    async def camera_stream(self, cam: str, frames: int = 1) -> list[bytes]:
        """`frames` successive JPEGs of the camera's MJPEG stream (then the stream is left)."""
        out: list[bytes] = []
        async with self._http.stream("GET", url_path("cameras", cam, "stream"),
                                     headers=self._headers(Requests.camera(cam))) as resp:
            if resp.status_code >= 400:
                raise error_from_body(resp.status_code, await resp.aread())
            async for jpeg in mjpeg_parts(resp.aiter_bytes()):
                out.append(jpeg)
                if len(out) >= frames:
                    break
        return out

    async def detections(self, cam: str, color: str | None = None,
                         min_area: int = 50) -> s.Detections:
        """Objects of `color` (every colour without) in the latest frame, largest first."""
        return await self.send(Requests.detections(cam, color, min_area))

    async def camera_calibration(self, cam: str) -> s.Calibration:
        return await self.send(Requests.camera_calibration(cam))

    async def calibrate_camera(self, cam: str,
                               points: Sequence[tuple[tuple[float, float],
                                                      tuple[float, float, float]]],
                               arm: str | None = None) -> s.Calibration:
        """Fit the camera's table calibration from (pixel (u, v), tip position (x, y, z))
        pairs, 4 or more; `arm`: the camera's arm, whose lease this client's requests carry."""
        req = s.CalibrationRequest(points=[
            s.Correspondence(pixel=s.Pixel(u=u, v=v), position=s.Vec3(x=x, y=y, z=z))
            for (u, v), (x, y, z) in points])
        return await self.send(Requests.calibrate_camera(cam, req, arm))

    @contextlib.asynccontextmanager
    async def queue_turn(self, arm: str, poll: float = 0.25, every: float | None = None,
                         timeout: float | None = None) -> AsyncIterator[LeaseKeeper]:
        """Join the arm's queue, wait for the offer, claim the lease and renew it for the
        duration of the block (its id goes on this client's requests to the arm); on exit
        release it, or leave the queue if the turn never came. The slot ends when the server
        says: then `keeper.error` is set and moves answer 409 `leased`."""
        entry = await self.join_queue(arm)
        deadline = None if timeout is None else time.monotonic() + timeout
        try:
            while turn_pending(arm, entry, deadline, timeout):
                await asyncio.sleep(poll)
                entry = await self.queue_entry(arm, entry.id)
            lease = await self.renew_lease(arm, entry.lease_id or "")  # claims it
        except BaseException:
            with contextlib.suppress(ArmServerError):
                await self.leave_queue(arm, entry.id)
            raise
        async with keep_lease(self, arm, lease, every) as keeper:
            yield keeper

    @contextlib.asynccontextmanager
    async def hold_lease(self, arm: str, every: float | None = None) -> AsyncIterator[LeaseKeeper]:
        """Take the arm's lease, send its id on this client's requests to the arm and renew it in
        the background (every `ttl / 3` s unless `every`); release it on exit."""
        lease = await self.take_lease(arm)
        async with keep_lease(self, arm, lease, every) as keeper:
            yield keeper

    # --------------------------------------------------------- telemetry

    async def telemetry_messages(self, arm: str, rate: float | None = None
                                 ) -> AsyncIterator[s.TelemetryMessage | s.EventMessage]:
        """Every WebSocket message, parsed: telemetry batches (with `dropped`) and events."""
        from websockets.asyncio.client import connect
        from websockets.exceptions import ConnectionClosed, InvalidHandshake

        headers = auth_headers(self.token) or None
        url = ws_url(self.base_url, arm, rate, None)
        try:
            ws = await connect(url, additional_headers=headers, open_timeout=self.timeout,
                               max_size=2 ** 24)
        except (InvalidHandshake, OSError, TimeoutError) as exc:
            raise ws_handshake_error(exc) from exc
        try:
            while True:
                try:
                    raw = await ws.recv()
                except ConnectionClosed as exc:
                    err = ws_close_error(exc)
                    if err is not None:
                        raise err from exc
                    return
                yield parse_ws_message(raw)
        finally:
            await ws.close()

    async def telemetry(self, arm: str, rate: float | None = None, events: bool = False
                        ) -> AsyncIterator[s.Sample | s.EventMessage]:
        """Samples in `seq` order, each once (a sample repeated across messages is skipped);
        events too if `events`. A gap in `seq` means the server dropped samples for this
        client (see `telemetry_messages` for the `dropped` counts)."""
        last = -1
        async for msg in self.telemetry_messages(arm, rate):
            if isinstance(msg, s.EventMessage):
                if events:
                    yield msg
                continue
            for sample in msg.samples:
                if sample.seq > last:
                    last = sample.seq
                    yield sample

