"""Calibration noise on camera poses, for robustness studies (SPEC 6: plan on noisy poses,
evaluate on the true ones)."""

from __future__ import annotations

import math

import numpy as np

from planner.poses import Poses


def _rotations(axes: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """(K, 3, 3) rotation matrices about unit axes (K, 3) by angles (K,) rad (Rodrigues)."""
    x, y, z = axes.T
    zero = np.zeros_like(x)
    k = np.stack([np.stack([zero, -z, y], -1), np.stack([z, zero, -x], -1), np.stack([-y, x, zero], -1)], 1)
    s, c = np.sin(angles)[:, None, None], np.cos(angles)[:, None, None]
    return np.eye(3) + s * k + (1 - c) * (k @ k)


def _unit_vectors(rng: np.random.Generator, count: int) -> np.ndarray:
    v = rng.normal(size=(count, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def perturb_poses(
    poses: Poses, *, translation_mm: float = 2.5, rotation_deg: float = 0.3, seed: int = 0
) -> Poses:
    """Every pose moved by exactly ``translation_mm`` in a random direction and turned by exactly
    ``rotation_deg`` about a random axis through its centre; reproducible for a seed."""
    if translation_mm < 0 or rotation_deg < 0:
        raise ValueError(f"perturbation must be non-negative, got {translation_mm} mm, {rotation_deg} deg")
    rng = np.random.default_rng(seed)
    n = len(poses)
    centres = poses.centres + translation_mm * _unit_vectors(rng, n)
    turn = _rotations(_unit_vectors(rng, n), np.full(n, math.radians(rotation_deg)))
    return Poses(
        centres,
        np.einsum("kij,kj->ki", turn, poses.forward),
        np.einsum("kij,kj->ki", turn, poses.right),
        np.einsum("kij,kj->ki", turn, poses.down),
        poses.angle_index.copy(),
        poses.camera_index.copy(),
    )
