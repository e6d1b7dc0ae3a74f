"""Robust focus: reward skin that more than one pose holds sharp.

A plan is made on N sample points, but it is judged on the continuous skin, on camera poses
that are only known to the calibration's accuracy, and on a subject who sways. A sample held
sharp by exactly one pose is fragile: the skin around it, a calibrated pose a little off or a
few millimetres of sway can put it outside that pose's depth of field. Model that as every
sharp (pose, point) view failing independently with probability ``miss_probability``; then a
point held sharp by k poses is missed with probability miss^k, and the plan also minimises

    weight * sum over points of miss ** k_p       (the expected number of points missed)

next to the seed's cost K. With the other poses fixed, one more sharp view of a point with k
others lowers that term by weight * miss^k * (1 - miss): a non-negative gain per pair, so each
pose's best focus stays an exact weighted interval sweep (``planner/refine.py``). The values
were chosen by measurement on fresh samples, calibration noise and sway (docs/planner.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planner.cost import CostTable


@dataclass(frozen=True)
class Redundancy:
    """weight: cost of one expected missed point (K's focus term is w3 = 1/3 per point);
    miss_probability: chance that one sharp view of a sample fails on the real skin, in (0, 1)."""

    weight: float
    miss_probability: float

    def __post_init__(self) -> None:
        if not self.weight >= 0.0:
            raise ValueError(f"redundancy weight must be >= 0, got {self.weight!r}")
        if not 0.0 < self.miss_probability < 1.0:
            raise ValueError(f"miss probability must be in (0, 1), got {self.miss_probability!r}")


def expected_misses(sharp_views: np.ndarray, miss_probability: float, weight: np.ndarray | None = None) -> float:
    """sum over points of weight * miss ** k: sharp_views (N,) int, k_p sharp views of each
    point; weight (N,) the skin each point stands for (default 1)."""
    misses = miss_probability ** np.asarray(sharp_views, dtype=float)
    return float(misses.sum() if weight is None else misses @ np.asarray(weight, dtype=float))


def sharp_views(table: CostTable, focus_mm: np.ndarray) -> np.ndarray:
    """(N,) int: how many poses hold each point sharp under the focus plan (P,) mm."""
    vis = table.vis
    return np.bincount(vis.point[table.pair_in_focus(focus_mm)], minlength=table.n_points)
