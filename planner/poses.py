"""Camera poses of the rig: every RGB phone at every capture angle, and depth cameras on the beam.

Camera frames follow the OpenCV convention: x right, y down, z forward (the optical axis).
A pose is stored as its centre and the three unit axes expressed in the world frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from planner.rig import DepthCamera, Rig

if TYPE_CHECKING:
    from planner.calibration.model import Calibration

_Z = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Poses:
    """P camera poses.

    Attributes:
        centres: (P, 3) float, mm.
        forward: (P, 3) float unit optical axes (n_c).
        right: (P, 3) float unit image x axes.
        down: (P, 3) float unit image y axes.
        angle_index: (P,) int, capture angle of each pose (RGB poses; -1 otherwise).
        camera_index: (P,) int, phone or depth camera of each pose.
    """

    centres: np.ndarray
    forward: np.ndarray
    right: np.ndarray
    down: np.ndarray
    angle_index: np.ndarray
    camera_index: np.ndarray

    def __len__(self) -> int:
        return len(self.centres)

    def camera_to_world(self, i: int) -> np.ndarray:
        """(4, 4) float transform of pose i from its camera frame to the world."""
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = (
            self.right[i],
            self.down[i],
            self.forward[i],
            self.centres[i],
        )
        return m

    def world_to_camera(self, i: int) -> np.ndarray:
        """(4, 4) float extrinsic matrix of pose i (world -> camera), as Open3D expects."""
        return np.linalg.inv(self.camera_to_world(i))

    def project(self, points: np.ndarray, i: int, focal_px: float, cx: float, cy: float) -> np.ndarray:
        """(N, 3) world points -> (N, 3) [u, v, depth] in pose i's pinhole image."""
        rel = points - self.centres[i]
        z = rel @ self.forward[i]
        u = focal_px * (rel @ self.right[i]) / z + cx
        v = focal_px * (rel @ self.down[i]) / z + cy
        return np.stack([u, v, z], axis=1)


def _look_towards_axis(
    centres: np.ndarray, azimuth: np.ndarray, tilt: np.ndarray, roll: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    inward = np.stack([-np.cos(azimuth), -np.sin(azimuth), np.zeros_like(azimuth)], axis=1)
    forward = np.cos(tilt)[:, None] * inward + np.sin(tilt)[:, None] * _Z
    right = np.cross(forward, _Z)
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    down = np.cross(forward, right)
    if np.any(roll):
        c, s = np.cos(roll)[:, None], np.sin(roll)[:, None]
        right, down = c * right + s * down, -s * right + c * down
    return forward, right, down


def rgb_poses(rig: Rig, angles_deg: np.ndarray | None = None) -> Poses:
    """All RGB poses in angle-major order (pose = angle_index * n_cameras + camera_index)."""
    angles = np.radians(rig.capture.angles_deg if angles_deg is None else np.asarray(angles_deg))
    n_cam = rig.n_cameras
    angle_index = np.repeat(np.arange(len(angles)), n_cam)
    camera_index = np.tile(np.arange(n_cam), len(angles))
    azimuth = angles[angle_index]
    heights = np.array([p.height_mm for p in rig.phones])[camera_index]
    tilts = np.radians([p.tilt_deg for p in rig.phones])[camera_index]
    r = rig.ring_radius_mm
    centres = np.stack([r * np.cos(azimuth), r * np.sin(azimuth), heights], axis=1)
    forward, right, down = _look_towards_axis(centres, azimuth, tilts, np.zeros_like(azimuth))
    return Poses(centres, forward, right, down, angle_index, camera_index)


def depth_camera_pose(camera: DepthCamera, beam_angle_rad: float) -> np.ndarray:
    """(4, 4) float camera-to-world transform of a depth camera at a beam angle."""
    azimuth = np.array([beam_angle_rad + math.radians(camera.angle_offset_deg)])
    centre = np.array(
        [[camera.radius_mm * math.cos(azimuth[0]), camera.radius_mm * math.sin(azimuth[0]), camera.height_mm]]
    )
    forward, right, down = _look_towards_axis(
        centre, azimuth, np.radians([camera.tilt_deg]), np.radians([camera.roll_deg])
    )
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right[0], down[0], forward[0], centre[0]
    return m


def poses_from_matrices(matrices: np.ndarray, angle_index: np.ndarray, camera_index: np.ndarray) -> Poses:
    """Poses from (P, 4, 4) camera-to-world matrices (OpenCV camera axes)."""
    m = np.asarray(matrices, dtype=float)
    return Poses(m[:, :3, 3].copy(), m[:, :3, 2].copy(), m[:, :3, 0].copy(), m[:, :3, 1].copy(),
                 np.asarray(angle_index), np.asarray(camera_index))


def rig_rgb_poses(rig: Rig, calibration: Calibration | None = None, angles_deg: np.ndarray | None = None) -> Poses:
    """Every phone at every capture angle (angle-major, like :func:`rgb_poses`): the calibrated poses
    when a calibration is given, else the rig file's nominal ones. The one place planning, the capture
    and navigation get their poses from."""
    if calibration is None:
        return rgb_poses(rig, angles_deg)
    angles = rig.capture.angles_deg if angles_deg is None else np.asarray(angles_deg, dtype=float)
    n_cam = rig.n_cameras
    matrices = np.array([calibration.world_from_camera(phone.id, float(a)) for a in angles for phone in rig.phones])
    return poses_from_matrices(matrices, np.repeat(np.arange(len(angles)), n_cam), np.tile(np.arange(n_cam), len(angles)))


def rig_depth_pose(camera: DepthCamera, beam_angle_rad: float, calibration: Calibration | None = None) -> np.ndarray:
    """(4, 4) camera-to-world of a depth camera at a beam angle: calibrated when a calibration is given."""
    if calibration is None:
        return depth_camera_pose(camera, beam_angle_rad)
    return calibration.world_from_camera(camera.id, math.degrees(beam_angle_rad))


def column_poses(radius_mm: float, heights_mm: np.ndarray, tilts_deg: np.ndarray, angles_deg: np.ndarray) -> Poses:
    """Poses of cameras in one column (heights (C,) mm, tilts (C,) deg, > 0 looks up) at a ring
    radius, at every angle (A,) deg, angle-major like :func:`rgb_poses`. For rig designs that
    are not (yet) a rig file."""
    angles = np.radians(np.asarray(angles_deg, dtype=float))
    heights = np.asarray(heights_mm, dtype=float)
    n_cam = len(heights)
    angle_index = np.repeat(np.arange(len(angles)), n_cam)
    camera_index = np.tile(np.arange(n_cam), len(angles))
    azimuth = angles[angle_index]
    centres = np.stack([radius_mm * np.cos(azimuth), radius_mm * np.sin(azimuth), heights[camera_index]], axis=1)
    tilts = np.radians(np.asarray(tilts_deg, dtype=float))[camera_index]
    forward, right, down = _look_towards_axis(centres, azimuth, tilts, np.zeros_like(azimuth))
    return Poses(centres, forward, right, down, angle_index, camera_index)


def depth_sweep_poses(camera: DepthCamera, beam_angles_deg: np.ndarray) -> Poses:
    """Poses (optical frames) of one depth camera at every beam angle (K,) deg of a sweep."""
    frames = [depth_camera_pose(camera, math.radians(a)) for a in np.asarray(beam_angles_deg, dtype=float)]
    m = np.array(frames).reshape(-1, 4, 4)
    n = len(m)
    return Poses(m[:, :3, 3], m[:, :3, 2], m[:, :3, 0], m[:, :3, 1], np.arange(n), np.zeros(n, dtype=int))
