"""Rigid and similarity transforms for calibration: 4 x 4 matrices in mm, rotation vectors in radians."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation


def transform(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(4, 4) float from a (3, 3) rotation and a (3,) translation."""
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rotation, translation
    return m


def from_rotvec(rotvec: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(4, 4) float from a (3,) rotation vector (rad) and a (3,) translation (mm)."""
    return transform(Rotation.from_rotvec(np.asarray(rotvec, dtype=float)).as_matrix(), translation)


def to_rotvec(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(3,) rotation vector (rad) and (3,) translation of a (4, 4) rigid transform."""
    return Rotation.from_matrix(m[:3, :3]).as_rotvec(), m[:3, 3].copy()


def rot_z(angle_rad: float) -> np.ndarray:
    """(4, 4) rotation about the world z axis (the beam's rotation axis)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    return m


def invert(m: np.ndarray) -> np.ndarray:
    """Inverse of a (4, 4) rigid transform."""
    out = np.eye(4)
    out[:3, :3] = m[:3, :3].T
    out[:3, 3] = -m[:3, :3].T @ m[:3, 3]
    return out


def pose_error(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """The seed's pose distance between two (4, 4) camera-to-world poses: centre distance (mm) and
    rotation angle acos((trace(Ra^T Rb) - 1) / 2) (deg)."""
    cos = (np.trace(a[:3, :3].T @ b[:3, :3]) - 1.0) / 2.0
    return float(np.linalg.norm(a[:3, 3] - b[:3, 3])), math.degrees(math.acos(min(1.0, max(-1.0, cos))))


def umeyama(source: np.ndarray, target: np.ndarray, *, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity target ~ s R source + t (Umeyama 1991) of (N, 3) point sets.

    Returns scale s, (3, 3) rotation R and (3,) translation t.
    """
    source, target = np.asarray(source, dtype=float), np.asarray(target, dtype=float)
    if source.shape != target.shape or source.ndim != 2 or source.shape[1] != 3 or len(source) < 3:
        raise ValueError(f"umeyama needs two (N >= 3, 3) point sets, got {source.shape} and {target.shape}")
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    ds, dt = source - mu_s, target - mu_t
    cov = dt.T @ ds / len(source)
    u, d, vt = np.linalg.svd(cov)
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2, 2] = -1.0
    rotation = u @ sign @ vt
    variance = (ds**2).sum() / len(source)
    scale = float(np.trace(np.diag(d) @ sign) / variance) if with_scale else 1.0
    return scale, rotation, mu_t - scale * rotation @ mu_s
