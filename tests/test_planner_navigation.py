"""Image navigation: the best view of a skin point sees it, and its pixel maps back to it."""

from __future__ import annotations

import numpy as np
import pytest

from planner.navigation import best_poses, find_views
from planner.plan import plan_focus
from planner.rig import load_rig
from planner.visibility import RayScene
from tests.planner_standin import standin_body

RIG = load_rig()


@pytest.fixture(scope="module")
def planned():
    body = standin_body()
    return body, plan_focus(body, RIG, points=1500, seed=2, methods=("em", "shape-aware"))


def test_best_view_sees_the_point_and_pixel_round_trips(planned) -> None:
    body, plan = planned
    scene = RayScene(body)
    vertices = body.vertices[np.random.default_rng(0).choice(len(body.vertices), 12, replace=False)]
    views = find_views(scene, RIG, plan.poses, plan.focus_mm, vertices)
    assert any(views)
    optics = RIG.optics
    f = optics.focal_length_px
    for point, found in zip(vertices, views):
        costs = [v.cost for v in found]
        assert costs == sorted(costs)
        for view in found:
            assert 0 <= view.u_px <= optics.image_width_px and 0 <= view.v_px <= optics.image_height_px
            # Back-project (u, v, depth) through the pose: lands on the point.
            p = plan.poses
            x = (view.u_px - optics.image_width_px / 2) / f * view.depth_mm
            y = (view.v_px - optics.image_height_px / 2) / f * view.depth_mm
            back = p.centres[view.pose] + x * p.right[view.pose] + y * p.down[view.pose]
            back += view.depth_mm * p.forward[view.pose]
            np.testing.assert_allclose(back, point, atol=1e-3)  # depths are float32-exact
            assert view.angle_deg == RIG.capture.angles_deg[view.angle_index]
            assert view.pose == RIG.pose_index(view.angle_index, view.camera_index)
            # The camera really sees it: nothing between the camera and the point.
            assert not scene.occluded(p.centres[view.pose][None], point[None], 0.5)[0]


def test_front_of_chest_is_best_seen_from_the_front(planned) -> None:
    body, plan = planned
    chest = np.array([[body.bounds[1, 0], 0.0, 1200.0]])
    hit = RayScene(body).closest_faces(chest)[0]
    views = find_views(RayScene(body), RIG, plan.poses, plan.focus_mm, hit)[0]
    assert views and abs(views[0].angle_deg) <= 40.0
    assert views[0].camera_index in (3, 4, 5)


def test_hidden_point_has_no_views(planned) -> None:
    body, plan = planned
    inside = np.array([[0.0, 0.0, 1200.0]])  # inside the torso: every ray crosses the skin
    assert find_views(RayScene(body), RIG, plan.poses, plan.focus_mm, inside, np.array([[1.0, 0, 0]])) == [[]]


def test_best_poses_of_the_planning_samples(planned) -> None:
    _, plan = planned
    poses = best_poses(plan.table, plan.focus_mm)
    seen = plan.table.seen
    assert np.all(poses[~seen] == -1) and np.all(poses[seen] >= 0)
    costs = plan.table.point_costs(plan.focus_mm)
    pair_cost = plan.table.pair_cost(plan.focus_mm)
    vis = plan.table.vis
    for p in np.flatnonzero(seen)[:50]:
        mine = np.flatnonzero((vis.point == p) & (vis.pose == poses[p]))
        assert pair_cost[mine[0]] == pytest.approx(costs[p])
