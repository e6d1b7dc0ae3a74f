"""The calibration rotation: the beam stops at every capture angle with the ChArUco cuboid in place,
and every phone and depth camera takes a picture of it while the beam stands still.

Stop and go, not the scan's continuous turn: at a stop every camera sees the cuboid from one beam
pose (the bundle adjustment has one beam angle and wobble per capture, docs/calibration.md), the
phones' pictures have no motion blur and the depth cameras' infrared frames (emitter off, so its
dot pattern does not cover the boards) come from the same pose. The encoder angle of a capture is
the mean of the encoder samples while the pictures were taken.

The rotation's folder (``<store>/calibration/<YYYYmmdd-HHMMSS>-<id>/``) is what ``tbp calibrate
--pictures`` reads: ``captures.json`` (rewritten atomically after every stop, so it always lists
exactly the pictures that are safely on disk) and one picture per camera and stop,
``<camera>/a<index>.jpg`` pulled from the phone (daemon/jobs/pulls.py: verified, retried) and deleted
there, ``<depth camera>/a<index>.png`` its infrared frame. ``captures.json`` says ``in progress``
until the rotation ends, then ``complete``, ``aborted`` or ``fault`` with the reason. A phone that
fails or vanishes is named and the rotation goes on with the others; a depth camera that cannot
stream infrared is named and the rotation goes on with the phones.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import math
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import structlog

from daemon.errors import DaemonError
from daemon.jobs.job import JOB_END, RigJob
from daemon.jobs.phones import focus_range_mm
from daemon.jobs.pulls import ImageKey, ImagePullFailed, Pull, PullQueue
from daemon.records.atomic import AtomicWriter, StoreError, fsync_dir, raise_for
from daemon.records.store import SCAN_ID, new_scan_id
from daemon.rig.beam import BeamTracker, rebase_angle
from daemon.rig.hardware import RigHardware
from daemon.rig.safety import SafetyMonitor
from daemon.rig.states import ScanOutcome, ScanState, ScanStateMachine
from daemon.utc import utc_now
from drivers.depth.base import DepthFrame
from drivers.phone.camera import CaptureDone
from planner.calibration.target import CuboidTarget
from planner.poses import rgb_poses
from planner.rig import Rig

log = structlog.get_logger("daemon.jobs.calibration_rotation")

FOLDER = "calibration"
"""The store's sub-folder of calibration rotations (scans never match its name)."""


class CalibrationRotationError(DaemonError):
    """A step of the calibration rotation failed (named: what, which device, why)."""


@dataclass(frozen=True)
class RotationSettings:
    """speed_deg_s / acceleration_deg_s2: the moves between stops. settle_s: wait after a stop for
    the beam to ring down. depth_timeout_s: longest wait for a depth camera's frame at a stop."""

    speed_deg_s: float = 20.0
    acceleration_deg_s2: float = 40.0
    settle_s: float = 0.5
    depth_timeout_s: float = 3.0
    pull_timeout_s: float = 60.0


@dataclass
class RotationReport:
    """How a calibration rotation ended and what it holds."""

    rotation_id: str
    folder: Path
    outcome: ScanOutcome = ScanOutcome.COMPLETED
    pictures: int = 0
    missing: int = 0
    problems: list[str] = field(default_factory=list)
    causes: list[Any] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return {"rotation_id": self.rotation_id, "folder": str(self.folder), "outcome": self.outcome.value,
                "pictures": self.pictures, "missing": self.missing, "problems": list(self.problems),
                "causes": [str(c) for c in self.causes]}


def create_rotation_folder(store_root: Path, rotation_id: str | None = None, *,
                           now: datetime | None = None) -> tuple[str, Path]:
    """A new, empty calibration rotation folder under the store; (rotation id, folder).

    Raises StoreError naming the path when it cannot be made."""
    rotation_id = rotation_id or new_scan_id()
    if not isinstance(rotation_id, str) or not SCAN_ID.match(rotation_id):
        shown = repr(rotation_id)[:80] if isinstance(rotation_id, str) else f"a {type(rotation_id).__name__}"
        raise StoreError(store_root, f"calibration rotation id {shown} must be 1-64 of [A-Za-z0-9_-]")
    now = now or utc_now()
    parent = Path(store_root) / FOLDER
    path = parent / f"{now:%Y%m%d-%H%M%S}-{rotation_id}"
    try:
        parent.mkdir(parents=True, exist_ok=True)
        path.mkdir()
        fsync_dir(parent)
    except FileExistsError:
        raise StoreError(path, "calibration rotation folder already exists") from None
    except OSError as exc:
        raise_for(path, exc, 0)
    return rotation_id, path


def focus_on_cuboid_mm(rig: Rig, target: CuboidTarget, angle_deg: float) -> np.ndarray:
    """(C,) each phone's focus distance at a beam angle: along its optical axis to the cuboid's near
    face, the cuboid standing upright at the rig's centre (an axis-aligned box: the target's size);
    a phone whose axis passes above or beside the cuboid focuses where its axis comes closest to the
    rig's axis."""
    poses = rgb_poses(rig, np.array([angle_deg]))
    half = np.array([target.size_mm[0] / 2, target.size_mm[1] / 2])
    low = np.array([-half[0], -half[1], 0.0])
    high = np.array([half[0], half[1], target.size_mm[2]])
    out = np.empty(rig.n_cameras)
    for c in range(rig.n_cameras):
        pose = poses.camera_to_world(c)
        origin, forward = pose[:3, 3], pose[:3, 2]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            t1, t2 = (low - origin) / forward, (high - origin) / forward
        near = np.nanmax(np.minimum(t1, t2))
        far = np.nanmin(np.maximum(t1, t2))
        if near <= far and near > 0:
            out[c] = near  # forward is a unit vector: t is distance along the axis
        else:
            across = forward[:2]
            closest = float(across @ -origin[:2]) / max(float(across @ across), 1e-9)
            out[c] = closest if closest > 0 else float(np.hypot(*origin[:2]))
    return out


@dataclass
class _Capture:
    """One picture of the rotation, as captures.json lists it."""

    camera: str
    kind: str
    angle_index: int
    encoder_deg: float
    file: str
    focus_mm: float | None = None
    size_bytes: int | None = None
    sha256: str | None = None
    intrinsics: dict[str, float] | None = None

    def as_dict(self) -> dict[str, Any]:
        out = {"camera": self.camera, "kind": self.kind, "angle_index": self.angle_index,
               "encoder_deg": self.encoder_deg, "file": self.file, "focus_mm": self.focus_mm,
               "size_bytes": self.size_bytes, "sha256": self.sha256}
        if self.intrinsics is not None:
            out["intrinsics"] = self.intrinsics
        return out


class CalibrationRotation(RigJob):
    """One calibration rotation on connected hardware: a job like a scan (abort, a latched fault
    and the folder's consistency follow the same rules, daemon/jobs/job.py)."""

    kind = "calibration rotation"
    device = "calibration"
    first_state = ScanState.CALIBRATING
    storing = "storing the calibration pictures"

    def __init__(self, rig: Rig, hardware: RigHardware, machine: ScanStateMachine, safety: SafetyMonitor,
                 tracker: BeamTracker, target: CuboidTarget, rotation_id: str, folder: Path, *,
                 settings: RotationSettings = RotationSettings(), writer: AtomicWriter | None = None) -> None:
        super().__init__(rig, hardware, machine, safety, tracker, rotation_id)
        self.target = target
        self.settings = settings
        self.folder = folder
        self.writer = writer or AtomicWriter()
        self.report = RotationReport(rotation_id, folder)
        self.captures: list[_Capture] = []
        self.pulls: PullQueue | None = None
        self._state = "in progress"
        self._shots: dict[tuple[int, int], tuple[float, float]] = {}
        self._streams: dict[int, AsyncIterator[DepthFrame]] = {}

    # ------------------------------------------------------------------ the job's parts

    def start_data(self) -> dict[str, Any]:
        return {"folder": str(self.folder), "stops": len(self.rig.capture.angles_deg)}

    def end_data(self) -> dict[str, Any]:
        return {"pictures": self.report.pictures, "folder": str(self.folder)}

    @property
    def stop_deceleration_deg_s2(self) -> float:
        return self.settings.acceleration_deg_s2

    def note(self, text: str) -> None:
        self.report.problems.append(text)

    async def close_folder(self) -> bool:
        """Write the final captures.json (in a thread) if not done yet; False (logged) when the disk
        refuses."""
        if self._state != "in progress":
            return True
        state = JOB_END[self.report.outcome].value
        try:
            await asyncio.to_thread(self._save, state)
        except Exception as exc:  # retried at the next reset or rotation
            self.report.problems.append(f"captures.json: {type(exc).__name__}: {exc}")
            log.error("calibration_folder_not_closed", folder=str(self.folder), error=str(exc))
            return False
        self._state = state
        return True

    async def body(self) -> None:
        """captures.json says ``in progress``, the pulls start (the rotation is their ledger), then
        the stops."""
        await asyncio.to_thread(self._save, "in progress")
        self.pulls = PullQueue(self, workers=max(len(self.hw.phones), 1))
        self.pulls.start()
        await self._sequence()

    async def store(self) -> None:
        """Stop the depth cameras, wait for the pulls, count, and close captures.json."""
        report = self.report
        await self._stop_depth_cameras()
        if self.pulls is not None:
            try:
                async with asyncio.timeout(self.settings.pull_timeout_s):
                    await self.pulls.join()
            except (StoreError, TimeoutError) as exc:
                self._problem(f"pulls: {type(exc).__name__}: {exc}")
            finally:
                await self.pulls.close()
        report.pictures = len(self.captures)
        expected = (len(self.rig.phones) + len(self.hw.depth_cameras)) * len(self.rig.capture.angles_deg)
        report.missing = expected - report.pictures
        await self.close_folder()
        log.info("calibration_rotation_stored", outcome=report.outcome.value, pictures=report.pictures,
                 problems=len(report.problems), folder=str(self.folder))

    # ------------------------------------------------------------------ the sequence

    async def _sequence(self) -> None:
        rig, drive, s = self.rig, self.hw.drive, self.settings
        self.safety.expect_samples = True
        await rebase_angle(self.tracker, drive, min(rig.capture.angles_deg))
        await self._start_depth_cameras()
        phones = list(range(len(self.hw.phones)))
        for index, angle in sorted(enumerate(rig.capture.angles_deg), key=lambda x: x[1]):
            await drive.move_to(float(angle), s.speed_deg_s, s.acceleration_deg_s2)
            await asyncio.sleep(s.settle_s)
            mark = self.tracker.mark()
            settled = asyncio.get_running_loop().time()
            focus = focus_on_cuboid_mm(rig, self.target, float(angle))
            shots = await asyncio.gather(*(self._shoot(c, float(focus[c])) for c in phones))
            failed = [c for c, shot in zip(phones, shots) if shot is None]
            depth = list(self._streams)  # a camera that fails at this stop leaves _streams meanwhile
            frames = await asyncio.gather(*(self._infrared(d, settled) for d in depth))
            encoder = self._encoder_deg(mark)
            for c, shot in zip(phones, shots):
                if shot is not None:
                    self._submit(c, index, encoder, shot, float(focus[c]))
            phones = [c for c in phones if c not in failed]
            for d, frame in zip(depth, frames):
                if frame is not None:
                    await self._keep_infrared(d, index, encoder, frame)
            document = self._document("in progress")
            await asyncio.get_running_loop().run_in_executor(None, self.writer.write, self.folder / "captures.json",
                                                             document)
            self.machine.progress("calibration stop", angle_index=index, encoder_deg=round(encoder, 4),
                                  pictures=len(self.captures))
        self.safety.expect_samples = False

    def _encoder_deg(self, mark: int) -> float:
        """Mean encoder angle since ``mark`` (the stop's pictures), the latest sample if none."""
        rows = self.tracker.trace(mark)
        if len(rows):
            return float(np.mean(rows[:, 1]))
        angle = self.tracker.angle_deg
        if angle is None:
            raise CalibrationRotationError("the encoder has given no angle at a calibration stop")
        return float(angle)

    async def _shoot(self, c: int, focus_mm: float) -> CaptureDone | None:
        """Focus phone ``c`` on the cuboid and take one picture; None on failure: the phone is named and
        left out of the rest of the rotation (its pictures so far stay)."""
        phone = self.hw.phones[c]
        near, far = focus_range_mm(phone)
        try:
            await phone.set_focus_mm(float(np.clip(focus_mm, near, far if math.isfinite(far) else focus_mm)))
            return await phone.capture()
        except DaemonError:
            raise
        except Exception as exc:  # the phone's typed error; the other cameras go on
            self._problem(f"phone {self.rig.phones[c].id}: {type(exc).__name__}: {exc}; left out of the rest "
                          "of the rotation")
            return None

    def _submit(self, c: int, index: int, encoder: float, shot: CaptureDone, focus_mm: float) -> None:
        """Pull the picture in the background (the beam moves on); it is deleted on the phone once
        verified and listed in captures.json then."""
        phone = self.hw.phones[c]
        camera = self.rig.phones[c].id
        self._shots[(c, index)] = (encoder, focus_mm)
        assert self.pulls is not None
        self.pulls.submit(Pull((c, index), camera, index, shot.path, self.folder / _picture(camera, index),
                               phone.pull, shot.size_bytes, delete=phone.delete))

    # ------------------------------------------------------------------ the pulls' ledger

    def attempt(self, job: Pull[ImageKey], attempt: int) -> None:
        """Attempts are not recorded: captures.json lists pictures safely on disk."""

    def verified(self, job: Pull[ImageKey], size: int, sha256: str) -> None:
        encoder, focus_mm = self._shots.pop(job.key)
        self.captures.append(_Capture(job.camera_id, "phone", job.angle_index or 0, encoder,
                                      _picture(job.camera_id, job.angle_index or 0), focus_mm, size, sha256))

    def failed(self, job: Pull[ImageKey], failure: ImagePullFailed) -> None:
        self._problem(f"phone {job.camera_id}: {failure}")

    def not_pulled(self, job: Pull[ImageKey], error: StoreError) -> None:
        self._problem(f"phone {job.camera_id}: {job.dest.name} not pulled (it stays on the phone): {error}")

    def not_deleted(self, job: Pull[ImageKey], error: Exception) -> None:
        self._problem(f"phone {job.camera_id}: {job.phone_path} not deleted on the phone: "
                      f"{type(error).__name__}: {error}")

    # ------------------------------------------------------------------ depth cameras

    async def _start_depth_cameras(self) -> None:
        for d, camera in enumerate(self.hw.depth_cameras):
            camera.infrared = True
            try:
                await camera.start()
            except Exception as exc:  # InfraredUnavailable (a recording), a camera gone: named, phones go on
                camera.infrared = False
                self._problem(f"depth camera {camera.id}: {type(exc).__name__}: {exc}")
                continue
            self._streams[d] = camera.frames()

    async def _stop_depth_cameras(self) -> None:
        for d in list(self._streams):
            camera = self.hw.depth_cameras[d]
            try:
                await camera.stop()
            except Exception as exc:  # named; the next scan starts it afresh
                self._problem(f"depth camera {camera.id}: stop: {type(exc).__name__}: {exc}")
            finally:
                camera.infrared = False
        self._streams.clear()

    async def _infrared(self, d: int, settled_s: float) -> DepthFrame | None:
        """The first frame of depth camera ``d`` taken after the beam settled (older queued frames are
        skipped); None (named) when it has no infrared image or does not come in time."""
        camera = self.hw.depth_cameras[d]
        stream = self._streams[d]
        try:
            async with asyncio.timeout(self.settings.depth_timeout_s):
                while True:
                    frame = await anext(stream)
                    if frame.timestamp_s >= settled_s:
                        break
        except (TimeoutError, StopAsyncIteration):
            self._problem(f"depth camera {camera.id}: no frame within {self.settings.depth_timeout_s:g} s of a stop; "
                          "left out of the rest of the rotation")
            self._streams.pop(d, None)
            return None
        except DaemonError:
            raise
        except Exception as exc:  # the camera's typed error (stalled, unplugged)
            self._problem(f"depth camera {camera.id}: {type(exc).__name__}: {exc}; "
                          "left out of the rest of the rotation")
            self._streams.pop(d, None)
            return None
        if frame.infrared is None:
            self._problem(f"depth camera {camera.id}: frame {frame.frame_number} has no infrared image")
            return None
        return frame

    async def _keep_infrared(self, d: int, index: int, encoder: float, frame: Any) -> None:
        camera = self.hw.depth_cameras[d].id
        name = f"{camera}/a{index:02d}.png"
        loop = asyncio.get_running_loop()
        ok, png = await loop.run_in_executor(None, cv2.imencode, ".png", frame.infrared)
        if not ok:
            raise CalibrationRotationError(f"{name}: the infrared frame could not be encoded as PNG")
        (self.folder / camera).mkdir(exist_ok=True)
        data = png.tobytes()
        await loop.run_in_executor(None, self.writer.write, self.folder / name, data)
        k = frame.intrinsics
        self.captures.append(_Capture(camera, "depth", index, encoder, name, size_bytes=len(data),
                                      sha256=hashlib.sha256(data).hexdigest(),
                                      intrinsics={"fx": float(k[0, 0]), "fy": float(k[1, 1]),
                                                  "cx": float(k[0, 2]), "cy": float(k[1, 2])}))

    # ------------------------------------------------------------------ folder

    def _problem(self, text: str) -> None:
        self.report.problems.append(text)
        log.warning("calibration_rotation_problem", problem=text)
        self.machine.progress("calibration problem", problem=text)

    def _save(self, state: str) -> None:
        self.writer.write(self.folder / "captures.json", self._document(state))

    def _document(self, state: str) -> bytes:
        """captures.json: what the rotation is and every picture safely on disk, in camera order."""
        order = {c: i for i, c in enumerate([p.id for p in self.rig.phones] + [d.id for d in self.rig.depth_cameras])}
        captures = sorted(self.captures, key=lambda x: (order.get(x.camera, len(order)), x.angle_index))
        doc = {"format": "tbp-rig calibration rotation 1", "rotation_id": self.report.rotation_id,
               "rig_digest": self.rig.digest, "target": self.target.name, "state": state,
               "reason": [str(c) for c in self.report.causes], "problems": list(self.report.problems),
               "captures": [c.as_dict() for c in captures]}
        return json.dumps(doc, indent=1).encode()


def _picture(camera: str, index: int) -> str:
    """A phone's picture at stop ``index``, relative to the rotation's folder."""
    return f"{camera}/a{index:02d}.jpg"
