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
        weight: (N,) float, the skin each sample stands for in units of one area-uniform sample
            (None: area-uniform, 1 each; planner/importance.py gives denser samples less).
    """

    points: np.ndarray
    normals: np.ndarray
    face_index: np.ndarray
    area_mm2: float
    weight: np.ndarray | None = None

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


@dataclass(frozen=True)
class Triangles:
    """A mesh's triangles as vectors, computed once for sampling and the orientation check.

    Attributes:
        a: (F, 3) float, each triangle's first corner, mm.
        ab, ac: (F, 3) float, its edges from that corner, mm.
        cross: (F, 3) float, ab x ac: twice the area long, along the right-handed normal.
    """

    a: np.ndarray
    ab: np.ndarray
    ac: np.ndarray
    cross: np.ndarray

    @classmethod
    def of(cls, mesh: trimesh.Trimesh) -> Triangles:
        vertices = np.asarray(mesh.vertices, dtype=float)
        corners = np.asarray(mesh.faces, dtype=np.int64)
        a = vertices[corners[:, 0]]
        ab, ac = vertices[corners[:, 1]] - a, vertices[corners[:, 2]] - a
        cross = np.empty_like(a)  # np.cross's formula, without its temporaries
        np.subtract(ab[:, 1] * ac[:, 2], ab[:, 2] * ac[:, 1], out=cross[:, 0])
        np.subtract(ab[:, 2] * ac[:, 0], ab[:, 0] * ac[:, 2], out=cross[:, 1])
        np.subtract(ab[:, 0] * ac[:, 1], ab[:, 1] * ac[:, 0], out=cross[:, 2])
        return cls(a, ab, ac, cross)

    def __len__(self) -> int:
        return len(self.a)

    @property
    def doubled_areas(self) -> np.ndarray:
        """(F,) twice each triangle's area, mm^2."""
        c = self.cross
        result: np.ndarray = np.sqrt(c[:, 0] * c[:, 0] + c[:, 1] * c[:, 1] + c[:, 2] * c[:, 2])
        return result

    @property
    def signed_volume_mm3(self) -> float:
        """Signed enclosed volume: negative when the triangles wind inward (normals into the body).
        Each triangle adds a . (b x c) / 6, and a . (b x c) = a . (ab x ac)."""
        return float(np.einsum("ij,ij->", self.a, self.cross)) / 6.0


def sample_surface(
    mesh: trimesh.Trimesh, count: int, *, seed: int = 0, triangles: Triangles | None = None,
    faces: np.ndarray | None = None,
) -> SurfaceSamples:
    """``count`` area-uniform samples of ``mesh``'s surface, reproducible for a given seed.

    Samples come ordered by height (z). Raises EmptyMesh when the mesh has no faces or no area.
    ``triangles``: the mesh's :class:`Triangles`, when the caller has them already. ``faces``:
    (F,) bool, sample only these triangles (area_mm2 is then theirs).
    """
    if count <= 0:
        raise ValueError(f"sample count must be positive, got {count}")
    if len(mesh.faces) == 0:
        raise EmptyMesh("<mesh>", 0, 0.0)
    t = Triangles.of(mesh) if triangles is None else triangles
    a, ab, ac = t.a, t.ab, t.ac
    doubled = t.doubled_areas
    if faces is not None:
        doubled = np.where(faces, doubled, 0.0)
    total = float(doubled.sum()) / 2.0
    if not total > 0:
        raise EmptyMesh("<mesh>", len(t), total)
    rng = np.random.default_rng(seed)
    cumulative = np.cumsum(doubled)
    faces = np.searchsorted(cumulative, rng.random(count) * cumulative[-1], side="right")
    faces = np.minimum(faces, len(t) - 1)
    # Uniform barycentric coordinates: fold the unit square onto the triangle.
    uv = rng.random((count, 2))
    flip = uv.sum(axis=1) > 1.0
    uv[flip] = 1.0 - uv[flip]
    points = a[faces] + uv[:, :1] * ab[faces] + uv[:, 1:] * ac[faces]
    # Inward normal: minus the right-handed (outward, for a consistently wound skin) normal.
    normals = -t.cross[faces] / doubled[faces][:, None]
    # Ordered by height: each camera sees a band of heights, so the per-pose and per-point
    # passes of the planner then touch memory in long runs instead of at random.
    by_height = np.argsort(points[:, 2], kind="stable")
    points, normals, faces = points[by_height], normals[by_height], faces[by_height]
    return SurfaceSamples(points, normals, faces, total)
