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

from planner.cost import INVISIBLE_COST, CostTable, cost_table
from planner.em import expectation_minimisation
from planner.redundancy import Redundancy, expected_misses
from planner.rig import Rig
from planner.visibility import Visibility

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
    from planner.descent import descend, init_point_best  # numba: only processes that plan load it

    focus = np.array(focus_mm, dtype=float, copy=True)
    vis = table.vis
    sharp_pair = table.pair_in_focus(focus)
    pair_cost = table.base + table.w_focus * ~sharp_pair
    n = table.n_points
    best, second = np.full(n, INVISIBLE_COST), np.full(n, INVISIBLE_COST)
    best_pair = np.full(n, -1, dtype=np.int64)
    order, point_ptr = table.order.astype(np.int64), table.point_ptr.astype(np.int64)
    init_point_best(order, point_ptr, pair_cost, best, second, best_pair, INVISIBLE_COST)
    # Sharp views per point, and the value of one more: weight * miss^k * (1 - miss).
    sharp_views = np.bincount(vis.point[sharp_pair], minlength=n).astype(np.int64)
    extra: np.ndarray = np.zeros(1)
    if redundancy is not None:
        # weight * (1 - miss) * miss^k for k = 0 .. the most views any point has.
        extra = redundancy.weight * (1.0 - redundancy.miss_probability) * (
            redundancy.miss_probability ** np.arange(int(np.diff(table.point_ptr).max(initial=0)) + 2)
        )
    ends = table.ends
    sweeps, updates = descend(
        vis.pose_ptr.astype(np.int64), vis.point.astype(np.int64), table.base, table.lo, table.hi,
        float(table.w_focus), order, point_ptr, ends.ptr, ends.end,
        focus, sharp_pair, pair_cost, best, second, best_pair, sharp_views, extra, redundancy is not None,
        table.weight, max_sweeps, MIN_GAIN,
    )
    total = float(best @ table.weight)
    objective = total
    if redundancy is not None:
        objective += redundancy.weight * expected_misses(sharp_views, redundancy.miss_probability, table.weight)
    log.debug("refine.done", sweeps=sweeps, updates=updates, total_cost=total, objective=objective)
    return RefineResult(focus, total, sweeps, updates, objective)


def warm_up(rig: Rig) -> None:
    """Compile the planner's loops (or load them from numba's cache) now rather than in the first
    plan, where compiling takes seconds: EM's assignment, the descent with the redundancy term
    and the group moves, on one pose seeing one point (out of focus at first, so each runs)."""
    from planner.group_moves import group_moves

    one = np.ones(1)
    vis = Visibility(1, 1, np.zeros(1, np.int32), np.zeros(1, np.int32), 500.0 * one, 0.0 * one, one,
                     np.array([0, 1], dtype=np.int64))
    table = cost_table(vis, rig.cost, rig.optics)
    expectation_minimisation(table, 500.0 * one)
    refine_focus(table, 500.0 * one, redundancy=Redundancy(1.0, 0.5))
    group_moves(table, 2000.0 * one, [np.zeros(1, dtype=np.int64)])
