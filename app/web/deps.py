"""Request dependencies as `Annotated` aliases (full-stack-fastapi-template style).

A route names what it needs and the access that implies:

- `ViewerArm`: the arm, for any authenticated client (reads, kinematics, estop latch);
- `OperatorArm`: the arm, operator token (stop, cancel: stopping is always allowed, lease or
  not);
- `InstructorArm`: the arm, instructor token (the safety envelope);
- `ControlArm`: the arm, operator token and, while a lease is held on it, that lease's id in
  `X-Arm-Lease` (moves, gripper, protocol commands).

Access is checked before the arm is looked up, so an unauthenticated client learns nothing
about which arms exist.

Every dependency is `async def`, though none awaits anything: FastAPI runs a plain `def`
dependency in its thread pool, a hand-over to a worker thread and back for each, six or more
a request (a pass-through register read spent about 2 ms in them on top of its 1.9 ms on the
bus).
"""

from __future__ import annotations

import hashlib
from typing import Annotated, cast

from fastapi import Depends, Header, Path, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from fastapi.security.utils import get_authorization_scheme_param

from app.classroom.lease import LeaseManager
from app.config import Settings
from app.errors import UnknownArm
from app.service import ArmService
from app.web.security import Access, Identity, Role

_bearer = HTTPBearer(auto_error=False, description="viewer or operator token (only when the "
                     "server is configured with tokens)")
Credentials = Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]
ArmName = Annotated[str, Path(description="arm name, as in GET /api/v1/arms", max_length=64)]
#: The `X-Arm-Lease` header of a request that moves or sets up an arm (None: no lease held).
LeaseId = Annotated[str | None, Header(description="the lease id, while a lease is held on "
                                       "the arm", max_length=128)]


async def get_settings(request: Request) -> Settings:
    return cast(Settings, request.app.state.settings)  # app.state is untyped: set in main


async def get_services(request: Request) -> dict[str, ArmService]:
    return cast("dict[str, ArmService]", request.app.state.services)


def get_access(request: Request) -> Access:
    return cast(Access, request.app.state.access)


async def get_leases(request: Request) -> LeaseManager:
    return cast(LeaseManager, request.app.state.leases)


SettingsDep = Annotated[Settings, Depends(get_settings)]
ServicesDep = Annotated[dict[str, ArmService], Depends(get_services)]
LeasesDep = Annotated[LeaseManager, Depends(get_leases)]


def lookup_arm(services: dict[str, ArmService], name: str) -> ArmService:
    svc = services.get(name)
    if svc is None:
        raise UnknownArm(f"no arm {name!r}; this server hosts {', '.join(sorted(services))}")
    return svc


def _token(cred: HTTPAuthorizationCredentials | None) -> str | None:
    return cred.credentials if cred is not None else None


async def require_viewer(request: Request, cred: Credentials) -> Role:
    return get_access(request).require(_token(cred), Role.VIEWER)


async def require_operator(request: Request, cred: Credentials) -> Role:
    return get_access(request).require(_token(cred), Role.OPERATOR)


async def require_instructor(request: Request, cred: Credentials) -> Role:
    return get_access(request).require(_token(cred), Role.INSTRUCTOR)


async def caller_viewer(request: Request, cred: Credentials) -> Identity:
    return get_access(request).require_identity(_token(cred), Role.VIEWER)


async def caller_operator(request: Request, cred: Credentials) -> Identity:
    return get_access(request).require_identity(_token(cred), Role.OPERATOR)


async def caller_instructor(request: Request, cred: Credentials) -> Identity:
    return get_access(request).require_identity(_token(cred), Role.INSTRUCTOR)


#: The caller's name and role (people: API.md "People and roles").
ViewerCaller = Annotated[Identity, Depends(caller_viewer)]
OperatorCaller = Annotated[Identity, Depends(caller_operator)]
InstructorCaller = Annotated[Identity, Depends(caller_instructor)]

ViewerRole = Annotated[Role, Depends(require_viewer)]
OperatorRole = Annotated[Role, Depends(require_operator)]
InstructorRole = Annotated[Role, Depends(require_instructor)]


async def viewer_arm(_: ViewerRole, services: ServicesDep, arm: ArmName) -> ArmService:
    return lookup_arm(services, arm)


async def operator_arm(_: OperatorRole, services: ServicesDep, arm: ArmName) -> ArmService:
    return lookup_arm(services, arm)


OperatorArm = Annotated[ArmService, Depends(operator_arm)]


async def instructor_arm(_: InstructorRole, services: ServicesDep, arm: ArmName) -> ArmService:
    return lookup_arm(services, arm)


InstructorArm = Annotated[ArmService, Depends(instructor_arm)]


async def control_arm(
    request: Request,
    cred: Credentials,
    arm: ArmName,
    x_arm_lease: LeaseId = None,
) -> ArmService:
    """An operator's (or instructor's) arm, with its lease checked: the same checks, in the
    same order, as `OperatorArm` then `OperatorCaller` then the lease, in one dependency
    (each dependency FastAPI solves costs a little on every command: this is the hot one)."""
    state = request.app.state
    return await check_control(state.access, state.services, state.leases, _token(cred), arm,
                               x_arm_lease)


async def check_control(access: Access, services: dict[str, ArmService], leases: LeaseManager,
                        token: str | None, arm: str, lease_id: str | None) -> ArmService:
    """`ControlArm`'s checks on plain values: 401/403 for the token (operator or above), 404
    `unknown_arm`, 409 `leased` for the lease; the arm. The dependency above and the goal's
    inner layer (`RegisterWriteFastPath`, app/arms/dynamixel/api.py) both call this one."""
    who = access.require_identity(token, Role.OPERATOR)
    svc = lookup_arm(services, arm)
    # an instructor may act on an arm that is nobody's (after a failed hand-off: release the
    # estop, bring the arm back); everyone else waits for the queue
    await leases.check(svc.name, lease_id, gated=who.role < Role.INSTRUCTOR)
    return svc


def bearer_credentials(authorization: str | None) -> str | None:
    """The token `Credentials` (FastAPI's `HTTPBearer(auto_error=False)`) gives for an
    `Authorization` header value: its own rule, `get_authorization_scheme_param` then a
    `bearer` scheme, so that a layer reading the raw header gets the very token the
    dependency would."""
    scheme, credentials = get_authorization_scheme_param(authorization)
    if not (authorization and scheme and credentials) or scheme.lower() != "bearer":
        return None
    return credentials


ViewerArm = Annotated[ArmService, Depends(viewer_arm)]
ControlArm = Annotated[ArmService, Depends(control_arm)]


async def caller(request: Request, cred: Credentials) -> str:
    """Who is asking, for the records of what they stopped: role, the token's name (the first
    8 hex digits of its SHA-256, never the token) and the client's address."""
    access = get_access(request)
    token = _token(cred)
    role = access.role_of(token)
    who = "anonymous client" if role is None else role.name.lower()
    if access.enabled and token:
        who += f" {hashlib.sha256(token.encode('utf-8', 'surrogatepass')).hexdigest()[:8]}"
    elif not access.enabled:
        who += " (open server)"
    host = request.client.host if request.client is not None else "unknown address"
    return f"{who} from {host}"


CallerDep = Annotated[str, Depends(caller)]
