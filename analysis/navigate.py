"""Image navigation: which captured image shows a given spot on the body best, and where."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from analysis.scan_views import open_scan
from daemon.manifest import ImageStatus


class NavigationError(ValueError):
    """The query does not name a point on the scanned body."""


def _parse_point(text: str) -> np.ndarray:
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 3 or not np.all(np.isfinite(values)):
        raise NavigationError(f"--point {text!r}: expected X,Y,Z in mm, three numbers")
    return np.array(values)


def navigate(
    scan_dir: Path | str,
    *,
    point: str | np.ndarray | None = None,
    vertex: int | None = None,
    count: int = 5,
    rig_path: Path | str | None = None,
) -> dict[str, Any]:
    """The best captured images of a skin point (snapped to the scan's mesh), best first.

    Only verified images whose file is still on disk count (``missing_files`` names verified
    ones that are gone); poses sit at their images' actual exposure angles.
    """
    from planner.navigation import find_views
    from planner.visibility import RayScene

    scan = open_scan(scan_dir, rig_path)
    mesh = scan.mesh()
    if vertex is not None:
        if not 0 <= vertex < len(mesh.vertices):
            raise NavigationError(f"--vertex {vertex}: the scan's mesh has vertices 0..{len(mesh.vertices) - 1}")
        query = np.asarray(mesh.vertices[vertex], dtype=float)
    elif point is not None:
        query = _parse_point(point) if isinstance(point, str) else np.asarray(point, dtype=float)
    else:
        raise NavigationError("give a point (X,Y,Z mm) or a mesh vertex")
    scene = RayScene(mesh)
    closest, faces = scene.closest_faces(query[None, :])
    on_skin = np.asarray(closest, dtype=float).reshape(-1, 3)[0]
    distance = float(np.linalg.norm(on_skin - query))
    focus = scan.captured_focus_mm()
    missing = []
    for image in scan.images:
        if image.status is ImageStatus.VERIFIED and not scan.image_on_disk(image):
            focus[scan.rig.pose_index(image.angle_index, image.camera_index)] = np.nan
            missing.append(image.file)
    views = find_views(scene, scan.rig, scan.poses(), np.nan_to_num(focus, nan=-1.0), on_skin[None, :],
                       limit=scan.rig.n_poses)[0]
    answers = []
    for view in views:
        image = scan.image_at(view.pose)
        if image is None or not np.isfinite(focus[view.pose]):
            continue
        answers.append({
            "file": image.file, "camera_id": image.camera_id, "camera_index": view.camera_index,
            "angle_index": view.angle_index, "angle_deg": image.actual_angle_deg if image.actual_angle_deg is not None else image.planned_angle_deg,
            "u_px": view.u_px, "v_px": view.v_px, "in_focus": view.in_focus, "depth_mm": view.depth_mm,
            "cost": view.cost, "pose": view.pose,
        })
        if len(answers) == count:
            break
    return {"point_mm": on_skin.tolist(), "snapped_mm": distance, "views": answers, "missing_files": missing}
