"""The seed's focus cost (SPEC 3) over the sparse visible pairs.

Per visible pair (camera c, point p) at focus s:
    w1 min(eps1 <p - p_c, n_c>^2 / <n_c, n_p>, 1) + w2 min(|off-axis| / eps2, 1)
    + w3 [depth outside the depth of field of s].
A pose that does not see p costs 1, so a point's cost is min(1, min over its visible pairs)
and the total cost K sums the point costs (at most N). Only the last term depends on s; it is
stored as each pair's focus interval [lo, hi].

Samples may carry weights (the skin each stands for, in units of one area-uniform sample:
planner/importance.py samples the skin few poses see more densely, at lower weight); K, the
in-focus and the visible share are then weighted sums.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from planner.interval_sweep import PresortedIntervals
from planner.optics import focus_interval
from planner.rig import Cost, Optics
from planner.visibility import Visibility, group_pointers

#: Cost of a point no pose sees (and of a pose that does not see a point).
INVISIBLE_COST = 1.0


def area_term(depth: np.ndarray, facing: np.ndarray, eps_area: float) -> np.ndarray:
    """min(eps1 z^2 / <n_c, n_p>, 1); 1 when the surface is edge-on or turned away (facing <= 0)."""
    depth = np.asarray(depth, dtype=float)
    facing = np.asarray(facing, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        raw = eps_area * depth**2 / facing
    return np.where(facing > 0, np.minimum(raw, 1.0), 1.0)


def axis_term(off_axis_mm: np.ndarray, axis_deviation_mm: float) -> np.ndarray:
    """min(distance from the optical axis / eps2, 1)."""
    return np.minimum(np.asarray(off_axis_mm, dtype=float) / axis_deviation_mm, 1.0)


@dataclass(frozen=True)
class CostTable:
    """Focus-independent cost of every visible pair, its focus interval, and a point ordering.

    Attributes:
        vis: the visible pairs (sorted by pose).
        w_focus: w3, the cost of being out of focus.
        area, axis: (M,) float, the clamped projected-area and off-axis terms.
        base: (M,) float, w1 area + w2 axis: the pair's cost when in focus.
        lo, hi: (M,) float, mm: the pair is in focus for lo <= s <= hi (hi may be inf).
        order: (M,) int64, pair indices sorted by point.
        point_ptr: (N + 1,) int64, point p's pairs are order[point_ptr[p]:point_ptr[p + 1]].
        by_point: (pose, base, lo, hi) of the pairs in point order, for fast per-point passes.
        weight: (N,) float, the skin each point stands for (1: one area-uniform sample).
    """

    vis: Visibility
    w_focus: float
    area: np.ndarray
    axis: np.ndarray
    base: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    order: np.ndarray
    point_ptr: np.ndarray
    by_point: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    weight: np.ndarray

    @property
    def n_points(self) -> int:
        return self.vis.n_points

    @property
    def n_poses(self) -> int:
        return self.vis.n_poses

    @property
    def seen(self) -> np.ndarray:
        """(N,) bool: points with at least one visible pair."""
        return np.diff(self.point_ptr) > 0

    @cached_property
    def ends(self) -> PresortedIntervals:
        """Every pose's interval ends in sorted order, built once per table: the descents (plain and
        robust) and the angle search sweep them with new weights."""
        return PresortedIntervals(self.lo, self.hi, self.vis.pose_ptr)

    @cached_property
    def total_weight(self) -> float:
        return float(self.weight.sum())

    @property
    def visible_fraction(self) -> float:
        return float(self.weight[self.seen].sum() / self.total_weight) if self.n_points else 0.0

    @cached_property
    def _segments(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        seen = self.seen
        counts = np.diff(self.point_ptr)[seen]
        return seen, self.point_ptr[:-1][seen], np.repeat(np.arange(len(counts)), counts)

    def segment_starts(self) -> np.ndarray:
        """Starts (into ``order``) of the non-empty point segments, for ``reduceat``."""
        return self._segments[1]

    def pair_in_focus(self, focus_mm: np.ndarray) -> np.ndarray:
        """(M,) bool in pose order: the pair's depth is inside its pose's depth of field."""
        s = np.asarray(focus_mm, dtype=float)[self.vis.pose]
        result: np.ndarray = (self.lo <= s) & (s <= self.hi)
        return result

    def pair_cost(self, focus_mm: np.ndarray) -> np.ndarray:
        """(M,) float in pose order: the full cost of every visible pair under focus (P,) mm."""
        return self.base + self.w_focus * ~self.pair_in_focus(focus_mm)

    def pair_cost_by_point(self, focus_mm: np.ndarray) -> np.ndarray:
        """(M,) float: ``pair_cost`` in point order (``order``)."""
        pose, base, lo, hi = self.by_point
        s = np.asarray(focus_mm, dtype=float)[pose]
        sharp = lo <= s
        sharp &= s <= hi
        return np.where(sharp, base, base + self.w_focus)

    def point_costs(self, focus_mm: np.ndarray) -> np.ndarray:
        """(N,) float point costs min(1, min over visible pairs)."""
        out = np.full(self.n_points, INVISIBLE_COST)
        if len(self.order):
            mins = np.minimum.reduceat(self.pair_cost_by_point(focus_mm), self.segment_starts())
            out[self.seen] = np.minimum(mins, INVISIBLE_COST)
        return out

    def total_cost(self, focus_mm: np.ndarray) -> float:
        """K: the weighted sum of point costs (N for a plan that images nothing)."""
        return float(self.point_costs(focus_mm) @ self.weight)

    def sharp_points(self, focus_mm: np.ndarray) -> np.ndarray:
        """(N,) bool: points visible from, and in the depth of field of, at least one pose."""
        sharp = np.zeros(self.n_points, dtype=bool)
        sharp[self.vis.point[self.pair_in_focus(focus_mm)]] = True
        return sharp

    def in_focus_fraction(self, focus_mm: np.ndarray) -> float:
        """Share of the skin (weighted points) that at least one pose holds sharp."""
        if not self.n_points:
            return 0.0
        return float(self.weight[self.sharp_points(focus_mm)].sum() / self.total_weight)

    def assignment(self, focus_mm: np.ndarray) -> tuple[np.ndarray, float]:
        """(best pair per point (N,) int64, -1 if unseen; K) under the focus plan (P,) mm.

        The best pair is a point's lowest-cost pair (the first one on ties).
        """
        if not len(self.order):
            return np.full(self.n_points, -1, dtype=np.int64), self.total_weight * INVISIBLE_COST
        best, mins = self._argmin_by_point(self.pair_cost_by_point(focus_mm))
        seen = self.seen
        unseen = float(self.weight[~seen].sum())
        return best, float(np.minimum(mins, INVISIBLE_COST) @ self.weight[seen]) + INVISIBLE_COST * unseen

    def best_pairs_by(self, pair_values: np.ndarray) -> np.ndarray:
        """(N,) int64: each point's pair with the lowest value of ``pair_values`` (M,), pose order."""
        if not len(self.order):
            return np.full(self.n_points, -1, dtype=np.int64)
        return self._argmin_by_point(pair_values[self.order])[0]

    def _argmin_by_point(self, ordered: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        seen, starts, segment = self._segments
        mins = np.minimum.reduceat(ordered, starts)
        hits = np.flatnonzero(ordered == mins[segment])
        first = hits[np.r_[True, segment[hits[1:]] != segment[hits[:-1]]]]
        best = np.full(self.n_points, -1, dtype=np.int64)
        best[seen] = self.order[first]
        return best, mins


def stable_argsort_indices(keys: np.ndarray) -> np.ndarray:
    """Stable argsort of non-negative integer keys < 2^32 by two 16-bit radix passes
    (NumPy radix-sorts 16-bit keys; wider keys fall back to a much slower timsort)."""
    keys = np.asarray(keys)
    order = np.argsort((keys & 0xFFFF).astype(np.uint16), kind="stable")
    if len(keys) and int(keys.max()) > 0xFFFF:
        order = order[np.argsort((keys[order] >> 16).astype(np.uint16), kind="stable")]
    return order


def base_cost(cost: Cost, area: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """The focus-independent cost of pairs (M,) from their area and axis terms: w1 area + w2 axis."""
    base: np.ndarray = cost.w_area * area + cost.w_axis * axis
    return base


def cost_table(vis: Visibility, cost: Cost, optics: Optics, weight: np.ndarray | None = None) -> CostTable:
    """Precompute the focus-independent terms and focus intervals of every visible pair.

    weight: (N,) the skin each point stands for (default 1 each: area-uniform samples)."""
    weight = np.ones(vis.n_points) if weight is None else np.asarray(weight, dtype=float)
    if weight.shape != (vis.n_points,) or not np.all(weight > 0):
        raise ValueError(f"point weights must be {vis.n_points} positive numbers, got shape {weight.shape}")
    area = area_term(vis.depth, vis.facing, cost.eps_area)
    axis = axis_term(vis.off_axis, cost.axis_deviation_mm)
    lo, hi = focus_interval(vis.depth, optics.hyperfocal_mm, optics.focal_length_mm)
    order = stable_argsort_indices(vis.point)
    point_ptr = group_pointers(vis.point, vis.n_points)
    base = base_cost(cost, area, axis)
    return CostTable(
        vis=vis,
        w_focus=cost.w_focus,
        area=area,
        axis=axis,
        base=base,
        lo=lo,
        hi=hi,
        order=order,
        point_ptr=point_ptr,
        by_point=(vis.pose[order], base[order], lo[order], hi[order]),
        weight=weight,
    )
