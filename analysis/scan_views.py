"""What a finished scan shows: its capture poses at the actual exposure angles, and which skin
each image holds sharp. Shared by the QA report and image navigation; the scan folder is read
through the store's typed manifest (daemon/records/store.py)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from daemon.records.manifest import MANIFEST, ImageRecord, ImageStatus, Manifest
from daemon.records.store import ScanFileError, ScanFolder, read_folder
from planner.calibration.model import Calibration, load_calibration
from planner.poses import Poses, rig_rgb_poses
from planner.rig import Rig, load_rig


@dataclass(frozen=True)
class ScanRecord:
    """A scan folder with its plan and the rig it was taken with, loaded for reading."""

    folder: ScanFolder
    plan: dict[str, Any] | None
    rig: Rig
    calibration: Calibration | None = None

    @property
    def path(self) -> Path:
        return self.folder.path

    @property
    def manifest(self) -> Manifest:
        return self.folder.manifest

    @property
    def images(self) -> list[ImageRecord]:
        return self.folder.manifest.images

    def mesh(self) -> Any:
        return self.folder.read_mesh()

    def captured_focus_mm(self) -> np.ndarray:
        """(P,) focus actually used per pose (angle-major); NaN where no verified image exists."""
        focus = np.full(self.rig.n_poses, np.nan)
        for image in self.images:
            if image.status is ImageStatus.VERIFIED:
                focus[self.rig.pose_index(image.angle_index, image.camera_index)] = image.focus_mm
        return focus

    def poses(self) -> Poses:
        """Every pose at its image's actual exposure angle (the planned angle where none was measured:
        the plan's own angles when it chose them per subject, recorded with every image), from the
        calibration the scan was taken with (nominal poses for a scan without one)."""
        rig = self.rig
        angles = np.tile(rig.capture.angles_deg[:, None], (1, rig.n_cameras))
        for image in self.images:
            measured = image.actual_angle_deg
            angles[image.angle_index, image.camera_index] = (
                measured if measured is not None else image.planned_angle_deg
            )
        per_camera = [rig_rgb_poses(rig, self.calibration, angles[:, c]) for c in range(rig.n_cameras)]
        pose_of = np.arange(rig.n_poses)
        cam = pose_of % rig.n_cameras

        def pick(attr: str) -> np.ndarray:
            stacked = np.stack([getattr(p, attr) for p in per_camera])  # (C, P, ...)
            return stacked[cam, pose_of]

        return Poses(pick("centres"), pick("forward"), pick("right"), pick("down"),
                     pose_of // rig.n_cameras, cam)

    def image_at(self, pose: int) -> ImageRecord | None:
        angle, camera = divmod(pose, self.rig.n_cameras)
        return self.folder.find_image(camera, angle)

    def image_on_disk(self, image: ImageRecord) -> bool:
        """A verified image whose file is still in the folder (a deleted one shows nothing)."""
        return image.status is ImageStatus.VERIFIED and bool(image.file) and (self.path / image.file).is_file()

    def pixels_at(self, pose: int) -> np.ndarray:
        """The pixels (H, W, 3) float32 of the verified image at a pose (ScanFileError: none on
        disk, or its file no longer decodes)."""
        image = self.image_at(pose)
        if image is None or image.file is None or not self.image_on_disk(image):
            raise ScanFileError(self.path, f"pose {pose} has no verified image on disk")
        return np.asarray(decoded(self.path / image.file), dtype=np.float32)


def decoded(path: Path) -> Any:
    """The picture at ``path`` decoded to RGB (a PIL image); ScanFileError naming the file and the
    decoder's reason when it does not decode (cut short, damaged on disk: ``tbp scans --check``
    compares it with its recorded SHA-256)."""
    return _read_picture(path, lambda picture: picture.convert("RGB"))


def picture_size(path: Path) -> tuple[int, int]:
    """(width, height) px of the picture at ``path`` from its header; ScanFileError as :func:`decoded`."""
    size: tuple[int, int] = _read_picture(path, lambda picture: picture.size)
    return size


def _read_picture(path: Path, read: Any) -> Any:
    from PIL import Image

    try:
        with Image.open(path) as picture:
            return read(picture)
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as exc:
        raise ScanFileError(path, f"the image does not decode ({exc}); tbp scans --check compares it with its "
                            "recorded size and SHA-256") from exc


def open_scan(folder: Path | str, rig_path: Path | str | None = None) -> ScanRecord:
    """Load a scan folder; the rig file defaults to the installed one (its digest is checked).

    Raises the store's errors: ManifestError (not a scan folder), ScanFileError (a file it
    lists is missing or unreadable, or the rig file is not the one the scan was taken with).
    """
    scan = read_folder(folder)
    rig = load_rig(rig_path) if rig_path else load_rig()
    recorded = scan.manifest.rig_digest
    if recorded and rig.digest and recorded != rig.digest:
        raise ScanFileError(
            scan.path / MANIFEST,
            f"scanned with rig file digest {recorded[:12]}, but {rig.path} has {rig.digest[:12]}; "
            "pass the rig file the scan was taken with (--rig)",
        )
    for n, image in enumerate(scan.manifest.images):
        if image.camera_index >= rig.n_cameras or image.angle_index >= rig.n_angles:
            raise ScanFileError(
                scan.path / MANIFEST,
                f"images[{n}]: camera {image.camera_index}, angle {image.angle_index} outside this rig's "
                f"{rig.n_cameras} cameras x {rig.n_angles} angles",
            )
    name = scan.manifest.files.get("calibration")
    calibration = load_calibration(scan.path / name) if name else None
    return ScanRecord(scan, scan.read_plan(), rig, calibration)
