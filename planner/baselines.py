"""Focus plans the shape-aware method is compared against (SPEC 3).

- closest: each pose focuses on the nearest depth it sees (the seed's "Closest Focus");
- average: each pose focuses on the mean depth it sees (the seed's "Average Focus");
- fixed: one focus distance for every pose, as older rigs do, chosen to minimise K;
- autofocus: each pose focuses on the surface at its image centre, as a phone's centre-weighted
  autofocus would; when the central ray misses the body, on the nearest visible depth.
A pose that sees nothing keeps ``fallback_mm`` (the planner uses the ring radius: the axis).
"""

from __future__ import annotations

import numpy as np

from planner.cost import CostTable
from planner.poses import Poses
from planner.visibility import RayScene, Visibility

#: Candidates per stage of the fixed-focus search (coarse grid in diopters, then a finer one).
FIXED_CANDIDATES = 24


def _per_pose(vis: Visibility, values: np.ndarray, ufunc: np.ufunc, fallback_mm: float) -> np.ndarray:
    out = np.full(vis.n_poses, float(fallback_mm))
    counts = np.diff(vis.pose_ptr)
    seen = counts > 0
    if seen.any():
        out[seen] = ufunc.reduceat(values, vis.pose_ptr[:-1][seen])
    return out


def closest_focus(vis: Visibility, fallback_mm: float) -> np.ndarray:
    """(P,) mm: the nearest visible depth of each pose."""
    return _per_pose(vis, vis.depth, np.minimum, fallback_mm)


def average_focus(vis: Visibility, fallback_mm: float) -> np.ndarray:
    """(P,) mm: the mean visible depth of each pose."""
    counts = np.diff(vis.pose_ptr)
    sums = _per_pose(vis, vis.depth, np.add, 0.0)
    return np.where(counts > 0, sums / np.maximum(counts, 1), float(fallback_mm))


def fixed_focus(table: CostTable, fallback_mm: float) -> np.ndarray:
    """(P,) mm, all equal: the single focus distance with the lowest K.

    K of a common focus is piecewise constant in s; it is searched on a grid uniform in
    diopters over the visible depths, then on a finer grid around the best coarse value.
    """
    depth = table.vis.depth
    if not len(depth):
        return np.full(table.n_poses, float(fallback_mm))
    near, far = 1.0 / float(depth.min()), 1.0 / float(depth.max())
    coarse = np.linspace(far, near, FIXED_CANDIDATES)

    def k_at(diopters: float) -> float:
        return table.total_cost(np.full(table.n_poses, 1.0 / diopters))

    best_d = min(coarse, key=k_at)
    step = (near - far) / (FIXED_CANDIDATES - 1)
    fine = np.linspace(best_d - step, best_d + step, FIXED_CANDIDATES)
    best_d = min([best_d, *fine[fine > 0]], key=k_at)
    return np.full(table.n_poses, 1.0 / best_d)


def autofocus(scene: RayScene, poses: Poses, vis: Visibility, fallback_mm: float) -> np.ndarray:
    """(P,) mm: depth of the first surface on each pose's optical axis, else its closest depth."""
    t = scene.first_hit(poses.centres, poses.forward)
    return np.where(np.isfinite(t), t, closest_focus(vis, fallback_mm))
