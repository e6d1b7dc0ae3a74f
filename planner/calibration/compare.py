"""Pose differences between two calibrations (or a calibration and the nominal rig) at every camera and angle.

The seed's measure: centre distance (mm) and the angle of the relative rotation (deg) of each
camera-to-world pose. Both calibrations share the world frame's definition (axis = z, floor =
0, phone column at +x at beam angle 0), so no registration is needed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planner.calibration.geometry import pose_error
from planner.calibration.model import Calibration


@dataclass(frozen=True)
class PoseDifferences:
    """(C, A) translation (mm) and rotation (deg) differences of cameras ``cameras`` at angles ``angles_deg``."""

    cameras: list[str]
    angles_deg: np.ndarray
    translation_mm: np.ndarray
    rotation_deg: np.ndarray

    def summary(self) -> dict[str, float]:
        t, r = self.translation_mm, self.rotation_deg
        return {"median_mm": float(np.median(t)), "max_mm": float(t.max()), "mean_mm": float(t.mean()),
                "median_deg": float(np.median(r)), "max_deg": float(r.max()), "mean_deg": float(r.mean())}


def compare(a: Calibration, b: Calibration, angles_deg: np.ndarray, cameras: list[str] | None = None) -> PoseDifferences:
    """Differences of every camera both calibrations hold, at each beam angle (deg)."""
    ids = cameras or [c.id for c in a.cameras if c.id in {x.id for x in b.cameras}]
    angles = np.asarray(angles_deg, dtype=float)
    t = np.zeros((len(ids), len(angles)))
    r = np.zeros_like(t)
    for i, cam in enumerate(ids):
        for j, angle in enumerate(angles):
            t[i, j], r[i, j] = pose_error(a.world_from_camera(cam, angle), b.world_from_camera(cam, angle))
    return PoseDifferences(ids, angles, t, r)
