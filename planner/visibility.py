"""Which camera poses see which surface samples: frustum, facing and occlusion tests.

A sample is visible from a pose when it lies inside the image frustum (portrait: the image
width spans the horizontal field of view), its surface faces the camera, and the segment from
the camera centre to it does not cross the mesh. Only visible (pose, point) pairs are kept, in
a sparse table grouped by pose: 336 poses x 100,000 points would be 270 MB per dense float64
array, while a pose sees about a tenth of the body.

Occlusion is ray casting against the mesh. Both Open3D's ``RaycastingScene`` and Embree via
``embreex`` are wrapped; Open3D is the default because it measured faster on this work (see
``tests/bench/planner.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import trimesh

from planner.poses import Poses
from planner.rig import Optics
from planner.sampling import SurfaceSamples

#: Occlusion rays stop this far (mm) before the sample, so its own triangle never hides it.
SURFACE_EPSILON_MM = 0.5
#: Rays per occlusion batch: bounds the temporary arrays (about 40 bytes a ray).
RAY_BATCH = 1 << 20
BACKENDS = ("open3d", "embree")


class RayScene:
    """A triangle mesh prepared for ray queries (Open3D or Embree backend)."""

    def __init__(self, mesh: trimesh.Trimesh, backend: str = "open3d") -> None:
        if backend not in BACKENDS:
            raise ValueError(f"unknown ray backend {backend!r}; allowed: {', '.join(BACKENDS)}")
        self.backend = backend
        self._mesh = mesh
        vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float32)
        faces = np.ascontiguousarray(mesh.faces, dtype=np.uint32)
        self._triangles = (vertices, faces)
        # Open3D's RaycastingScene or embreex's EmbreeScene: both libraries are untyped here
        self._open3d: Any = None
        self._scene: Any
        if backend == "open3d":
            self._scene = self._open3d_scene()
        else:
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh

            self._scene = rtcore_scene.EmbreeScene()
            TriangleMesh(self._scene, np.ascontiguousarray(vertices[faces]))

    @staticmethod
    def import_backend(backend: str) -> None:
        """Import a backend's module now (Open3D takes a second or two on first import)."""
        if backend == "open3d":
            import open3d  # noqa: F401
        else:
            import embreex  # noqa: F401

    def _open3d_scene(self) -> Any:
        if self._open3d is None:
            import open3d as o3d

            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(*(o3d.core.Tensor(a) for a in self._triangles))
            self._open3d = scene
        return self._open3d

    @property
    def face_normals(self) -> np.ndarray:
        """(F, 3) float unit outward normals of the mesh's triangles."""
        return np.asarray(self._mesh.face_normals, dtype=float)

    def closest_faces(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For (Q, 3) points: the closest surface points (Q, 3) and their triangle indices (Q,)."""
        import open3d as o3d

        query = o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3))
        found = self._open3d_scene().compute_closest_points(query)
        return found["points"].numpy().astype(float), found["primitive_ids"].numpy().astype(np.int64)

    def first_hits(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """(K,) distance (mm) along each ray (K, 3) origins, unit directions to the first
        surface it meets; inf where it meets none."""
        origins = np.asarray(origins, dtype=np.float32).reshape(-1, 3)
        directions = np.asarray(directions, dtype=np.float32).reshape(-1, 3)
        if self.backend == "open3d":
            import open3d as o3d

            rays = np.concatenate([origins, directions], axis=1)
            result: np.ndarray = self._scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(float)
            return result
        hit = self._scene.run(origins, directions, output=1)
        return np.where(np.asarray(hit["geomID"]) != -1, np.asarray(hit["tfar"], dtype=float), np.inf)

    def occluded(self, origins: np.ndarray, targets: np.ndarray, epsilon_mm: float) -> np.ndarray:
        """(K,) bool: the mesh crosses the segment origin -> target, ignoring its last epsilon_mm.

        origins, targets: (K, 3) float, mm.
        """
        out = np.empty(len(origins), dtype=bool)
        for start in range(0, len(origins), RAY_BATCH):
            stop = start + RAY_BATCH
            o = np.asarray(origins[start:stop], dtype=np.float32)
            d = np.asarray(targets[start:stop], dtype=np.float32) - o
            length = np.sqrt(np.einsum("ij,ij->i", d, d))
            reach = np.maximum(length - np.float32(epsilon_mm), np.float32(0.0))
            if self.backend == "open3d":
                import open3d as o3d

                # Scale the direction so t = 1 lands epsilon before the target.
                rays = np.empty((len(o), 6), dtype=np.float32)
                rays[:, :3] = o
                np.multiply(d, (reach / np.maximum(length, np.float32(1e-12)))[:, None], out=rays[:, 3:])
                hit = self._scene.test_occlusions(o3d.core.Tensor(rays), tnear=0.0, tfar=1.0)
                out[start:stop] = hit.numpy().astype(bool)
            else:
                unit = d / np.maximum(length, np.float32(1e-12))[:, None]
                hit = self._scene.run(o, unit, dists=reach, query="OCCLUDED")
                out[start:stop] = np.asarray(hit) != -1
        return out

    def first_hit(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """(K,) float distance along each unit direction to the first surface hit (inf: miss)."""
        o = np.ascontiguousarray(origins, dtype=np.float32)
        d = np.ascontiguousarray(directions, dtype=np.float32)
        if self.backend == "open3d":
            import open3d as o3d

            hits = self._scene.cast_rays(o3d.core.Tensor(np.hstack([o, d])))
            result: np.ndarray = hits["t_hit"].numpy().astype(float)
            return result
        t = np.asarray(self._scene.run(o, d, query="DISTANCE"), dtype=float)
        return np.where(t >= 1e37, np.inf, t)


@dataclass(frozen=True)
class Visibility:
    """Sparse visible (pose, point) pairs, sorted by pose.

    Attributes:
        n_poses, n_points: P and N of the problem.
        pose: (M,) int32 pose index of each pair.
        point: (M,) int32 sample index of each pair.
        depth: (M,) float, mm along the pose's optical axis (the focus-relevant depth z).
        off_axis: (M,) float, mm from the optical axis (distance perpendicular to n_c).
        facing: (M,) float, <n_c, n_p> with the inward normal (1 = surface square to the axis).
        pose_ptr: (P + 1,) int64, pairs of pose c are pose_ptr[c]:pose_ptr[c + 1].
    """

    n_poses: int
    n_points: int
    pose: np.ndarray
    point: np.ndarray
    depth: np.ndarray
    off_axis: np.ndarray
    facing: np.ndarray
    pose_ptr: np.ndarray

    def __len__(self) -> int:
        return len(self.pose)

    @property
    def visible_points(self) -> np.ndarray:
        """(N,) bool: seen by at least one pose."""
        seen = np.zeros(self.n_points, dtype=bool)
        seen[self.point] = True
        return seen

    def pairs_of(self, pose: int) -> slice:
        """The slice of the pair arrays that belongs to ``pose``."""
        return slice(int(self.pose_ptr[pose]), int(self.pose_ptr[pose + 1]))


def group_pointers(keys: np.ndarray, n_groups: int) -> np.ndarray:
    """(n_groups + 1,) int64 offsets of each group in ``keys`` sorted by group (0 <= key < n_groups):
    group g is [ptr[g], ptr[g + 1])."""
    ptr = np.zeros(n_groups + 1, dtype=np.int64)
    np.cumsum(np.bincount(keys, minlength=n_groups), out=ptr[1:])
    return ptr


def frustum_tangents(optics: Optics) -> tuple[float, float]:
    """tan of the half fields of view: (across the image width, across its height)."""
    tan_w = math.tan(math.radians(optics.hfov_deg) / 2.0)
    return tan_w, tan_w * optics.image_height_px / optics.image_width_px


#: Poses per block of the frustum test: bounds the (3 x block, N) float32 temporaries.
POSE_BLOCK = 16


def _height_windows(poses: Poses, points: np.ndarray, tan_w: float, tan_h: float) -> np.ndarray:
    """(P, 2) float: a z range outside which no point can be in each pose's frustum.

    Every frustum ray lies within the circumscribed cone of half-angle alpha around the optical
    axis, so its elevation is within alpha of the axis' elevation; a point's height differs from
    the camera's by at most its horizontal distance times the tangent of that elevation.
    """
    alpha = math.atan(math.hypot(tan_w, tan_h))
    elevation = np.arcsin(np.clip(poses.forward[:, 2], -1.0, 1.0))
    reach = np.hypot(poses.centres[:, 0], poses.centres[:, 1]) + np.hypot(points[:, 0], points[:, 1]).max()
    limit = math.radians(89.0)
    up, down = elevation + alpha, elevation - alpha
    with np.errstate(over="ignore", invalid="ignore"):
        high = np.where(up < limit, poses.centres[:, 2] + reach * np.maximum(np.tan(up), 0.0), np.inf)
        low = np.where(down > -limit, poses.centres[:, 2] + reach * np.minimum(np.tan(down), 0.0), -np.inf)
    return np.stack([low, high], axis=1)


def _candidates(
    poses: Poses, samples: SurfaceSamples, optics: Optics
) -> tuple[np.ndarray, ...]:
    """In-frustum, front-facing pairs of every pose (grouped by block), before the occlusion test.

    Points are sorted by height and each block of poses with similar height windows tests only
    the points inside its window (about half the body per camera). Returns pose, point, depth,
    off_axis, facing arrays as in :class:`Visibility`.
    """
    tan_w, tan_h = frustum_tangents(optics)
    by_height = np.argsort(samples.points[:, 2], kind="stable")
    heights = samples.points[by_height, 2]
    pts_t = np.ascontiguousarray(samples.points[by_height].T, dtype=np.float32)  # (3, N)
    nrm_t = np.ascontiguousarray(samples.normals[by_height].T, dtype=np.float32)  # (3, N)
    point_dot_normal = np.einsum("ij,ij->j", pts_t, nrm_t)  # (N,) <p, n_p>
    windows = _height_windows(poses, samples.points, tan_w, tan_h)
    first = np.searchsorted(heights, windows[:, 0], side="left")
    last = np.searchsorted(heights, windows[:, 1], side="right")
    pose_order = np.lexsort((last, first))
    parts: list[tuple[np.ndarray, ...]] = []
    for b in range(0, len(poses), POSE_BLOCK):
        block = pose_order[b : b + POSE_BLOCK]
        k = len(block)
        lo, hi = int(first[block].min()), int(last[block].max())
        if hi <= lo:
            continue
        n = hi - lo
        # Rows: right / tan_w, down / tan_h and forward of every pose in the block, so the frustum
        # test is |x'| <= z and |y'| <= z.
        rows = np.concatenate(
            [poses.right[block] / tan_w, poses.down[block] / tan_h, poses.forward[block]]
        ).astype(np.float32)
        cam = (rows @ pts_t[:, lo:hi]).reshape(3, k, n)
        cam -= np.einsum("akj,kj->ak", rows.reshape(3, k, 3), poses.centres[block]).astype(np.float32)[:, :, None]
        x, y, z = cam
        inside = np.abs(x) <= z
        inside &= np.abs(y) <= z
        # Front-facing: <p - p_c, n_p> > 0 with the inward normal n_p.
        inside &= point_dot_normal[lo:hi] > poses.centres[block].astype(np.float32) @ nrm_t[:, lo:hi]
        flat = np.flatnonzero(inside)
        which, local = np.divmod(flat, n)
        facing = (poses.forward[block].astype(np.float32) @ nrm_t[:, lo:hi]).ravel()[flat]
        parts.append(
            (
                block[which].astype(np.int16 if len(poses) < 32768 else np.int32),
                by_height[local + lo].astype(np.int32),
                z.ravel()[flat],
                np.hypot(tan_w * x.ravel()[flat], tan_h * y.ravel()[flat]),
                facing,
            )
        )
    if not parts:
        return (np.zeros(0, np.int16), np.zeros(0, np.int32), *(np.zeros(0, np.float32),) * 3)
    return tuple(np.concatenate(column) for column in zip(*parts))


def _candidates_among(
    poses: Poses, samples: SurfaceSamples, optics: Optics, pose: np.ndarray, point: np.ndarray
) -> tuple[np.ndarray, ...]:
    """:func:`_candidates` of only the given (pose (K,), point (K,)) pairs: each pose's frustum
    and facing test on its own points."""
    pose, point = np.asarray(pose, dtype=np.int64), np.asarray(point, dtype=np.int64)
    order = np.argsort(pose, kind="stable")
    ptr = group_pointers(pose[order], len(poses))
    parts: list[tuple[np.ndarray, ...]] = []
    for p in np.flatnonzero(np.diff(ptr)):
        mine = point[order[ptr[p]:ptr[p + 1]]]
        one = Poses(*(np.asarray(a)[[p]] for a in (poses.centres, poses.forward, poses.right, poses.down,
                                                   poses.angle_index, poses.camera_index)))
        found = _candidates(one, SurfaceSamples(samples.points[mine], samples.normals[mine],
                                                samples.face_index[mine], samples.area_mm2), optics)
        if len(found[0]):
            parts.append((np.full(len(found[0]), p, dtype=np.int32), mine[found[1]].astype(np.int32), *found[2:]))
    if not parts:
        return (np.zeros(0, np.int32), np.zeros(0, np.int32), *(np.zeros(0, np.float32),) * 3)
    return tuple(np.concatenate(column) for column in zip(*parts))


def visible_pairs(
    scene: RayScene,
    poses: Poses,
    samples: SurfaceSamples,
    optics: Optics,
    *,
    epsilon_mm: float = SURFACE_EPSILON_MM,
    among: tuple[np.ndarray, np.ndarray] | None = None,
) -> Visibility:
    """All visible (pose, sample) pairs of ``samples`` on the mesh held by ``scene``; among:
    (pose (K,), sample (K,)) the only pairs to test (default: every pose with every sample)."""
    if among is None:
        pose, point, depth, off_axis, facing = _candidates(poses, samples, optics)
    else:
        pose, point, depth, off_axis, facing = _candidates_among(poses, samples, optics, *among)
    centres = poses.centres.astype(np.float32)
    points = samples.points.astype(np.float32)
    clear = np.empty(len(pose), dtype=bool)
    for start in range(0, len(pose), RAY_BATCH):
        batch = slice(start, start + RAY_BATCH)
        clear[batch] = ~scene.occluded(centres[pose[batch]], points[point[batch]], epsilon_mm)
    keep = np.flatnonzero(clear)
    keep = keep[np.argsort(pose[keep], kind="stable")]  # group by pose (16-bit keys: radix sort)
    pose, point = pose[keep].astype(np.int32), point[keep]
    return Visibility(
        n_poses=len(poses),
        n_points=len(samples),
        pose=pose,
        point=point,
        depth=depth[keep].astype(float),
        off_axis=off_axis[keep].astype(float),
        facing=facing[keep].astype(float),
        pose_ptr=group_pointers(pose, len(poses)),
    )
