"""EM and the exact refinement never increase the total cost K; refinement reaches a
coordinate-wise optimum."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from planner.baselines import average_focus, closest_focus, fixed_focus
from planner.cost import cost_table
from planner.em import Assignment, expectation_minimisation
from planner.poses import rgb_poses
from planner.redundancy import Redundancy, expected_misses, sharp_views
from planner.refine import refine_focus
from planner.rig import load_rig
from planner.sampling import sample_surface
from planner.visibility import RayScene, Visibility, group_pointers, visible_pairs
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


def random_table(seed: int, n_poses: int, n_points: int, weight: np.ndarray | None = None):
    """A random sparse problem: each point seen by a few poses at depths 200..1200 mm;
    ``weight`` (n_points,) the skin each point stands for (default 1 each)."""
    rng = np.random.default_rng(seed)
    pose, point = [], []
    for p in range(n_points):
        seen = rng.choice(n_poses, size=rng.integers(0, min(4, n_poses) + 1), replace=False)
        pose += seen.tolist()
        point += [p] * len(seen)
    pose, point = np.array(pose, dtype=np.int32), np.array(point, dtype=np.int32)
    by_pose = np.argsort(pose, kind="stable")
    pose, point = pose[by_pose], point[by_pose]
    m = len(pose)
    ptr = group_pointers(pose, n_poses)
    vis = Visibility(
        n_poses, n_points, pose, point,
        depth=rng.uniform(200.0, 1200.0, m), off_axis=rng.uniform(0.0, 400.0, m),
        facing=rng.uniform(0.05, 1.0, m), pose_ptr=ptr,
    )
    return cost_table(vis, RIG.cost, RIG.optics, weight)


@given(seed=st.integers(0, 10_000), n_poses=st.integers(1, 5), n_points=st.integers(1, 25))
@settings(max_examples=60, deadline=None)
def test_random_problems_em_refine_monotone_and_refine_optimal(seed: int, n_poses: int, n_points: int) -> None:
    table = random_table(seed, n_poses, n_points)
    start = np.random.default_rng(seed + 1).uniform(200.0, 1500.0, n_poses)
    em = expectation_minimisation(table, start)
    assert em.total_cost <= table.total_cost(start) + 1e-9
    refined = refine_focus(table, em.focus_mm, max_sweeps=1000)
    k = table.total_cost(refined.focus_mm)
    assert k <= em.total_cost + 1e-9
    assert refined.total_cost == pytest.approx(k, abs=1e-9)
    # No single pose can do better: try every interval end of its pairs.
    for c in range(n_poses):
        sl = table.vis.pairs_of(c)
        for s in np.concatenate([table.lo[sl], table.hi[sl][np.isfinite(table.hi[sl])]]):
            trial = refined.focus_mm.copy()
            trial[c] = s
            assert table.total_cost(trial) >= k - 1e-9


@given(seed=st.integers(0, 10_000), n_poses=st.integers(1, 6), n_points=st.integers(1, 30),
       on_ends=st.booleans(), weighted=st.booleans())
@settings(max_examples=80, deadline=None)
def test_em_compiled_assignment_is_the_tables(seed: int, n_poses: int, n_points: int, on_ends: bool,
                                               weighted: bool) -> None:
    """EM's compiled assignment gives the table's best pair per point (the first lowest where pairs
    cost the same) and K, also with every focus exactly on an interval end and with weights."""
    rng = np.random.default_rng(seed + 2)
    weight = rng.uniform(0.1, 3.0, n_points) if weighted else None
    v = random_table(seed, n_poses, n_points).vis
    # Depths and angles on a coarse grid: a point's pairs often cost exactly the same (ties).
    coarse = Visibility(v.n_poses, v.n_points, v.pose, v.point, depth=np.round(v.depth, -2),
                        off_axis=np.round(v.off_axis, -2), facing=np.maximum(np.round(v.facing, 1), 0.1),
                        pose_ptr=v.pose_ptr)
    table = cost_table(coarse, RIG.cost, RIG.optics, weight)
    focus = rng.uniform(150.0, 2500.0, n_poses)
    if on_ends and len(table.lo):
        ends = np.concatenate([table.lo, table.hi[np.isfinite(table.hi)]])
        focus = rng.choice(ends, size=n_poses)
    best, k = Assignment(table)(focus)
    expected_best, expected_k = table.assignment(focus)
    np.testing.assert_array_equal(best, expected_best)
    assert k == pytest.approx(expected_k, rel=1e-12, abs=1e-12)


def robust_objective(table, focus: np.ndarray, redundancy: Redundancy) -> float:
    return table.total_cost(focus) + redundancy.weight * expected_misses(
        sharp_views(table, focus), redundancy.miss_probability, table.weight
    )


@given(seed=st.integers(0, 10_000), n_poses=st.integers(1, 5), n_points=st.integers(1, 25),
       miss=st.floats(0.05, 0.9), weight=st.floats(0.0, 3.0), weighted=st.booleans())
@settings(max_examples=80, deadline=None)
def test_robust_refinement_is_monotone_and_a_coordinate_wise_optimum(
    seed: int, n_poses: int, n_points: int, miss: float, weight: float, weighted: bool
) -> None:
    # Weighted samples (planner/importance.py) too: each point's gains count with its weight.
    point_weight = np.random.default_rng(seed + 5).uniform(0.1, 3.0, n_points) if weighted else None
    table = random_table(seed, n_poses, n_points, point_weight)
    redundancy = Redundancy(weight, miss)
    start = np.random.default_rng(seed + 1).uniform(200.0, 1500.0, n_poses)
    assert expectation_minimisation(table, start).total_cost <= table.total_cost(start) + 1e-9
    refined = refine_focus(table, start, max_sweeps=1000, redundancy=redundancy)
    j = robust_objective(table, refined.focus_mm, redundancy)
    assert j <= robust_objective(table, start, redundancy) + 1e-9
    assert refined.objective == pytest.approx(j, abs=1e-9)
    assert refined.total_cost == pytest.approx(table.total_cost(refined.focus_mm), abs=1e-9)
    for c in range(n_poses):
        sl = table.vis.pairs_of(c)
        for s in np.concatenate([table.lo[sl], table.hi[sl][np.isfinite(table.hi[sl])]]):
            trial = refined.focus_mm.copy()
            trial[c] = s
            assert robust_objective(table, trial, redundancy) >= j - 1e-9


def test_robust_plan_holds_more_skin_sharp_in_two_poses(table) -> None:
    em = expectation_minimisation(table, average_focus(table.vis, 450.0)).focus_mm
    plain = refine_focus(table, em).focus_mm
    robust = refine_focus(table, em, redundancy=Redundancy(1.0, 0.2)).focus_mm
    assert (sharp_views(table, robust) >= 2).sum() > (sharp_views(table, plain) >= 2).sum()
    assert table.total_cost(robust) <= 1.02 * table.total_cost(plain)


def test_redundancy_parameters_are_checked() -> None:
    with pytest.raises(ValueError, match="miss probability"):
        Redundancy(1.0, 1.0)
    with pytest.raises(ValueError, match="weight"):
        Redundancy(-1.0, 0.2)


def test_descent_loop_compiles_where_no_cache_directory_is_writable(monkeypatch) -> None:
    import numba

    from planner import jit

    asked: list[bool] = []
    real_njit = numba.njit

    def njit(**options):
        asked.append(bool(options.get("cache")))
        if options.get("cache"):
            raise RuntimeError("cannot cache function 'f': no locator available for file 'f.py'")
        return real_njit(**options)

    monkeypatch.setattr(jit.numba, "njit", njit)
    double = jit.jit(lambda x: 2 * x)
    assert double(21) == 42
    assert asked == [True, False]
