"""Visibility on analytic scenes: frustum, facing and occlusion."""

from __future__ import annotations

import numpy as np
import pytest

from planner.rig import load_rig
from planner.sampling import SurfaceSamples, sample_surface
from planner.visibility import RayScene, frustum_tangents, visible_pairs
from tests.planner_scenes import looking_at, square
from tests.planner_standin import sphere

OPTICS = load_rig().optics


@pytest.mark.parametrize("backend", ["open3d", "embree"])
def test_sphere_shows_only_its_near_cap(backend: str) -> None:
    ball = sphere(200.0, (0.0, 0.0, 0.0))
    samples = sample_surface(ball, 4000, seed=3)
    poses = looking_at([[1000.0, 0.0, 0.0]], [[0.0, 0.0, 0.0]])
    vis = visible_pairs(RayScene(ball, backend), poses, samples, OPTICS)
    seen = vis.visible_points
    # The cap seen from distance d is x > r^2 / d = 40 mm (tangent rays); faceting blurs the rim.
    x = samples.points[:, 0]
    assert np.all(seen[x > 50.0])
    assert not np.any(seen[x < 30.0])
    assert 0.35 < seen.mean() < 0.45
    # Depth along the axis of the nearest point is about 800 mm.
    assert vis.depth.min() == pytest.approx(800.0, abs=2.0)


@pytest.mark.parametrize("backend", ["open3d", "embree"])
def test_plane_behind_another_is_hidden(backend: str) -> None:
    front, back = square(400.0, 0.0), square(200.0, -100.0)
    scene = RayScene(front + back, backend)
    pts = np.array([[-100.0, 0.0, 0.0], [-100.0, 50.0, 50.0], [0.0, 0.0, 0.0], [0.0, 150.0, -150.0]])
    samples = SurfaceSamples.from_arrays(pts, np.tile([-1.0, 0.0, 0.0], (4, 1)))
    poses = looking_at([[800.0, 0.0, 0.0]], [[0.0, 0.0, 0.0]])
    vis = visible_pairs(scene, poses, samples, OPTICS)
    assert vis.visible_points.tolist() == [False, False, True, True]


def test_back_facing_and_out_of_frustum_points_are_dropped() -> None:
    plane = square(2000.0, 0.0)
    tan_w, tan_h = frustum_tangents(OPTICS)
    d = 1000.0
    pts = np.array(
        [
            [0.0, 0.0, 0.0],  # centre
            [0.0, 0.99 * tan_w * d, 0.0],  # just inside horizontally
            [0.0, 1.01 * tan_w * d, 0.0],  # just outside horizontally
            [0.0, 0.0, 0.99 * tan_h * d],  # just inside vertically (the long, portrait side)
            [0.0, 0.0, 1.01 * tan_h * d],  # just outside vertically
        ]
    )
    inward = np.tile([-1.0, 0.0, 0.0], (len(pts), 1))
    poses = looking_at([[d, 0.0, 0.0]], [[0.0, 0.0, 0.0]])
    scene = RayScene(plane)
    seen = visible_pairs(scene, poses, SurfaceSamples.from_arrays(pts, inward), OPTICS).visible_points
    assert seen.tolist() == [True, True, False, True, False]
    flipped = visible_pairs(scene, poses, SurfaceSamples.from_arrays(pts, -inward), OPTICS)
    assert len(flipped) == 0
    assert tan_h > tan_w  # portrait: the vertical field of view is the wider one


def test_pairs_are_grouped_by_pose_and_carry_geometry() -> None:
    ball = sphere(150.0, (0.0, 0.0, 0.0))
    samples = sample_surface(ball, 2000, seed=1)
    poses = looking_at([[600.0, 0.0, 0.0], [0.0, 600.0, 0.0], [-600.0, 0.0, 100.0]], np.zeros((3, 3)))
    vis = visible_pairs(RayScene(ball), poses, samples, OPTICS)
    assert np.all(np.diff(vis.pose) >= 0)
    for c in range(3):
        sl = vis.pairs_of(c)
        assert np.all(vis.pose[sl] == c)
        rel = samples.points[vis.point[sl]] - poses.centres[c]
        np.testing.assert_allclose(vis.depth[sl], rel @ poses.forward[c], rtol=1e-5, atol=1e-3)
        lateral = np.linalg.norm(rel - np.outer(rel @ poses.forward[c], poses.forward[c]), axis=1)
        np.testing.assert_allclose(vis.off_axis[sl], lateral, rtol=1e-5, atol=1e-3)
        np.testing.assert_allclose(vis.facing[sl], samples.normals[vis.point[sl]] @ poses.forward[c], atol=1e-6)


def test_unknown_backend_is_refused() -> None:
    with pytest.raises(ValueError, match="unknown ray backend 'optix'"):
        RayScene(sphere(), "optix")
