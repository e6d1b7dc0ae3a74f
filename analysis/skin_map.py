"""Which skin each captured image holds sharp: per surface sample or per mesh vertex.

A skin point is *sharp* when a verified image sees it in focus, *blurred* when verified
images see it but none in focus, *unseen* otherwise (the focus plan's own visibility and
depth-of-field test, at the actual exposure angles and the focus actually used). The QA
report shows it from four sides; the web viewer colours the mesh with the per-vertex map,
which the report stores beside its figures with the mesh (``report/skin_mesh.bin``).

*Sharp skin*, the one figure the QA report, the viewer and the scan lists show, is the share
of the mesh's surface area that is sharp in that per-vertex map (:func:`skin_shares`): each
vertex stands for a third of the area of every triangle it is a corner of. Counting vertices
instead overweighs where the TSDF mesh has many small triangles (folds, the arms by the
torso). The report keeps the shares in ``report/skin.json`` for the lists.
"""

from __future__ import annotations

import hashlib
import json
import struct
from pathlib import Path
from typing import Any

import numpy as np

from analysis.scan_views import ScanRecord

UNSEEN, BLURRED, SHARP = 0, 1, 2
REPORT_DIR = "report"
SKIN_MESH = "skin_mesh.bin"
SKIN_SHARES = "skin.json"
SHARE_NAMES = {SHARP: "sharp", BLURRED: "blurred", UNSEEN: "unseen"}
MAGIC = b"TBPM"
HEADER = struct.Struct("<4sII32s")


def skin_status_at(scan: ScanRecord, mesh: Any, samples: Any, scene: Any = None) -> dict[str, np.ndarray]:
    """status (N,) uint8 (2 sharp, 1 blurred, 0 unseen) and resolution (N,) mm/px in each
    point's best captured image (NaN if unseen), for SurfaceSamples on ``mesh``."""
    from planner.optics import focus_interval, resolution_mm_per_px
    from planner.visibility import RayScene, visible_pairs

    rig = scan.rig
    focus = scan.captured_focus_mm()
    vis = visible_pairs(scene or RayScene(mesh), scan.poses(), samples, rig.optics)
    # The plan's own depth-of-field test (CostTable.pair_in_focus), without the cost terms.
    lo, hi = focus_interval(vis.depth, rig.optics.hyperfocal_mm, rig.optics.focal_length_mm)
    used = np.nan_to_num(focus, nan=-1.0)[vis.pose]
    captured = np.isfinite(focus)[vis.pose]
    sharp_pair = (lo <= used) & (used <= hi) & captured
    status = np.zeros(len(samples.points), dtype=np.uint8)
    status[vis.point[captured]] = BLURRED
    status[vis.point[sharp_pair]] = SHARP
    resolution = np.full(len(samples.points), np.inf)
    per_pair = resolution_mm_per_px(vis.depth, rig.optics)
    np.minimum.at(resolution, vis.point[captured], per_pair[captured])
    resolution[np.isinf(resolution)] = np.nan
    return {"status": status, "resolution": resolution}


def mesh_digest(scan: ScanRecord) -> bytes:
    """SHA-256 of the scan's mesh file (a stored skin mesh belongs to exactly that mesh)."""
    path = scan.folder.listed("mesh")
    return hashlib.sha256(path.read_bytes()).digest() if path is not None else bytes(32)


def vertex_skin(scan: ScanRecord, mesh: Any | None = None) -> dict[str, np.ndarray]:
    """The skin map at every vertex of the scan's mesh: status (V,) uint8, resolution (V,) mm/px.

    Each vertex takes the normal of its closest triangle, as a navigation query of that vertex
    does (planner.navigation.find_views), so the colour under a click and the images the click
    finds always agree.
    """
    from planner.sampling import SurfaceSamples
    from planner.visibility import RayScene

    mesh = scan.mesh() if mesh is None else mesh
    scene = RayScene(mesh)
    vertices = np.asarray(mesh.vertices, dtype=float)
    _, faces = scene.closest_faces(vertices)
    inward = -np.asarray(scene.face_normals)[faces]
    degenerate = np.linalg.norm(inward, axis=1) == 0  # a zero-area triangle: no direction to image from
    inward[degenerate] = [1.0, 0.0, 0.0]
    skin = skin_status_at(scan, mesh, SurfaceSamples.from_arrays(vertices, inward), scene)
    skin["status"][degenerate] = UNSEEN
    skin["resolution"][degenerate] = np.nan
    return skin


def skin_mesh(mesh: Any, status: np.ndarray, digest: bytes) -> bytes:
    """The viewer's mesh payload: ``TBPM``, V, F (uint32 LE), the mesh file's SHA-256 (32 bytes),
    positions (V, 3) float32 mm, faces (F, 3) uint32, skin status (V,) uint8."""
    vertices = np.ascontiguousarray(mesh.vertices, dtype="<f4")
    faces = np.ascontiguousarray(mesh.faces, dtype="<u4")
    return b"".join([HEADER.pack(MAGIC, len(vertices), len(faces), digest), vertices.tobytes(), faces.tobytes(),
                     np.asarray(status, dtype=np.uint8).tobytes()])


def skin_mesh_status(payload: bytes) -> np.ndarray:
    """(V,) uint8 skin status of a :func:`skin_mesh` payload."""
    _, nv, nf, _ = HEADER.unpack_from(payload)
    return np.frombuffer(payload, np.uint8, nv, HEADER.size + 12 * nv + 12 * nf)


def skin_shares(vertices: np.ndarray, faces: np.ndarray, status: np.ndarray) -> dict[str, float]:
    """Shares of the surface's area that are sharp, blurred and unseen, from the per-vertex map:
    (V, 3) vertices mm, (F, 3) faces, (V,) status. Each vertex carries a third of the area of
    each of its triangles; a mesh without area is all unseen."""
    corners = np.asarray(vertices, dtype=float)[np.asarray(faces, dtype=np.int64)]
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    weight = np.bincount(np.asarray(faces, dtype=np.int64).ravel(), np.repeat(area / 3.0, 3),
                         minlength=len(status))
    total = float(weight.sum())
    if total <= 0.0:
        return {name: float(code == UNSEEN) for code, name in SHARE_NAMES.items()}
    status = np.asarray(status)
    return {name: float(weight[status == code].sum() / total) for code, name in SHARE_NAMES.items()}


def payload_shares(payload: bytes) -> dict[str, float]:
    """:func:`skin_shares` of a :func:`skin_mesh` payload (what the viewer shows)."""
    _, nv, nf, _ = HEADER.unpack_from(payload)
    vertices = np.frombuffer(payload, "<f4", 3 * nv, HEADER.size).reshape(-1, 3)
    faces = np.frombuffer(payload, "<u4", 3 * nf, HEADER.size + 12 * nv).reshape(-1, 3)
    return skin_shares(vertices, faces, skin_mesh_status(payload))


def write_skin_mesh(scan: ScanRecord, mesh: Any | None = None) -> dict[str, float]:
    """Compute the per-vertex map and store the viewer's payload as ``report/skin_mesh.bin``
    and its shares (:func:`payload_shares`) as ``report/skin.json`` (derived, written
    atomically through the store), so opening the scan costs a file read; returns the shares."""
    mesh = scan.mesh() if mesh is None else mesh
    payload = skin_mesh(mesh, vertex_skin(scan, mesh)["status"], mesh_digest(scan))
    shares = payload_shares(payload)
    scan.folder.write_derived(f"{REPORT_DIR}/{SKIN_MESH}", payload)
    scan.folder.write_derived(f"{REPORT_DIR}/{SKIN_SHARES}", (json.dumps(shares) + "\n").encode())
    return shares


def read_skin_shares(folder: Path) -> dict[str, float] | None:
    """The shares the QA report stored for a scan folder (None: no report, or unreadable).
    Not checked against the mesh: a scan's mesh never changes once written."""
    try:
        shares = json.loads((Path(folder) / REPORT_DIR / SKIN_SHARES).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(shares, dict) or not all(isinstance(shares.get(n), (int, float)) for n in SHARE_NAMES.values()):
        return None
    return {n: float(shares[n]) for n in SHARE_NAMES.values()}


def read_skin_mesh(scan: ScanRecord) -> bytes | None:
    """The stored payload if it exists and belongs to the scan's current mesh, else None."""
    path = scan.path / REPORT_DIR / SKIN_MESH
    try:
        payload = path.read_bytes()
        magic, nv, nf, digest = HEADER.unpack_from(payload)
    except (OSError, struct.error):
        return None
    if magic != MAGIC or len(payload) != HEADER.size + 12 * nv + 12 * nf + nv or digest != mesh_digest(scan):
        return None
    return payload
