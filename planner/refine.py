"""Exact block-coordinate descent on the true focus cost, started from the EM result.

EM stops at a fixed point of its assignment, not at a local optimum of K. With every other
pose's focus fixed, the exact best focus of one pose is a weighted interval sweep: a point p
seen by pose c costs min(other_p, base_cp + w3 [out of focus]), where other_p is its best cost
over the remaining poses, so bringing p into focus saves
    gain_cp = min(other_p, base_cp + w3) - min(other_p, base_cp) >= 0,
and K(s) = const - sum of gain_cp over the intervals containing s. Keeping each point's best and
second-best cost makes other_p O(1), so one pose update costs O(pairs of that pose) plus the
points whose cost it changes. A pose is revisited only after a neighbour changed its points.

With a :class:`~planner.redundancy.Redundancy` the descent minimises K plus the expected number
of points left out of focus when every sharp view independently fails (``planner/redundancy.py``);
that term is also additive over one pose's pairs once the others are fixed, so each step is
still an exact weighted sweep.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import structlog

from planner.cost import INVISIBLE_COST, CostTable
from planner.interval_sweep import PresortedIntervals
from planner.redundancy import Redundancy, expected_misses

log = structlog.get_logger(__name__)

#: A pose's focus moves only if K drops by more than this (guards against float ties).
MIN_GAIN = 1e-9


@dataclass(frozen=True)
class RefineResult:
    """focus_mm (P,) after descent, its K, full passes over the poses, accepted pose moves, and the
    objective descended (K, plus the redundancy term when one was given)."""

    focus_mm: np.ndarray
    total_cost: float
    sweeps: int
    updates: int
    objective: float


class _PointBest:
    """Per point: best and second-best pair cost (capped at 1) and the best pair's index."""

    def __init__(self, table: CostTable, pair_cost: np.ndarray) -> None:
        self.table = table
        self.pair_cost = pair_cost
        n = table.n_points
        self.best = np.full(n, INVISIBLE_COST)
        self.second = np.full(n, INVISIBLE_COST)
        self.best_pair = np.full(n, -1, dtype=np.int64)
        self.recompute(np.flatnonzero(table.seen))

    def positions(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions in point order (``table.order``) of all pairs of ``points``, where each
        point's run starts, and how many pairs each has."""
        t = self.table
        starts = t.point_ptr[points]
        counts = t.point_ptr[points + 1] - starts
        seg_starts = np.zeros(len(points), dtype=np.int64)
        np.cumsum(counts[:-1], out=seg_starts[1:])
        return np.repeat(starts - seg_starts, counts) + np.arange(int(counts.sum())), seg_starts, counts

    def recompute(self, points: np.ndarray) -> np.ndarray:
        """Refresh ``points`` (each with >= 1 pair) from pair_cost.

        Returns the points whose best or second-best cost changed: only the poses seeing them
        face a different subproblem.
        """
        if len(points) == 0:
            return points
        positions, seg_starts, counts = self.positions(points)
        pairs = self.table.order[positions]
        segment = np.repeat(np.arange(len(points)), counts)
        costs = self.pair_cost[pairs]
        mins = np.minimum.reduceat(costs, seg_starts)
        hits = np.flatnonzero(costs == mins[segment])
        # every point has a hit (its minimum); its first one is where its segment number starts
        first = hits[np.searchsorted(segment[hits], np.arange(len(points)))]
        rest = costs.copy()
        rest[first] = np.inf
        seconds = np.minimum.reduceat(rest, seg_starts)
        best = np.minimum(mins, INVISIBLE_COST)
        second = np.minimum(seconds, INVISIBLE_COST)
        best_pair = pairs[first]
        changed = (
            (best != self.best[points])
            | (second != self.second[points])
            | (best_pair != self.best_pair[points])
        )
        self.best[points] = best
        self.second[points] = second
        self.best_pair[points] = best_pair
        return points[changed]

    def update(self, index: np.ndarray, points: np.ndarray, old: np.ndarray) -> np.ndarray:
        """Pairs ``index`` (of distinct ``points``) changed cost from ``old`` to pair_cost[index].

        Updates best/second in O(1) per pair where that is exact (a cost fell, or a pair that
        was neither best nor second rose); recomputes the rest. Returns the points whose best
        or second changed.
        """
        new = np.minimum(self.pair_cost[index], INVISIBLE_COST)
        old = np.minimum(old, INVISIBLE_COST)
        best, second, best_pair = self.best[points], self.second[points], self.best_pair[points]
        is_best = best_pair == index
        fell = new < old
        rose = new > old
        other_fell = fell & ~is_best
        # A best pair that fell or rose no higher than the second stays best at its new cost.
        keep_best = is_best & (fell | (rose & (new <= second)))
        takes_over = other_fell & (new < best)
        nb = np.where(keep_best | takes_over, new, best)
        ns = np.where(takes_over, best, np.where(other_fell, np.minimum(second, new), second))
        nbp = np.where(takes_over, index, best_pair)
        redo = rose & np.where(is_best, new > second, old <= second)
        direct = ((nb != best) | (ns != second) | (nbp != best_pair)) & ~redo
        at = points[direct]
        self.best[at] = nb[direct]
        self.second[at] = ns[direct]
        self.best_pair[at] = nbp[direct]
        return np.concatenate([at, self.recompute(points[redo])])


def refine_focus(
    table: CostTable,
    focus_mm: np.ndarray,
    *,
    max_sweeps: int = 20,
    redundancy: Redundancy | None = None,
) -> RefineResult:
    """Block-coordinate descent over poses from ``focus_mm`` (P,); the objective never increases.

    The objective is K, or K + redundancy.weight * expected misses when ``redundancy`` is given.
    """
    focus = np.array(focus_mm, dtype=float, copy=True)
    vis = table.vis
    w3 = table.w_focus
    sharp_pair = table.pair_in_focus(focus)
    pair_cost = table.base + w3 * ~sharp_pair
    state = _PointBest(table, pair_cost)
    # Sharp views per point, and the value of one more: weight * miss^k * (1 - miss).
    sharp_views = np.bincount(vis.point[sharp_pair], minlength=table.n_points)
    if redundancy is not None:
        # weight * (1 - miss) * miss^k for k = 0 .. the most views any point has.
        extra = redundancy.weight * (1.0 - redundancy.miss_probability) * (
            redundancy.miss_probability ** np.arange(int(np.diff(table.point_ptr).max(initial=0)) + 2)
        )
    ends = PresortedIntervals(table.lo, table.hi, vis.pose_ptr)
    has_pairs = np.diff(vis.pose_ptr) > 0
    # A pose needs another look when one of its points changed after its last look: points carry
    # the step of their last change, poses the step of their last look (one reduction per pass
    # finds them, where marking every pose of every changed point cost more than the descent).
    changed_at = np.zeros(table.n_points, dtype=np.int64)
    looked_at = np.full(table.n_poses, -1, dtype=np.int64)
    step = 0
    pair_index = np.arange(len(vis), dtype=np.int64)
    base_all, lo_all, hi_all = table.base, table.lo, table.hi
    ptr = vis.pose_ptr.tolist()
    slices = [slice(a, b) for a, b in zip(ptr[:-1], ptr[1:])]
    sweeps = updates = 0
    while sweeps < max_sweeps:
        latest = np.full(table.n_poses, -1, dtype=np.int64)
        latest[has_pairs] = np.maximum.reduceat(changed_at[vis.point], vis.pose_ptr[:-1][has_pairs])
        dirty = np.flatnonzero(latest > looked_at)
        if len(dirty) == 0:
            break
        sweeps += 1
        changed_any = False
        for c in dirty.tolist():
            step += 1
            looked_at[c] = step
            sl = slices[c]
            points = vis.point[sl]
            # other_p: the point's best cost without this pose.
            other = state.best[points]
            mine = np.flatnonzero(state.best_pair[points] == pair_index[sl])
            other[mine] = state.second[points[mine]]
            base = base_all[sl]
            sharp_now = sharp_pair[sl]
            # What bringing each point into focus in this pose saves (0 where the point is
            # better served elsewhere whatever this pose does).
            gain = np.maximum(np.minimum(other, base + w3) - base, 0.0)
            if redundancy is not None:
                gain += extra[sharp_views[points] - sharp_now]
            current = float(gain[sharp_now].sum())
            if not float(gain.sum()) - current > MIN_GAIN:
                continue  # everything this pose could gain is already in focus
            s, score = ends.sweep(c, gain)
            if score <= current + MIN_GAIN:
                continue
            focus[c] = s
            updates += 1
            changed_any = True
            lo, hi = lo_all[sl], hi_all[sl]
            now = (lo <= s) & (s <= hi)
            moved = np.flatnonzero(sharp_now != now)
            moved_pairs = moved + sl.start
            sharp_pair[moved_pairs] = now[moved]
            sharp_views[points[moved]] += np.where(now[moved], 1, -1)
            old_cost = pair_cost[moved_pairs]
            pair_cost[moved_pairs] = np.where(now[moved], base[moved], base[moved] + w3)
            changed = state.update(moved_pairs, points[moved], old_cost)
            if redundancy is not None:  # every pose seeing a point whose sharp views changed
                changed = np.concatenate([changed, points[moved]])
            changed_at[changed] = step  # this pose's own changes: not newer than its look
        if not changed_any:
            break
    total = float(state.best.sum())
    objective = total
    if redundancy is not None:
        objective += redundancy.weight * expected_misses(sharp_views, redundancy.miss_probability)
    log.debug("refine.done", sweeps=sweeps, updates=updates, total_cost=total, objective=objective)
    return RefineResult(focus, total, sweeps, updates, objective)
