"""Image navigation: which capture shows a chosen skin point best, and where in that image.

A by-product of the focus cost (seed, "Image Navigation"): under a focus plan, a surface point
is best imaged by the pose of lowest cost, which accounts for sharpness as well as projected
area and distance from the optical axis. Pixels are in the portrait image (width across the
rotation, origin top-left, u right, v down).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planner.cost import CostTable, cost_table
from planner.poses import Poses
from planner.rig import Rig
from planner.sampling import SurfaceSamples
from planner.visibility import RayScene, visible_pairs


@dataclass(frozen=True)
class View:
    """One capture that sees the point: pose (angle-major index), its cost, the pixel (u, v)."""

    pose: int
    camera_index: int
    angle_index: int
    angle_deg: float
    cost: float
    in_focus: bool
    depth_mm: float
    u_px: float
    v_px: float


def pixel_of(poses: Poses, pose: np.ndarray, points: np.ndarray, rig: Rig) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) pixel coordinates (K,) of points (K, 3) in the images of poses (K,) (pinhole)."""
    optics = rig.optics
    rel = points - poses.centres[pose]
    z = np.einsum("ij,ij->i", rel, poses.forward[pose])
    f = optics.focal_length_px
    u = f * np.einsum("ij,ij->i", rel, poses.right[pose]) / z + optics.image_width_px / 2.0
    v = f * np.einsum("ij,ij->i", rel, poses.down[pose]) / z + optics.image_height_px / 2.0
    return u, v


def view_costs(
    scene: RayScene, rig: Rig, poses: Poses, focus_mm: np.ndarray, points: np.ndarray, normals: np.ndarray,
    *, among: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[CostTable, np.ndarray, np.ndarray]:
    """Every pose that sees each point (Q, 3) mm with inward normals (Q, 3): the cost table of
    the visible pairs, each pair's cost (M,) under the focus (P,) mm and whether the point is in
    its depth of field (M,). The one ranking of images for a skin point: the lowest cost is the
    best image (navigation, the textured body). among: (pose, point) the only pairs to consider."""
    samples = SurfaceSamples.from_arrays(points, normals)
    table = cost_table(visible_pairs(scene, poses, samples, rig.optics, among=among), rig.cost, rig.optics)
    return table, table.pair_cost(focus_mm), table.pair_in_focus(focus_mm)


def find_views(
    scene: RayScene,
    rig: Rig,
    poses: Poses,
    focus_mm: np.ndarray,
    points: np.ndarray,
    normals: np.ndarray | None = None,
    *,
    limit: int = 5,
    angles_deg: np.ndarray | None = None,
) -> list[list[View]]:
    """For each query point (Q, 3) mm on the mesh: up to ``limit`` views, best (lowest cost) first.

    normals: (Q, 3) inward normals; by default those of the closest mesh triangle. A point no
    pose sees gets an empty list.
    """
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    if normals is None:
        _, faces = scene.closest_faces(points)
        normals = -scene.face_normals[faces]
    table, cost, in_focus = view_costs(scene, rig, poses, focus_mm, points, normals)
    vis = table.vis
    u, v = pixel_of(poses, vis.pose, points[vis.point], rig)
    angles = rig.capture.angles_deg if angles_deg is None else np.asarray(angles_deg, dtype=float)
    order = np.lexsort((vis.pose, cost, vis.point))
    views: list[list[View]] = [[] for _ in range(len(points))]
    for i in order:
        mine = views[vis.point[i]]
        if len(mine) >= limit:
            continue
        pose = int(vis.pose[i])
        angle_index = int(poses.angle_index[pose])
        mine.append(
            View(
                pose=pose,
                camera_index=int(poses.camera_index[pose]),
                angle_index=angle_index,
                angle_deg=float(angles[angle_index]) if angle_index >= 0 else float("nan"),
                cost=float(cost[i]),
                in_focus=bool(in_focus[i]),
                depth_mm=float(vis.depth[i]),
                u_px=float(u[i]),
                v_px=float(v[i]),
            )
        )
    return views


def best_poses(table: CostTable, focus_mm: np.ndarray) -> np.ndarray:
    """(N,) int: the pose that images each planning sample best under the plan (-1: unseen)."""
    best, _ = table.assignment(focus_mm)
    return np.where(best >= 0, table.vis.pose[np.maximum(best, 0)], -1)
