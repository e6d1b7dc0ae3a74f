"""Exact block-coordinate descent on the true focus cost, started from the EM result.

EM stops at a fixed point of its assignment, not at a local optimum of K. With every other
pose's focus fixed, the exact best focus of one pose is a weighted interval sweep: a point p
seen by pose c costs min(other_p, base_cp + w3 [out of focus]), where other_p is its best cost
over the remaining poses, so bringing p into focus saves
    gain_cp = min(other_p, base_cp + w3) - min(other_p, base_cp) >= 0,
and K(s) = const - sum of gain_cp over the intervals containing s. Keeping each point's best and
second-best cost makes other_p O(1), so one pose update costs O(pairs of that pose) plus the
points whose cost it changes. A pose is revisited only after a neighbour changed its points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import structlog

from planner.cost import INVISIBLE_COST, CostTable
from planner.interval_sweep import sweep

log = structlog.get_logger(__name__)

#: A pose's focus moves only if K drops by more than this (guards against float ties).
MIN_GAIN = 1e-9


@dataclass(frozen=True)
class RefineResult:
    focus_mm: np.ndarray
    total_cost: float
    sweeps: int
    updates: int


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

    def pairs_of(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All pairs of ``points`` grouped by point: (pairs, segment of each, segment starts)."""
        t = self.table
        starts = t.point_ptr[points]
        counts = t.point_ptr[points + 1] - starts
        seg_starts = np.zeros(len(points), dtype=np.int64)
        np.cumsum(counts[:-1], out=seg_starts[1:])
        within = np.arange(int(counts.sum())) - np.repeat(seg_starts, counts)
        pairs = t.order[np.repeat(starts, counts) + within]
        return pairs, np.repeat(np.arange(len(points)), counts), seg_starts

    def recompute(self, points: np.ndarray) -> np.ndarray:
        """Refresh ``points`` (each with >= 1 pair) from pair_cost.

        Returns the pairs of the points whose best or second-best cost changed: only the poses
        of those pairs see a different subproblem.
        """
        if len(points) == 0:
            return np.zeros(0, dtype=np.int64)
        pairs, segment, seg_starts = self.pairs_of(points)
        costs = self.pair_cost[pairs]
        mins = np.minimum.reduceat(costs, seg_starts)
        hits = np.flatnonzero(costs == mins[segment])
        first = hits[np.r_[True, segment[hits[1:]] != segment[hits[:-1]]]]
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
        return pairs[changed[segment]]

    def update(self, index: np.ndarray, points: np.ndarray, old: np.ndarray) -> np.ndarray:
        """Pairs ``index`` (of distinct ``points``) changed cost from ``old`` to pair_cost[index].

        Updates best/second in O(1) per pair where that is exact (a cost fell, or a pair that
        was neither best nor second rose); recomputes the rest. Returns the pairs of every
        point whose best or second changed.
        """
        new = np.minimum(self.pair_cost[index], INVISIBLE_COST)
        old = np.minimum(old, INVISIBLE_COST)
        best, second, best_pair = self.best[points], self.second[points], self.best_pair[points]
        is_best = best_pair == index
        fell = new < old
        rose = new > old
        nb, ns, nbp = best.copy(), second.copy(), best_pair.copy()
        # A best pair that fell or rose no higher than the second stays best at its new cost.
        keep_best = is_best & (fell | (rose & (new <= second)))
        nb[keep_best] = new[keep_best]
        takes_over = fell & ~is_best & (new < best)
        ns[takes_over] = best[takes_over]
        nb[takes_over] = new[takes_over]
        nbp[takes_over] = index[takes_over]
        below_second = fell & ~is_best & ~takes_over
        ns[below_second] = np.minimum(second[below_second], new[below_second])
        redo = rose & ((is_best & (new > second)) | (~is_best & (old <= second)))
        changed = (nb != best) | (ns != second) | (nbp != best_pair)
        direct = points[changed & ~redo]
        self.best[direct] = nb[changed & ~redo]
        self.second[direct] = ns[changed & ~redo]
        self.best_pair[direct] = nbp[changed & ~redo]
        touched = self.recompute(points[redo])
        if len(direct):
            touched = np.concatenate([touched, self.pairs_of(direct)[0]])
        return touched


def refine_focus(table: CostTable, focus_mm: np.ndarray, *, max_sweeps: int = 20) -> RefineResult:
    """Block-coordinate descent over poses from ``focus_mm`` (P,); K never increases."""
    focus = np.array(focus_mm, dtype=float, copy=True)
    vis = table.vis
    w3 = table.w_focus
    pair_cost = table.pair_cost(focus)
    state = _PointBest(table, pair_cost)
    dirty = np.diff(vis.pose_ptr) > 0
    sweeps = updates = 0
    while sweeps < max_sweeps and dirty.any():
        sweeps += 1
        changed_any = False
        for c in np.flatnonzero(dirty):
            dirty[c] = False
            sl = vis.pairs_of(int(c))
            points = vis.point[sl]
            index = np.arange(sl.start, sl.stop)
            other = np.where(state.best_pair[points] == index, state.second[points], state.best[points])
            base = table.base[sl]
            gain = np.minimum(other, base + w3) - np.minimum(other, base)
            useful = gain > 0
            if not useful.any():
                continue
            lo, hi, gain = table.lo[sl][useful], table.hi[sl][useful], gain[useful]
            s_now = focus[c]
            current = float(gain[(lo <= s_now) & (s_now <= hi)].sum())
            s, score = sweep(lo, hi, gain)
            if score <= current + MIN_GAIN:
                continue
            focus[c] = s
            updates += 1
            changed_any = True
            new_cost = base + w3 * ~((table.lo[sl] <= s) & (s <= table.hi[sl]))
            moved = np.flatnonzero(new_cost != pair_cost[sl])
            old_cost = pair_cost[sl][moved]
            pair_cost[sl] = new_cost
            touched = state.update(moved + sl.start, points[moved], old_cost)
            dirty[vis.pose[touched]] = True
            dirty[c] = False
        if not changed_any:
            break
    total = float(state.best.sum())
    log.debug("refine.done", sweeps=sweeps, updates=updates, total_cost=total)
    return RefineResult(focus, total, sweeps, updates)
