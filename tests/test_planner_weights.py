"""Weighted samples: a weight counts like that many copies of a sample and the bound stays
certified (the optimisers on weighted problems: tests/test_planner_optimise.py)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from planner.bound import in_focus_bound
from planner.cost import cost_table
from planner.em import expectation_minimisation
from planner.redundancy import expected_misses, sharp_views
from planner.visibility import Visibility, group_pointers
from tests.test_planner_bound import best_plan_by_brute_force
from tests.test_planner_optimise import RIG, random_table

FOCUS = st.lists(st.floats(150.0, 3000.0), min_size=5, max_size=5)


def copies(table) -> object:
    """The same problem with each point repeated weight times (integer weights)."""
    vis, weight = table.vis, table.weight.astype(int)
    first = np.r_[0, np.cumsum(weight)[:-1]]
    rows = [(c, first[p] + k, i) for i, (c, p) in enumerate(zip(vis.pose.tolist(), vis.point.tolist()))
            for k in range(weight[p])]
    pose = np.array([r[0] for r in rows], dtype=np.int32)
    point = np.array([r[1] for r in rows], dtype=np.int32)
    src = np.array([r[2] for r in rows], dtype=np.int64)
    ptr = group_pointers(pose, vis.n_poses)
    dup = Visibility(vis.n_poses, int(weight.sum()), pose, point, vis.depth[src], vis.off_axis[src],
                     vis.facing[src], ptr)
    return cost_table(dup, RIG.cost, RIG.optics)


@given(seed=st.integers(0, 10_000), n_poses=st.integers(1, 5), n_points=st.integers(1, 20), focus=FOCUS)
@settings(max_examples=60, deadline=None)
def test_a_weight_counts_like_that_many_copies(seed: int, n_poses: int, n_points: int, focus: list[float]) -> None:
    weight = np.random.default_rng(seed + 3).integers(1, 4, n_points).astype(float)
    table = random_table(seed, n_poses, n_points, weight)
    dup = copies(table)
    s = np.array(focus[:n_poses])
    assert table.total_cost(s) == pytest.approx(dup.total_cost(s), abs=1e-9)
    assert table.in_focus_fraction(s) == pytest.approx(dup.in_focus_fraction(s), abs=1e-12)
    assert table.visible_fraction == pytest.approx(dup.visible_fraction, abs=1e-12)
    assert table.assignment(s)[1] == pytest.approx(dup.total_cost(s), abs=1e-9)
    assert expected_misses(sharp_views(table, s), 0.2, table.weight) == pytest.approx(
        expected_misses(sharp_views(dup, s), 0.2), abs=1e-9)
    # The EM step's weighted sweep lands where the copies' sweep does.
    em, em_dup = expectation_minimisation(table, s), expectation_minimisation(dup, s)
    assert em.total_cost == pytest.approx(em_dup.total_cost, abs=1e-9)


@given(seed=st.integers(0, 10_000), n_poses=st.integers(1, 3), n_points=st.integers(1, 9))
@settings(max_examples=60, deadline=None)
def test_no_plan_beats_the_weighted_bound(seed: int, n_poses: int, n_points: int) -> None:
    weight = np.random.default_rng(seed + 7).uniform(0.1, 3.0, n_points)
    table = random_table(seed, n_poses, n_points, weight)
    bound = in_focus_bound(table)
    best = best_plan_by_brute_force(table)
    assert best <= bound.sharp_at_most + 1e-9
    assert bound.sharp_at_most <= bound.visible + 1e-9
    assert bound.visible == pytest.approx(float(weight[table.seen].sum()))
    if n_poses <= 2:  # every sample lies in one group: the bound is exact
        assert bound.sharp_at_most == pytest.approx(best)




@given(seed=st.integers(0, 10_000), n_poses=st.integers(1, 5), n_points=st.integers(1, 20), focus=FOCUS)
@settings(max_examples=30, deadline=None)
def test_a_subset_of_the_poses_keeps_the_weights(seed: int, n_poses: int, n_points: int, focus: list[float]) -> None:
    from planner.angles import subset_table

    weight = np.random.default_rng(seed + 9).uniform(0.1, 3.0, n_points)
    table = random_table(seed, n_poses, n_points, weight)
    keep = np.arange(0, n_poses, 2)
    sub = subset_table(table, keep, RIG)
    s = np.array(focus[:n_poses])
    # The same skin seen by fewer poses: the kept poses' pairs, each point at its weight.
    alone = s.copy()
    alone[np.setdiff1d(np.arange(n_poses), keep)] = np.nan  # poses left out hold nothing sharp
    assert sub.in_focus_fraction(s[keep]) == pytest.approx(table.in_focus_fraction(alone), abs=1e-12)
    assert sub.total_weight == pytest.approx(weight.sum())
