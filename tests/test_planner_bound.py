"""The in-focus bound is certified: no focus plan beats it, and it never exceeds the visible count."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from planner import bound as bound_module
from planner.bound import GROUP_POSES, coverage_sets, in_focus_bound, sharp_count
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


@given(seed=st.integers(0, 10_000), n_poses=st.integers(1, 5), n_points=st.integers(1, 8))
@settings(max_examples=80, deadline=None)
def test_no_plan_beats_the_bound(seed: int, n_poses: int, n_points: int) -> None:
    table = random_table(seed, n_poses, n_points)
    bound = in_focus_bound(table)
    best = best_plan_by_brute_force(table)
    assert best <= bound.sharp_at_most <= bound.visible
    assert bound.visible == int(table.seen.sum())
    if n_poses <= GROUP_POSES:  # every pose in one group: the bound is exact
        assert bound.sharp_at_most == best


@given(seed=st.integers(0, 10_000), n_poses=st.integers(2, 5), n_points=st.integers(1, 8))
@settings(max_examples=40, deadline=None)
def test_a_group_too_large_to_search_is_bounded_in_halves(seed: int, n_poses: int, n_points: int) -> None:
    table = random_table(seed, n_poses, n_points)
    exact = in_focus_bound(table).sharp_at_most
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(bound_module, "SEARCH_BUDGET", 0)
        halves = in_focus_bound(table)
    assert best_plan_by_brute_force(table) <= exact <= halves.sharp_at_most <= halves.visible


@given(lo=st.lists(st.floats(100.0, 2000.0), min_size=1, max_size=12), width=st.floats(0.0, 400.0),
       s=st.floats(50.0, 3000.0))
def test_every_focus_distance_holds_one_of_the_maximal_sets_or_less(lo: list[float], width: float, s: float) -> None:
    lo_a = np.array(lo)
    hi_a = lo_a + width * np.linspace(0.2, 1.0, len(lo_a))
    sets = coverage_sets(lo_a, hi_a)
    held = (lo_a <= s) & (s <= hi_a)
    assert np.any(np.all(~held | sets, axis=1))  # within some maximal set
    for row in sets:  # each set is held by a focus distance (its largest lower end)
        start = lo_a[row].max()
        assert np.array_equal(row, (lo_a <= start) & (start <= hi_a))
    assert not any(np.all(~a | b) for i, a in enumerate(sets) for j, b in enumerate(sets) if i != j)


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


def test_bound_counts_close_skin_three_poses_cannot_all_hold() -> None:
    # Skin 15-70 cm from three phones, each depth seen by all three: close skin is sharp over
    # a few millimetres of focus only, so three focus distances hold three of the five depths.
    from planner.cost import cost_table
    from planner.rig import load_rig
    from planner.visibility import Visibility

    rig = load_rig()
    depth = np.array([150.0, 200.0, 300.0, 450.0, 700.0])
    pose = np.repeat([0, 1, 2], 5).astype(np.int32)
    point = np.tile(np.arange(5), 3).astype(np.int32)
    vis = Visibility(3, 5, pose, point, np.tile(depth, 3), np.zeros(15), np.ones(15), np.array([0, 5, 10, 15]))
    table = cost_table(vis, rig.cost, rig.optics)
    assert in_focus_bound(table, max_poses=2).sharp_at_most == 5  # pairs see no conflict here
    assert in_focus_bound(table).sharp_at_most == 3 == best_plan_by_brute_force(table)
