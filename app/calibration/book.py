"""One arm's calibration: per joint whether its zero is known, the offset, where it came from
(`profile`, `stored`, `declared`) and when; the gravity fit. Kept in the store (app/store.py,
scope `calibration`) under the hardware's identity (`Driver.hardware_identity`: the HID serial
number, a Dynamixel bus and its IDs), found again when the same hardware comes up, and not
when other hardware is on the same port.

Everything here runs on the control thread (the driver's transmission and flags are its):
`on_connect` in the owner task as the link comes up, the rest through the arm's facade
(app/service.py), which crosses there.

Where the firmware zeroes its encoders at power-on (the profile's `power_on_pose`: the
RBE3001 Nucleo firmware's `ZeroPID()` at start-up in src/main.cpp of
WPIRoboticsEngineering/RBE3001_nucleo_firmware), the joints start calibrated at that pose and a
stored offset is not used: it was taken against an earlier power-on's zero.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from app import schemas as s
from app.calibration.gravity import GravityFit
from app.calibration.gravity_run import GravityRun
from app.config import ArmProfile

if TYPE_CHECKING:
    from app.device.driver import Driver
    from app.store import Store
    from app.telemetry.hub import TelemetryHub

log = logging.getLogger(__name__)

#: The store's scope for calibrations; the key is the hardware identity.
SCOPE = "calibration"

Source = Literal["profile", "stored", "declared"]


@dataclass
class JointState:
    calibrated: bool
    source: Source | None
    time: float | None


class CalibrationBook:
    """The calibration of one arm; the driver's `calibrated` flags and transmission follow it."""

    def __init__(self, profile: ArmProfile, driver: Driver, hub: TelemetryHub) -> None:
        self.profile = profile
        self.driver = driver
        self.hub = hub
        self.store: Store | None = None
        #: The identity of the hardware the calibration is for (None before the first connect).
        self.identity: str | None = None
        self.joints: list[JointState] = []
        self.gravity: GravityFit | None = None
        #: Whether what is shown is in the store (False: not stored, or the write failed).
        self.stored = False
        self.store_error: str | None = None
        self._start()

    # ------------------------------------------------------------ the start state

    def starts_calibrated(self) -> bool:
        """The link's `calibrated_at_start`, else: a simulated link yes, a real one no."""
        cfg = self.profile.link
        return cfg.calibrated_at_start if cfg.calibrated_at_start is not None \
            else cfg.kind == "sim"

    def _start(self) -> None:
        """Every joint as the profile alone knows it; the transmission back to its offsets."""
        p = self.profile
        power_on = p.calibration_poses.get(p.power_on_pose) if p.power_on_pose else None
        sim = self.starts_calibrated()
        self.joints = []
        tpu = self.driver.model.transmission.ticks_per_unit
        for k, j in enumerate(p.joints):
            offset = float(j.offset_ticks)
            if j.zero_known or sim:
                state = JointState(True, "profile", None)
            elif power_on is not None:
                # the firmware reads 0 ticks at the power-on pose
                offset = -float(power_on[k]) * float(tpu[k])
                state = JointState(True, "profile", None)
            else:
                state = JointState(False, None, None)
            self.driver.set_offset(k, offset)
            self.joints.append(state)
        self.gravity = None
        self.driver.gravity = None
        self.stored = False
        self._sync()

    def _sync(self) -> None:
        self.driver.calibrated = [j.calibrated for j in self.joints]
        fit, model = self.gravity, self.driver.model
        self.driver.gravity = None if fit is None else (lambda q: fit.torques(model, q))

    # ------------------------------------------------------------ at connect

    async def on_connect(self) -> None:
        """In the owner task as the link comes up: other hardware than before starts from
        the profile again; the calibration stored for this hardware is applied."""
        ident = self.driver.hardware_identity()
        if self.identity is not None and ident != self.identity:
            log.warning("%s: other hardware on the link (%s, was %s): calibration from the "
                        "profile again", self.profile.name, ident, self.identity)
            self._start()
            self.hub.event("calibration", reason="other hardware", identity=ident,
                           calibrated=list(self.driver.calibrated))
        changed = ident != self.identity
        self.identity = ident
        if changed:
            await self._load()

    async def _load(self) -> None:
        if self.store is None or self.identity is None:
            return
        try:
            data = await self.store.get_setting(SCOPE, self.identity)
        except Exception as exc:  # noqa: BLE001 - a store that fails leaves the profile's
            self.store_error = f"stored calibration not read: {exc}"
            log.error("%s: %s", self.profile.name, self.store_error)  # noqa: TRY400
            return
        if data is None:
            return
        try:
            self._apply_stored(data)
        except (KeyError, TypeError, ValueError) as exc:
            self.store_error = f"stored calibration not used: {exc}"
            log.error("%s: %s", self.profile.name, self.store_error)  # noqa: TRY400
            return
        self.stored = True
        log.info("%s: calibration found for %s: %s", self.profile.name, self.identity,
                 [j.source for j in self.joints])

    def _apply_stored(self, data: dict[str, Any]) -> None:
        names = self.profile.joint_names
        fit = data.get("gravity")
        gravity = None if fit is None else GravityFit.from_json(fit, len(names))
        if self.profile.power_on_pose is None:
            for entry in data.get("joints", []):
                k = names.index(entry["name"])
                self.driver.set_offset(k, float(entry["offset_ticks"]))
                self.joints[k] = JointState(True, "stored", float(entry["time"]))
        self.gravity = gravity
        self._sync()

    # ------------------------------------------------------------ declared

    def declare(self, q: np.ndarray) -> list[int]:
        """The arm is at joint values `q` now: the joints whose zero the hardware does not
        know take them (`Driver.set_home`: the offset moves so the reading is q); the others
        keep their reading. Answers the joints set."""
        now = time.time()
        joints = [k for k, j in enumerate(self.profile.joints) if not j.zero_known]
        for k in joints:
            self.driver.set_home(k, float(q[k]))
            self.joints[k] = JointState(True, "declared", now)
        self.stored = False
        self._sync()
        return joints

    def set_gravity(self, fit: GravityFit) -> None:
        self.gravity = fit
        self.stored = False
        self._sync()

    def forget(self) -> None:
        """Back to what the profile alone knows (the stored record is the caller's to drop)."""
        self._start()

    # ------------------------------------------------------------ the stored record

    def record(self) -> dict[str, Any]:
        """What is stored: the joints calibrated here (declared or stored) and the fit."""
        tr = self.driver.model.transmission
        joints = [{"name": j.name, "offset_ticks": float(tr.offset_ticks[k]),
                   "time": self.joints[k].time}
                  for k, j in enumerate(self.profile.joints)
                  if self.joints[k].source in ("declared", "stored")]
        return {"arm": self.profile.name, "model": self.profile.model,
                "identity": self.identity, "joints": joints,
                "gravity": None if self.gravity is None else self.gravity.to_json()}

    async def save(self) -> None:
        """Write `record()` under the identity; `stored` says whether it is on disk."""
        if self.store is None or self.identity is None:
            self.store_error = "no store (or the link never came up): kept in memory only"
            return
        try:
            self.stored = await self.store.put_setting(SCOPE, self.identity, self.record())
        except Exception as exc:  # noqa: BLE001 - the calibration holds; the store says why
            self.stored = False
            self.store_error = f"calibration not stored: {exc}"
            log.error("%s: %s", self.profile.name, self.store_error)  # noqa: TRY400
        else:
            self.store_error = None if self.stored else self.store.health().error

    async def drop(self) -> None:
        if self.store is not None and self.identity is not None:
            await self.store.put_setting(SCOPE, self.identity, None)
        self.stored = False

    def offsets(self) -> list[float]:
        """Per joint, the joint value (rad or m) at which the device reads zero ticks."""
        tr = self.driver.model.transmission
        return [float(v) for v in np.asarray(tr.from_ticks(np.zeros(len(self.joints))))]

    # ------------------------------------------------------------ views

    def view(self, run: GravityRun | None) -> s.ArmCalibration:
        names = self.profile.joint_names
        offsets = self.offsets()
        fit = self.gravity
        return s.ArmCalibration(
            arm=self.profile.name, identity=self.identity,
            joints=[s.JointCalibration(name=names[k], calibrated=j.calibrated,
                                       offset=offsets[k], source=j.source, time=j.time)
                    for k, j in enumerate(self.joints)],
            gravity=None if fit is None else s.GravityFit(**fit.to_json()),
            gravity_run=None if run is None else self.run_view(run),
            poses={k: list(v) for k, v in self.profile.calibration_poses.items()},
            power_on_pose=self.profile.power_on_pose, stored=self.stored,
            store_error=self.store_error)

    @staticmethod
    def run_view(run: GravityRun) -> s.GravityRun:
        return s.GravityRun(status=run.status, poses=run.poses, done=run.done,
                            motions=list(run.motions), reason=run.reason, started=run.started,
                            ended=run.ended)
