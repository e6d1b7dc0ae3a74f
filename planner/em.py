"""The seed's Expectation-Minimisation for shape-aware focus (SPEC 3, paper Algorithm 1).

Assignment: every visible point goes to the pose where it costs least under the current focus.
Minimisation: per pose, the focus where most of its assigned points (by weight) are sharp
(interval sweep).
Stops when K falls by less than a relative tolerance or at the iteration cap; a step that does
not lower K is never taken, so K never increases.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import structlog

from planner.cost import INVISIBLE_COST, CostTable
from planner.interval_sweep import best_focus_per_group

log = structlog.get_logger(__name__)


@dataclass(frozen=True)
class EmResult:
    """focus_mm: (P,) float; total_cost: K of that focus; history: K after each accepted step."""

    focus_mm: np.ndarray
    total_cost: float
    iterations: int
    history: list[float] = field(default_factory=list)


class Assignment:
    """``CostTable.assignment`` for the many steps of one EM run: the same best pairs and K,
    by the compiled loop (``planner.descent.lowest_pairs``)."""

    def __init__(self, table: CostTable) -> None:
        self.table = table
        self.seen = table.seen
        self.seen_points = np.flatnonzero(self.seen)
        self.seen_weight = table.weight[self.seen]
        self.unseen = float(table.weight[~self.seen].sum())

    def __call__(self, focus_mm: np.ndarray) -> tuple[np.ndarray, float]:
        from planner.descent import lowest_pairs  # numba: only processes that plan load it

        t = self.table
        pose, base, lo, hi = t.by_point
        best_seen, lowest = lowest_pairs(self.seen_points, t.point_ptr, t.order, pose, base, lo, hi,
                                         np.asarray(focus_mm, dtype=float), float(t.w_focus))
        best = np.full(t.n_points, -1, dtype=np.int64)
        best[self.seen] = best_seen
        return best, float(np.minimum(lowest, INVISIBLE_COST) @ self.seen_weight) + INVISIBLE_COST * self.unseen


def minimisation_step(table: CostTable, assigned_pairs: np.ndarray, focus_mm: np.ndarray) -> np.ndarray:
    """(P,) focus: per pose, the sweep optimum over its assigned pairs (unchanged if none)."""
    pairs = assigned_pairs[assigned_pairs >= 0]
    s, _ = best_focus_per_group(table.lo[pairs], table.hi[pairs], table.vis.pose[pairs], table.n_poses,
                                table.weight[table.vis.point[pairs]])
    return np.where(np.isnan(s), focus_mm, s)


def expectation_minimisation(
    table: CostTable,
    initial_focus_mm: np.ndarray,
    *,
    relative_tolerance: float = 1e-4,
    max_iterations: int = 50,
) -> EmResult:
    """Alternate assignment and per-pose minimisation from ``initial_focus_mm`` (P,) mm."""
    focus = np.array(initial_focus_mm, dtype=float, copy=True)
    if focus.shape != (table.n_poses,):
        raise ValueError(f"initial focus has shape {focus.shape}; expected ({table.n_poses},)")
    assignment = Assignment(table)
    assigned, k = assignment(focus)
    history = [k]
    iterations = 0
    while iterations < max_iterations:
        iterations += 1
        candidate = minimisation_step(table, assigned, focus)
        next_assigned, k_new = assignment(candidate)
        if not k_new < k:
            break
        improvement = k - k_new
        focus, assigned, k = candidate, next_assigned, k_new
        history.append(k)
        if improvement <= relative_tolerance * (k + improvement):
            break
    log.debug("em.done", iterations=iterations, total_cost=k)
    return EmResult(focus, k, iterations, history)
