"""Which skin each captured image holds sharp: per surface sample or per mesh vertex.

A skin point is *sharp* when a verified image sees it in focus, *blurred* when verified
images see it but none in focus, *unseen* otherwise (the focus plan's own visibility and
depth-of-field test, at the actual exposure angles and the focus actually used). The QA
report shows it from four sides; the web viewer colours the mesh with the per-vertex map,
which the report stores beside its figures (``report/skin_vertices.npz``).
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import numpy as np

from analysis.scan_views import ScanRecord

UNSEEN, BLURRED, SHARP = 0, 1, 2
VERTEX_MAP = "skin_vertices.npz"


def skin_status_at(scan: ScanRecord, mesh: Any, samples: Any) -> dict[str, np.ndarray]:
    """status (N,) uint8 (2 sharp, 1 blurred, 0 unseen) and resolution (N,) mm/px in each
    point's best captured image (NaN if unseen), for SurfaceSamples on ``mesh``."""
    from planner.cost import cost_table
    from planner.optics import resolution_mm_per_px
    from planner.visibility import RayScene, visible_pairs

    rig = scan.rig
    focus = scan.captured_focus_mm()
    table = cost_table(visible_pairs(RayScene(mesh), scan.poses(), samples, rig.optics), rig.cost, rig.optics)
    captured = np.isfinite(focus)[table.vis.pose]
    sharp_pair = table.pair_in_focus(np.nan_to_num(focus, nan=-1.0)) & captured
    status = np.zeros(len(samples.points), dtype=np.uint8)
    status[table.vis.point[captured]] = BLURRED
    status[table.vis.point[sharp_pair]] = SHARP
    resolution = np.full(len(samples.points), np.inf)
    per_pair = resolution_mm_per_px(table.vis.depth, rig.optics)
    np.minimum.at(resolution, table.vis.point[captured], per_pair[captured])
    resolution[np.isinf(resolution)] = np.nan
    return {"status": status, "resolution": resolution}


def mesh_digest(path: Path) -> str:
    """SHA-256 of the mesh file (a stored vertex map belongs to exactly that mesh)."""
    return hashlib.sha256(path.read_bytes()).hexdigest()


def vertex_skin(scan: ScanRecord, mesh: Any | None = None) -> dict[str, np.ndarray]:
    """The skin map at every vertex of the scan's mesh: status (V,) uint8, resolution (V,) mm/px."""
    from planner.sampling import SurfaceSamples

    mesh = scan.mesh() if mesh is None else mesh
    inward = -np.asarray(mesh.vertex_normals, dtype=float)
    loose = np.linalg.norm(inward, axis=1) == 0  # vertices of no face: nothing to image
    inward[loose] = [1.0, 0.0, 0.0]
    skin = skin_status_at(scan, mesh, SurfaceSamples.from_arrays(np.asarray(mesh.vertices), inward))
    skin["status"][loose] = UNSEEN
    skin["resolution"][loose] = np.nan
    return skin


def write_vertex_map(scan: ScanRecord, out_dir: Path, mesh: Any | None = None) -> Path:
    """Compute and store the per-vertex map in ``out_dir`` (atomic rename); returns its path."""
    skin = vertex_skin(scan, mesh)
    path = out_dir / VERTEX_MAP
    tmp = out_dir / (VERTEX_MAP + ".tmp")
    with open(tmp, "wb") as f:
        np.savez(f, status=skin["status"], resolution=skin["resolution"].astype(np.float32),
                 mesh_sha256=np.array(mesh_digest(scan.folder / "mesh.ply")))
    tmp.replace(path)
    return path


def read_vertex_map(scan: ScanRecord, out_dir: Path) -> dict[str, np.ndarray] | None:
    """The stored per-vertex map if it exists and belongs to the scan's current mesh, else None."""
    path = out_dir / VERTEX_MAP
    if not path.is_file():
        return None
    try:
        with np.load(path) as data:
            if str(data["mesh_sha256"]) != mesh_digest(scan.folder / "mesh.ply"):
                return None
            return {"status": data["status"].astype(np.uint8), "resolution": data["resolution"]}
    except (OSError, KeyError, ValueError):
        return None
