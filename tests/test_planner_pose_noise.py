"""Calibration-noise perturbation of poses: exact magnitudes, rigid axes, reproducible."""

from __future__ import annotations

import numpy as np
import pytest

from planner.pose_noise import perturb_poses
from planner.poses import rgb_poses
from planner.rig import load_rig

POSES = rgb_poses(load_rig())


def test_magnitudes_are_exact_and_axes_stay_orthonormal() -> None:
    noisy = perturb_poses(POSES, translation_mm=2.5, rotation_deg=0.3, seed=1)
    np.testing.assert_allclose(np.linalg.norm(noisy.centres - POSES.centres, axis=1), 2.5)
    angle = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", noisy.forward, POSES.forward), -1, 1)))
    assert np.all(angle <= 0.3 + 1e-9) and angle.mean() > 0.1
    for a, b in [("forward", "right"), ("right", "down"), ("down", "forward")]:
        np.testing.assert_allclose(np.einsum("ij,ij->i", getattr(noisy, a), getattr(noisy, b)), 0, atol=1e-12)
    np.testing.assert_allclose(np.cross(noisy.right, noisy.down), noisy.forward, atol=1e-12)


def test_seeded_and_zero_is_identity() -> None:
    a = perturb_poses(POSES, seed=3)
    b = perturb_poses(POSES, seed=3)
    np.testing.assert_array_equal(a.centres, b.centres)
    assert not np.allclose(a.centres, perturb_poses(POSES, seed=4).centres)
    same = perturb_poses(POSES, translation_mm=0.0, rotation_deg=0.0)
    np.testing.assert_allclose(same.forward, POSES.forward, atol=1e-15)


def test_negative_noise_is_refused() -> None:
    with pytest.raises(ValueError, match="non-negative"):
        perturb_poses(POSES, translation_mm=-1.0)
