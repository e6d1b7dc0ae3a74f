"""Two visits of one simulated person: the second scan has a new seed, postural sway and the
person standing a little elsewhere. Ground truth for carrying lesion marks between them."""

from __future__ import annotations

import pickle
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

VISIT_SHIFT_MM = (25.0, -15.0, 0.0)
VISIT_TURN_DEG = 6.0
SWAY_DEG = 2.0  # the evaluation's postural sway (analysis/evaluation.py)


@dataclass(frozen=True)
class Visits:
    earlier: Path
    later: Path
    subject_earlier: Any
    subject_later: Any
    lesion_changes: Any = None
    """The seeded lesion changes of the later visit (drivers/sim/skin_texture.LesionChanges), or None."""


def placed(mesh: Any, shift_mm: tuple[float, float, float], turn_deg: float) -> Any:
    """The mesh turned about the ring's vertical axis and shifted (where the person stood)."""
    a = np.radians(turn_deg)
    rot = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    moved = mesh.copy()
    moved.vertices = np.asarray(mesh.vertices) @ rot.T + np.asarray(shift_mm)
    return moved


def dented(mesh: Any, centre: np.ndarray, radius_mm: float, depth_mm: float, *, ring: bool = False) -> Any:
    """The mesh pushed in along its normals around ``centre``, ``depth_mm`` there and smoothly
    less out to ``radius_mm``: skin a scan reconstructed inside the true surface. ``ring``: all
    round the body at the centre's height (a groove)."""
    vertices = np.asarray(mesh.vertices, dtype=float)
    offset = vertices[:, 2:] - centre[2:] if ring else vertices - centre
    near = np.clip(1.0 - np.sum(offset**2, axis=1) / radius_mm**2, 0.0, None) ** 2
    out = mesh.copy()
    out.vertices = vertices - depth_mm * near[:, None] * np.asarray(mesh.vertex_normals)
    return out


def kept_visits(root: Path, name: str, *, person_seed: int = 3, lesion_changes: Any = None,
                render_scale: int = 1, depth_decimation: int = 2) -> Visits:
    """:func:`two_visits` into ``root / name``, kept between runs in ``root / (name + ".pickle")``:
    scanned again only when the kept scans are gone or their lesion changes differ. A render
    scale other than 1 and a depth decimation other than 2 are names of their own (``name-x2``,
    ``name-d1``)."""
    name = name if render_scale == 1 else f"{name}-x{render_scale}"
    name = name if depth_decimation == 2 else f"{name}-d{depth_decimation}"
    cache = root / f"{name}.pickle"
    if cache.exists():
        visits: Visits = pickle.loads(cache.read_bytes())
        if visits.earlier.exists() and visits.later.exists() and visits.lesion_changes == lesion_changes:
            return visits
    visits = two_visits(root / name, person_seed=person_seed, lesion_changes=lesion_changes, render_scale=render_scale,
                        depth_decimation=depth_decimation)
    cache.write_bytes(pickle.dumps(visits))
    return visits


def two_visits(store: Path, *, person_seed: int = 3, plan_points: int = 1500, depth_decimation: int = 2,
               lesion_changes: Any = None, render_scale: int = 1) -> Visits:
    """Scan the same simulated adult (one synthetic patient) twice (seeds 1 and 2) into ``store``;
    QA reports included. ``lesion_changes``: spots grown and new at the second visit;
    ``render_scale``: the simulated phones' pictures that many times finer a side (sim/rig.py)."""
    from analysis.qa_report import generate_report
    from daemon.clinic.patient import ScanSubject
    from sim.body import make_body
    from sim.run import run_sim_scan

    still = make_body(seed=person_seed)
    swayed = placed(make_body(seed=person_seed, sway_deg=SWAY_DEG, sway_seed=person_seed * 100 + 7),
                    VISIT_SHIFT_MM, VISIT_TURN_DEG)
    folders = []
    for seed, subject, changes in ((1, still, None), (2, swayed, lesion_changes)):
        report = run_sim_scan(store=store, seed=seed, plan_points=plan_points, depth_decimation=depth_decimation,
                              subject=subject, panel=False, qa_report=generate_report, lesion_changes=changes,
                              render_scale=render_scale,
                              patient=ScanSubject.from_args({"patient_id": f"SYN-{person_seed:04d}",
                                                             "patient_name": f"Testperson^Seed{person_seed}"}))
        folders.append(Path(report.folder))
    return Visits(folders[0], folders[1], still, swayed, lesion_changes)


def carry_errors(visits: Visits, count: int = 100, seed: int = 0) -> dict[str, Any]:
    """Marks at ``count`` skin points seen sharp in the earlier scan (feet soles excluded),
    carried to the later scan by the shapes alone and then on the pictures; distance (mm) from
    the same skin point on the later mesh, how far that point of the later mesh is from the
    true skin (the later scan's own shape error there: a mark drawn on the later mesh can be
    judged no finer than that), distance from the true skin point itself, and the carrier's
    doubt (the later surface's gap from where the fit put the skin)."""
    from analysis.mark_match import PictureMatcher
    from analysis.navigate import Navigator
    from analysis.registration import MarkCarrier
    from analysis.scan_views import open_scan
    from analysis.skin_map import SHARP, vertex_skin
    from planner.visibility import RayScene

    earlier, later = open_scan(visits.earlier), open_scan(visits.later)
    mesh_a, mesh_b = earlier.mesh(), later.mesh()
    skin_a = vertex_skin(earlier, mesh_a)["status"]
    scene_a, scene_b = RayScene(mesh_a), RayScene(mesh_b)
    truth_a = np.asarray(visits.subject_earlier.vertices)
    truth_b = np.asarray(visits.subject_later.vertices)
    on_a, _ = scene_a.closest_faces(truth_a)
    on_a = np.asarray(on_a, dtype=float).reshape(-1, 3)
    # Skin the earlier scan holds sharp, and that the scanned surface really is (within 3 mm).
    near_vertex = _nearest(mesh_a, on_a)
    usable = np.flatnonzero((skin_a[near_vertex] == SHARP) & (np.linalg.norm(on_a - truth_a, axis=1) < 3.0)
                            & (truth_a[:, 2] > 150.0))
    chosen = np.random.default_rng(seed).choice(usable, size=min(count, len(usable)), replace=False)
    carrier = MarkCarrier(mesh_a, mesh_b)
    target, _ = scene_b.closest_faces(truth_b[chosen])
    target = np.asarray(target, dtype=float).reshape(-1, 3)
    by_shape = carrier.carry(on_a[chosen])
    carried = carrier.carry(on_a[chosen], PictureMatcher(Navigator(earlier, mesh_a), Navigator(later, mesh_b)))
    return {"error_mm": np.linalg.norm(carried.points_mm - target, axis=1),
            "shape_error_mm": np.linalg.norm(by_shape.points_mm - target, axis=1),
            "later_surface_mm": np.linalg.norm(target - truth_b[chosen], axis=1),
            "skin_error_mm": np.linalg.norm(carried.points_mm - truth_b[chosen], axis=1),
            "surface_gap_mm": carried.surface_gap_mm, "in_doubt": carried.in_doubt, "fit_rmse_mm": carried.fit_rmse_mm,
            "picture_score": carried.picture_score, "points": on_a[chosen], "fitness": carrier.whole.fitness,
            "rmse_mm": carrier.whole.rmse_mm}


def _nearest(mesh: Any, points: np.ndarray) -> np.ndarray:
    from scipy.spatial import cKDTree

    return cKDTree(np.asarray(mesh.vertices)).query(points)[1]
