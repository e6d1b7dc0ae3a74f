"""Shape-estimate quality: Chamfer distances both ways and surface coverage, in mm.

Distances are exact point-to-triangle distances (Open3D ``RaycastingScene.compute_distance``) from
area-uniform samples of one mesh to the other mesh.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import trimesh

#: Surface samples per mesh: enough for 0.1 mm stable means on a body.
DEFAULT_SAMPLES = 50_000
#: Coverage thresholds (mm).
COVERAGE_MM = (5.0, 10.0)


@dataclass(frozen=True)
class ShapeMetrics:
    """Chamfer true->estimate (how much of the body the estimate misses or misplaces) and back, mm;
    the share of the true surface within 5 / 10 mm of the estimate (coverage); the share of the
    estimate within 5 mm of the true surface and its area more than 10 mm off it (cm^2: surface
    that is not skin, such as webbing bridging two body parts)."""

    true_to_estimate_mean_mm: float
    true_to_estimate_p95_mm: float
    estimate_to_true_mean_mm: float
    estimate_to_true_p95_mm: float
    coverage_5mm: float
    coverage_10mm: float
    estimate_within_5mm: float
    estimate_off_10mm_cm2: float

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def surface_distance(points: np.ndarray, mesh: trimesh.Trimesh) -> np.ndarray:
    """(N,) float unsigned distance (mm) from (N, 3) points to the mesh surface."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
        o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)),
    )
    return scene.compute_distance(o3d.core.Tensor(np.asarray(points, dtype=np.float32))).numpy().astype(float)


def sample_surface(mesh: trimesh.Trimesh, count: int, seed: int) -> np.ndarray:
    """(count, 3) area-uniform surface samples, seeded."""
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return np.asarray(points)


def shape_metrics(
    true_mesh: trimesh.Trimesh, estimate: trimesh.Trimesh, *, samples: int = DEFAULT_SAMPLES, seed: int = 0
) -> ShapeMetrics:
    """Chamfer (mean, 95th percentile) both ways, the share of the true surface within 5 / 10 mm of
    the estimate and of the estimate within 5 / beyond 10 mm of the true surface."""
    to_estimate = surface_distance(sample_surface(true_mesh, samples, seed), estimate)
    to_true = surface_distance(sample_surface(estimate, samples, seed + 1), true_mesh)
    return ShapeMetrics(
        true_to_estimate_mean_mm=float(to_estimate.mean()),
        true_to_estimate_p95_mm=float(np.percentile(to_estimate, 95)),
        estimate_to_true_mean_mm=float(to_true.mean()),
        estimate_to_true_p95_mm=float(np.percentile(to_true, 95)),
        coverage_5mm=float(np.mean(to_estimate <= COVERAGE_MM[0])),
        coverage_10mm=float(np.mean(to_estimate <= COVERAGE_MM[1])),
        estimate_within_5mm=float(np.mean(to_true <= COVERAGE_MM[0])),
        estimate_off_10mm_cm2=float(np.mean(to_true > COVERAGE_MM[1]) * estimate.area / 100.0),
    )
