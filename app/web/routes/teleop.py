"""Teleoperation (API.md "Teleoperation (v1.2)"): start a leader/follower session under the
caller's lease on the follower, list the sessions with their figures, stop one. The sessions
and their checks are app/teleop's; this module maps HTTP onto them."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Header, Path, Request, status

from app import schemas as s
from app.classroom.lease import LeaseManager
from app.teleop.config import TeleopPair, with_pair
from app.teleop.leader import Leader
from app.teleop.remote import Peer, RemoteLeader, peer_of
from app.teleop.sessions import LeaseRef, TeleopSessions, frees_leader
from app.web.deps import (
    CallerDep,
    OperatorCaller,
    OperatorRole,
    ServicesDep,
    ViewerRole,
    lookup_arm,
)
from app.web.routes.common import DEVICE, READ, errors
from app.web.security import Role

router = APIRouter(tags=["teleoperation"])

SessionId = Annotated[str, Path(description="session id, as answered by POST /teleop",
                                max_length=64)]


def pairs_of(request: Request) -> list[TeleopPair]:
    """The config's `[[teleop]]` defaults."""
    return list(getattr(request.app.state, "teleop_pairs", []))


def sessions_of(request: Request) -> TeleopSessions:
    """The server's sessions (made with the app's state on first use)."""
    found: TeleopSessions | None = getattr(request.app.state, "teleop", None)
    if found is None:
        found = request.app.state.teleop = TeleopSessions(request.app.state.leases,
                                                          pairs_of(request))
    return found


@router.post(
    "/teleop",
    response_model=s.TeleopSession,
    status_code=status.HTTP_201_CREATED,
    summary="Start teleoperation: a leader arm drives a follower",
    description="Every 1/`rate_hz` s (30..100) the leader's newest joint sample is mapped to a "
    "follower target (`joints`: one to one for like arms, scaled, offset, clamped; "
    "`tip`: the leader's forward kinematics, the follower's IK nearest where it is) "
    "and sent to the follower through its guard (joint limits, speed, keep-out zones, "
    "the estop latch) at most at its velocity limit. A leader sample older than "
    "`deadman_s` (default 0.2 s), a target the guard refuses, or a planned motion on "
    "the follower holds the follower (a hold, counted); the emergency stop on either "
    "arm ends the session. Needs an operator token and the follower's lease "
    "(X-Arm-Lease), and a real leader's lease where one is held (X-Leader-Lease: its "
    "torque goes off). 404 `unknown_arm`; 422 when the leader is the follower or the "
    "mapping does not fit; 409 `busy` when the follower already follows; 409 "
    "`estop_latched` when either arm is latched. A real (not simulated) leader has "
    "its torque off for the session (moved by hand) and on again, holding, when it "
    "ends, as has a simulated one with `free_leader: true` (moved by PUT "
    "/api/v1/arms/{leader}/world/hand); 409 `not_supported` where its device cannot, "
    "and 409 `in_use` where such a leader has joints that fall without torque (its "
    "profile's `falls_without_torque`: the angler's z winch, an OpenManipulator-X's "
    "shoulder, elbow and wrist) unless the body says `load_supported: true` (held by "
    "hand, or resting), as a reboot's. The session ends when another client's lease "
    "holds the follower. In a lab of worker processes (`armserver serve --workers`) "
    "the session runs in the follower's worker and reads a leader on another worker "
    "over that worker's telemetry socket (its latency includes the hop), and a leader "
    "freed for the session has its torque switched in its own worker (PUT "
    "/api/v1/arms/{leader}/torque, with X-Leader-Lease and `load_supported`): that "
    "worker's refusals are the answer's.",
    responses=errors(*DEVICE),
)
async def start_teleop(request: Request, req: s.TeleopStart, services: ServicesDep,
                       who: OperatorCaller,
                       x_arm_lease: Annotated[str | None, Header(
                           description="the follower's lease id", max_length=128)] = None,
                       x_leader_lease: Annotated[str | None, Header(
                           description="a real leader's lease id, where one is held (its "
                           "torque goes off for the session)", max_length=128)] = None,
                       ) -> s.TeleopSession:
    # a lab's worker knows the arms of the others (app/lab/worker.py): a leader there is read
    # over its worker's telemetry socket (app/teleop/remote.py)
    peer = None if req.leader in services else peer_of(
        getattr(request.app.state, "lab_peers", None), req.leader)
    follower = lookup_arm(services, req.follower)
    leader: Leader = lookup_arm(services, req.leader) if peer is None else \
        await open_remote(peer, request, req, x_leader_lease)
    try:
        leases: LeaseManager = request.app.state.leases
        gated = who.role < Role.INSTRUCTOR
        await leases.check(follower.name, x_arm_lease, gated=gated)
        if frees_leader(with_pair(req, pairs_of(request)), leader):
            # its torque goes off: the arm goes limp, which is a command to it like a move, so
            # whoever holds its lease must be the one asking (X-Leader-Lease)
            await leases.check(leader.name, x_leader_lease, gated=gated)
        session = await sessions_of(request).start(req, leader, follower,
                                                   LeaseRef(x_arm_lease, gated))
    except BaseException:
        if isinstance(leader, RemoteLeader):
            leader.close()
        raise
    return session.describe()


async def open_remote(peer: Peer, request: Request, req: s.TeleopStart,
                      leader_lease: str | None) -> RemoteLeader:
    """A leader on another worker, read with the caller's token; where the session frees it,
    its torque is switched in its own worker with that token, `leader_lease` and the body's
    `load_supported` (app/teleop/remote.py)."""
    auth = request.headers.get("authorization")
    leader = RemoteLeader(peer, [("Authorization", auth)] if auth else [], leader_lease,
                          req.load_supported)
    await leader.open()
    return leader


@router.get(
    "/teleop",
    response_model=list[s.TeleopSession],
    summary="Teleoperation sessions and their figures",
    description="Running sessions, then the last 16 ended ones (`status`, `reason`): the rate "
    "asked and achieved, the latency from a leader sample to the follower's command (p50, "
    "p99, ms), commands sent and holds.",
    responses=errors(401),
)
async def list_teleop(_: ViewerRole, request: Request) -> list[s.TeleopSession]:
    return sessions_of(request).list()


@router.delete(
    "/teleop/{session_id}",
    response_model=s.TeleopSession,
    summary="Stop a teleoperation session",
    description="The session ends and the follower holds where it is (open to operators, "
    "like POST /arms/{arm}/stop). A session that has ended already is answered as it is. "
    "404 `not_found` for an unknown id.",
    responses=errors(*READ, 403),
)
async def stop_teleop(_: OperatorRole, request: Request, session_id: SessionId,
                      who: CallerDep) -> s.TeleopSession:
    session = await sessions_of(request).stop(session_id, f"stopped by {who}")
    return session.describe()

