"""The texture's compiled view costs (planner/candidate_costs.py) are the planner's: the frustum
and facing tests of planner.visibility and the terms of planner.cost, pair by pair."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from scipy import sparse

from planner.candidate_costs import candidate_costs
from planner.cost import area_term, axis_term, base_cost
from planner.optics import focus_interval
from planner.poses import rgb_poses
from planner.rig import load_rig
from planner.visibility import frustum_tangents

RIG = load_rig()
POSES = rgb_poses(RIG)


def _planner_pairs(focus, points, normals, candidates, face):  # noqa: ANN001, ANN202
    """The same pairs from the planner's NumPy terms, grouped by point, poses ascending."""
    optics, cost = RIG.optics, RIG.cost
    point, pose = np.nonzero((candidates.toarray()[face] > 0) & np.isfinite(focus)[None, :])
    rel = points[point] - POSES.centres[pose]
    x, y, z = ((rel * axis[pose]).sum(axis=1) for axis in (POSES.right, POSES.down, POSES.forward))
    tan_w, tan_h = frustum_tangents(optics)
    keep = (np.abs(x) <= tan_w * z) & (np.abs(y) <= tan_h * z) & ((rel * normals[point]).sum(axis=1) > 0)
    point, pose, x, y, z = point[keep], pose[keep], x[keep], y[keep], z[keep]
    facing = (POSES.forward[pose] * normals[point]).sum(axis=1)
    lo, hi = focus_interval(z, optics.hyperfocal_mm, optics.focal_length_mm)
    sharp = (lo <= focus[pose]) & (focus[pose] <= hi)
    total = base_cost(cost, area_term(z, facing, cost.eps_area), axis_term(np.hypot(x, y), cost.axis_deviation_mm))
    return point, pose, total + cost.w_focus * ~sharp, sharp, z


@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 60), missing=st.integers(0, 20))
def test_the_compiled_costs_are_the_planners(seed: int, n: int, missing: int) -> None:
    rng = np.random.default_rng(seed)
    n_poses = RIG.n_poses
    focus = rng.uniform(300.0, 900.0, n_poses)
    focus[rng.choice(n_poses, missing, replace=False)] = np.nan  # images not on disk
    # points on and around a body-sized cylinder, normals inward with a random tilt
    angle, height = rng.uniform(0, 2 * np.pi, n), rng.uniform(100.0, 1800.0, n)
    radius = rng.uniform(80.0, 250.0, n)
    points = np.stack([radius * np.cos(angle), radius * np.sin(angle), height], axis=1)
    normals = -np.stack([np.cos(angle), np.sin(angle), np.zeros(n)], axis=1) + rng.normal(0, 0.4, (n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    n_faces = 7
    candidates = sparse.csr_matrix(rng.random((n_faces, n_poses)) < 0.3).astype(float)
    candidates.sort_indices()
    face = rng.integers(0, n_faces, n)

    point, pose, cost, sharp, x, y, z = candidate_costs(RIG, POSES, focus, points, normals, candidates, face)
    want = _planner_pairs(focus, points, normals, candidates, face)
    assert np.array_equal(point, want[0]) and np.array_equal(pose, want[1])
    np.testing.assert_allclose(cost, want[2], rtol=0, atol=1e-12)
    assert np.array_equal(sharp, want[3])
    np.testing.assert_allclose(z, want[4], rtol=1e-12)
    # the pixel the pair's x, y, z give lies in the image
    f, optics = RIG.optics.focal_length_px, RIG.optics
    u, v = f * x / z + optics.image_width_px / 2, f * y / z + optics.image_height_px / 2
    assert np.all((u >= -1e-6) & (u <= optics.image_width_px + 1e-6) & (v >= -1e-6) & (v <= optics.image_height_px + 1e-6))
