"""The cost of each texel's candidate images, in one compiled pass (numba, planner/jit.py).

For every point and every available candidate pose of its triangle: the frustum and facing tests
of planner.visibility and the cost of planner.cost (area term, off-axis term, focus term), the
same formulas (tests/test_candidate_costs.py holds the two equal), with each three-term dot
product summed in the order NumPy's einsum sums it. One pass over the pairs with no temporary
arrays: the texture's view choice tests about 50 M pairs at its largest, and in NumPy it spent
most of its time writing and reading the pairs' intermediate arrays (a block's two threads then
wait on memory, not on arithmetic).
Occlusion is not tested here (analysis/texel_views.py, which textures the body, casts its rays)."""

from __future__ import annotations

import functools
import math
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from planner.poses import Poses
    from planner.rig import Rig


def candidate_costs(rig: Rig, poses: Poses, focus_mm: np.ndarray, points: np.ndarray, normals: np.ndarray,
                    candidates: Any, face: np.ndarray) -> tuple[np.ndarray, ...]:
    """The pairs of points (Q, 3) mm, inward normals (Q, 3), with the candidate poses of their
    triangles face (Q,) (candidates: (F, P) CSR, sorted indices) whose image is available (focus
    (P,) mm finite), that the camera's frustum holds and whose point faces it, grouped by point,
    poses ascending: point (M,) int64, pose (M,) int64, cost (M,), sharp (M,) bool and the point
    in the camera's frame x, y, z (M,) mm (z the depth)."""
    from planner.visibility import frustum_tangents

    optics, cost = rig.optics, rig.cost
    tan_w, tan_h = frustum_tangents(optics)
    begin = candidates.indptr[face].astype(np.int64)
    end = candidates.indptr[face + 1].astype(np.int64)
    focus = np.asarray(focus_mm, dtype=np.float64)
    frames = np.ascontiguousarray(np.stack([poses.centres, poses.right, poses.down, poses.forward], axis=1),
                                  dtype=np.float64)  # (P, 4, 3)
    settings = np.array([tan_w, tan_h, cost.w_area, cost.w_axis, cost.w_focus, cost.eps_area,
                         cost.axis_deviation_mm, optics.hyperfocal_mm, optics.focal_length_mm], dtype=np.float64)
    out_point = np.empty(int((end - begin).sum()), dtype=np.int64)
    out_pose = np.empty_like(out_point)
    out = np.empty((4, len(out_point)), dtype=np.float64)  # cost, x, y, z
    sharp = np.empty(len(out_point), dtype=np.bool_)
    n = _kernel()(np.ascontiguousarray(points, dtype=np.float64), np.ascontiguousarray(normals, dtype=np.float64),
                  begin, end, candidates.indices, focus, frames, settings,
                  out_point, out_pose, out, sharp)
    return out_point[:n], out_pose[:n], out[0, :n], sharp[:n], out[1, :n], out[2, :n], out[3, :n]


def _pairs(points, normals, begin, end, indices, focus, frames, settings,  # type: ignore[no-untyped-def]
           out_point, out_pose, out, sharp):
    """Fill the outputs with the kept pairs; returns how many (the loop of :func:`candidate_costs`)."""
    tan_w, tan_h, w_area, w_axis, w_focus, eps_area, axis_mm, h, f = settings
    n = 0
    for i in range(points.shape[0]):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        for k in range(begin[i], end[i]):
            p = indices[k]
            s = focus[p]
            if not math.isfinite(s):
                continue
            rx, ry, rz = px - frames[p, 0, 0], py - frames[p, 0, 1], pz - frames[p, 0, 2]
            # three-term dot products summed as NumPy's einsum sums them: (first + last) + middle
            x = (rx * frames[p, 1, 0] + rz * frames[p, 1, 2]) + ry * frames[p, 1, 1]
            y = (rx * frames[p, 2, 0] + rz * frames[p, 2, 2]) + ry * frames[p, 2, 1]
            z = (rx * frames[p, 3, 0] + rz * frames[p, 3, 2]) + ry * frames[p, 3, 1]
            if not (abs(x) <= tan_w * z and abs(y) <= tan_h * z and (rx * nx + rz * nz) + ry * ny > 0):
                continue
            facing = (frames[p, 3, 0] * nx + frames[p, 3, 2] * nz) + frames[p, 3, 1] * ny
            area = min(eps_area * z**2 / facing, 1.0) if facing > 0 else 1.0
            axis = min(math.hypot(x, y) / axis_mm, 1.0)
            lo = z * h / (h - f + z)
            hi = z * (h - 2 * f) / (h - f - z) if z < h - f else math.inf
            in_focus = lo <= s and s <= hi
            total = w_area * area + w_axis * axis
            if not in_focus:
                total += w_focus
            out_point[n] = i
            out_pose[n] = p
            out[0, n] = total
            out[1, n] = x
            out[2, n] = y
            out[3, n] = z
            sharp[n] = in_focus
            n += 1
    return n


@functools.cache
def _kernel():  # type: ignore[no-untyped-def]
    """:func:`_pairs` compiled (numba's import takes most of a second: only where bodies are textured)."""
    from planner.jit import jit

    return jit(_pairs)  # type: ignore[no-untyped-call]


def warm_up() -> None:
    """Compile the pass (or load it from numba's cache) now rather than in the first texture, for
    the CSR's 32-bit pose indices SciPy gives a texture's candidates."""
    one = np.zeros((1, 3))
    _kernel()(one, one, np.zeros(1, np.int64), np.zeros(1, np.int64), np.zeros(0, np.int32), np.zeros(0),
              np.zeros((0, 4, 3)), np.zeros(9), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((4, 0)),
              np.zeros(0, np.bool_))
