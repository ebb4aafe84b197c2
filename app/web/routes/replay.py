"""Replay (API.md "Recordings (v1.2)", `POST /arms/{arm}/replay`): a recorded episode's
actions played back on an arm as one motion (app/motion/replay.py), read from the server's
datasets (`app.state.recordings`, app/recording). This module picks the arm's columns of the
episode and maps HTTP onto the arm's facade."""

from __future__ import annotations

import asyncio
from typing import cast

import numpy as np
from fastapi import APIRouter, Request, Response, status

from app import schemas as s
from app.errors import InvalidRequest, NotFound
from app.recording.dataset import Episode
from app.recording.manager import Recordings
from app.service import ArmService
from app.web.deps import ControlArm
from app.web.routes.common import DEVICE, errors, motion_answer

router = APIRouter(tags=["motion"])


def episode_targets(episode: Episode, arm: ArmService) -> tuple[np.ndarray, np.ndarray | None]:
    """The episode's actions for `arm` (T, n), in its joint order: the columns named
    `<arm>.<joint>.pos`; on another arm, those of the one recorded arm with the same joint
    names (an episode recorded on `leader` replays on `follower`). Then that arm's gripper
    actions (T,), `<arm>.gripper.pos`, where the episode has them and `arm` has an actuated
    gripper, else None. 422 `invalid_request` when no recorded arm, or more than one,
    matches."""
    joints = [j.name for j in arm.profile.joints]
    recorded = sorted({n.split(".", 1)[0] for n in episode.names})
    candidates = [arm.name] if arm.name in recorded else recorded
    fits = [who for who in candidates
            if all(f"{who}.{j}.pos" in episode.names for j in joints)]
    if len(fits) == 1:
        cols = [episode.names.index(f"{fits[0]}.{j}.pos") for j in joints]
        grip = f"{fits[0]}.gripper.pos"
        gripper = (np.asarray(episode.actions[:, episode.names.index(grip)], dtype=float)
                   if grip in episode.names and arm.profile.gripper.actuated else None)
        return np.asarray(episode.actions[:, cols], dtype=float), gripper
    raise InvalidRequest(
        f"episode {episode.index} has no actions for {arm.name}'s joints ({', '.join(joints)}): "
        f"it was recorded on {', '.join(recorded)}"
        + (" (several fit: replay on the arm of the same name)" if len(fits) > 1 else ""))


@router.post(
    "/arms/{arm}/replay",
    response_model=s.Motion,
    status_code=status.HTTP_202_ACCEPTED,
    summary="Replay a recorded episode's actions on the arm",
    description="A soft start (a planned joint move at the planner's limits) to the episode's "
    "first action, then its actions at the dataset's fps, as one motion of the arm (the "
    "gripper's actions too, where the episode and the arm have one, each sent as the motion "
    "reaches its frame, with POST /gripper's checks): checked "
    "first (joint limits 422 `joint_limit`, speed between frames 422 `velocity_limit`, the "
    "keep-out envelope 422 `keep_out`), stopped by POST /stop or DELETE /motions/{id}, held "
    "by the estop, like any move. Answers 202 with the motion, or with `wait: true` 200 when "
    "it ends. 404 `not_found` for an unknown recording or episode; 422 `invalid_request` "
    "when the episode holds no actions for this arm's joints.",
    responses={200: {"model": s.Motion, "description": "final state (with `wait: true`)"},
               **errors(*DEVICE)},
)
async def replay(svc: ControlArm, req: s.ReplayRequest, request: Request,
                 response: Response) -> s.Motion:
    recs = cast(Recordings | None, getattr(request.app.state, "recordings", None))
    if recs is None:
        raise NotFound("this server keeps no recordings")
    dataset = recs.get(req.recording).dataset
    try:
        episode = await asyncio.to_thread(dataset.load_episode, req.episode)
    except IndexError as exc:
        raise NotFound(f"recording {req.recording!r}: {exc}") from None
    targets, gripper = episode_targets(episode, svc)
    record = await svc.replay(targets, float(episode.fps), gripper)
    return await motion_answer(record, req.wait, response)
