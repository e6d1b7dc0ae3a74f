"""A certified upper bound on the in-focus share any focus plan can reach for a body and rig.

"How far from optimal is the plan?" is answered by a number, not a guess. Every visible sample
counts as possibly sharp, except where the poses that see it cannot all be satisfied at once.
The poses are split into disjoint groups of at most GROUP_POSES (greedily, joining the poses
that share the most samples seen by few poses). A group's *own* samples are those every pose
that sees them belongs to the group; only the group's focus distances decide which of them are
sharp, so the most of them the group can hold sharp is found exactly, and the rest are lost by
every plan. Own sample sets of different groups are disjoint, so the losses add up:
bound = visible - sum of group losses. Samples seen across groups count as sharp.

The exact search: one focus distance holds sharp the samples whose intervals contain it, and
only the maximal such sets matter (holding more never loses a sample), so each pose tries its
maximal sets (one per interval lower end that starts a new one, a few dozen at most); all but
the last two poses of a group are enumerated, and every choice of the last two is one small
matrix product. Skin close to a phone (an arm as the column passes, 10-15 cm away) is in focus
over a few millimetres only, and the few poses that see it cannot cover it all: that is what
groups of three and four poses certify that pairs cannot.

The bound holds for the sample set it is computed on; on the continuous skin it is an estimate
with the sampling error of that set. Weighted samples (planner/importance.py) count with their
weights throughout.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from planner.cost import CostTable
from planner.order import stable_argsort


@dataclass(frozen=True)
class InFocusBound:
    """n_points: samples; visible: weight of the samples some pose sees; sharp_at_most: no plan
    holds more weight sharp; groups: pose groups that lose samples under every plan;
    total_weight: of all samples (n_points for area-uniform samples of weight 1)."""

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


GROUP_POSES = 4
"""Most poses in one exactly searched group (3 -> 4 tightens the bound on a 2.1 m adult by 0.2
points; the search grows with the maximal sets of all but the last two poses)."""
SEARCH_BUDGET = 50_000
"""Most choices of a group's leading poses enumerated; a group whose search would be larger is
bounded as two halves searched apart (the best of the union is at most the sum of the best of
each half: still certified, less tight)."""


def coverage_sets(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(m, n) bool: the maximal sets of samples one focus distance of a pose holds sharp.

    lo, hi: (n,) the pose's focus intervals of the samples (nan where it does not see one).
    Every set a focus distance s holds sharp is contained in the set at the largest interval
    lower end <= s; of those, a set contained in the next one is dropped. A pose that sees
    nothing has the one empty set.
    """
    seen = ~np.isnan(lo)
    starts = np.unique(lo[seen])
    if not len(starts):
        return np.zeros((1, len(lo)), dtype=bool)
    low = np.where(seen, lo, np.inf)
    high = np.where(seen, hi, -np.inf)
    sets = (low[None, :] <= starts[:, None]) & (starts[:, None] <= high[None, :])
    keep = np.ones(len(starts), dtype=bool)
    keep[:-1] = ~np.all(~sets[:-1] | sets[1:], axis=1)  # contained in the next set
    return sets[keep]


def search_group(sets: list[np.ndarray], weight: np.ndarray) -> tuple[float, list[int]]:
    """The exact best choice of one coverage set per pose: (weight held sharp, index of the chosen
    set per pose). ``sets``: per pose (m, n) bool (:func:`coverage_sets`), weight (n,).

    All but the two poses with the most sets are enumerated; every choice of those two is one
    matrix product: sets i, j hold (before_i + last_j - both) of what the others leave."""
    k = len(sets)
    if k == 1:
        held = sets[0] @ weight
        return float(held.max()), [int(np.argmax(held))]
    rank = sorted(range(k), key=lambda i: len(sets[i]))
    leading, (b, c) = rank[:-2], rank[-2:]
    before, last = sets[b].astype(float), sets[c].astype(float)
    best, choice = -1.0, [0] * k
    for picked in itertools.product(*(range(len(sets[i])) for i in leading)):
        held = np.zeros(len(weight), dtype=bool)
        for i, j in zip(leading, picked):
            held |= sets[i][j]
        left = np.where(held, 0.0, weight)
        gain = (before @ left)[:, None] + (last @ left)[None, :] - (before * left) @ last.T
        row, col = np.unravel_index(int(np.argmax(gain)), gain.shape)
        value = float(weight[held].sum()) + float(gain[row, col])
        if value > best:
            best = value
            for pose, set_index in zip(leading, picked):
                choice[pose] = set_index
            choice[b], choice[c] = int(row), int(col)
    return best, choice


def search_size(sets: list[np.ndarray]) -> int:
    """Choices :func:`search_group` enumerates for these sets."""
    return int(np.prod(sorted(len(m) for m in sets)[:-2]))


def best_group(lo: np.ndarray, hi: np.ndarray, weight: np.ndarray) -> float:
    """Most of a group's samples (by weight (n,)) its k poses can hold sharp together, or (for a
    search over SEARCH_BUDGET) an upper bound on it.

    lo, hi: (k, n) the poses' focus intervals of the samples, nan where a pose does not see one.
    """
    sets = [coverage_sets(lo[i], hi[i]) for i in range(len(lo))]
    if len(sets) > 1 and search_size(sets) > SEARCH_BUDGET:
        half = len(lo) // 2
        return best_group(lo[:half], hi[:half], weight) + best_group(lo[half:], hi[half:], weight)
    return search_group(sets, weight)[0]


def pose_groups(n_poses: int, viewers: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """(P,) group label of every pose: disjoint groups of at most ``viewers.shape[1]`` poses,
    formed by joining the pose pairs that share the most weight of the samples seen by that few
    poses, heaviest first (Kruskal's order, with a size cap). ``viewers``: (n, width) the poses
    that see each such sample, -1 padded (:func:`_padded_viewers`); ``weight`` (n,) theirs."""
    max_poses = viewers.shape[1]
    keys, weights = [], []
    for i, j in itertools.combinations(range(max_poses), 2):
        both = (viewers[:, i] >= 0) & (viewers[:, j] >= 0)
        a, b = viewers[both, i], viewers[both, j]
        keys.append(np.minimum(a, b).astype(np.int64) * n_poses + np.maximum(a, b))
        weights.append(weight[both])
    key = np.concatenate(keys) if keys else np.zeros(0, dtype=np.int64)
    unique, inverse = np.unique(key, return_inverse=True)
    shared = np.bincount(inverse, weights=np.concatenate(weights) if weights else None, minlength=len(unique))
    parent = np.arange(n_poses)
    size = np.ones(n_poses, dtype=np.int64)

    def root(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = int(parent[x])
        return x

    for edge in unique[stable_argsort(-shared)].tolist():
        a, b = root(edge // n_poses), root(edge % n_poses)
        if a != b and size[a] + size[b] <= max_poses:
            parent[b] = a
            size[a] += size[b]
    return np.array([root(x) for x in range(n_poses)], dtype=np.int64)


def _padded_viewers(table: CostTable, points: np.ndarray, width: int) -> np.ndarray:
    """(len(points), width) the poses that see each point (each sees at most ``width``), -1 padded."""
    ptr = table.point_ptr
    out = np.full((len(points), width), -1, dtype=np.int64)
    pose_of = table.vis.pose[table.order]
    for k in range(width):
        has = ptr[points] + k < ptr[points + 1]
        out[has, k] = pose_of[ptr[points[has]] + k]
    return out


def in_focus_bound(table: CostTable, max_poses: int = GROUP_POSES) -> InFocusBound:
    """The certified bound for the table's samples and poses (see the module docstring)."""
    vis, order, ptr, weight = table.vis, table.order, table.point_ptr, table.weight
    views = np.diff(ptr)
    visible = float(weight[views > 0].sum())
    few = np.flatnonzero((views >= 1) & (views <= max_poses))
    viewers = _padded_viewers(table, few, max_poses)
    group = pose_groups(vis.n_poses, viewers, weight[few])
    first = group[viewers[:, 0]]
    own = np.all((group[viewers] == first[:, None]) | (viewers < 0), axis=1)  # every viewer in one group
    few, first = few[own], first[own]
    by_group = stable_argsort(first)
    few, first = few[by_group], first[by_group]
    bounds = np.flatnonzero(np.diff(first, prepend=-1, append=-2))
    loss = 0.0
    groups = 0
    for start, stop in zip(bounds[:-1].tolist(), bounds[1:].tolist()):
        points = few[start:stop]
        members = np.flatnonzero(group == first[start])
        row = np.full(vis.n_poses, -1, dtype=np.int64)
        row[members] = np.arange(len(members))
        count = views[points]
        pairs = order[np.repeat(ptr[points], count) + _ranks(count)]
        column = np.repeat(np.arange(len(points)), count)
        lo = np.full((len(members), len(points)), np.nan)
        hi = np.full((len(members), len(points)), np.nan)
        lo[row[vis.pose[pairs]], column] = table.lo[pairs]
        hi[row[vis.pose[pairs]], column] = table.hi[pairs]
        w = weight[points]
        lost = float(w.sum()) - best_group(lo, hi, w)
        if lost > 0:
            loss += lost
            groups += 1
    return InFocusBound(table.n_points, visible, max(visible - loss, 0.0), groups, table.total_weight)


def _ranks(count: np.ndarray) -> np.ndarray:
    """0..c-1 for every c in ``count``, concatenated."""
    result: np.ndarray = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
    return result


def sharp_count(table: CostTable, focus_mm: np.ndarray) -> float:
    """Weight of the samples a plan holds sharp, for comparison with the bound."""
    return float(table.weight[table.sharp_points(focus_mm)].sum())

