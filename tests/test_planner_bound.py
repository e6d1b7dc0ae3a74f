"""The in-focus bound is certified: no focus plan beats it, and it never exceeds the visible count."""

from __future__ import annotations

import itertools

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from planner.bound import in_focus_bound, sharp_count
from tests.test_planner_optimise import random_table


def best_plan_by_brute_force(table) -> int:
    """Most samples any plan holds sharp: every pose tries every interval lower end (coverage
    maxima start there) or nothing."""
    candidates = []
    for c in range(table.n_poses):
        sl = table.vis.pairs_of(c)
        candidates.append(sorted(set(table.lo[sl].tolist())) or [1.0])
    best = 0
    for focus in itertools.product(*candidates):
        best = max(best, sharp_count(table, np.array(focus)))
    return best


@given(seed=st.integers(0, 10_000), n_poses=st.integers(1, 3), n_points=st.integers(1, 9))
@settings(max_examples=80, deadline=None)
def test_no_plan_beats_the_bound(seed: int, n_poses: int, n_points: int) -> None:
    table = random_table(seed, n_poses, n_points)
    bound = in_focus_bound(table)
    best = best_plan_by_brute_force(table)
    assert best <= bound.sharp_at_most <= bound.visible
    assert bound.visible == int(table.seen.sum())
    if n_poses <= 2:  # every sample lies in one group: the bound is exact
        assert bound.sharp_at_most == best


def test_bound_counts_a_conflict_between_two_poses() -> None:
    # Two poses, four samples each seen by both at depths no single focus pair can serve all of.
    from planner.cost import cost_table
    from planner.rig import load_rig
    from planner.visibility import Visibility

    rig = load_rig()
    depth = np.array([200.0, 400.0, 800.0, 1600.0])
    pose = np.repeat([0, 1], 4).astype(np.int32)
    point = np.tile(np.arange(4), 2).astype(np.int32)
    vis = Visibility(2, 4, pose, point, np.tile(depth, 2), np.zeros(8), np.ones(8), np.array([0, 4, 8]))
    table = cost_table(vis, rig.cost, rig.optics)
    bound = in_focus_bound(table)
    assert bound.visible == 4 and bound.sharp_at_most == 2 == best_plan_by_brute_force(table)
    assert bound.fraction == 0.5
