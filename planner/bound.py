"""A certified upper bound on the in-focus share any focus plan can reach for a body and rig.

"How far from optimal is the plan?" is answered by a number, not a guess. Every visible sample
counts as possibly sharp, except where the poses that see it cannot all be satisfied at once:

* a sample seen by one pose only (a *private* sample) is sharp only if that pose's single focus
  distance lies in its interval, so of pose c's private samples at most max_s (count sharp at s)
  can be sharp: an exact interval sweep;
* samples seen by exactly two poses c, c' are grouped with c's and c''s private samples, and the
  best pair of focus distances for that group is found exactly (every coverage maximum of c
  starts at one of its interval lower ends, and c' then takes its best sweep on the rest).

Groups of poses are disjoint (a greedy matching of the pose pairs that share the most samples),
so their sample sets are disjoint and the losses add up: bound = visible - sum of group losses.
The bound holds for the sample set it is computed on; on the continuous skin it is an estimate
with the sampling error of that set. Weighted samples (planner/importance.py) count with their
weights throughout.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planner.cost import CostTable
from planner.interval_sweep import sweep


@dataclass(frozen=True)
class InFocusBound:
    """n_points: samples; visible: weight of the samples some pose sees; sharp_at_most: no plan
    holds more weight sharp; groups: pose groups whose conflicts were counted (singles and
    pairs); total_weight: of all samples (n_points for area-uniform samples of weight 1)."""

    n_points: int
    visible: float
    sharp_at_most: float
    groups: int
    total_weight: float

    @property
    def fraction(self) -> float:
        """Upper bound on the in-focus fraction (of all samples)."""
        return self.sharp_at_most / self.total_weight if self.n_points else 0.0

    @property
    def visible_fraction(self) -> float:
        return self.visible / self.total_weight if self.n_points else 0.0


def _best_single(lo: np.ndarray, hi: np.ndarray, weight: np.ndarray) -> float:
    return float(sweep(lo, hi, weight)[1]) if len(lo) else 0.0


def _best_pair(lo_a: np.ndarray, hi_a: np.ndarray, lo_b: np.ndarray, hi_b: np.ndarray,
               weight: np.ndarray) -> float:
    """Most of one group's samples (by weight (n,)) two poses can hold sharp together.

    lo_a, hi_a: (n,) intervals of pose a for the group's samples (nan where a does not see the
    sample); likewise for b. Exact: pose a's focus is tried at every interval lower end (and
    nowhere), pose b takes its best sweep over the samples a leaves.
    """
    seen_a = ~np.isnan(lo_a)
    seen_b = ~np.isnan(lo_b)
    best = _best_single(lo_b[seen_b], hi_b[seen_b], weight[seen_b])
    for s in np.unique(lo_a[seen_a]):
        sharp_a = seen_a & (np.nan_to_num(lo_a, nan=np.inf) <= s) & (s <= np.nan_to_num(hi_a, nan=-np.inf))
        rest = seen_b & ~sharp_a
        best = max(best, float(weight[sharp_a].sum()) + _best_single(lo_b[rest], hi_b[rest], weight[rest]))
    return best


def in_focus_bound(table: CostTable) -> InFocusBound:
    """The certified bound for the table's samples and poses (see the module docstring)."""
    vis = table.vis
    views = np.diff(table.point_ptr)
    weight = table.weight
    visible = float(weight[views > 0].sum())
    order = table.order
    ptr = table.point_ptr
    pose_of = vis.pose[order]

    # Samples seen by exactly two poses, keyed by their pose pair (a < b).
    two = np.flatnonzero(views == 2)
    first = pose_of[ptr[two]]
    second = pose_of[ptr[two] + 1]
    a, b = np.minimum(first, second), np.maximum(first, second)
    pair_key = a.astype(np.int64) * vis.n_poses + b
    keys, counts = np.unique(pair_key, return_counts=True)
    partner = np.full(vis.n_poses, -1, dtype=np.int64)
    for key in keys[np.argsort(-counts, kind="stable")].tolist():
        p, q = divmod(key, vis.n_poses)
        if partner[p] < 0 and partner[q] < 0:
            partner[p], partner[q] = q, p

    # Private samples by pose.
    one = np.flatnonzero(views == 1)
    one_pair = order[ptr[one]]
    private_pose = vis.pose[one_pair]
    by_pose = np.argsort(private_pose, kind="stable")
    one, one_pair, private_pose = one[by_pose], one_pair[by_pose], private_pose[by_pose]
    private_ptr = np.searchsorted(private_pose, np.arange(vis.n_poses + 1))

    loss = 0.0
    groups = 0
    for c in range(vis.n_poses):
        q = int(partner[c])
        if q >= 0 and q < c:
            continue  # counted with its partner
        if q < 0:
            pairs = one_pair[private_ptr[c] : private_ptr[c + 1]]
            if len(pairs):
                w = weight[vis.point[pairs]]
                loss += float(w.sum()) - _best_single(table.lo[pairs], table.hi[pairs], w)
                groups += 1
            continue
        shared = two[pair_key == min(c, q) * vis.n_poses + max(c, q)]
        group_points = np.concatenate(
            [one[private_ptr[c] : private_ptr[c + 1]], one[private_ptr[q] : private_ptr[q + 1]], shared]
        )
        if not len(group_points):
            continue
        index = {int(p): i for i, p in enumerate(group_points.tolist())}
        lo = np.full((2, len(group_points)), np.nan)
        hi = np.full((2, len(group_points)), np.nan)
        for p in group_points.tolist():
            for pair in order[ptr[p] : ptr[p + 1]].tolist():
                row = 0 if vis.pose[pair] == c else 1
                lo[row, index[p]], hi[row, index[p]] = table.lo[pair], table.hi[pair]
        w = weight[group_points]
        loss += float(w.sum()) - _best_pair(lo[0], hi[0], lo[1], hi[1], w)
        groups += 1
    return InFocusBound(table.n_points, visible, max(visible - loss, 0.0), groups, table.total_weight)


def sharp_count(table: CostTable, focus_mm: np.ndarray) -> float:
    """Weight of the samples a plan holds sharp, for comparison with the bound."""
    return float(table.weight[table.sharp_points(focus_mm)].sum())

