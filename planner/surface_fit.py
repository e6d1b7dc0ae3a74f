"""The stored surface moved onto the depth frames it was fused from.

The TSDF fuses each frame decimated to about a voxel a pixel and reads a voxel's depth at the
pixel it falls in, so its surface is placed to a fraction of a voxel: on a simulated adult
(`tbp reconstruct`, 4 mm voxels) its vertices lie 0.31 mm from the skin (median; 90th percentile
0.87 mm), 0.12 mm outside it on average. Every frame measured the skin far more finely than
that. Here each vertex moves along its normal by the weighted mean of the distances from its
tangent plane of the points every frame measured around it: a frame's depth pixels within
``RADIUS_MM`` (at the vertex's depth) of the pixel the vertex's ray meets, back-projected, those
within ``BAND_MM`` of the plane (farther is another surface: an occluder in front, the skin
behind). A frame that sees the vertex's skin within ``MIN_COS`` of edge-on, or has fewer than
``MIN_PIXELS`` such pixels, says nothing; a vertex fewer than ``MIN_VIEWS`` frames measure stays
where the TSDF put it. Each frame weighs cos^2 of its incidence times its pixels over the fourth
power of its depth (a stereo camera's depth error grows with the square of the depth). The fit
runs ``PASSES`` times, the normals each time from the surface as the last pass left it; a
compiled loop over vertices and frames (planner/jit.py), under a second for a body's 130,000
vertices and 69 full-resolution frames.

"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import numpy as np

from planner.sweep import PosedDepth

#: Frames that must measure a vertex for it to move.
MIN_VIEWS = 3
#: A frame that sees the skin more obliquely than this (cos of the angle between its ray and the
#: surface's normal) does not place it.
MIN_COS = 0.3
#: A frame's skin further than this along the normal from the vertex is another surface (mm).
BAND_MM = 4.0
#: A vertex is measured by the depth pixels within this of its ray (mm at its depth): many pixels
#: (a few dozen at the rig camera's full resolution) average the depth noise out, and the skin
#: curves by a few hundredths of a millimetre over it.
RADIUS_MM = 2.0
#: Pixels a frame must have within RADIUS_MM of a vertex to measure it.
MIN_PIXELS = 3
#: Largest half side of a vertex's pixel window (px).
MAX_HALF_PX = 8
#: Passes of the fit (the normals are those of the surface as the last pass left it).
PASSES = 2
#: Depth the weights are relative to (mm; only their ratios matter).
REFERENCE_DEPTH_MM = 600.0


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) unit outward normals, area-weighted over the vertex's faces (zero where it has none)."""
    corners = vertices[faces]
    area = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, faces[:, k], area)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    out: np.ndarray = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
    return out


def normal_offsets(vertices: np.ndarray, normals: np.ndarray,
                   frames: Sequence[PosedDepth]) -> tuple[np.ndarray, np.ndarray]:
    """Per vertex (V,) the weighted mean distance (mm, along its outward normal (V, 3)) from the
    vertex (V, 3) mm to the skin the frames measured around it, and how many frames measured it."""
    total = np.zeros(len(vertices))
    weight = np.zeros(len(vertices))
    views = np.zeros(len(vertices), dtype=np.int64)
    points = np.ascontiguousarray(vertices, dtype=np.float64)
    outward = np.ascontiguousarray(normals, dtype=np.float64)
    settings = np.array([RADIUS_MM, BAND_MM, MIN_COS, MIN_PIXELS, REFERENCE_DEPTH_MM, MAX_HALF_PX])
    for frame in frames:
        k = frame.intrinsics
        camera = np.array([k[0, 0], k[1, 1], k[0, 2], k[1, 2]], dtype=np.float64)
        _kernel()(points, outward, np.ascontiguousarray(frame.depth), float(frame.depth_unit_mm), camera,
                  np.ascontiguousarray(frame.camera_to_world, dtype=np.float64), settings, total, weight, views)
    mean = np.divide(total, weight, out=np.zeros_like(total), where=weight > 0)
    return mean, views


def _accumulate(points, normals, depth, unit, camera, pose, settings,  # type: ignore[no-untyped-def]
                total, weight, views):
    """Add one frame's measurement of every vertex it sees squarely enough to total, weight and
    views (the loop of :func:`normal_offsets`): the mean distance from the vertex's tangent plane
    of the points of the depth pixels within RADIUS_MM (at the vertex's depth) of the pixel its
    ray meets, those within BAND_MM of the plane, weighted by cos^2 of the incidence, the pixels
    used and (reference depth / depth)^4."""
    radius, band, min_cos, min_pixels, reference, max_half = settings
    fx, fy, cx, cy = camera
    height, width = depth.shape
    for i in range(points.shape[0]):
        rx = points[i, 0] - pose[0, 3]
        ry = points[i, 1] - pose[1, 3]
        rz = points[i, 2] - pose[2, 3]
        x = rx * pose[0, 0] + ry * pose[1, 0] + rz * pose[2, 0]  # camera axes: the pose's columns
        y = rx * pose[0, 1] + ry * pose[1, 1] + rz * pose[2, 1]
        z = rx * pose[0, 2] + ry * pose[1, 2] + rz * pose[2, 2]
        if z <= 1.0:
            continue
        nx = normals[i, 0] * pose[0, 0] + normals[i, 1] * pose[1, 0] + normals[i, 2] * pose[2, 0]
        ny = normals[i, 0] * pose[0, 1] + normals[i, 1] * pose[1, 1] + normals[i, 2] * pose[2, 1]
        nz = normals[i, 0] * pose[0, 2] + normals[i, 1] * pose[1, 2] + normals[i, 2] * pose[2, 2]
        cos = -(x * nx + y * ny + z * nz) / math.sqrt(x * x + y * y + z * z)
        if cos < min_cos:
            continue
        u = int(round(fx * x / z + cx))  # pixel centres at integers
        v = int(round(fy * y / z + cy))
        half = min(int(math.ceil(radius * fx / z)), int(max_half))
        if u < -half or v < -half or u > width - 1 + half or v > height - 1 + half:
            continue
        offsets = 0.0
        used = 0
        for row in range(max(v - half, 0), min(v + half, height - 1) + 1):
            for col in range(max(u - half, 0), min(u + half, width - 1) + 1):
                if (row - v) ** 2 + (col - u) ** 2 > half * half:
                    continue
                d = depth[row, col] * unit
                if d <= 0.0:
                    continue
                dx = (col - cx) / fx * d - x
                dy = (row - cy) / fy * d - y
                dz = d - z
                along = dx * nx + dy * ny + dz * nz
                if abs(along) >= band:
                    continue
                offsets += along
                used += 1
        if used < min_pixels:
            continue
        w = cos * cos * used * (reference / z) ** 4
        total[i] += w * offsets / used
        weight[i] += w
        views[i] += 1


@functools.cache
def _kernel():  # type: ignore[no-untyped-def]
    """:func:`_accumulate` compiled (planner/jit.py)."""
    from planner.jit import jit

    return jit(_accumulate)  # type: ignore[no-untyped-call]


def warm_up() -> None:
    """Compile the fit's loop (or load it from numba's cache) now rather than in the first scan's
    stored surface, for the depth frames' 16-bit depth."""
    one = np.zeros((1, 3))
    _kernel()(one, one, np.zeros((1, 1), dtype=np.uint16), 1.0, np.ones(4), np.eye(4), np.ones(6), np.zeros(1),
              np.zeros(1), np.zeros(1, dtype=np.int64))


def fit_to_frames(vertices: np.ndarray, faces: np.ndarray, frames: Sequence[PosedDepth],
                  passes: int = PASSES) -> np.ndarray:
    """(V, 3) the surface's vertices (V, 3) mm moved along their normals onto the skin the
    frames measured (see the module docstring); faces (F, 3) as they are."""
    moved = np.asarray(vertices, dtype=np.float64).copy()
    for _ in range(passes):
        normals = vertex_normals(moved, faces)
        offset, views = normal_offsets(moved, normals, frames)
        moved += np.where(views >= MIN_VIEWS, offset, 0.0)[:, None] * normals
    return moved
