"""The seed's cost terms by hand, and the table's point and total costs."""

from __future__ import annotations

import numpy as np
import pytest

from planner.cost import area_term, axis_term, cost_table
from planner.rig import load_rig
from planner.sampling import SurfaceSamples
from planner.visibility import RayScene, visible_pairs
from tests.planner_scenes import looking_at, square

RIG = load_rig()
EPS1 = 0.5 / 450.0**2  # cos 60 deg / 450^2 (SPEC 3)


def test_eps_area_matches_spec() -> None:
    assert RIG.cost.eps_area == pytest.approx(EPS1)
    assert RIG.cost.eps_area == pytest.approx(2.47e-6, rel=1e-3)


def test_terms_by_hand() -> None:
    assert area_term(np.array([300.0]), np.array([1.0]), EPS1)[0] == pytest.approx(90000 * EPS1)
    assert area_term(np.array([300.0]), np.array([0.5]), EPS1)[0] == pytest.approx(2 * 90000 * EPS1)
    # 450 mm at 60 deg incidence costs exactly 1; farther or more oblique is clamped to 1.
    assert area_term(np.array([450.0, 600.0]), np.array([0.5, 0.5]), EPS1) == pytest.approx([1.0, 1.0])
    assert area_term(np.array([300.0]), np.array([0.0]), EPS1)[0] == 1.0
    assert area_term(np.array([300.0]), np.array([-0.2]), EPS1)[0] == 1.0
    assert axis_term(np.array([0.0, 100.0, 450.0, 900.0]), 450.0) == pytest.approx([0.0, 100 / 450, 1.0, 1.0])


def _table():
    scene = RayScene(square(1000.0, 0.0))
    tilt = np.array([-0.5, np.sqrt(3) / 2, 0.0])  # facing <n_c, n_p> = 0.5 (60 deg incidence)
    pts = np.array([[0.0, 0.0, 0.0], [0.0, 100.0, 0.0], [0.0, 0.0, 50.0], [0.0, 0.0, 2000.0]])
    normals = np.array([[-1.0, 0, 0], [-1.0, 0, 0], tilt, [-1.0, 0, 0]])
    poses = looking_at([[300.0, 0.0, 0.0]], [[0.0, 0.0, 0.0]])
    vis = visible_pairs(scene, poses, SurfaceSamples.from_arrays(pts, normals), RIG.optics)
    return cost_table(vis, RIG.cost, RIG.optics)


def test_pair_costs_by_hand() -> None:
    table = _table()
    assert table.vis.point.tolist() == [0, 1, 2]  # the last point is outside the frustum
    third = 1.0 / 3.0
    a = 90000 * EPS1
    expected_base = [third * a, third * (a + 100 / 450), third * (2 * a + 50 / 450)]
    np.testing.assert_allclose(table.base, expected_base, rtol=1e-6)
    sharp = table.pair_cost(np.array([300.0]))
    blurred = table.pair_cost(np.array([1000.0]))
    np.testing.assert_allclose(sharp, expected_base, rtol=1e-6)
    np.testing.assert_allclose(blurred, np.array(expected_base) + third, rtol=1e-6)
    # The invisible point costs 1; K sums the point costs.
    assert table.point_costs(np.array([300.0]))[3] == 1.0
    assert table.total_cost(np.array([300.0])) == pytest.approx(sum(expected_base) + 1.0, rel=1e-6)
    assert table.in_focus_fraction(np.array([300.0])) == 0.75
    assert table.in_focus_fraction(np.array([1000.0])) == 0.0
    assert table.visible_fraction == 0.75


def test_assignment_picks_lowest_cost_and_counts_invisible_points() -> None:
    table = _table()
    best, k = table.assignment(np.array([300.0]))
    assert best.tolist() == [0, 1, 2, -1]
    assert k == pytest.approx(table.total_cost(np.array([300.0])))


def test_radix_argsort_matches_numpy_stable_sort() -> None:
    from planner.cost import stable_argsort_indices

    rng = np.random.default_rng(0)
    for high in (5, 70_000, 3_000_000):
        keys = rng.integers(0, high, 5000).astype(np.int32)
        np.testing.assert_array_equal(stable_argsort_indices(keys), np.argsort(keys, kind="stable"))
    assert len(stable_argsort_indices(np.zeros(0, dtype=np.int32))) == 0
