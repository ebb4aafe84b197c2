"""`armserver estop [ARM ...]`: the emergency stop of every arm of a server (or a lab) at once,
from a shell: the instructor's button where there is no dashboard.

    armserver estop --url http://lab-pc:8000 --token $TOKEN          # every arm it hosts
    armserver estop left right                                         # only these

Every arm named (none: every arm `GET /api/v1/health` names) is pressed at once, each with its
own `POST /api/v1/arms/{arm}/estop` (anyone authenticated may press, a viewer too; no lease).
It prints `{"latched": [...], "failed": [{"arm", "code", "detail", "status"}, ...]}` and exits
0 when every arm answered latched, 1 when some did not (each one's reason is in `failed`: an
unknown arm, a worker restarting, whose press the lab keeps: its detail says so), 2 when the
server could not be reached at all. A press is answered once the hold is commanded and the
latch is on disk, so an arm listed under `latched` stays latched across a restart.

Releasing is deliberately per arm (`armserver call ARM release`, an operator's token and the
lease where one is held): each release re-enables an arm's motion, and should be a decision
made for that arm.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
from typing import Any

from app.client.aio import AsyncArmClient
from app.client.cli import _add_connection
from app.client.errors import ArmServerError, ConnectionFailed


def add_estop(sub: Any) -> None:
    """Add `estop` to an argparse subparsers object."""
    what = "latch the emergency stop of every arm (or those named) at once"
    p = sub.add_parser("estop", help=what, description=what[0].upper() + what[1:] + ".")
    _add_connection(p)
    p.add_argument("arms", nargs="*", metavar="ARM",
                   help="the arms to stop (default: every arm the server hosts)")
    p.set_defaults(func=run_estop)


def _failure(arm: str, exc: ArmServerError) -> dict[str, Any]:
    return {"arm": arm, "code": exc.code, "detail": exc.detail, "status": exc.status}


async def press_all(client: AsyncArmClient, arms: list[str]) -> tuple[list[str],
                                                                      list[dict[str, Any]]]:
    """Press every arm of `arms` at once (none: every arm the server lists): the arms that
    answered latched, and the failures (arm, code, detail, status) in `arms`' order."""
    if not arms:  # health names every arm, a lab's whose worker is down too (and needs no
        # token: a press without one is refused arm by arm, each said)
        arms = list((await client.health()).arms)
    answers = await asyncio.gather(*(client.estop(a) for a in arms), return_exceptions=True)
    latched: list[str] = []
    failed: list[dict[str, Any]] = []
    for arm, answer in zip(arms, answers, strict=True):
        if isinstance(answer, ArmServerError):
            failed.append(_failure(arm, answer))
        elif isinstance(answer, BaseException):
            raise answer
        elif answer.estop:
            latched.append(arm)
        else:  # (the route answers latched or fails: never this)
            failed.append({"arm": arm, "code": "not_latched", "detail": "answered not latched",
                           "status": 200})
    return latched, failed


def run_estop(a: argparse.Namespace) -> int:
    async def main() -> tuple[list[str], list[dict[str, Any]]]:
        async with AsyncArmClient(a.url, token=a.token, timeout=a.timeout) as client:
            return await press_all(client, list(dict.fromkeys(a.arms)))

    try:
        latched, failed = asyncio.run(main())
    except ArmServerError as exc:  # the arms' names could not be had
        print(json.dumps(_failure("*", exc), indent=2), file=sys.stderr)
        return 2 if isinstance(exc, ConnectionFailed) else 1
    print(json.dumps({"latched": latched, "failed": failed}, indent=2))
    if failed and not latched and all(f["code"] == "connection_failed" for f in failed):
        return 2
    return 1 if failed else 0
