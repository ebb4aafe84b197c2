"""Recordings (API.md "Recordings (v1.2)"): LeRobot v3.0 datasets under the data folder, their
episodes started, stopped and discarded, each folder downloadable as a tar archive
(app/recording does the work; `app.state.recordings`).

Recording moves no arm: an operator token starts and stops episodes (no lease); any viewer
lists, reads and downloads.
"""

from __future__ import annotations

import os
import tarfile
from collections.abc import Iterator
from pathlib import Path
from typing import cast

from fastapi import APIRouter, Request
from fastapi.responses import StreamingResponse

from app import schemas as s
from app.recording.manager import Recording, Recordings
from app.web.deps import OperatorRole, ViewerRole
from app.web.routes.common import errors

router = APIRouter(prefix="/recordings", tags=["recordings"])

#: Bytes read from a file per chunk of the archive.
CHUNK = 1 << 20
RecId = str


def _recs(request: Request) -> Recordings:
    return cast(Recordings, request.app.state.recordings)


def _detail(recs: Recordings, rec: Recording) -> s.RecordingDetail:
    return s.RecordingDetail.model_validate(recs.describe(rec, detail=True))


@router.post("", response_model=s.RecordingDetail, status_code=201, summary="Create a dataset",
             description="Operator token. A LeRobot v3.0 dataset in `<data_dir>/recordings/"
             "<name>`: `observation.state` and `action` of the arms in the order given (their "
             "joints, then the gripper where there is one), `observation.images.<camera>` per "
             "camera, `fps` frames a second. 404 `unknown_arm` / `not_found` (camera), 409 "
             "`conflict` when the name is taken; in a lab of worker processes, 409 "
             "`different_workers` when its arms or cameras live on different workers (give "
             "them one `worker = K` in the config).",
             responses=errors(401, 403, 404, 409, 422, 503))
async def create(_: OperatorRole, request: Request,
                 body: s.RecordingCreate) -> s.RecordingDetail:
    recs = _recs(request)
    rec = await recs.create(body.name, body.arms, body.cameras, body.fps, body.task)
    return _detail(recs, rec)


@router.get("", response_model=list[s.RecordingSummary], summary="List the datasets",
            description="Every dataset under `<data_dir>/recordings/`: its id, episodes, "
            "frames, path, and whether an episode is recording now. Viewer token.",
            responses=errors(401))
async def list_all(_: ViewerRole, request: Request) -> list[s.RecordingSummary]:
    recs = _recs(request)
    return [s.RecordingSummary.model_validate(recs.describe(r)) for r in recs]


@router.get("/{rid}", response_model=s.RecordingDetail, summary="One dataset",
            description="With its episodes and the episode recording now, if any.",
            responses=errors(401, 404, 422))
async def detail(_: ViewerRole, request: Request, rid: RecId) -> s.RecordingDetail:
    recs = _recs(request)
    return _detail(recs, recs.get(rid))


@router.post("/{rid}/episodes", response_model=s.RecordingDetail, status_code=201,
             summary="Start an episode",
             description="Operator token. 409 `busy` while an episode records or is being "
             "written.", responses=errors(401, 403, 404, 409, 422))
async def start(_: OperatorRole, request: Request, rid: RecId,
                body: s.EpisodeStart | None = None) -> s.RecordingDetail:
    recs = _recs(request)
    rec = recs.start(rid, body.task if body is not None else None)
    return _detail(recs, rec)


@router.post("/{rid}/episodes/stop", response_model=s.RecordingDetail,
             summary="End the episode and write it",
             description="Operator token. Answers when the episode is written. 409 `conflict` "
             "when none records; 503 `recording_failed` when it cannot be written (disk full: "
             "the dataset keeps its earlier episodes).",
             responses=errors(401, 403, 404, 409, 422, 503))
async def stop(_: OperatorRole, request: Request, rid: RecId) -> s.RecordingDetail:
    recs = _recs(request)
    await recs.stop(rid)
    return _detail(recs, recs.get(rid))


@router.delete("/{rid}/episodes/current", response_model=s.RecordingDetail,
               summary="Discard the episode", description="Operator token. Nothing of it is "
               "written. 409 `conflict` when none records.",
               responses=errors(401, 403, 404, 409, 422))
async def discard(_: OperatorRole, request: Request, rid: RecId) -> s.RecordingDetail:
    recs = _recs(request)
    await recs.discard(rid)
    return _detail(recs, recs.get(rid))


@router.get("/{rid}/archive", summary="The dataset as a tar archive",
            description="The dataset's folder, `<name>/...`, as an uncompressed tar streamed "
            "file by file (MP4 and parquet are compressed already). An episode being written "
            "meanwhile is in it whole or not at all per file.",
            responses={**errors(401, 404, 422),
                       200: {"content": {"application/x-tar": {}}, "description": "tar"}})
async def archive(_: ViewerRole, request: Request, rid: RecId) -> StreamingResponse:
    rec = _recs(request).get(rid)
    root = rec.path
    return StreamingResponse(tar_stream(root), media_type="application/x-tar", headers={
        "Content-Disposition": f'attachment; filename="{rec.id}.tar"'})


def tar_stream(root: Path) -> Iterator[bytes]:
    """The folder as a POSIX tar, a file at a time (Starlette iterates it in a worker thread):
    each file's header, its bytes as they are when opened, the padding; temporary and partial
    files left out."""
    for path in sorted(root.rglob("*")):
        rel = path.relative_to(root)
        if any(p.startswith(".") for p in rel.parts) or not path.is_file():
            continue
        try:
            f = open(path, "rb")  # noqa: SIM115 - closed below, across yields
        except FileNotFoundError:
            continue
        with f:
            st = os.fstat(f.fileno())
            info = tarfile.TarInfo(f"{root.name}/{rel.as_posix()}")
            info.size, info.mtime, info.mode = st.st_size, int(st.st_mtime), 0o644
            yield info.tobuf(format=tarfile.PAX_FORMAT)
            left = st.st_size
            while left > 0:
                chunk = f.read(min(CHUNK, left))
                if not chunk:  # cannot happen to a file replaced by rename; pad anyway
                    chunk = bytes(min(CHUNK, left))
                left -= len(chunk)
                yield chunk
            if st.st_size % tarfile.BLOCKSIZE:
                yield bytes(tarfile.BLOCKSIZE - st.st_size % tarfile.BLOCKSIZE)
    yield bytes(2 * tarfile.BLOCKSIZE)
