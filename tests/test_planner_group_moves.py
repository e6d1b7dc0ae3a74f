"""Group moves: never lose sharp skin, and a group of every pose finds the best plan."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from planner.bound import sharp_count
from planner.group_moves import group_moves, rig_groups
from tests.test_planner_bound import best_plan_by_brute_force
from tests.test_planner_optimise import random_table


@given(seed=st.integers(0, 10_000), n_poses=st.integers(1, 3), n_points=st.integers(1, 8))
@settings(max_examples=60, deadline=None)
def test_a_group_of_every_pose_reaches_the_best_plan(seed: int, n_poses: int, n_points: int) -> None:
    table = random_table(seed, n_poses, n_points)
    start = np.random.default_rng(seed).uniform(150.0, 1500.0, n_poses)
    moved = group_moves(table, start, [np.arange(n_poses)])
    assert sharp_count(table, moved.focus_mm) == best_plan_by_brute_force(table)
    assert sharp_count(table, moved.focus_mm) >= sharp_count(table, start) + moved.gained - 1e-9


@given(seed=st.integers(0, 10_000), n_poses=st.integers(2, 7), n_points=st.integers(1, 30),
       weighted=st.booleans())
@settings(max_examples=60, deadline=None)
def test_moves_of_some_poses_never_lose_sharp_skin(seed: int, n_poses: int, n_points: int, weighted: bool) -> None:
    rng = np.random.default_rng(seed)
    weight = rng.uniform(0.2, 3.0, n_points) if weighted else None
    table = random_table(seed, n_poses, n_points, weight)
    start = rng.uniform(150.0, 1500.0, n_poses)
    groups = [np.sort(rng.choice(n_poses, size=min(3, n_poses), replace=False)) for _ in range(4)]
    moved = group_moves(table, start, groups)
    before, after = sharp_count(table, start), sharp_count(table, moved.focus_mm)
    assert after >= before + moved.gained - 1e-9 and moved.gained >= 0.0
    assert (moved.moves == 0) == (moved.gained == 0.0)
    untouched = np.setdiff1d(np.arange(n_poses), np.concatenate(groups))
    assert np.array_equal(moved.focus_mm[untouched], start[untouched])


@given(seed=st.integers(0, 10_000), n_poses=st.integers(1, 7), n_points=st.integers(1, 40))
@settings(max_examples=80, deadline=None)  # the first example compiles the kernel
def test_own_samples_are_the_seen_samples_only_the_group_holds_sharp(seed: int, n_poses: int, n_points: int) -> None:
    from planner.own_samples import own_samples

    table = random_table(seed, n_poses, n_points)
    rng = np.random.default_rng(seed)
    focus = rng.uniform(150.0, 1500.0, n_poses)
    members = np.sort(rng.choice(n_poses, size=min(3, n_poses), replace=False)).astype(np.int64)
    vis = table.vis
    sharp = table.pair_in_focus(focus)
    held = np.bincount(vis.point[sharp], minlength=n_points)
    in_group = np.isin(vis.pose, members)
    by_group = np.bincount(vis.point[sharp & in_group], minlength=n_points)
    expected = np.flatnonzero((np.bincount(vis.point[in_group], minlength=n_points) > 0) & (held == by_group))
    count, column = np.zeros(n_points, dtype=np.int64), np.full(n_points, -1, dtype=np.int64)
    own, lo, hi = own_samples(members, vis.pose_ptr.astype(np.int64), vis.point.astype(np.int64), table.lo,
                              table.hi, focus, held, count, column)
    assert own.tolist() == expected.tolist()
    for row, pose in enumerate(members.tolist()):
        for col, p in enumerate(own.tolist()):
            pair = np.flatnonzero((vis.pose == pose) & (vis.point == p))
            want = (table.lo[pair[0]], table.hi[pair[0]]) if len(pair) else (np.nan, np.nan)
            assert np.array_equal([lo[row, col], hi[row, col]], want, equal_nan=True)
    assert not count.any() and (column == -1).all()  # the scratch comes back as it went in


def test_rig_groups_are_neighbouring_cameras_and_consecutive_angles() -> None:
    groups = rig_groups(48, 7)
    assert len(groups) == 48 * 5 + 7 * 48
    assert [g.tolist() for g in groups[:2]] == [[0, 1, 2], [1, 2, 3]]  # angle 0, cameras 0-2 and 1-3
    assert [47 * 7 + 3, 3, 7 + 3] in [g.tolist() for g in groups]  # camera 3, angles 47, 0, 1
    assert all(len(set(g.tolist())) == 3 and g.min() >= 0 and g.max() < 48 * 7 for g in groups)
