"""Baseline focus plans on a scene with known depths."""

from __future__ import annotations

import numpy as np
import pytest

from planner.baselines import autofocus, average_focus, closest_focus, fixed_focus
from planner.cost import cost_table
from planner.rig import load_rig
from planner.sampling import SurfaceSamples
from planner.visibility import RayScene, visible_pairs
from tests.planner_scenes import looking_at, square

RIG = load_rig()


@pytest.fixture()
def scene():
    # A wall at x = 0 and a pose 600 mm in front of it; a second pose looks away and sees nothing.
    wall = square(1200.0, 0.0)
    pts = np.array([[0.0, y, z] for y in (-100.0, 0.0, 100.0) for z in (-100.0, 0.0, 100.0)])
    samples = SurfaceSamples.from_arrays(pts, np.tile([-1.0, 0.0, 0.0], (len(pts), 1)))
    poses = looking_at([[600.0, 0.0, 0.0], [600.0, 0.0, 0.0]], [[0.0, 0.0, 0.0], [1200.0, 0.0, 0.0]])
    ray = RayScene(wall)
    vis = visible_pairs(ray, poses, samples, RIG.optics)
    return ray, poses, vis


def test_closest_and_average_use_the_visible_depths(scene) -> None:
    _, _, vis = scene
    # Depth along the axis of a fronto-parallel wall is 600 mm for every point.
    assert closest_focus(vis, 450.0) == pytest.approx([600.0, 450.0])
    assert average_focus(vis, 450.0) == pytest.approx([600.0, 450.0])


def test_autofocus_casts_the_central_ray_and_falls_back(scene) -> None:
    ray, poses, vis = scene
    # Pose 1 looks away from the wall: its central ray misses, and it sees nothing either.
    assert autofocus(ray, poses, vis, 450.0) == pytest.approx([600.0, 450.0], abs=1e-3)


def test_fixed_focus_is_one_distance_with_minimal_cost(scene) -> None:
    _, _, vis = scene
    table = cost_table(vis, RIG.cost, RIG.optics)
    fixed = fixed_focus(table, 450.0)
    assert fixed[0] == fixed[1]
    assert table.in_focus_fraction(fixed) == 1.0
    assert table.total_cost(fixed) == pytest.approx(table.total_cost(np.full(2, 600.0)))
