"""The rig file's nominal cameras in calibration terms: where each camera sits on the beam, and its lens.

The nominal poses start the calibration and are what planning uses when no calibration exists;
the calibration report shows how far each calibrated camera sits from them.
"""

from __future__ import annotations

import numpy as np

from planner.calibration.model import CameraCalibration, Intrinsics
from planner.poses import depth_camera_pose, rgb_poses
from planner.rig import Rig


def phone_intrinsics(rig: Rig, width_px: int, height_px: int) -> Intrinsics:
    """The nominal phone lens (rig optics, no distortion) for images of width x height px."""
    f = rig.optics.focal_length_px * width_px / rig.optics.image_width_px
    return Intrinsics(width_px, height_px, f, f, (width_px - 1) / 2, (height_px - 1) / 2)


def depth_intrinsics(rig: Rig, width_px: int | None = None, height_px: int | None = None) -> Intrinsics:
    """The nominal depth camera lens (infrared imager = depth frame) at width x height px."""
    m = rig.depth_camera_model
    scale = (width_px or m.width_px) / m.width_px
    return Intrinsics(m.width_px, m.height_px, m.fx_px, m.fy_px, m.cx_px, m.cy_px).scaled(scale)


def phone_beam_poses(rig: Rig) -> list[np.ndarray]:
    """(4, 4) nominal beam_from_camera of every phone (its pose at beam angle 0)."""
    poses = rgb_poses(rig, np.array([0.0]))
    return [poses.camera_to_world(i) for i in range(rig.n_cameras)]


def depth_beam_poses(rig: Rig) -> list[np.ndarray]:
    """(4, 4) nominal beam_from_camera of every depth camera."""
    return [depth_camera_pose(cam, 0.0) for cam in rig.depth_cameras]


def nominal_cameras(rig: Rig, phone_size: tuple[int, int], depth_size: tuple[int, int] | None = None
                    ) -> list[CameraCalibration]:
    """Every camera of the rig at its nominal place with its nominal lens (phones first)."""
    cams = [CameraCalibration(p.id, "phone", phone_intrinsics(rig, *phone_size), m)
            for p, m in zip(rig.phones, phone_beam_poses(rig))]
    size = depth_size or (rig.depth_camera_model.width_px, rig.depth_camera_model.height_px)
    cams += [CameraCalibration(d.id, "depth", depth_intrinsics(rig, *size), m)
             for d, m in zip(rig.depth_cameras, depth_beam_poses(rig))]
    return cams

