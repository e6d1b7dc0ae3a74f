"""Space carving of the TSDF surface with the depth frames' free space.

Open3D's VoxelBlockGrid updates only voxels within the truncation band of each measured depth, so
the space a depth ray crossed far in front of its surface is never marked free; and where few frames
saw into a narrow gap between body parts (an arm and the torso, a hand and the thigh) the extraction
leaves a hole that the hole filling (``planner.tsdf.close_openings``) spans from one part to the
other. Both leave "webbing": surface bridging the gap, up to centimetres off the skin. :class:`FreeSpace` keeps each fused frame's depth
(decimated as fused) and answers whether a point lies where some frame saw through; :func:`carve`
drops the faces touching such points and the small pieces this cuts off.

A point is free in a frame when it projects inside the image, lies within the camera's range, and
every pixel of the :data:`NEIGHBOURHOOD_PX` square around its pixel measured a depth beyond it by
more than ``margin_mm`` plus :data:`SIGMAS` times the depth noise at the measured depth. The square
(a hole counts as no evidence) keeps the skin at a silhouette or seen at a grazing angle, whose
pixel may hold the background or a steep slope, from being carved; the margin covers the surface's
own placement error (a voxel).
"""

from __future__ import annotations

import functools

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from planner.rig import DepthCameraModel

#: Side of the pixel square (decimated pixels) that must all have measured beyond a point.
NEIGHBOURHOOD_PX = 3
#: Depth noise multiples added to the margin.
SIGMAS = 3.0
#: Faces with an edge longer than this many margins are also tested inside (the hole fill's fans
#: reach across gaps with their vertices on the skin either side).
LONG_EDGE_MARGINS = 2.0
#: Barycentric points tested inside a long face: its centroid and the points 2/3 of the way to each corner.
INNER_POINTS = np.array([[1 / 3, 1 / 3, 1 / 3], [2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6], [1 / 6, 1 / 6, 2 / 3]])
#: After carving, pieces with fewer than this share of the largest piece's faces are dropped.
MIN_PIECE_SHARE = 0.002


class FreeSpace:
    """The free space seen by a set of depth frames (each decimated as fused): about 150 kB a frame
    for the default camera and voxel size."""

    def __init__(self, model: DepthCameraModel, margin_mm: float) -> None:
        self.model = model
        self.margin_mm = margin_mm
        self._reach: list[np.ndarray] = []  # per frame (H, W) float32: the farthest depth still free
        self._projection: list[np.ndarray] = []  # per frame (3, 4): world point (homogeneous) -> (u z, v z, z)

    def __len__(self) -> int:
        return len(self._reach)

    def add(self, depth_mm: np.ndarray, intrinsics: np.ndarray, camera_to_world: np.ndarray) -> None:
        """One frame: (H, W) depth in mm (0 = no measurement), (3, 3) intrinsics, (4, 4) pose (OpenCV axes)."""
        shapes = (np.ndim(depth_mm), np.shape(intrinsics), np.shape(camera_to_world))
        if shapes[0] != 2 or shapes[1:] != ((3, 3), (4, 4)):
            raise ValueError(f"a frame needs (H, W) depth, (3, 3) intrinsics and a (4, 4) pose; got {np.shape(depth_mm)}, "
                             f"{shapes[1]}, {shapes[2]}")
        m = self.model
        depth = np.where((depth_mm >= m.min_range_mm) & (depth_mm <= m.max_range_mm), depth_mm, 0).astype(np.float32)
        nearest = ndimage.minimum_filter(depth, size=NEIGHBOURHOOD_PX, mode="constant", cval=0.0)
        noise = np.float32(SIGMAS * m.subpixel_px / (m.fx_px * m.baseline_mm))  # sigma = z^2 * subpixel / (fx b)
        reach = np.where(nearest > 0, nearest - np.float32(self.margin_mm) - noise * nearest * nearest, -np.inf)
        self._reach.append(reach.astype(np.float32))
        self._projection.append(np.asarray(intrinsics, dtype=float) @ np.linalg.inv(camera_to_world)[:3])

    def free(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: which of the (N, 3) points (mm, world) some frame saw through."""
        sizes = np.array([r.shape for r in self._reach], dtype=np.int64).reshape(-1, 2)
        offsets = np.concatenate([[0], np.cumsum(sizes[:, 0] * sizes[:, 1])])
        reach = np.concatenate([r.ravel() for r in self._reach]) if self._reach else np.zeros(0, np.float32)
        projections = np.array(self._projection, dtype=np.float64).reshape(-1, 3, 4)
        result: np.ndarray = _kernel()(np.ascontiguousarray(points, dtype=np.float64), projections, reach, offsets,
                                    sizes, float(self.model.min_range_mm), float(self.model.max_range_mm))
        return result


def _free_points(points, projections, reach, offsets, sizes, min_z, max_z):  # type: ignore[no-untyped-def]
    """(N,) bool: points (N, 3) some view sees through; view k: projection (3, 4), reach image
    sizes[k] = (H, W) flattened at reach[offsets[k]:]."""
    n = points.shape[0]
    result = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        x, y, zw = points[i, 0], points[i, 1], points[i, 2]
        for k in range(projections.shape[0]):
            p = projections[k]
            z = p[2, 0] * x + p[2, 1] * y + p[2, 2] * zw + p[2, 3]
            if z < min_z or z > max_z:
                continue
            u = np.floor((p[0, 0] * x + p[0, 1] * y + p[0, 2] * zw + p[0, 3]) / z + 0.5)  # pixel centres at integers
            v = np.floor((p[1, 0] * x + p[1, 1] * y + p[1, 2] * zw + p[1, 3]) / z + 0.5)
            h, w = sizes[k, 0], sizes[k, 1]
            if u < 0 or v < 0 or u >= w or v >= h:
                continue
            if z < reach[offsets[k] + int(v) * w + int(u)]:
                result[i] = True
                break
    return result


def warm_up(model: DepthCameraModel) -> None:
    """Compile the free-space test (or load it from numba's cache) now rather than in the first
    scan's carving, where compiling takes about a second."""
    space = FreeSpace(model, margin_mm=1.0)
    space.add(np.zeros((NEIGHBOURHOOD_PX, NEIGHBOURHOOD_PX), dtype=np.float32), np.eye(3), np.eye(4))
    space.free(np.zeros((1, 3)))


@functools.cache
def _kernel():  # type: ignore[no-untyped-def]
    """:func:`_free_points` compiled (numba's import takes most of a second: only where meshes are carved)."""
    from planner.jit import jit

    return jit(_free_points)  # type: ignore[no-untyped-call]


def carve(vertices: np.ndarray, faces: np.ndarray, space: FreeSpace) -> tuple[np.ndarray, np.ndarray]:
    """Drop the faces of (V, 3) vertices (mm) / (F, 3) faces that reach into ``space``'s free space
    (a vertex free, or for a long face an inner point), then the pieces left with fewer than
    :data:`MIN_PIECE_SHARE` of the largest piece's faces. Returns the vertices still used (in their
    order) and the kept faces (in their order), so a canonical mesh stays canonical."""
    if len(space) == 0 or len(faces) == 0:
        return vertices, faces
    drop = space.free(vertices)[faces].any(axis=1)
    corners = vertices[faces]
    edges = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max(axis=1)
    long = np.flatnonzero(~drop & (edges > LONG_EDGE_MARGINS * space.margin_mm))
    if len(long):
        inner = np.einsum("pk,fkc->fpc", INNER_POINTS, corners[long]).reshape(-1, 3)
        drop[long] = space.free(inner).reshape(len(long), len(INNER_POINTS)).any(axis=1)
    if not drop.any():
        return vertices, faces
    kept = _without_small_pieces(faces[~drop], len(vertices))
    used = np.flatnonzero(np.bincount(kept.ravel(), minlength=len(vertices)))
    remap = np.full(len(vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return vertices[used], remap[kept]


def _without_small_pieces(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """(F, 3) faces without the edge-connected pieces smaller than MIN_PIECE_SHARE of the largest."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(edges), dtype=np.int8), (edges[:, 0], edges[:, 1])), shape=(n_vertices,) * 2)
    _, labels = connected_components(graph, directed=False)
    face_labels = labels[faces[:, 0]]
    sizes = np.bincount(face_labels)
    kept: np.ndarray = faces[sizes[face_labels] >= MIN_PIECE_SHARE * sizes.max()]
    return kept

