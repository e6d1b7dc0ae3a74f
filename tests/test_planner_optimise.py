"""EM and the exact refinement never increase the total cost K; refinement reaches a
coordinate-wise optimum."""

from __future__ import annotations

import numpy as np
import pytest

from planner.baselines import average_focus, closest_focus, fixed_focus
from planner.cost import cost_table
from planner.em import expectation_minimisation
from planner.poses import rgb_poses
from planner.refine import refine_focus
from planner.rig import load_rig
from planner.sampling import sample_surface
from planner.visibility import RayScene, visible_pairs
from tests.planner_standin import standin_body

RIG = load_rig()


@pytest.fixture(scope="module")
def table():
    body = standin_body()
    poses = rgb_poses(RIG)
    samples = sample_surface(body, 1500, seed=11)
    return cost_table(visible_pairs(RayScene(body), poses, samples, RIG.optics), RIG.cost, RIG.optics)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_em_and_refinement_never_increase_cost(table, seed: int) -> None:
    rng = np.random.default_rng(seed)
    start = rng.uniform(150.0, 1500.0, table.n_poses)
    k0 = table.total_cost(start)
    em = expectation_minimisation(table, start)
    assert np.all(np.diff(em.history) < 0)
    assert em.history[0] == pytest.approx(k0)
    assert em.total_cost == pytest.approx(table.total_cost(em.focus_mm))
    assert em.total_cost <= k0
    refined = refine_focus(table, em.focus_mm)
    assert refined.total_cost == pytest.approx(table.total_cost(refined.focus_mm), abs=1e-9)
    assert refined.total_cost <= em.total_cost + 1e-9


def test_refinement_from_any_start_never_increases_cost(table) -> None:
    for start in (closest_focus(table.vis, 450.0), fixed_focus(table, 450.0)):
        refined = refine_focus(table, start, max_sweeps=3)
        assert refined.total_cost <= table.total_cost(start) + 1e-9


def test_refinement_is_a_coordinate_wise_optimum(table) -> None:
    em = expectation_minimisation(table, average_focus(table.vis, 450.0))
    refined = refine_focus(table, em.focus_mm, max_sweeps=100)
    k = table.total_cost(refined.focus_mm)
    rng = np.random.default_rng(5)
    for c in rng.choice(np.flatnonzero(np.diff(table.vis.pose_ptr) > 0), 4, replace=False):
        sl = table.vis.pairs_of(int(c))
        for s in np.unique(table.lo[sl]):  # coverage maxima start at an interval's lower end
            trial = refined.focus_mm.copy()
            trial[c] = s
            assert table.total_cost(trial) >= k - 1e-9


def test_shape_aware_beats_baselines_on_stand_in(table) -> None:
    average = average_focus(table.vis, 450.0)
    em = expectation_minimisation(table, average)
    refined = refine_focus(table, em.focus_mm)
    closest = closest_focus(table.vis, 450.0)
    assert table.in_focus_fraction(refined.focus_mm) > table.in_focus_fraction(average)
    assert table.in_focus_fraction(average) > table.in_focus_fraction(closest)
    assert refined.total_cost < em.total_cost < table.total_cost(average)


def test_bad_initial_focus_shape_is_refused(table) -> None:
    with pytest.raises(ValueError, match="initial focus has shape"):
        expectation_minimisation(table, np.ones(3))
