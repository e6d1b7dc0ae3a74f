"""Image navigation: which captured image shows a given spot on the body best, and where.

One implementation for every caller: ``tbp navigate`` builds a :class:`Navigator` for one
question, the web viewer keeps one per open scan (the ray-casting scene takes most of a
second to build; a query then takes milliseconds).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from analysis.scan_views import ScanRecord, open_scan
from daemon.records.manifest import ImageStatus


class NavigationError(ValueError):
    """The query does not name a point on the scanned body."""


def parse_point(text: str) -> np.ndarray:
    """"X,Y,Z" in mm -> (3,) float; NavigationError naming the text otherwise."""
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 3 or not np.all(np.isfinite(values)):
        raise NavigationError(f"--point {text!r}: expected X,Y,Z in mm, three numbers")
    return np.array(values)


class Navigator:
    """A scan's mesh, ray-casting scene, poses at the actual exposure angles and captured focus.

    Only verified images whose file is still on disk count (``missing_files`` names verified
    ones that are gone). Build it once per scan, query it many times.
    """

    def __init__(self, scan: ScanRecord, mesh: Any | None = None) -> None:
        from planner.visibility import RayScene

        self.scan = scan
        self.mesh = scan.mesh() if mesh is None else mesh
        self.scene = RayScene(self.mesh)
        self.poses = scan.poses()
        self.focus_mm = scan.captured_focus_mm()
        self.missing_files = []  # verified once, gone from the disk since: not offered
        for image in scan.images:
            if image.status is ImageStatus.VERIFIED and not scan.image_on_disk(image):
                self.focus_mm[scan.rig.pose_index(image.angle_index, image.camera_index)] = np.nan
                self.missing_files.append(image.file)

    def prepare(self) -> None:
        """Build the ray-casting structures now (the scene builds them on its first query,
        about half a second for a body mesh) so that the first real query is fast."""
        self.query(vertex=0, count=1)

    @classmethod
    def open(cls, scan_dir: Path | str, rig_path: Path | str | None = None) -> Navigator:
        return cls(open_scan(scan_dir, rig_path))

    def skin_point(self, *, point: str | np.ndarray | None = None,
                   vertex: int | None = None) -> tuple[np.ndarray, float]:
        """(3,) mm on the mesh for the query (a vertex, or a point snapped to the skin) and the
        snapping distance, mm."""
        n = len(self.mesh.vertices)
        if vertex is not None:
            if not 0 <= vertex < n:
                raise NavigationError(f"--vertex {vertex}: the scan's mesh has vertices 0..{n - 1}")
            return np.asarray(self.mesh.vertices[vertex], dtype=float), 0.0
        if point is None:
            raise NavigationError("give a point (X,Y,Z mm) or a mesh vertex")
        query = parse_point(point) if isinstance(point, str) else np.asarray(point, dtype=float).reshape(-1)
        if query.shape != (3,) or not np.all(np.isfinite(query)):
            raise NavigationError(f"point {query.tolist()!r}: expected three finite numbers (mm)")
        closest, _faces = self.scene.closest_faces(query[None, :])
        on_skin = np.asarray(closest, dtype=float).reshape(-1, 3)[0]
        return on_skin, float(np.linalg.norm(on_skin - query))

    def query(self, *, point: str | np.ndarray | None = None, vertex: int | None = None,
              count: int | None = 5) -> dict[str, Any]:
        """The best captured images of a skin point, best (lowest plan cost) first.

        count None returns every verified image that sees the point. Each view carries the
        image record's file, camera, actual exposure angle, focus distance (mm), the pixel
        (u, v) in the full-resolution portrait image, depth (mm) and resolution (mm/px).
        """
        from planner.navigation import find_views
        from planner.optics import resolution_mm_per_px

        on_skin, snapped = self.skin_point(point=point if vertex is None else None, vertex=vertex)
        rig = self.scan.rig
        views = find_views(self.scene, rig, self.poses, np.nan_to_num(self.focus_mm, nan=-1.0),
                           on_skin[None, :], limit=rig.n_poses)[0]
        answers = []
        for view in views:
            image = self.scan.image_at(view.pose)
            if image is None or not np.isfinite(self.focus_mm[view.pose]):
                continue
            answers.append({
                "file": image.file, "camera_id": image.camera_id, "camera_index": view.camera_index,
                "angle_index": view.angle_index, "angle_deg": image.actual_angle_deg if image.actual_angle_deg is not None else image.planned_angle_deg,
                "u_px": view.u_px, "v_px": view.v_px, "in_focus": view.in_focus, "depth_mm": view.depth_mm,
                "focus_mm": float(self.focus_mm[view.pose]),
                "resolution_mm_px": float(resolution_mm_per_px(view.depth_mm, rig.optics)),
                "cost": view.cost, "pose": view.pose,
            })
            if count is not None and len(answers) == count:
                break
        return {"point_mm": on_skin.tolist(), "snapped_mm": snapped, "views": answers,
                "missing_files": list(self.missing_files)}


def navigate(
    scan_dir: Path | str,
    *,
    point: str | np.ndarray | None = None,
    vertex: int | None = None,
    count: int = 5,
    rig_path: Path | str | None = None,
) -> dict[str, Any]:
    """The best captured images of a skin point (snapped to the scan's mesh), best first."""
    return Navigator.open(scan_dir, rig_path).query(point=point, vertex=vertex, count=count)
