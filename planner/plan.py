"""Plan the focus of every pose for a subject mesh, compare methods, evaluate plans elsewhere.

``plan_focus`` samples the surface, finds the visible (pose, point) pairs, and runs the
baselines, the seed's EM, EM + exact refinement ("shape-aware") and EM + refinement with the
redundancy term, then group moves of neighbouring poses ("robust", the plan to capture with). ``evaluate`` scores any
focus plan on another mesh, sample or pose set: plan on an estimated mesh or noisy poses,
judge on the true body and poses.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import structlog
import trimesh

from planner.baselines import autofocus, average_focus, closest_focus, fixed_focus
from planner.cores import spare_core
from planner.cost import CostTable, cost_table
from planner.em import expectation_minimisation
from planner.focus_errors import (
    BadFocusPlan,
    EmptyMesh,
    InvertedMesh,
    MeshLoadError,
    NothingVisible,
    PlanTooLarge,
    SubjectOutsideRing,
)
from planner.group_moves import group_moves, rig_groups
from planner.importance import Importance, refine_samples
from planner.optics import resolution_mm_per_px
from planner.poses import Poses, rgb_poses, rig_rgb_poses
from planner.redundancy import Redundancy
from planner.refine import refine_focus
from planner.rig import PLAN_MEMORY_BUDGET_BYTES, Rig, planning_memory_bytes
from planner.sampling import SurfaceSamples, Triangles, sample_surface
from planner.visibility import RayScene, visible_pairs

if TYPE_CHECKING:
    from planner.calibration.model import Calibration

log = structlog.get_logger(__name__)

METHODS = ("closest", "average", "fixed", "autofocus", "em", "shape-aware", "robust", "robust-angles")
#: The resolution a 1.5 mm lesion needs (SPEC 2), mm per pixel.
LESION_RESOLUTION_MM_PER_PX = 0.075


@dataclass(frozen=True)
class MethodPlan:
    """One method's focus plan: focus_mm (P,) in pose order, its K and in-focus share."""

    name: str
    focus_mm: np.ndarray
    total_cost: float
    in_focus_fraction: float
    seconds: float
    #: (A,) deg: capture angles of a plan with its own angles (robust-angles); None: the rig's.
    angles_deg: np.ndarray | None = None

    def to_json(self) -> dict[str, Any]:
        out = {
            "total_cost": round(self.total_cost, 4),
            "in_focus_fraction": round(self.in_focus_fraction, 6),
            "focus_mm": [round(float(s), 3) for s in self.focus_mm],
            "seconds": round(self.seconds, 4),
        }
        if self.angles_deg is not None:
            out["angles_deg"] = [round(float(a), 4) for a in self.angles_deg]
        return out


@dataclass(frozen=True)
class Evaluation:
    """A focus plan scored on one sample: K, in-focus and visible shares of n_points."""

    n_points: int
    total_cost: float
    in_focus_fraction: float
    visible_fraction: float


@dataclass(frozen=True)
class PlanResult:
    """All methods' plans for one mesh, with the inputs needed to navigate or re-score them."""

    rig: Rig
    poses: Poses
    samples: SurfaceSamples
    table: CostTable
    methods: dict[str, MethodPlan]
    resolution: dict[str, float]
    timing_s: dict[str, float] = field(default_factory=dict)
    beam_angles_deg: np.ndarray | None = None
    """(A,) deg, the beam angle of each angle index of ``poses`` when known (the rig's own poses,
    nominal or calibrated); None for given poses, whose angles are estimated from their centres."""
    points: int = 0
    """Area-uniform samples asked for; ``samples`` adds the importance samples (0: as many as
    ``samples``)."""

    @property
    def pose_angles_deg(self) -> np.ndarray:
        """(A,) deg, the beam angle of each angle index of :attr:`poses`."""
        if self.beam_angles_deg is not None:
            return self.beam_angles_deg
        return pose_angles_deg(self.poses, self.rig)

    @property
    def capture_method(self) -> str:
        """The plan to capture with: robust-angles, robust or shape-aware when computed, else the
        best by K."""
        for name in ("robust-angles", "robust", "shape-aware"):
            if name in self.methods:
                return name
        return min(self.methods.values(), key=lambda m: m.total_cost).name

    @property
    def focus_mm(self) -> np.ndarray:
        """(P,) mm, the focus of the plan to capture with (at :attr:`capture_angles_deg`)."""
        return self.methods[self.capture_method].focus_mm

    @property
    def capture_angles_deg(self) -> np.ndarray:
        """(A,) deg, the angles of the plan to capture with (the rig's unless it chose its own)."""
        own = self.methods[self.capture_method].angles_deg
        return own if own is not None else self.pose_angles_deg

    @property
    def visible_fraction(self) -> float:
        return self.table.visible_fraction

    def to_json(self) -> dict[str, Any]:
        camera_heights = [p.height_mm for p in self.rig.phones]
        angles = self.pose_angles_deg
        return {
            "points": self.points or len(self.samples),
            "samples": len(self.samples),
            "poses": len(self.poses),
            "angles_deg": [float(a) for a in angles],
            "camera_heights_mm": camera_heights,
            "visible_fraction": round(self.visible_fraction, 6),
            "resolution_mm_per_px": self.resolution,
            "methods": {name: m.to_json() for name, m in self.methods.items()},
            "capture_method": self.capture_method,
            "capture_angles_deg": [float(a) for a in self.capture_angles_deg],
            "timing_s": {k: round(v, 4) for k, v in self.timing_s.items()},
            "pose_order": "angle-major: pose = angle_index * cameras + camera_index",
        }


def pose_angles_deg(poses: Poses, rig: Rig) -> np.ndarray:
    """(A,) capture angle of each angle index: the rig's, or for other pose sets (custom angles,
    noisy calibrations) the mean azimuth of the poses that share an angle index."""
    n_angles = int(poses.angle_index.max()) + 1 if len(poses) else 0
    if n_angles == rig.n_angles and len(poses) == rig.n_poses:
        nominal = rgb_poses(rig)
        if np.allclose(nominal.centres, poses.centres, atol=1e-6):
            return rig.capture.angles_deg
    xy = np.zeros((n_angles, 2))
    np.add.at(xy, poses.angle_index, poses.centres[:, :2])
    angles = np.degrees(np.arctan2(xy[:, 1], xy[:, 0]))
    if n_angles == rig.n_angles:  # e.g. noisy poses of this rig: stay next to its angles
        nominal_deg = rig.capture.angles_deg
        angles = nominal_deg + (angles - nominal_deg + 180.0) % 360.0 - 180.0
    return np.round(angles, 3)


MAX_MESH_BYTES = 512 * 1024 * 1024
"""A body mesh from the TSDF is 10-40 MB; a scanned body at 0.5 mm, a few hundred MB at most."""


def load_subject_mesh(path: Path | str, max_bytes: int = MAX_MESH_BYTES) -> trimesh.Trimesh:
    """Read a triangle mesh (mm) from a file trimesh understands (PLY, OBJ, STL, GLB...)."""
    path = Path(path)
    if not path.is_file():
        raise MeshLoadError(str(path), "no such file")
    size = path.stat().st_size
    if size > max_bytes:
        raise MeshLoadError(str(path), f"{size} bytes, larger than the {max_bytes} a body mesh may have")
    try:
        mesh = trimesh.load(path, force="mesh", process=True)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise MeshLoadError(str(path), f"cannot be read as a mesh: {exc}") from exc
    if not isinstance(mesh, trimesh.Trimesh):
        raise MeshLoadError(str(path), f"holds a {type(mesh).__name__}, not a triangle mesh")
    return mesh


def _samples(
    mesh: trimesh.Trimesh, rig: Rig, points: int | SurfaceSamples | None, seed: int, name: str
) -> tuple[SurfaceSamples, Triangles]:
    """The given samples, or fresh ones, and the mesh's triangles; EmptyMesh or InvertedMesh
    (naming the mesh) if the mesh has no surface or is wound inside out."""
    if len(mesh.faces) == 0:
        raise EmptyMesh(name, 0, 0.0)
    check_inside_ring(mesh, rig, name)
    triangles = Triangles.of(mesh)
    volume = triangles.signed_volume_mm3
    if volume < 0:
        raise InvertedMesh(name, volume)
    if isinstance(points, SurfaceSamples):
        return points, triangles
    count = rig.planner.points if points is None else int(points)
    need = planning_memory_bytes(count, rig.n_poses)
    if need > PLAN_MEMORY_BUDGET_BYTES:
        raise PlanTooLarge(count, rig.n_poses, need, PLAN_MEMORY_BUDGET_BYTES)
    try:
        return sample_surface(mesh, count, seed=seed, triangles=triangles), triangles
    except EmptyMesh as exc:
        raise EmptyMesh(name, exc.faces, exc.area_mm2) from exc


def check_inside_ring(mesh: trimesh.Trimesh, rig: Rig, name: str) -> None:
    """SubjectOutsideRing naming the first vertex that is not finite or lies beyond the camera ring
    (distance from the rotation axis, mm); the planner's numbers mean nothing for such a mesh."""
    v = np.asarray(mesh.vertices, dtype=float)
    with np.errstate(over="ignore", invalid="ignore"):
        radial = np.hypot(v[:, 0], v[:, 1])
        bad = np.flatnonzero(~np.isfinite(v).all(axis=1) | ~(radial < rig.ring_radius_mm))
    if len(bad):
        i = int(bad[0])
        x, y, z = (float(c) for c in v[i])
        raise SubjectOutsideRing(name, i, (x, y, z), rig.ring_radius_mm)


def check_focus(focus_mm: np.ndarray, n_poses: int) -> np.ndarray:
    """The plan as a (P,) float array, or BadFocusPlan naming what is wrong."""
    focus = np.asarray(focus_mm, dtype=float)
    if focus.shape != (n_poses,):
        raise BadFocusPlan(f"has shape {focus.shape}", n_poses)
    bad = np.flatnonzero(~(np.isfinite(focus) & (focus > 0)))
    if len(bad):
        raise BadFocusPlan(f"pose {bad[0]} has focus {float(focus[bad[0]])!r} mm", n_poses)
    return focus


def resolution_stats(table: CostTable, rig: Rig) -> dict[str, float]:
    """mm/px over visible samples, each seen from its best pose by the focus-independent cost.

    share_at_most_0.075 is the share of ALL samples imaged at 0.075 mm/px or finer (the seed's
    lesion criterion), so invisible skin counts against it.
    """
    best = table.best_pairs_by(table.base)
    seen = best >= 0
    res = resolution_mm_per_px(table.vis.depth[best[seen]], rig.optics)
    if not len(res):
        return {"mean": float("nan"), "std": float("nan"), "share_at_most_0.075": 0.0}
    weight = table.weight[seen]  # the skin each sample stands for
    mean = float(np.average(res, weights=weight))
    fine = float(weight[res <= LESION_RESOLUTION_MM_PER_PX].sum() / table.total_weight)
    return {
        "mean": round(mean, 6),
        "std": round(float(np.sqrt(np.average((res - mean) ** 2, weights=weight))), 6),
        "share_at_most_0.075": round(fine, 6),
    }


def candidate_table(scene: RayScene, rig: Rig, samples: SurfaceSamples,
                    calibration: Calibration | None = None) -> tuple[np.ndarray, CostTable]:
    """The candidate capture angles (K,) deg of the rig's rotation and the cost table of
    ``samples`` seen by every phone at every one of them (K * C poses, angle-major)."""
    from planner.angles import candidate_angles
    from planner.schedule import rig_profile

    candidates = candidate_angles(rig, rig_profile(rig), rig.planner.angle_step_deg)
    poses = rig_rgb_poses(rig, calibration, candidates)
    return candidates, cost_table(visible_pairs(scene, poses, samples, rig.optics), rig.cost, rig.optics,
                                  samples.weight)


def _plan_angles(scene: RayScene, rig: Rig, samples: SurfaceSamples, robust_focus: np.ndarray,
                 fallback_mm: float, calibration: Calibration | None) -> Any:
    """Per-subject capture angles (planner/angles.py) for these samples, from the robust plan."""
    from planner.angles import plan_angles

    candidates, table = candidate_table(scene, rig, samples, calibration)
    return plan_angles(table, candidates, rig, robust_focus, redundancy=rig_redundancy(rig),
                       fallback_mm=fallback_mm, poses_at=lambda angles: rig_rgb_poses(rig, calibration, angles))


def rig_importance(rig: Rig) -> Importance:
    """The planning samples' importance refinement from the rig file's planner section."""
    p = rig.planner
    return Importance(p.importance_views, p.importance_radius_mm, p.importance_density)


def rig_redundancy(rig: Rig) -> Redundancy:
    """The robust plan's redundancy term from the rig file's planner section."""
    return Redundancy(rig.planner.redundancy_weight, rig.planner.view_miss_probability)


def plan_focus(
    mesh: trimesh.Trimesh,
    rig: Rig,
    *,
    points: int | SurfaceSamples | None = None,
    seed: int = 0,
    poses: Poses | None = None,
    calibration: Calibration | None = None,
    methods: tuple[str, ...] | None = None,
    backend: str = "open3d",
    mesh_name: str = "<mesh>",
) -> PlanResult:
    """Plan one focus distance per pose (angle-major order) for ``mesh`` (mm) on ``rig``.

    points: sample count (default rig.planner.points) or given samples. poses: camera poses to
    plan for (default: the rig's RGB poses, calibrated when ``calibration`` is given; per-subject
    capture angles need the rig's own poses, so they are refused with given ``poses``).
    Raises EmptyMesh, InvertedMesh, NothingVisible (all FocusPlanError, naming the mesh).
    """
    if methods is None:  # every method; per-subject angles only for the rig's own poses
        methods = METHODS if poses is None else tuple(m for m in METHODS if m != "robust-angles")
    unknown = sorted(set(methods) - set(METHODS))
    if unknown:
        raise ValueError(f"unknown focus method {unknown[0]!r}; allowed: {', '.join(METHODS)}")
    if "robust-angles" in methods and poses is not None:
        raise ValueError("per-subject capture angles are planned from the rig's own poses, not given ones")
    RayScene.import_backend(backend)  # a one-off cost, not part of planning
    t_start = time.perf_counter()
    given_poses = poses
    poses = rig_rgb_poses(rig, calibration) if poses is None else poses
    samples, triangles = _samples(mesh, rig, points, seed, mesh_name)
    t_sampled = time.perf_counter()
    scene = RayScene(mesh, backend)
    vis = visible_pairs(scene, poses, samples, rig.optics)
    asked = len(samples)
    if not isinstance(points, SurfaceSamples):  # given samples are planned on as they are
        budget = PLAN_MEMORY_BUDGET_BYTES // planning_memory_bytes(1, len(poses))
        samples, vis = refine_samples(mesh, triangles, samples, vis, scene, poses, rig.optics,
                                      rig_importance(rig), seed, max_samples=budget)
    table = cost_table(vis, rig.cost, rig.optics, samples.weight)
    t_visible = time.perf_counter()
    if not table.seen.any():
        raise NothingVisible(mesh_name, len(samples), len(poses), mesh.bounds.round(1).tolist())

    fallback = rig.ring_radius_mm
    timing = {"sampling": t_sampled - t_start, "visibility": t_visible - t_sampled}
    plans: dict[str, MethodPlan] = {}

    def record(name: str, focus: np.ndarray, seconds: float) -> None:
        plans[name] = MethodPlan(
            name, focus, table.total_cost(focus), table.in_focus_fraction(focus), seconds
        )

    def timed(make: Callable[[], np.ndarray]) -> tuple[np.ndarray, float]:
        started = time.perf_counter()
        focus = make()
        return focus, time.perf_counter() - started

    average, average_seconds = timed(lambda: average_focus(table.vis, fallback))
    if "average" in methods:
        record("average", average, average_seconds)
    if "closest" in methods:
        record("closest", *timed(lambda: closest_focus(table.vis, fallback)))
    if "fixed" in methods:
        record("fixed", *timed(lambda: fixed_focus(table, fallback)))
    if "autofocus" in methods:
        record("autofocus", *timed(lambda: autofocus(scene, poses, table.vis, fallback)))
    if {"em", "shape-aware", "robust", "robust-angles"} & set(methods):
        descends = bool({"shape-aware", "robust", "robust-angles"} & set(methods))
        side_thread = ThreadPoolExecutor(1, thread_name_prefix="presort") if descends and spare_core() else None
        with side_thread or nullcontext() as side:
            # The descents' sorted interval ends do not depend on EM: a spare core sorts them meanwhile.
            presorted = side.submit(lambda: table.ends) if side is not None else None
            em_focus, timing["em"] = timed(
                lambda: expectation_minimisation(
                    table,
                    average,
                    relative_tolerance=rig.planner.em_relative_tolerance,
                    max_iterations=rig.planner.em_max_iterations,
                ).focus_mm
            )
            if presorted is not None:
                presorted.result()
        if "em" in methods:
            record("em", em_focus, timing["em"])
        if "shape-aware" in methods:
            refined, timing["refine"] = timed(
                lambda: refine_focus(table, em_focus, max_sweeps=rig.planner.refine_max_sweeps).focus_mm
            )
            record("shape-aware", refined, timing["em"] + timing["refine"])
        if "robust" in methods or "robust-angles" in methods:
            robust, timing["robust"] = timed(
                lambda: group_moves(
                    table,
                    refine_focus(
                        table, em_focus, max_sweeps=rig.planner.robust_max_sweeps, redundancy=rig_redundancy(rig)
                    ).focus_mm,
                    rig_groups(table.n_poses // rig.n_cameras, rig.n_cameras),
                ).focus_mm
            )
            record("robust", robust, timing["em"] + timing["robust"])
        if "robust-angles" in methods:
            started = time.perf_counter()
            chosen = _plan_angles(scene, rig, samples, robust, fallback, calibration)
            timing["angles"] = time.perf_counter() - started
            plans["robust-angles"] = MethodPlan(
                "robust-angles", chosen.focus_mm, chosen.total_cost, chosen.in_focus_fraction,
                timing["em"] + timing["robust"] + timing["angles"], chosen.angles_deg,
            )
    last = timing.get("robust", timing.get("refine", 0.0)) + timing.get("angles", 0.0)
    timing["plan"] = timing["visibility"] + timing.get("em", 0.0) + last
    timing["total"] = time.perf_counter() - t_start
    result = PlanResult(rig, poses, samples, table, plans, resolution_stats(table, rig), timing,
                        beam_angles_deg=rig.capture.angles_deg if given_poses is None else None, points=asked)
    log.info(
        "plan.done",
        points=asked,
        samples=len(samples),
        poses=len(poses),
        visible=round(table.visible_fraction, 4),
        **{f"in_focus_{k}": round(m.in_focus_fraction, 4) for k, m in plans.items()},
        seconds=round(timing["total"], 3),
    )
    return result


def evaluate(
    focus_mm: np.ndarray,
    mesh: trimesh.Trimesh,
    rig: Rig,
    *,
    points: int | SurfaceSamples | None = None,
    seed: int = 1,
    poses: Poses | None = None,
    backend: str = "open3d",
    mesh_name: str = "<mesh>",
) -> Evaluation:
    """Score a focus plan (P,) mm on ``mesh`` seen from ``poses`` (default: the rig's poses).

    Use a different mesh, sample seed or pose set than the plan was made with to measure how
    the plan transfers to the true body, a fresh sample or the true calibration.
    """
    poses = rgb_poses(rig) if poses is None else poses
    focus = check_focus(focus_mm, len(poses))
    samples, _ = _samples(mesh, rig, points, seed, mesh_name)
    table = cost_table(visible_pairs(RayScene(mesh, backend), poses, samples, rig.optics), rig.cost, rig.optics,
                       samples.weight)
    return Evaluation(
        n_points=len(samples),
        total_cost=table.total_cost(focus),
        in_focus_fraction=table.in_focus_fraction(focus),
        visible_fraction=table.visible_fraction,
    )
