"""The best focus distance for a set of focus intervals: an O(n log n) sweep (SPEC 3).

Each point contributes a closed interval [lo, hi] of focus distances that keep it sharp, with
a non-negative weight. The weighted count of intervals covering s is piecewise constant; the
sweep over sorted interval ends finds the cell where it is largest.
"""

from __future__ import annotations

import numpy as np

from planner.order import stable_argsort


def best_focus(
    lo: np.ndarray, hi: np.ndarray, weights: np.ndarray | None = None
) -> tuple[float, float]:
    """(s, score): a focus distance s where the weighted count of intervals containing s is maximal.

    lo, hi: (n,) float, mm, lo <= hi, hi may be inf. weights: (n,) float >= 0 (default 1).
    Intervals are closed. Among equal maxima the cell with the smallest s wins; s is the
    midpoint of that cell in diopters (harmonic mean of its ends), which leaves the widest
    margin in depth of field, or twice its start when the cell is unbounded.
    """
    lo = np.asarray(lo, dtype=float)
    hi = np.asarray(hi, dtype=float)
    n = len(lo)
    if n == 0 or len(hi) != n:
        raise ValueError(f"need matching, non-empty interval ends; got {n} lo and {len(hi)} hi")
    if np.any(~(lo <= hi)) or np.any(~np.isfinite(lo)):
        bad = int(np.flatnonzero(~(lo <= hi) | ~np.isfinite(lo))[0])
        raise ValueError(f"interval {bad} is [{lo[bad]:g}, {hi[bad]:g}]; need finite lo <= hi")
    if weights is None:
        w = np.ones(n)
    else:
        w = np.asarray(weights, dtype=float)
        if len(w) != n or np.any(~(w >= 0)):
            raise ValueError(f"weights must be {n} non-negative numbers")
    return sweep(lo, hi, w)


def sweep(lo: np.ndarray, hi: np.ndarray, w: np.ndarray) -> tuple[float, float]:
    """:func:`best_focus` without input checks, for inner loops that guarantee valid input."""
    coords = np.concatenate([lo, hi])
    # A stable sort keeps starts (first half) before ends at the same coordinate: closed
    # intervals touching at a point overlap there.
    order = stable_argsort(coords)
    running = np.cumsum(np.concatenate([w, -w])[order])
    # The last coordinate closes every interval: no cell starts there. Excluding it also keeps
    # a rounding residue (weights that are differences of costs) from electing it.
    k = int(np.argmax(running[:-1]))
    return cell_focus(coords[order[k]], coords[order[k + 1]]), float(running[k])


def cell_focus(left: float, right: float) -> float:
    """The focus distance inside the cell [left, right] mm with the widest depth-of-field margin:
    its midpoint in diopters (the harmonic mean of its ends), or twice its start when unbounded."""
    if np.isinf(right):
        return float(2.0 * left)
    s = 2.0 * left * right / (left + right) if left + right > 0 else left
    return float(min(max(s, left), right))


def coverage(lo: np.ndarray, hi: np.ndarray, s: float, weights: np.ndarray | None = None) -> float:
    """Weighted count of closed intervals [lo, hi] that contain s."""
    inside = (np.asarray(lo) <= s) & (s <= np.asarray(hi))
    return float(inside.sum() if weights is None else np.asarray(weights, dtype=float)[inside].sum())


def best_focus_per_group(
    lo: np.ndarray, hi: np.ndarray, group: np.ndarray, n_groups: int, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`best_focus` for many groups of intervals in one vectorised sweep.

    lo, hi: (n,) float interval ends; group: (n,) int in [0, n_groups); weights: (n,) > 0 or
    None (each interval counts 1). Returns s (n_groups,) float (nan for a group without
    intervals) and score (n_groups,): int without weights, float with them.
    """
    lo = np.asarray(lo, dtype=float)
    hi = np.asarray(hi, dtype=float)
    group = np.asarray(group, dtype=np.int64)
    n = len(lo)
    s = np.full(n_groups, np.nan)
    score = np.zeros(n_groups, dtype=np.int64 if weights is None else float)
    if n == 0:
        return s, score
    coords = np.concatenate([lo, hi])
    groups = np.concatenate([group, group])
    # 16-bit keys let NumPy use a radix sort for the group pass.
    key = groups.astype(np.int16) if n_groups <= np.iinfo(np.int16).max else groups
    # Stable sorts: by coordinate (starts, the first half, before ends on ties), then by group.
    order = stable_argsort(coords)
    order = order[np.argsort(key[order], kind="stable")]
    steps = np.where(order < n, 1, -1)
    if weights is not None:
        w = np.asarray(weights, dtype=float)
        steps = steps * np.concatenate([w, w])[order]
    # Each group's steps sum to zero, so a global running sum restarts at 0 per group (weighted:
    # up to rounding, which is taken off at each group's start).
    running = np.cumsum(steps)
    g_sorted = groups[order]
    starts = np.flatnonzero(np.r_[True, g_sorted[1:] != g_sorted[:-1]])
    if weights is not None:
        carried = np.r_[0.0, running[starts[1:] - 1]]
        running = running - np.repeat(carried, np.diff(np.r_[starts, 2 * n]))
    best = np.maximum.reduceat(running, starts)
    present = g_sorted[starts]
    hits = np.flatnonzero(running == np.repeat(best, np.diff(np.r_[starts, 2 * n])))
    hit_group = g_sorted[hits]
    k = hits[np.r_[True, hit_group[1:] != hit_group[:-1]]]
    left = coords[order[k]]
    right = coords[order[k + 1]]
    with np.errstate(invalid="ignore", divide="ignore"):
        mid = np.where(np.isinf(right), 2.0 * left, 2.0 * left * right / (left + right))
    s[present] = np.clip(mid, left, right)
    score[present] = best
    return s, score


class PresortedIntervals:
    """Every pose's interval ends sorted once, so a weighted sweep is a cumulative sum, not a sort.

    The refinement sweeps the same intervals of a pose many times with new weights; sorting
    2n ends each time dominated its cost. lo, hi: (M,) float, pairs grouped by pose as given by
    ptr (P + 1,). Ends are ordered by pose, then coordinate, starts before ends on ties (closed
    intervals), as in :func:`sweep`. ``end`` (2M,) int32 holds each end as its pair's index
    within the pose, ~index for an upper end: one array of 4 bytes an end (at 100,000 samples
    27 MB; coordinates, signs and indices apart took 160 MB, and filling fresh memory is slow).
    """

    def __init__(self, lo: np.ndarray, hi: np.ndarray, ptr: np.ndarray) -> None:
        from planner.end_order import follows, merge_ends  # numba: only processes that plan load it

        self.lo, self.hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
        self.pair_ptr = np.asarray(ptr, dtype=np.int64)
        bounds = list(zip(self.pair_ptr[:-1].tolist(), self.pair_ptr[1:].tolist()))
        starts = np.empty(len(lo), dtype=np.int32)
        for a, b in bounds:  # many small sorts are several times faster than one of every end
            starts[a:b] = stable_argsort(self.lo[a:b])
        ends = starts
        unlike = np.flatnonzero(~follows(self.hi, starts, self.pair_ptr))
        if len(unlike):
            ends = starts.copy()
            for c in unlike.tolist():
                a, b = bounds[c]
                ends[a:b] = stable_argsort(self.hi[a:b])
        self.end = np.empty(2 * len(lo), dtype=np.int32)
        merge_ends(self.lo, self.hi, starts, ends, self.pair_ptr, self.end)
        self.ptr = 2 * self.pair_ptr

    def pose_ends(self, pose: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(coords, sign, local) of ``pose``'s sorted ends: coordinate, +1 for a lower end and -1
        for an upper one, and the pair's index within the pose."""
        seg = self.end[int(self.ptr[pose]) : int(self.ptr[pose + 1])]
        start = seg >= 0
        local = np.where(start, seg, ~seg)
        pairs = local + int(self.pair_ptr[pose])
        return np.where(start, self.lo[pairs], self.hi[pairs]), np.where(start, 1.0, -1.0), local

    def sweep(self, pose: int, weights: np.ndarray) -> tuple[float, float]:
        """(s, score) of the best cell of ``pose``'s intervals under ``weights`` (n,) >= 0, given in
        the pose's pair order; cells of equal score next to each other count as one cell, so s is
        the diopter midpoint of the widest stretch at the best score, as :func:`sweep` gives
        when only the weighted intervals are swept."""
        coords, sign, local = self.pose_ends(pose)
        running = np.cumsum(weights[local] * sign)
        inner = running[:-1]
        k = int(np.argmax(inner))
        best = float(inner[k])
        tolerance = 1e-12 * max(1.0, abs(best))
        below = np.flatnonzero(inner[k:] < best - tolerance)
        j = k + (int(below[0]) if len(below) else len(inner) - k)
        return cell_focus(coords[k], coords[j]), best
