"""Area-uniform surface samples of a mesh with inward normals (the planner's point set P).

The focus cost integrates over the skin, so samples are drawn with probability proportional
to triangle area. Normals point INTO the body, as in the seed's cost function.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from planner.focus_errors import EmptyMesh


@dataclass(frozen=True)
class SurfaceSamples:
    """N surface samples.

    Attributes:
        points: (N, 3) float, mm.
        normals: (N, 3) float unit inward normals.
        face_index: (N,) int, the triangle each sample lies on (-1 when not from a mesh).
        area_mm2: total surface area the samples represent (mm^2).
    """

    points: np.ndarray
    normals: np.ndarray
    face_index: np.ndarray
    area_mm2: float

    def __len__(self) -> int:
        return len(self.points)

    @classmethod
    def from_arrays(cls, points: np.ndarray, inward_normals: np.ndarray) -> SurfaceSamples:
        """Samples from given points (N, 3) and inward normals (N, 3) (normalised here)."""
        points = np.asarray(points, dtype=float).reshape(-1, 3)
        normals = np.asarray(inward_normals, dtype=float).reshape(-1, 3)
        if len(points) != len(normals):
            raise ValueError(f"{len(points)} points but {len(normals)} normals")
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        if np.any(length == 0):
            raise ValueError("a normal has zero length")
        return cls(points, normals / length, np.full(len(points), -1), float("nan"))


def sample_surface(mesh: trimesh.Trimesh, count: int, *, seed: int = 0) -> SurfaceSamples:
    """``count`` area-uniform samples of ``mesh``'s surface, reproducible for a given seed.

    Samples come ordered by height (z). Raises EmptyMesh when the mesh has no faces or no area.
    """
    if count <= 0:
        raise ValueError(f"sample count must be positive, got {count}")
    vertices = np.asarray(mesh.vertices, dtype=float)
    corners = np.asarray(mesh.faces, dtype=np.int64)
    if len(corners) == 0:
        raise EmptyMesh("<mesh>", 0, 0.0)
    a = vertices[corners[:, 0]]
    ab, ac = vertices[corners[:, 1]] - a, vertices[corners[:, 2]] - a
    doubled = np.linalg.norm(np.cross(ab, ac), axis=1)  # twice each triangle's area
    total = float(doubled.sum()) / 2.0
    if not total > 0:
        raise EmptyMesh("<mesh>", len(corners), total)
    rng = np.random.default_rng(seed)
    cumulative = np.cumsum(doubled)
    faces = np.searchsorted(cumulative, rng.random(count) * cumulative[-1], side="right")
    faces = np.minimum(faces, len(corners) - 1)
    # Uniform barycentric coordinates: fold the unit square onto the triangle.
    uv = rng.random((count, 2))
    flip = uv.sum(axis=1) > 1.0
    uv[flip] = 1.0 - uv[flip]
    points = a[faces] + uv[:, :1] * ab[faces] + uv[:, 1:] * ac[faces]
    # Inward normal: minus the right-handed (outward, for a consistently wound skin) normal.
    normals = -np.cross(ab[faces], ac[faces]) / doubled[faces][:, None]
    # Ordered by height: each camera sees a band of heights, so the per-pose and per-point
    # passes of the planner then touch memory in long runs instead of at random.
    by_height = np.argsort(points[:, 2], kind="stable")
    points, normals, faces = points[by_height], normals[by_height], faces[by_height]
    return SurfaceSamples(points, normals, faces, total)
