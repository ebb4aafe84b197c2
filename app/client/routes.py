"""Every route of the contract as a `Call`: what to send, how to read the answer, whether it is
safe to retry. Both clients send these; nothing here does I/O."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Generic, Literal, TypeVar
from urllib.parse import quote

from pydantic import BaseModel, TypeAdapter

from app import schemas as s

T = TypeVar("T")

API = s.API_PREFIX
LEASE_HEADER = "X-Arm-Lease"
#: How long a `wait=true` move may hold the request open: the planner caps a move at 600 s.
WAIT_TIMEOUT_S = 660.0
#: How long writing an episode (or sending a dataset's archive) may take: a long episode's
#: videos are joined to the dataset's files before the answer.
RECORDING_WRITE_S = 300.0
#: How long a servo scan or set-up may take: a scan of every standard rate on a real port.
SETUP_S = 60.0


@dataclass(frozen=True)
class Call(Generic[T]):
    """One request of the contract: what to send, how to read the answer, whether to retry."""

    method: str
    path: str
    parse: Callable[[Any], T]
    body: Any = None
    params: Mapping[str, Any] | None = None
    arm: str | None = None
    safe: bool = False
    timeout: float | None = None
    headers: dict[str, str] = field(default_factory=dict)
    #: Parse the answer's text rather than its JSON (e.g. the audit log as CSV).
    text: bool = False
    #: Parse the answer's bytes (e.g. a camera's JPEG frame).
    raw: bool = False


def url_path(*parts: object) -> str:
    """`/api/v1/...` with each part percent-encoded."""
    return API + "".join("/" + quote(str(x), safe="") for x in parts)


def _model(model: type[BaseModel]) -> Callable[[Any], Any]:
    return model.model_validate


def _none(_: Any) -> None:
    return None


def _audit_rows(data: Any) -> list[s.AuditRecord]:
    return [s.AuditRecord.model_validate(r) for r in data]


def _cameras(data: Any) -> list[s.CameraSummary]:
    return TypeAdapter(list[s.CameraSummary]).validate_python(data)


def _recordings(data: Any) -> list[s.RecordingSummary]:
    return TypeAdapter(list[s.RecordingSummary]).validate_python(data)


def _arms(data: Any) -> list[s.ArmSummary]:
    items = data["arms"] if isinstance(data, dict) and "arms" in data else data
    return TypeAdapter(list[s.ArmSummary]).validate_python(items)


def _teleop_sessions(data: Any) -> list[s.TeleopSession]:
    return TypeAdapter(list[s.TeleopSession]).validate_python(data)


def _body(model: BaseModel) -> dict[str, Any]:
    return model.model_dump(mode="json", exclude_none=True)


def _pid(j: s.PidSetpoint | Mapping[str, float] | float) -> s.PidSetpoint:
    if isinstance(j, s.PidSetpoint):
        return j
    if isinstance(j, Mapping):
        return s.PidSetpoint.model_validate(j)
    return s.PidSetpoint(position_ticks=float(j))


class Requests:
    """Builds the `Call` for every route; both clients send these. Arguments in SI units."""

    @staticmethod
    def health() -> Call[s.Health]:
        return Call("GET", url_path("health"), _model(s.Health), safe=True)

    @staticmethod
    def arms() -> Call[list[s.ArmSummary]]:
        return Call("GET", url_path("arms"), _arms, safe=True)

    @staticmethod
    def arm(arm: str) -> Call[s.ArmDetail]:
        return Call("GET", url_path("arms", arm), _model(s.ArmDetail), arm=arm, safe=True)

    @staticmethod
    def state(arm: str) -> Call[s.Sample]:
        return Call("GET", url_path("arms", arm, "state"), _model(s.Sample), arm=arm, safe=True)

    @staticmethod
    def joints_request(verb: str, arm: str, req: s.MoveJoints, safe: bool) -> Call[s.Motion]:
        return Call("POST", url_path("arms", arm, verb, "joints"), _model(s.Motion), _body(req),
                    arm=arm, safe=safe, timeout=WAIT_TIMEOUT_S if req.wait else None)

    @staticmethod
    def pose_request(verb: str, arm: str, req: s.MovePose, safe: bool) -> Call[s.Motion]:
        return Call("POST", url_path("arms", arm, verb, "pose"), _model(s.Motion), _body(req),
                    arm=arm, safe=safe, timeout=WAIT_TIMEOUT_S if req.wait else None)

    @staticmethod
    def motion(arm: str, motion_id: str) -> Call[s.Motion]:
        return Call("GET", url_path("arms", arm, "motions", motion_id), _model(s.Motion), arm=arm,
                    safe=True)

    @staticmethod
    def cancel_motion(arm: str, motion_id: str) -> Call[s.Motion]:
        # The server answers once a running motion has decelerated: allow for it.
        return Call("DELETE", url_path("arms", arm, "motions", motion_id), _model(s.Motion),
                    arm=arm, safe=True, timeout=60.0)

    @staticmethod
    def stop(arm: str) -> Call[s.StopResult]:
        return Call("POST", url_path("arms", arm, "stop"), _model(s.StopResult), arm=arm, safe=True,
                    timeout=60.0)

    @staticmethod
    def estop(arm: str) -> Call[s.EstopState]:
        return Call("POST", url_path("arms", arm, "estop"), _model(s.EstopState), arm=arm,
                    safe=True)

    @staticmethod
    def release_estop(arm: str) -> Call[s.EstopState]:
        return Call("DELETE", url_path("arms", arm, "estop"), _model(s.EstopState), arm=arm,
                    safe=True)

    @staticmethod
    def gripper(arm: str, value: float) -> Call[s.GripperState]:
        return Call("POST", url_path("arms", arm, "gripper"), _model(s.GripperState),
                    _body(s.GripperCommand(value=value)), arm=arm)

    @staticmethod
    def tare_force(arm: str) -> Call[s.ForceTare]:
        return Call("POST", url_path("arms", arm, "force", "tare"), _model(s.ForceTare), arm=arm)

    @staticmethod
    def clear_tare(arm: str) -> Call[s.ForceTare]:
        return Call("DELETE", url_path("arms", arm, "force", "tare"), _model(s.ForceTare), arm=arm)

    @staticmethod
    def forward(arm: str, positions: Sequence[float]) -> Call[s.ForwardResult]:
        return Call("POST", url_path("arms", arm, "kinematics", "forward"), _model(s.ForwardResult),
                    _body(s.JointVector(positions=list(positions))), arm=arm, safe=True)

    @staticmethod
    def inverse(arm: str, req: s.InverseRequest) -> Call[s.InverseResult]:
        return Call("POST", url_path("arms", arm, "kinematics", "inverse"), _model(s.InverseResult),
                    _body(req), arm=arm, safe=True)

    @staticmethod
    def inverse_velocity(arm: str, req: s.InverseVelocityRequest
                         ) -> Call[s.InverseVelocityResult]:
        return Call("POST", url_path("arms", arm, "kinematics", "inverse-velocity"),
                    _model(s.InverseVelocityResult), _body(req), arm=arm, safe=True)

    @staticmethod
    def workspace(arm: str, params: Mapping[str, Any]) -> Call[s.Workspace]:
        return Call("GET", url_path("arms", arm, "workspace"), _model(s.Workspace),
                    params=params or None, arm=arm, safe=True)

    @staticmethod
    def rbe3001_set_pid(arm: str, joints: Sequence[Any]) -> Call[s.SetPidReply]:
        body = _body(s.SetPid(joints=[_pid(j) for j in joints]))
        return Call("POST", url_path("arms", arm, "rbe3001", "set-pid"), _model(s.SetPidReply),
                    body, arm=arm)

    @staticmethod
    def rbe3001_status(arm: str) -> Call[s.Rbe3001Status]:
        return Call("GET", url_path("arms", arm, "rbe3001", "status"), _model(s.Rbe3001Status),
                    arm=arm, safe=True)

    @staticmethod
    def rbe3001_set_gain(arm: str, axis: int, kp: float, ki: float, kd: float) -> Call[s.Ack]:
        body = _body(s.SetGain(axis=axis, kp=kp, ki=ki, kd=kd))
        return Call("POST", url_path("arms", arm, "rbe3001", "set-gain"), _model(s.Ack), body,
                    arm=arm)

    @staticmethod
    def rbe3001_set_claw(arm: str, value: float) -> Call[s.Ack]:
        return Call("POST", url_path("arms", arm, "rbe3001", "set-claw"), _model(s.Ack),
                    _body(s.SetClaw(value=value)), arm=arm)

    @staticmethod
    def dxl_ping(arm: str, dxl_id: int | None) -> Call[s.PingResult]:
        return Call("POST", url_path("arms", arm, "dynamixel", "ping"), _model(s.PingResult),
                    s.PingRequest(id=dxl_id).model_dump(mode="json"), arm=arm, safe=True)

    @staticmethod
    def dxl_read_register(arm: str, dxl_id: int, name: str) -> Call[s.RegisterValue]:
        return Call("GET", url_path("arms", arm, "dynamixel", dxl_id, "registers", name),
                    _model(s.RegisterValue), arm=arm, safe=True)

    @staticmethod
    def dxl_write_register(arm: str, dxl_id: int, name: str, raw: int) -> Call[s.RegisterValue]:
        return Call("PUT", url_path("arms", arm, "dynamixel", dxl_id, "registers", name),
                    _model(s.RegisterValue), _body(s.RegisterWrite(raw=raw)), arm=arm, safe=True)

    @staticmethod
    def dxl_sync_read(arm: str, name: str, ids: Sequence[int]) -> Call[s.SyncReadResult]:
        return Call("POST", url_path("arms", arm, "dynamixel", "sync-read"),
                    _model(s.SyncReadResult),
                    _body(s.SyncReadRequest(name=name, ids=list(ids))), arm=arm, safe=True)

    @staticmethod
    def dxl_sync_write(arm: str, name: str, values: Mapping[int, int]) -> Call[s.Ack]:
        return Call("POST", url_path("arms", arm, "dynamixel", "sync-write"), _model(s.Ack),
                    _body(s.SyncWriteRequest(name=name, values=dict(values))), arm=arm)

    @staticmethod
    def dxl_reboot(arm: str, dxl_id: int, load_supported: bool = False) -> Call[s.Ack]:
        return Call("POST", url_path("arms", arm, "dynamixel", dxl_id, "reboot"), _model(s.Ack),
                    _body(s.RebootRequest(load_supported=True)) if load_supported else None,
                    arm=arm)

    @staticmethod
    def safety(arm: str) -> Call[s.Safety]:
        return Call("GET", url_path("arms", arm, "safety"), _model(s.Safety), arm=arm, safe=True)

    @staticmethod
    def set_safety(arm: str, update: s.SafetyUpdate) -> Call[s.Safety]:
        body = update.model_dump(mode="json", exclude_unset=True)  # floor_z None: no floor
        return Call("PUT", url_path("arms", arm, "safety"), _model(s.Safety), body, arm=arm,
                    safe=True)

    @staticmethod
    def world(arm: str) -> Call[s.WorldScene]:
        return Call("GET", url_path("arms", arm, "world"), _model(s.WorldScene), arm=arm,
                    safe=True)

    @staticmethod
    def set_world(arm: str, scene: s.WorldScene) -> Call[s.WorldScene]:
        return Call("PUT", url_path("arms", arm, "world"), _model(s.WorldScene),
                    _body(scene), arm=arm, safe=True)

    @staticmethod
    def move_hand(arm: str, req: s.HandMoveRequest) -> Call[s.HandState]:
        return Call("PUT", url_path("arms", arm, "world", "hand"), _model(s.HandState),
                    _body(req), arm=arm, timeout=WAIT_TIMEOUT_S if req.wait else None)

    @staticmethod
    def let_go_hand(arm: str) -> Call[None]:
        return Call("DELETE", url_path("arms", arm, "world", "hand"), _none, arm=arm, safe=True)

    @staticmethod
    def start_teleop(req: s.TeleopStart, leader_lease: str | None = None
                     ) -> Call[s.TeleopSession]:
        # the lease header is the follower's: the session moves it; a real leader's torque
        # goes off, so its lease (where one is held) goes in X-Leader-Lease
        headers = {"X-Leader-Lease": leader_lease} if leader_lease else {}
        return Call("POST", url_path("teleop"), _model(s.TeleopSession), _body(req),
                    arm=req.follower, headers=headers)

    @staticmethod
    def replay(arm: str, req: s.ReplayRequest) -> Call[s.Motion]:
        return Call("POST", url_path("arms", arm, "replay"), _model(s.Motion), _body(req),
                    arm=arm, timeout=WAIT_TIMEOUT_S if req.wait else None)

    @staticmethod
    def teleop_sessions() -> Call[list[s.TeleopSession]]:
        return Call("GET", url_path("teleop"), _teleop_sessions, safe=True)

    @staticmethod
    def stop_teleop(session_id: str) -> Call[s.TeleopSession]:
        return Call("DELETE", url_path("teleop", session_id), _model(s.TeleopSession),
                    safe=True)

    @staticmethod
    def home(arm: str, positions: Sequence[float] | None = None) -> Call[s.ArmDetail]:
        body = None if positions is None else _body(s.HomeRequest(positions=list(positions)))
        return Call("POST", url_path("arms", arm, "home"), _model(s.ArmDetail), body, arm=arm)

    @staticmethod
    def unhome(arm: str) -> Call[s.ArmDetail]:
        return Call("DELETE", url_path("arms", arm, "home"), _model(s.ArmDetail), arm=arm)

    @staticmethod
    def set_torque(arm: str, on: bool, load_supported: bool = False) -> Call[s.TorqueState]:
        return Call("PUT", url_path("arms", arm, "torque"), _model(s.TorqueState),
                    _body(s.TorqueRequest(on=on, load_supported=load_supported)), arm=arm)

    @staticmethod
    def calibration(arm: str) -> Call[s.ArmCalibration]:
        return Call("GET", url_path("arms", arm, "calibration"), _model(s.ArmCalibration),
                    arm=arm, safe=True)

    @staticmethod
    def calibrate(arm: str, positions: Sequence[float] | None = None,
                  pose: str | None = None) -> Call[s.ArmCalibration]:
        body = _body(s.ArmCalibrationRequest(
            positions=None if positions is None else list(positions), pose=pose))
        return Call("POST", url_path("arms", arm, "calibration"), _model(s.ArmCalibration),
                    body, arm=arm)

    @staticmethod
    def forget_calibration(arm: str) -> Call[s.ArmCalibration]:
        return Call("DELETE", url_path("arms", arm, "calibration"), _model(s.ArmCalibration),
                    arm=arm)

    @staticmethod
    def calibrate_gravity(arm: str, poses: Sequence[Sequence[float]] | None = None,
                          wait: bool = False) -> Call[s.GravityRun]:
        body = _body(s.GravityCalibrationRequest(
            poses=None if poses is None else [list(p) for p in poses], wait=wait))
        return Call("POST", url_path("arms", arm, "calibration", "gravity"),
                    _model(s.GravityRun), body, arm=arm)

    @staticmethod
    def servo_setup() -> Call[s.ServoSetupInfo]:
        return Call("GET", url_path("setup-servos"), _model(s.ServoSetupInfo), safe=True)

    @staticmethod
    def scan_servos(port: str, profile: str, baudrates: Sequence[int] | None = None,
                    scan_timeout: float | None = None) -> Call[s.ServoScan]:
        body: dict[str, Any] = {"port": port, "profile": profile}
        if baudrates is not None:
            body["baudrates"] = list(baudrates)
        if scan_timeout is not None:
            body["timeout"] = scan_timeout
        return Call("POST", url_path("setup-servos", "scan"), _model(s.ServoScan), body,
                    safe=True, timeout=SETUP_S)

    @staticmethod
    def assign_servo(port: str, profile: str, joint: str,
                     baudrates: Sequence[int] | None = None,
                     scan_timeout: float | None = None) -> Call[s.ServoAssigned]:
        body: dict[str, Any] = {"port": port, "profile": profile, "joint": joint}
        if baudrates is not None:
            body["baudrates"] = list(baudrates)
        if scan_timeout is not None:
            body["timeout"] = scan_timeout
        return Call("POST", url_path("setup-servos", "assign"), _model(s.ServoAssigned), body,
                    timeout=SETUP_S)

    @staticmethod
    def start_practice_bus(servos: int = 1) -> Call[s.PracticeBus]:
        return Call("POST", url_path("setup-servos", "practice"), _model(s.PracticeBus),
                    _body(s.PracticeBusRequest(servos=servos)))

    @staticmethod
    def plug_practice_servo() -> Call[s.PracticeBus]:
        return Call("POST", url_path("setup-servos", "practice", "servos"),
                    _model(s.PracticeBus))

    @staticmethod
    def stop_practice_bus() -> Call[s.PracticeBus]:
        return Call("DELETE", url_path("setup-servos", "practice"), _model(s.PracticeBus),
                    safe=True)

    @staticmethod
    def take_lease(arm: str) -> Call[s.Lease]:
        return Call("POST", url_path("arms", arm, "lease"), _model(s.Lease), arm=arm)

    @staticmethod
    def renew_lease(arm: str, lease_id: str) -> Call[s.Lease]:
        return Call("PUT", url_path("arms", arm, "lease", lease_id), _model(s.Lease), arm=arm,
                    safe=True, headers={LEASE_HEADER: lease_id})

    @staticmethod
    def release_lease(arm: str, lease_id: str) -> Call[None]:
        return Call("DELETE", url_path("arms", arm, "lease", lease_id), _none, arm=arm, safe=True,
                    headers={LEASE_HEADER: lease_id})

    # classroom: people, queue, audit (API.md "People and roles", "Queue and hand-off")

    @staticmethod
    def me() -> Call[s.Me]:
        return Call("GET", url_path("me"), _model(s.Me), safe=True)

    @staticmethod
    def join_queue(arm: str) -> Call[s.QueueEntry]:
        return Call("POST", url_path("arms", arm, "queue"), _model(s.QueueEntry), arm=arm)

    @staticmethod
    def queue(arm: str) -> Call[s.QueueStatus]:
        return Call("GET", url_path("arms", arm, "queue"), _model(s.QueueStatus), arm=arm,
                    safe=True)

    @staticmethod
    def queue_entry(arm: str, entry_id: str) -> Call[s.QueueEntry]:
        return Call("GET", url_path("arms", arm, "queue", entry_id), _model(s.QueueEntry), arm=arm,
                    safe=True)

    @staticmethod
    def leave_queue(arm: str, entry_id: str) -> Call[s.QueueEntry]:
        return Call("DELETE", url_path("arms", arm, "queue", entry_id), _model(s.QueueEntry),
                    arm=arm, safe=True)

    @staticmethod
    def reorder_queue(arm: str, order: Sequence[str]) -> Call[s.QueueStatus]:
        return Call("PUT", url_path("arms", arm, "queue"), _model(s.QueueStatus),
                    s.QueueOrder(order=list(order)).model_dump(), arm=arm, safe=True)

    @staticmethod
    def clear_queue(arm: str) -> Call[s.QueueStatus]:
        return Call("DELETE", url_path("arms", arm, "queue"), _model(s.QueueStatus), arm=arm,
                    safe=True)

    @staticmethod
    def revoke_lease(arm: str) -> Call[None]:
        return Call("DELETE", url_path("arms", arm, "lease"), _none, arm=arm)

    @staticmethod
    def audit(params: Mapping[str, Any]) -> Call[list[s.AuditRecord]]:
        return Call("GET", url_path("audit"), _audit_rows, params=_given(params), safe=True)

    @staticmethod
    def audit_csv(params: Mapping[str, Any]) -> Call[str]:
        return Call("GET", url_path("audit"), str, params=_given(params), safe=True, text=True,
                    headers={"Accept": "text/csv"})

    # recordings (API.md "Recordings (v1.2)")

    @staticmethod
    def recordings() -> Call[list[s.RecordingSummary]]:
        return Call("GET", url_path("recordings"), _recordings, safe=True)

    @staticmethod
    def recording(rid: str) -> Call[s.RecordingDetail]:
        return Call("GET", url_path("recordings", rid), _model(s.RecordingDetail), safe=True)

    @staticmethod
    def create_recording(req: s.RecordingCreate) -> Call[s.RecordingDetail]:
        return Call("POST", url_path("recordings"), _model(s.RecordingDetail), _body(req))

    @staticmethod
    def start_episode(rid: str, task: str | None) -> Call[s.RecordingDetail]:
        return Call("POST", url_path("recordings", rid, "episodes"), _model(s.RecordingDetail),
                    _body(s.EpisodeStart(task=task)))

    @staticmethod
    def stop_episode(rid: str) -> Call[s.RecordingDetail]:
        # answers once the episode is written (its videos joined to the dataset's files)
        return Call("POST", url_path("recordings", rid, "episodes", "stop"),
                    _model(s.RecordingDetail), timeout=RECORDING_WRITE_S)

    @staticmethod
    def discard_episode(rid: str) -> Call[s.RecordingDetail]:
        return Call("DELETE", url_path("recordings", rid, "episodes", "current"),
                    _model(s.RecordingDetail))

    @staticmethod
    def recording_archive(rid: str) -> Call[bytes]:
        return Call("GET", url_path("recordings", rid, "archive"), bytes, safe=True, raw=True,
                    timeout=RECORDING_WRITE_S)

    # cameras (API.md "Cameras (v1.2)")

    @staticmethod
    def cameras() -> Call[list[s.CameraSummary]]:
        return Call("GET", url_path("cameras"), _cameras, safe=True)

    @staticmethod
    def camera(cam: str) -> Call[s.CameraDetail]:
        return Call("GET", url_path("cameras", cam), _model(s.CameraDetail), safe=True)

    @staticmethod
    def camera_frame(cam: str) -> Call[bytes]:
        return Call("GET", url_path("cameras", cam, "frame.jpg"), bytes, safe=True, raw=True)

    @staticmethod
    def detections(cam: str, color: str | None, min_area: int) -> Call[s.Detections]:
        return Call("GET", url_path("cameras", cam, "detections"), _model(s.Detections),
                    params=_given({"color": color, "min_area": min_area}), safe=True)

    @staticmethod
    def camera_calibration(cam: str) -> Call[s.Calibration]:
        return Call("GET", url_path("cameras", cam, "calibration"), _model(s.Calibration),
                    safe=True)

    @staticmethod
    def calibrate_camera(cam: str, req: s.CalibrationRequest, arm: str | None
                         ) -> Call[s.Calibration]:
        return Call("POST", url_path("cameras", cam, "calibration"), _model(s.Calibration),
                    _body(req), arm=arm, safe=True)


def _given(params: Mapping[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in params.items() if v is not None}


def move_joints_model(positions: Sequence[float], duration: float | None, speed: float,
                      mode: s.QueueMode, wait: bool) -> s.MoveJoints:
    return s.MoveJoints(positions=list(positions), duration=duration, speed=speed, mode=mode,
                        wait=wait)


def move_pose_model(x: float, y: float, z: float, path: Literal["joint", "line"],
                    branch: int | None, ik_case: Literal["dx_zero", "dx_used"] | None,
                    duration: float | None, speed: float, mode: s.QueueMode,
                    wait: bool) -> s.MovePose:
    return s.MovePose(x=x, y=y, z=z, path=path, branch=branch, ik_case=ik_case,
                      duration=duration, speed=speed, mode=mode, wait=wait)

