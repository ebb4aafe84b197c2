"""The server's cameras (app/cameras, `app.state.cameras`) as a recording sees them: a
`CameraFeed` per name, whose `latest` asks an on-demand (simulated) camera to keep rendering."""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Mapping
from pathlib import Path

from app.cameras.camera import Camera
from app.cameras.hub import CameraHub
from app.recording.inputs import CameraFeed, CameraFrame
from app.recording.manager import Recordings
from app.service import ArmService

#: The datasets' folder under the data folder (`Settings.data_dir`).
RECORDINGS_DIR = "recordings"


def feed(cam: Camera) -> CameraFeed:
    def latest() -> CameraFrame | None:
        cam.demand()
        f = cam.latest
        return None if f is None else CameraFrame(f.seq, f.time, f.image)

    def listen(fn: Callable[[CameraFrame], None]) -> Callable[[], None]:
        return cam.add_listener(lambda f: fn(CameraFrame(f.seq, f.time, f.image)))
    return CameraFeed(cam.name, cam.config.width, cam.config.height, latest, listen)


def hub_feeds(hub: CameraHub | None) -> Callable[[str], CameraFeed | None]:
    """Name -> feed; 404 `not_found` (the hub's) for a camera it does not have."""
    def find(name: str) -> CameraFeed | None:
        return None if hub is None else feed(hub.get(name))
    return find


async def open_recordings(data_dir: str, services: Mapping[str, ArmService],
                          hub: CameraHub | None) -> Recordings:
    """The server's recordings, the datasets already in the folder opened (in a thread)."""
    rec = Recordings(Path(data_dir) / RECORDINGS_DIR, services, hub_feeds(hub))
    await asyncio.to_thread(rec.load)
    return rec
