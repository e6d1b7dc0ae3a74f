"""The interval sweep finds the focus covered by the most (weighted) intervals."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from planner.interval_sweep import PresortedIntervals, best_focus, best_focus_per_group, coverage, sweep


def brute_force(lo: np.ndarray, hi: np.ndarray, w: np.ndarray | None) -> float:
    candidates = np.concatenate([lo, hi[np.isfinite(hi)]])
    return max(coverage(lo, hi, float(s), w) for s in candidates)


@st.composite
def intervals(draw: st.DrawFn, weighted: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    n = draw(st.integers(1, 25))
    # Small integer grid: many shared ends, touching and degenerate intervals.
    lo = np.array(draw(st.lists(st.integers(1, 30), min_size=n, max_size=n)), dtype=float)
    length = np.array(draw(st.lists(st.integers(0, 12), min_size=n, max_size=n)), dtype=float)
    unbounded = np.array(draw(st.lists(st.booleans(), min_size=n, max_size=n)))
    hi = np.where(unbounded & (length > 8), np.inf, lo + length)
    w = None
    if weighted:
        w = np.array(draw(st.lists(st.sampled_from([0.0, 0.25, 0.5, 1.0, 3.0]), min_size=n, max_size=n)))
    return lo, hi, w


@given(intervals(weighted=False))
@settings(max_examples=200)
def test_unweighted_sweep_matches_brute_force(case) -> None:
    lo, hi, _ = case
    s, score = best_focus(lo, hi)
    assert score == brute_force(lo, hi, None)
    assert coverage(lo, hi, s) == score
    assert np.isfinite(s)


@given(intervals(weighted=True))
@settings(max_examples=200)
def test_weighted_sweep_matches_brute_force(case) -> None:
    lo, hi, w = case
    s, score = best_focus(lo, hi, w)
    assert score == pytest.approx(brute_force(lo, hi, w))
    assert coverage(lo, hi, s, w) == pytest.approx(score)


@given(st.lists(intervals(weighted=False), min_size=1, max_size=6))
@settings(max_examples=80)
def test_grouped_sweep_matches_single_sweeps(cases) -> None:
    lo = np.concatenate([c[0] for c in cases])
    hi = np.concatenate([c[1] for c in cases])
    group = np.concatenate([np.full(len(c[0]), 2 * i) for i, c in enumerate(cases)])
    s, score = best_focus_per_group(lo, hi, group, 2 * len(cases) + 1)
    for i, (lo_i, hi_i, _) in enumerate(cases):
        one_s, one_score = best_focus(lo_i, hi_i)
        assert score[2 * i] == one_score
        assert s[2 * i] == pytest.approx(one_s)
        assert np.isnan(s[2 * i + 1]) and score[2 * i + 1] == 0


@given(st.lists(intervals(weighted=False), min_size=1, max_size=5), st.lists(st.booleans(), min_size=5, max_size=5),
       st.integers(0, 4))
@settings(max_examples=150, deadline=None)  # the first example compiles the merge
def test_presorted_ends_are_each_poses_stable_sort_of_its_starts_then_ends(cases, monotone, empty) -> None:
    """Poses whose upper ends follow their lower ends' order (as a depth's interval does: the
    merge without a second sort) and poses whose do not, ties and empty poses included."""
    cases = [(lo, lo + 7.0 if monotone[i] else hi) for i, (lo, hi, _) in enumerate(cases)]
    cases.insert(min(empty, len(cases)), (np.zeros(0), np.zeros(0)))
    lo = np.concatenate([c[0] for c in cases])
    hi = np.concatenate([c[1] for c in cases])
    ptr = np.r_[0, np.cumsum([len(c[0]) for c in cases])]
    ends = PresortedIntervals(lo, hi, ptr)
    assert np.array_equal(ends.ptr, 2 * ptr)
    for pose, (lo_i, hi_i) in enumerate(cases):
        order = np.argsort(np.concatenate([lo_i, hi_i]), kind="stable")
        coords, sign, local = ends.pose_ends(pose)
        assert np.array_equal(coords, np.concatenate([lo_i, hi_i])[order])
        assert np.array_equal(sign, np.where(order < len(lo_i), 1.0, -1.0))
        assert np.array_equal(local, order % max(len(lo_i), 1))


def test_presorted_upper_ends_tied_out_of_pair_order_are_sorted_again() -> None:
    """Equal upper ends stay in pair order even where the lower ends' order puts them the other way."""
    ends = PresortedIntervals(np.array([2.0, 1.0]), np.array([5.0, 5.0]), np.array([0, 2]))
    assert ends.end.tolist() == [1, 0, ~0, ~1]


@given(intervals(weighted=True))
@settings(max_examples=150, deadline=None)
def test_presorted_sweep_matches_the_sweep_of_the_weighted_intervals(case) -> None:
    lo, hi, w = case
    if not (w > 0).any():
        return
    s, score = PresortedIntervals(lo, hi, np.array([0, len(lo)])).sweep(0, w)
    keep = w > 0
    assert score == pytest.approx(best_focus(lo[keep], hi[keep], w[keep])[1])
    assert coverage(lo, hi, s, w) == pytest.approx(score)


def test_touching_closed_intervals_overlap() -> None:
    s, score = best_focus(np.array([1.0, 2.0]), np.array([2.0, 3.0]))
    assert (s, score) == (2.0, 2.0)


def test_unbounded_cell_gives_finite_focus() -> None:
    s, score = best_focus(np.array([1000.0, 1500.0]), np.array([np.inf, np.inf]))
    assert score == 2 and s == 3000.0


def test_focus_is_midpoint_in_diopters() -> None:
    s, _ = best_focus(np.array([400.0]), np.array([600.0]))
    assert 1 / s == pytest.approx((1 / 400 + 1 / 600) / 2)


@pytest.mark.parametrize(
    "lo, hi, w",
    [
        ([], [], None),
        ([3.0], [2.0], None),
        ([1.0, 2.0], [3.0], None),
        ([np.nan], [1.0], None),
        ([1.0], [2.0], [-1.0]),
    ],
)
def test_bad_input_is_refused(lo, hi, w) -> None:
    with pytest.raises(ValueError):
        best_focus(np.array(lo), np.array(hi), None if w is None else np.array(w))


def test_rounding_residue_in_the_weights_never_elects_the_last_end() -> None:
    """Refinement gains are differences of costs: -1e-17 instead of 0 must not break the sweep."""
    s, score = sweep(np.array([300.0]), np.array([400.0]), np.array([-1e-17]))
    assert 300.0 <= s <= 400.0 and score <= 0.0
    s, _ = sweep(np.array([300.0, 350.0]), np.array([400.0, np.inf]), np.array([-1e-17, -2e-17]))
    assert np.isfinite(s)
