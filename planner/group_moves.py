"""Group moves: a few neighbouring poses refocused together on the skin only they hold sharp.

After the robust refinement no single pose can move its focus and gain, but skin close to the
column (an arm as the beam passes, 10-15 cm from the phones) is sharp over a few millimetres of
focus only and seen by a few neighbouring poses: the phones next to each other at one capture
angle, or one phone at consecutive angles. Holding more of it needs those poses to split its
depths between them, which no single-pose move can do (the k-view idea of arXiv 2407.15883:
optimise small sets of views jointly).

For each group, with every other pose's focus fixed, the group's samples are those no other
pose holds sharp. The group's focus distances that hold most of them are found exactly (the
search of the certified bound, planner/bound.py) and taken when they hold more than now. A
sample another pose holds sharp stays sharp, so the in-focus share never falls; each pose's new
focus is the harmonic middle of the depths its chosen set allows (the widest margin).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planner.bound import coverage_sets, search_group, search_size
from planner.cost import CostTable
from planner.interval_sweep import cell_focus

#: A group's move is taken only if it holds more than this weight more (guards float ties).
MIN_GAIN = 1e-9
#: Most choices of a group's leading pose searched; a group with more is left as it is (a few
#: groups whose own skin spreads over many depths; they cost the plan time, not its skin).
SEARCH_BUDGET = 50


@dataclass(frozen=True)
class GroupMoves:
    """focus_mm (P,) after the moves, the weight they brought into focus, and the moves taken."""

    focus_mm: np.ndarray
    gained: float
    moves: int


def rig_groups(n_angles: int, n_cameras: int, size: int = 3) -> list[np.ndarray]:
    """Pose groups of an angle-major rig (pose = angle * n_cameras + camera): ``size`` cameras
    next to each other on the column at every angle, and every camera at ``size`` consecutive
    angles (the turn wraps)."""
    groups = []
    if n_cameras >= size:
        for angle in range(n_angles):
            for camera in range(n_cameras - size + 1):
                groups.append(angle * n_cameras + camera + np.arange(size))
    if n_angles >= size:
        for camera in range(n_cameras):
            for angle in range(n_angles):
                groups.append((angle + np.arange(size)) % n_angles * n_cameras + camera)
    return groups


def group_moves(table: CostTable, focus_mm: np.ndarray, groups: list[np.ndarray], *,
                rounds: int = 2) -> GroupMoves:
    """Every group in turn (``rounds`` passes, stopping early when a pass takes no move)."""
    from planner.own_samples import own_samples  # numba: only processes that plan load it

    vis = table.vis
    focus = np.asarray(focus_mm, dtype=float).copy()
    held = np.bincount(vis.point[table.pair_in_focus(focus)], minlength=vis.n_points)
    pose_ptr, point = vis.pose_ptr, vis.point  # the kernel takes them as they are, no copies
    groups = [np.asarray(members, dtype=np.int64) for members in groups]
    count = np.zeros(vis.n_points, dtype=np.int64)  # the kernel's scratch
    column = np.full(vis.n_points, -1, dtype=np.int64)
    gained, moves = 0.0, 0
    for _ in range(rounds):
        taken = 0
        # A group can gain only where one of its poses sees skin nobody holds sharp.
        wanting = np.zeros(vis.n_poses, dtype=bool)
        wanting[vis.pose[held[vis.point] == 0]] = True
        for members in groups:
            if not wanting[members].any():
                continue
            own, lo, hi = own_samples(members, pose_ptr, point, table.lo, table.hi, focus, held, count, column)
            if not len(own):
                continue
            weight = table.weight[own]
            now = float(weight[held[own] > 0].sum())
            if now >= weight.sum() - MIN_GAIN:
                continue  # the group holds all of its own skin already
            sets = [coverage_sets(lo[i], hi[i]) for i in range(len(members))]
            if search_size(sets) > SEARCH_BUDGET:
                continue
            best, choice = search_group(sets, weight)
            if best <= now + MIN_GAIN:
                continue
            for i, pose in enumerate(members.tolist()):
                chosen = sets[i][choice[i]]
                if chosen.any():  # a pose that sees none of the group's own skin keeps its focus
                    before = _sharp(table, pose, focus[pose])
                    focus[pose] = cell_focus(float(np.max(lo[i][chosen])), float(np.min(hi[i][chosen])))
                    # a pose sees a sample once: its pairs' samples are distinct
                    held[point[pose_ptr[pose]:pose_ptr[pose + 1]]] += _sharp(table, pose, focus[pose]) - before
            gained += best - now
            taken += 1
        moves += taken
        if not taken:
            break
    return GroupMoves(focus, gained, moves)


def _sharp(table: CostTable, pose: int, focus: float) -> np.ndarray:
    """(pairs of ``pose``,) int: 1 where the pair is in focus at ``focus`` mm."""
    pairs = slice(int(table.vis.pose_ptr[pose]), int(table.vis.pose_ptr[pose + 1]))
    return ((table.lo[pairs] <= focus) & (focus <= table.hi[pairs])).astype(np.int64)
