"""What a finished scan shows: its capture poses at the actual exposure angles, and which skin
each image holds sharp. Shared by the QA report and image navigation."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from planner.poses import Poses, rgb_poses
from planner.rig import Rig, load_rig


class ScanFolderError(ValueError):
    """A scan folder lacks a file the question needs, or the file is unreadable."""

    def __init__(self, folder: Path, name: str, problem: str) -> None:
        self.folder, self.name, self.problem = str(folder), name, problem
        super().__init__(f"{folder}: {name}: {problem}")


@dataclass(frozen=True)
class ScanRecord:
    """A scan folder's manifest, plan, mesh and rig, loaded for reading."""

    folder: Path
    manifest: dict[str, Any]
    plan: dict[str, Any] | None
    rig: Rig

    @property
    def images(self) -> list[dict[str, Any]]:
        return self.manifest.get("images", [])

    def mesh(self) -> Any:
        import trimesh

        path = self.folder / "mesh.ply"
        if not path.exists():
            raise ScanFolderError(self.folder, "mesh.ply", "missing (the scan ended before the depth sweep)")
        return trimesh.load(path, force="mesh", process=False)

    def captured_focus_mm(self) -> np.ndarray:
        """(P,) focus actually used per pose (angle-major); NaN where no verified image exists."""
        focus = np.full(self.rig.n_poses, np.nan)
        for image in self.images:
            if image.get("status") == "verified" and image.get("focus_mm") is not None:
                focus[self.rig.pose_index(image["angle_index"], image["camera_index"])] = image["focus_mm"]
        return focus

    def poses(self) -> Poses:
        """Every pose at its image's actual exposure angle (the planned angle where none was measured)."""
        rig = self.rig
        angles = np.tile(rig.capture.angles_deg[:, None], (1, rig.n_cameras))
        for image in self.images:
            if image.get("actual_angle_deg") is not None:
                angles[image["angle_index"], image["camera_index"]] = image["actual_angle_deg"]
        per_camera = [rgb_poses(rig, angles[:, c]) for c in range(rig.n_cameras)]
        pose_of = np.arange(rig.n_poses)
        cam = pose_of % rig.n_cameras

        def pick(attr: str) -> np.ndarray:
            stacked = np.stack([getattr(p, attr) for p in per_camera])  # (C, P, ...)
            return stacked[cam, pose_of]

        return Poses(pick("centres"), pick("forward"), pick("right"), pick("down"),
                     pose_of // rig.n_cameras, cam)

    def image_at(self, pose: int) -> dict[str, Any] | None:
        angle, camera = divmod(pose, self.rig.n_cameras)
        for image in self.images:
            if image["angle_index"] == angle and image["camera_index"] == camera:
                return image
        return None


def _read_json(folder: Path, name: str, required: bool) -> dict[str, Any] | None:
    path = folder / name
    if not path.exists():
        if required:
            raise ScanFolderError(folder, name, "missing; is this a scan folder?")
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ScanFolderError(folder, name, f"unreadable: {exc}") from exc


def open_scan(folder: Path | str, rig_path: Path | str | None = None) -> ScanRecord:
    """Load a scan folder; the rig file defaults to the installed one (its digest is checked)."""
    folder = Path(folder)
    manifest = _read_json(folder, "manifest.json", required=True)
    assert manifest is not None
    rig = load_rig(rig_path) if rig_path else load_rig()
    recorded = manifest.get("rig_digest")
    if recorded and rig.digest and recorded != rig.digest:
        raise ScanFolderError(
            folder, "manifest.json",
            f"scanned with rig file digest {recorded[:12]}, but {rig.path} has {rig.digest[:12]}; "
            "pass the rig file the scan was taken with (--rig)",
        )
    return ScanRecord(folder, manifest, _read_json(folder, "plan.json", required=False), rig)
