"""Per-subject capture angles: where the beam fires, chosen with the focus for each subject.

The phones are fixed on the beam, but when they fire is software. Every capture angle may move
along the rotation as long as the capture still happens at a constant sector speed (away from
the profile's speed ramps) and each phone has its capture cycle and lens settling time between
two captures. The number of images and the motion profile (so the scan time) stay the same.

Method: visibility and costs are computed once for a grid of candidate angles (all phones at
every candidate). Starting from the rig's angles and the robust focus plan on them, each angle
in turn is moved to the candidate, inside the window its neighbours' timing allows, where its
phones would gain most (K and the redundancy term of ``planner/redundancy.py``, every phone's
best focus found by an exact interval sweep against the rest of the plan). After a round over
all angles the focus of the new pose set is refined exactly; the round is kept only if the
objective fell, so the result is never worse than the rig's angles on the planning samples.
Last, neighbouring poses of the chosen set are refocused together (``planner/group_moves.py``),
which never loses sharp skin.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import structlog

from planner.cost import CostTable, cost_table
from planner.group_moves import group_moves, rig_groups
from planner.poses import Poses, rgb_poses
from planner.redundancy import Redundancy, expected_misses, sharp_views
from planner.refine import refine_focus
from planner.rig import Rig
from planner.schedule import MotionProfile, rig_profile
from planner.visibility import Visibility

log = structlog.get_logger(__name__)

#: Candidate angles are this far apart (deg) unless the caller asks otherwise.
CANDIDATE_STEP_DEG = 1.0
#: Extra time (fraction of cycle + settle) kept between two captures of a phone.
GAP_MARGIN = 0.1
#: Cost of an inactive pair: above the invisible cost 1, so it never counts.
_INACTIVE = 2.0


@dataclass(frozen=True)
class AnglePlan:
    """Chosen angles (A,) deg in rotation order, their focus (A * C,) mm angle-major, the poses
    and cost table of the chosen set, and how the search went."""

    angles_deg: np.ndarray
    focus_mm: np.ndarray
    poses: Poses
    table: CostTable
    objective: float
    start_objective: float
    rounds: int
    candidates: int

    @property
    def total_cost(self) -> float:
        return self.table.total_cost(self.focus_mm)

    @property
    def in_focus_fraction(self) -> float:
        return self.table.in_focus_fraction(self.focus_mm)


def min_capture_gap_s(rig: Rig) -> float:
    """Shortest time between two captures of one phone: its capture cycle, the lens settling
    for the next focus, and a margin for the encoder-predicted trigger."""
    return (rig.capture.capture_cycle_s + rig.capture.lens_settle_s) * (1.0 + GAP_MARGIN)


def candidate_angles(rig: Rig, profile: MotionProfile, step_deg: float = CANDIDATE_STEP_DEG) -> np.ndarray:
    """(K,) deg: a grid over the rotation plus the rig's own angles, keeping only angles the beam
    crosses at its sector's constant speed with the rig's angle tolerance to spare."""
    if not step_deg > 0:
        raise ValueError(f"candidate step must be positive, got {step_deg!r} deg")
    start, end = rig.capture.start_deg, rig.capture.end_deg
    grid = np.arange(np.ceil(start / step_deg) * step_deg, end + 1e-9, step_deg)
    angles = np.unique(np.round(np.concatenate([grid, rig.capture.angles_deg]), 9))
    tol = rig.capture.angle_tolerance_deg
    ok = np.ones(len(angles), dtype=bool)
    for shift in (-tol, 0.0, tol):
        probe = np.clip(angles + shift, profile.start_deg, profile.end_deg)
        speed = profile.speed_at_angle(probe)
        nominal = profile.nominal_speed(probe)
        ok &= (nominal > 0) & np.isclose(speed, nominal, rtol=1e-9, atol=1e-9)
    return angles[ok]


def subset_table(table: CostTable, poses: np.ndarray, rig: Rig) -> CostTable:
    """The cost table of ``poses`` (indices into table's poses) renumbered 0..len-1 in order."""
    vis = table.vis
    parts = [np.arange(vis.pose_ptr[q], vis.pose_ptr[q + 1]) for q in np.asarray(poses).tolist()]
    pairs = np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)
    counts = np.array([len(p) for p in parts], dtype=np.int64)
    ptr = np.zeros(len(parts) + 1, dtype=np.int64)
    np.cumsum(counts, out=ptr[1:])
    sub = Visibility(
        n_poses=len(parts),
        n_points=vis.n_points,
        pose=np.repeat(np.arange(len(parts), dtype=np.int32), counts),
        point=vis.point[pairs],
        depth=vis.depth[pairs],
        off_axis=vis.off_axis[pairs],
        facing=vis.facing[pairs],
        pose_ptr=ptr,
    )
    return cost_table(sub, rig.cost, rig.optics, table.weight)


def _objective(table: CostTable, focus: np.ndarray, redundancy: Redundancy) -> float:
    return table.total_cost(focus) + redundancy.weight * expected_misses(
        sharp_views(table, focus), redundancy.miss_probability, table.weight
    )


class _Search:
    """The candidate table and the current choice: one candidate per capture angle."""

    #: Best pair costs kept per point: enough that one angle's phones never hold all of them.
    KEEP = 4

    def __init__(self, table: CostTable, n_cameras: int, times: np.ndarray, gap_s: float,
                 redundancy: Redundancy) -> None:
        self.table = table
        self.n_cameras = n_cameras
        self.times = times
        self.gap_s = gap_s
        r = redundancy
        views = int(np.diff(table.point_ptr).max(initial=0)) + 2
        self.extra = r.weight * (1.0 - r.miss_probability) * r.miss_probability ** np.arange(views)
        self.ends = table.ends

    def poses_of(self, candidate: int) -> np.ndarray:
        return candidate * self.n_cameras + np.arange(self.n_cameras)

    def snapshot(self, chosen: np.ndarray, focus: np.ndarray) -> None:
        """Per point, the KEEP lowest pair costs over the chosen poses and the capture angle each
        comes from, and its sharp views per angle (for leaving one angle out)."""
        t = self.table
        ids = _pose_ids(chosen, self.n_cameras)
        pairs = np.concatenate([np.arange(t.vis.pose_ptr[q], t.vis.pose_ptr[q + 1]) for q in ids.tolist()])
        angle = np.repeat(np.arange(len(chosen)), self.n_cameras)[
            np.repeat(np.arange(len(ids)), np.diff(t.vis.pose_ptr)[ids])]
        point = t.vis.point[pairs]
        s = focus[t.vis.pose[pairs]]
        sharp = (t.lo[pairs] <= s) & (s <= t.hi[pairs])
        cost = np.where(sharp, t.base[pairs], t.base[pairs] + t.w_focus)
        order = np.lexsort((cost, point))
        point_sorted = point[order]
        first = np.searchsorted(point_sorted, np.arange(t.n_points))
        rank = np.arange(len(order)) - first[point_sorted]
        keep = rank < self.KEEP
        self.top_cost = np.ones((t.n_points, self.KEEP))
        self.top_angle = np.full((t.n_points, self.KEEP), -1)
        self.top_cost[point_sorted[keep], rank[keep]] = np.minimum(cost[order][keep], 1.0)
        self.top_angle[point_sorted[keep], rank[keep]] = angle[order][keep]
        self.views = np.bincount(point[sharp], minlength=t.n_points)
        self.sharp_point, self.sharp_angle = point[sharp], angle[sharp]

    def without(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Each point's best cost (N,) and sharp views (N,) with capture angle k left out."""
        other_angle = self.top_angle != k
        first = np.argmax(other_angle, axis=1)
        other = np.where(other_angle.any(axis=1), self.top_cost[np.arange(len(first)), first], 1.0)
        mine = self.sharp_angle == k
        views = self.views - np.bincount(self.sharp_point[mine], minlength=len(self.views))
        return other, views

    def value(self, candidate: int, other: np.ndarray, views: np.ndarray) -> tuple[float, np.ndarray]:
        """How much the phones at ``candidate`` would lower the objective, and their best focus.

        Each phone is scored against the rest of the plan on its own (the phones of one angle
        overlap little; the exact refinement afterwards settles their shared points)."""
        t = self.table
        w3 = t.w_focus
        total = 0.0
        focus = np.full(self.n_cameras, np.nan)
        for i, q in enumerate(self.poses_of(candidate).tolist()):
            sl = slice(int(t.vis.pose_ptr[q]), int(t.vis.pose_ptr[q + 1]))
            if sl.stop == sl.start:
                continue
            points = t.vis.point[sl]
            o, base, weight = other[points], t.base[sl], t.weight[points]
            in_focus_cost = np.minimum(o, base + w3)
            total += float((o - in_focus_cost) @ weight)
            gain = (np.maximum(in_focus_cost - base, 0.0) + self.extra[views[points]]) * weight
            focus[i], score = self.ends.sweep(q, gain)
            total += score
        return total, focus

    def window(self, chosen: np.ndarray, k: int) -> np.ndarray:
        """Candidates angle k may move to: between its neighbours, a capture gap away from each."""
        lo_t = self.times[chosen[k - 1]] + self.gap_s if k > 0 else -np.inf
        hi_t = self.times[chosen[k + 1]] - self.gap_s if k + 1 < len(chosen) else np.inf
        return np.flatnonzero((self.times >= lo_t) & (self.times <= hi_t))


def plan_angles(
    table: CostTable,
    candidates_deg: np.ndarray,
    rig: Rig,
    start_focus_mm: np.ndarray,
    *,
    redundancy: Redundancy,
    profile: MotionProfile | None = None,
    rounds: int = 3,
    refine_sweeps: int = 2,
    fallback_mm: float | None = None,
    poses_at: Callable[[np.ndarray], Poses] | None = None,
) -> AnglePlan:
    """Choose rig.n_angles capture angles among ``candidates_deg`` (K,) and their focus.

    table: the cost table of rgb_poses(rig, candidates_deg) (K * C poses, angle-major).
    start_focus_mm: (n_angles * C,) focus of the rig's own angles (which must be candidates).
    fallback_mm: focus of a phone that sees nothing at its angle (default the ring radius).
    poses_at: angles (A,) deg -> the rig's poses there (default nominal :func:`rgb_poses`; a
        calibrated rig passes its calibrated poses).
    """
    fallback = rig.ring_radius_mm if fallback_mm is None else fallback_mm
    profile = profile if profile is not None else rig_profile(rig)
    n_cam = rig.n_cameras
    if table.n_poses != len(candidates_deg) * n_cam:
        raise ValueError(f"table has {table.n_poses} poses; expected {len(candidates_deg)} x {n_cam}")
    where = np.searchsorted(candidates_deg, rig.capture.angles_deg)
    where = np.clip(where, 0, len(candidates_deg) - 1)
    if not np.allclose(candidates_deg[where], rig.capture.angles_deg):
        raise ValueError("the rig's capture angles must be among the candidates")
    times = profile.time_at(candidates_deg)
    search = _Search(table, n_cam, times, min_capture_gap_s(rig), redundancy)

    chosen = where.copy()
    focus = np.full(table.n_poses, fallback)
    focus[(chosen[:, None] * n_cam + np.arange(n_cam)).ravel()] = start_focus_mm
    start = _objective(subset_table(table, _pose_ids(chosen, n_cam), rig), start_focus_mm, redundancy)
    best_objective, best_chosen, best_focus = start, chosen.copy(), np.asarray(start_focus_mm, dtype=float)
    done = 0
    for done in range(1, rounds + 1):
        # Even angles, then odd ones: neighbours never move on the same snapshot of the plan.
        for parity in (0, 1):
            search.snapshot(chosen, focus)
            for k in range(parity, len(chosen), 2):
                window = search.window(chosen, k)
                if len(window) <= 1:
                    continue
                other, views = search.without(k)
                values = [search.value(int(j), other, views) for j in window.tolist()]
                j = int(np.argmax([v for v, _ in values]))
                new_focus = values[j][1]
                chosen[k] = window[j]
                focus[search.poses_of(int(chosen[k]))] = np.where(np.isnan(new_focus), fallback, new_focus)
        ids = _pose_ids(chosen, n_cam)
        sub = subset_table(table, ids, rig)
        refined = refine_focus(sub, focus[ids], max_sweeps=refine_sweeps, redundancy=redundancy)
        focus[ids] = refined.focus_mm
        log.debug("angles.round", round=done, objective=refined.objective, best=best_objective)
        if not refined.objective < best_objective - 1e-9:
            break
        best_objective, best_chosen, best_focus = refined.objective, chosen.copy(), refined.focus_mm.copy()
    angles = candidates_deg[best_chosen]
    poses = rgb_poses(rig, angles) if poses_at is None else poses_at(angles)
    chosen_table = subset_table(table, _pose_ids(best_chosen, n_cam), rig)
    # Neighbouring poses refocused together, as for the robust plan at the rig's angles.
    best_focus = group_moves(chosen_table, best_focus, rig_groups(len(angles), n_cam)).focus_mm
    return AnglePlan(angles, best_focus, poses, chosen_table, best_objective, start, done, len(candidates_deg))


def _pose_ids(chosen: np.ndarray, n_cameras: int) -> np.ndarray:
    return (chosen[:, None] * n_cameras + np.arange(n_cameras)).ravel()
