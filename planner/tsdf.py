"""TSDF shape estimate: fuse a posed depth sweep into an Open3D VoxelBlockGrid and extract the subject.

Steps: pick frames a fixed beam-angle step apart per camera; integrate them on the CPU (units mm:
voxel size, truncation and weight threshold from ``rig.tsdf``) as they arrive (:class:`TsdfFusion`;
the daemon fuses during the sweep); extract the zero-level triangle mesh;
keep the subject only (inside the scan-volume cylinder, above the floor, largest connected
component); close its holes and the soles' openings (the stored surface leaves the soles, which
no frame sees, open); carve away the surface the frames saw through (planner/carve.py); validate
that it is a plausible, fully contained person. The result is a trimesh in mm.

Two surfaces come from one sweep: the planner's (``rig.tsdf.voxel_mm``, extracted as soon as the
sweep ends, on the path to the capture) and the stored one (:meth:`TsdfFusion.surface`: the same
frames fused again at ``rig.tsdf.surface_voxel_mm``, finer, while the capture runs, its vertices
then moved onto the frames' depth: planner/surface_fit.py), which holds the skin closer where limbs
are near the body.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import structlog
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from planner.carve import FreeSpace, carve
from planner.order import stable_argsort
from planner.rig import Rig
from planner.shape_errors import (
    ImplausibleSubject,
    NoSubject,
    SubjectTooCloseToCameras,
    SubjectTouchesBoundary,
    TooFewFrames,
)
from planner.surface_fit import fit_to_frames
from planner.sweep import AngleSpacing, PosedDepth

log = structlog.get_logger(__name__)

#: Beam rotation between fused frames of one camera (deg); 30 fps at 30 deg/s gives 1 deg steps,
#: and frames closer than this add little to the fusion but cost time.
FRAME_SPACING_DEG = 8.0
#: Fewer usable frames than this cannot cover a person from all sides.
MIN_FRAMES = 12
#: A frame with fewer measured pixels inside the scan volume adds nothing (stray floor noise).
MIN_FRAME_PIXELS = 100
#: Depth images are decimated so a pixel spans at most one voxel at this depth (mm): for the default
#: camera and 4 mm voxels every 4th pixel, a sixteenth of the pixels to fuse.
DECIMATION_DEPTH_MM = 1000.0
#: Voxel blocks are block_resolution^3 voxels; the hash map starts with room for BLOCK_COUNT blocks
#: (a standing adult touches about 10,000 at 4 mm voxels) and grows when needed.
BLOCK_RESOLUTION = 8
BLOCK_COUNT = 12_000
#: A surface within this many voxels of the volume's side or top counts as touching it.
BOUNDARY_MARGIN_VOXELS = 1.5
#: Open loops reaching this close to the floor clearance, and not above FOOT_TOP_MM, are the soles'
#: openings: the planner's mesh closes them down to the floor, the stored surface leaves them open
#: (no frame measures a sole); other loops of at most HOLE_MAX_VERTICES vertices (the occluded
#: crotch, armpits, under the chin, between hand and thigh: at most ~700 on simulated adults) are
#: filled, which closes the surface the planner's occlusion test sees (true->estimate Chamfer
#: 1.41 -> 1.24 mm).
FLOOR_BAND_MM = 25.0
FOOT_TOP_MM = 250.0
HOLE_MAX_VERTICES = 1500
#: A person: height and horizontal extent ranges (mm).
HEIGHT_RANGE_MM = (900.0, 2300.0)
EXTENT_RANGE_MM = (150.0, 1200.0)
#: Besides the largest component, keep components with at least this share of its triangles
#: (a hand or an arm the TSDF separated from the body by a narrow gap).
MIN_COMPONENT_SHARE = 0.02


@dataclass(frozen=True)
class TsdfResult:
    """The subject mesh (mm) and how it was made."""

    mesh: trimesh.Trimesh
    frames_used: int
    per_camera: dict[str, int]
    timings_s: dict[str, float] = field(default_factory=dict)

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickles the mesh as its vertex and face arrays only: a Trimesh pickles its caches too
        (normals, adjacency: 10x the bytes), and the daemon unpickles what the compute worker
        sends on a thread holding the interpreter lock the event loop needs."""
        mesh = self.mesh
        arrays = (np.asarray(mesh.vertices).view(np.ndarray), np.asarray(mesh.faces).view(np.ndarray))
        return _rebuild_result, (arrays, self.frames_used, self.per_camera, self.timings_s)


def _rebuild_result(arrays: tuple[np.ndarray, np.ndarray], frames_used: int, per_camera: dict[str, int],
                    timings_s: dict[str, float]) -> TsdfResult:
    vertices, faces = arrays
    return TsdfResult(trimesh.Trimesh(vertices, faces, process=False), frames_used, per_camera, timings_s)


def _decimate(depth: np.ndarray, intrinsics: np.ndarray, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """Keep every factor-th pixel; K scaled so pixel centres stay consistent."""
    if factor == 1:
        return depth, intrinsics
    d = np.ascontiguousarray(depth[::factor, ::factor])
    k = intrinsics.copy()
    k[0, 0] /= factor
    k[1, 1] /= factor
    k[0, 2] /= factor
    k[1, 2] /= factor
    return d, k


def open3d_intrinsics(k: np.ndarray) -> np.ndarray:
    """``k`` (pixel centres at integer coordinates, as the depth cameras report) as Open3D's
    ``VoxelBlockGrid.integrate`` needs it: it reads the depth at the pixel whose index is the
    projected coordinate cut to an integer, so pixel i answers for [i, i + 1). Shifting the
    principal point by half a pixel makes it answer for [i - 0.5, i + 0.5); without the shift the
    surface lies half a (decimated) pixel off along both image axes, about 2 mm at 1 m."""
    shifted = np.array(k, dtype=np.float64)
    shifted[0, 2] += 0.5
    shifted[1, 2] += 0.5
    return shifted


def _mask_outside_volume(depth: np.ndarray, k: np.ndarray, camera_to_world: np.ndarray, rig: Rig) -> np.ndarray:
    """Zero the pixels whose points lie outside the scan cylinder or on the floor.

    The floor and the room would otherwise allocate most voxel blocks and dominate fusion time.
    """
    cfg = rig.tsdf
    h, w = depth.shape
    z = depth.astype(np.float32)
    x = (np.arange(w, dtype=np.float32) - np.float32(k[0, 2])) / np.float32(k[0, 0])
    y = (np.arange(h, dtype=np.float32) - np.float32(k[1, 2])) / np.float32(k[1, 1])
    r = camera_to_world[:3, :3].astype(np.float32)
    t = camera_to_world[:3, 3].astype(np.float32)
    wx = z * (r[0, 0] * x[None, :] + r[0, 1] * y[:, None] + r[0, 2]) + t[0]
    wy = z * (r[1, 0] * x[None, :] + r[1, 1] * y[:, None] + r[1, 2]) + t[1]
    wz = z * (r[2, 0] * x[None, :] + r[2, 1] * y[:, None] + r[2, 2]) + t[2]
    margin = 2 * cfg.voxel_mm
    keep = (wx * wx + wy * wy <= (cfg.volume_radius_mm + margin) ** 2) & (wz <= cfg.volume_height_mm + margin)
    # floor points scatter upwards with the depth noise: clear them by 3 sigma at their depth
    m = rig.depth_camera_model
    sigma = z * z * np.float32(m.subpixel_px / (m.fx_px * m.baseline_mm))
    keep &= wz >= cfg.floor_clearance_mm + 3.0 * sigma
    return np.where(keep, depth, 0).astype(depth.dtype)


def _new_grid(rig: Rig) -> object:
    """An empty VoxelBlockGrid (mm units) on the CPU for ``rig.tsdf``."""
    import open3d as o3d
    import open3d.core as o3c

    return o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight"),
        attr_dtypes=(o3c.float32, o3c.float32),
        attr_channels=((1), (1)),
        voxel_size=rig.tsdf.voxel_mm,
        block_resolution=BLOCK_RESOLUTION,
        block_count=BLOCK_COUNT,
        device=o3c.Device("CPU:0"),
    )


def _integrate_frame(vbg: object, f: PosedDepth, rig: Rig, space: FreeSpace) -> bool:
    """Fuse one posed frame (only depth inside the scan volume) and add all its depth to ``space``;
    False (and nothing added) when nothing of it was inside."""
    import open3d as o3d
    import open3d.core as o3c

    cfg = rig.tsdf
    factor = max(1, int(cfg.voxel_mm * min(f.intrinsics[0, 0], f.intrinsics[1, 1]) / DECIMATION_DEPTH_MM))
    measured, k = _decimate(f.depth, f.intrinsics, factor)
    measured = measured * np.float32(f.depth_unit_mm)
    depth = _mask_outside_volume(measured, k, f.camera_to_world, rig)
    if np.count_nonzero(depth) < MIN_FRAME_PIXELS:
        return False
    space.add(measured, k, f.camera_to_world)
    image = o3d.t.geometry.Image(o3c.Tensor(depth))
    intrinsic = o3c.Tensor(open3d_intrinsics(k), dtype=o3c.float64)
    extrinsic = o3c.Tensor(np.linalg.inv(f.camera_to_world), dtype=o3c.float64)
    depth_max, scale = rig.depth_camera_model.max_range_mm, 1.0
    blocks = vbg.compute_unique_block_coordinates(  # type: ignore[attr-defined]
        image, intrinsic, extrinsic, scale, depth_max, cfg.truncation_voxels
    )
    vbg.integrate(blocks, image, intrinsic, extrinsic, scale, depth_max, cfg.truncation_voxels)  # type: ignore[attr-defined]
    return True


class TsdfFusion:
    """A TSDF fused frame by frame as the sweep delivers them; :meth:`result` extracts the subject.

    Frames are chosen as :func:`fuse` chooses them (per camera, :data:`FRAME_SPACING_DEG` of beam
    rotation apart, empty frames skipped), so each camera's frames must come in time order; the
    cameras may interleave. Each fused frame's decimated depth is kept (:class:`FreeSpace`) to carve
    the extracted surface, and the frame itself for :meth:`surface`. One fusion is used from one
    thread at a time (a lock makes sure).
    """

    def __init__(self, rig: Rig) -> None:
        self.rig = rig
        self._frames: list[PosedDepth] = []
        self.offered = 0
        self.per_camera: dict[str, int] = {}
        self.integrated = 0
        self.integrate_s = 0.0
        self._spacing = AngleSpacing(FRAME_SPACING_DEG)
        self._vbg: object | None = None
        self._space = FreeSpace(rig.depth_camera_model, margin_mm=rig.tsdf.voxel_mm)
        self._lock = threading.Lock()
        self._result: tuple[bool, TsdfResult] | None = None  # (validated, result) until the next add

    def add(self, frames: Iterable[PosedDepth]) -> int:
        """Fuse the chosen ones of ``frames``; returns how many were chosen."""
        with self._lock:
            started = time.perf_counter()
            chosen = 0
            for f in frames:
                self.offered += 1
                if not f.valid_pixels or not self._spacing.keep(f.camera_id, f.beam_angle_deg):
                    continue
                chosen += 1
                self.per_camera[f.camera_id] = self.per_camera.get(f.camera_id, 0) + 1
                self._frames.append(f)
                if self._vbg is None:
                    self._vbg = _new_grid(self.rig)
                self.integrated += _integrate_frame(self._vbg, f, self.rig, self._space)
            self.integrate_s += time.perf_counter() - started
            if chosen:
                self._result = None
            return chosen

    def result(self, *, validate: bool = True) -> TsdfResult:
        """The subject's surface mesh (mm) from the frames fused so far.

        validate=False skips the person-size and containment checks (analytic test shapes); a
        missing subject and too few frames are refused either way. The mesh is extracted once:
        asked again before another frame is fused, the same result is returned.
        """
        with self._lock:
            if self._result is None or self._result[0] != validate:
                self._result = (validate, self._extract(validate))
            return self._result[1]

    def surface(self, *, validate: bool = True) -> TsdfResult:
        """The stored surface: the frames fused so far, fused again at ``rig.tsdf.surface_voxel_mm``
        (the planner's grid itself when that is its voxel), with the soles left open
        (:func:`close_openings`), its vertices then moved onto the frames' depth
        (planner/surface_fit.py). Its timings are the second fusion's and the fit's (``fit``); it
        refuses what :meth:`result` refuses."""
        same_voxel = self.rig.tsdf.surface_voxel_mm == self.rig.tsdf.voxel_mm
        with self._lock:
            frames = list(self._frames)
            extracted = self._extract(validate, close_soles=False) if same_voxel else None  # this grid again
        if extracted is None:
            fine = TsdfFusion(surface_rig(self.rig))
            fine.add(frames)
            with fine._lock:
                extracted = fine._extract(validate, close_soles=False)
        started = time.perf_counter()
        mesh = extracted.mesh
        vertices = fit_to_frames(np.asarray(mesh.vertices), np.asarray(mesh.faces), frames)
        fit_s = time.perf_counter() - started
        timings = {**extracted.timings_s, "fit": fit_s, "total": extracted.timings_s.get("total", 0.0) + fit_s}
        return TsdfResult(trimesh.Trimesh(vertices, np.asarray(mesh.faces), process=False), extracted.frames_used,
                          extracted.per_camera, timings)

    def _extract(self, validate: bool, *, close_soles: bool = True) -> TsdfResult:
        cfg = self.rig.tsdf
        chosen = sum(self.per_camera.values())
        if chosen < MIN_FRAMES:
            raise TooFewFrames(chosen, MIN_FRAMES, dict(self.per_camera))
        if self.integrated == 0 or self._vbg is None:
            raise NoSubject(
                f"none of {self.offered} frames measured anything within radius {cfg.volume_radius_mm:g} mm "
                f"and height {cfg.volume_height_mm:g} mm above the floor"
            )
        t1 = time.perf_counter()
        try:
            tmesh = self._vbg.extract_triangle_mesh(weight_threshold=cfg.weight_threshold)  # type: ignore[attr-defined]
        except RuntimeError as exc:  # Open3D cannot give an empty mesh its (empty) vertex colours
            if "shape {0}" not in str(exc):
                raise
            raise NoSubject(f"the fused volume holds no surface ({chosen} frames)") from None
        vertices = tmesh.vertex.positions.numpy().astype(np.float64)
        triangles = tmesh.triangle.indices.numpy().astype(np.int64)
        t2 = time.perf_counter()
        if len(triangles) == 0:
            raise NoSubject(f"the fused volume holds no surface ({chosen} frames)")
        vertices, faces = _subject(vertices, triangles, self.rig, close_soles)
        t3 = time.perf_counter()
        subject = trimesh.Trimesh(*carve(vertices, faces, self._space), process=False)
        if validate:
            _validate(subject, self.rig)
        t4 = time.perf_counter()
        timings = {"integrate": self.integrate_s, "extract": t2 - t1, "clean": t3 - t2, "carve": t4 - t3,
                   "total": self.integrate_s + t4 - t1}
        log.info("tsdf.fused", frames=chosen, vertices=len(subject.vertices),
                 **{f"{k}_s": round(v, 3) for k, v in timings.items()})
        return TsdfResult(subject, chosen, dict(self.per_camera), timings)


def _used(indices: np.ndarray, count: int) -> np.ndarray:
    """Sorted unique vertex indices referenced by an index array (a bincount is faster than a sort)."""
    return np.flatnonzero(np.bincount(indices.ravel(), minlength=count))


def _lowest_first(faces: np.ndarray) -> np.ndarray:
    """(F, 3) faces rotated (winding kept) so each starts at its lowest vertex index (the first
    lowest when an index repeats)."""
    a, b, c = faces.T
    by_b = (b < a) & (b <= c)
    by_c = (c < a) & (c < b)
    return np.stack([np.where(by_b, b, np.where(by_c, c, a)),
                     np.where(by_b, c, np.where(by_c, a, b)),
                     np.where(by_b, a, np.where(by_c, b, c))], axis=1)


def _face_keys(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """(F,) one int64 per face ordering faces as (first, second, third) index would; a
    lexicographic sort of three keys takes three times as long."""
    if n_vertices ** 3 >= 2 ** 63:
        raise ValueError(f"{n_vertices} vertices: face keys would overflow 64 bits")
    n = np.int64(n_vertices)
    result: np.ndarray = (faces[:, 0] * n + faces[:, 1]) * n + faces[:, 2]
    return result


def _subject(v: np.ndarray, triangles: np.ndarray, rig: Rig, close_soles: bool) -> tuple[np.ndarray, np.ndarray]:
    """Crop (V, 3) vertices / (T, 3) triangles to the scan cylinder above the floor; keep the largest
    component; close its openings (:func:`close_openings`). Returns the canonical (V', 3) vertices
    and (F', 3) faces."""
    cfg = rig.tsdf
    r = np.hypot(v[:, 0], v[:, 1])
    inside = (r <= cfg.volume_radius_mm) & (v[:, 2] >= cfg.floor_clearance_mm) & (v[:, 2] <= cfg.volume_height_mm)
    faces = triangles[inside[triangles].all(axis=1)]
    if len(faces) == 0:
        raise NoSubject(
            f"no surface above {cfg.floor_clearance_mm:g} mm within radius {cfg.volume_radius_mm:g} mm "
            f"and height {cfg.volume_height_mm:g} mm"
        )
    used = _used(faces, len(v))
    remap = np.full(len(v), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    local = remap[faces]
    edges = np.concatenate([local[:, [0, 1]], local[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(edges), dtype=np.int8), (edges[:, 0], edges[:, 1])), shape=(len(used),) * 2)
    _, labels = connected_components(graph, directed=False)
    face_labels = labels[local[:, 0]]
    sizes = np.bincount(face_labels)
    keep = faces[sizes[face_labels] >= MIN_COMPONENT_SHARE * sizes.max()]
    used = _used(keep, len(v))
    # canonical order (vertices by position, faces by vertex): the voxel hash map hands out blocks
    # in a run-dependent order, and a canonical mesh keeps seeded sampling downstream reproducible
    used = used[np.lexsort(v[used].T[::-1])]
    remap = np.full(len(v), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    keep = remap[keep]
    keep = _lowest_first(keep)
    keep = keep[stable_argsort(_face_keys(keep, len(used)))]
    return close_openings(v[used], keep, FLOOR_BAND_MM + cfg.floor_clearance_mm, close_soles=close_soles)


def close_openings(vertices: np.ndarray, faces: np.ndarray, floor_band_mm: float, *,
                   close_soles: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Close the holes of the extracted surface and, with close_soles, the openings at the feet.

    Where the subject stands, the cropped TSDF surface ends in open loops around the feet (the soles
    cannot be seen): a loop reaching below ``floor_band_mm`` and staying below FOOT_TOP_MM is a
    sole's. With close_soles it gets a vertical strip down to z = 0 and a fan across the floor (the
    planner's mesh: a closed foot for its occlusion test); without, it stays open (the stored
    surface: a flat fan lies up to centimetres off a foot's arch). Other loops of at most
    HOLE_MAX_VERTICES vertices (surface no frame saw often enough) get a fan at their centroid. New
    faces are wound to match the adjacent ones. vertices (V, 3) mm, faces (F, 3) int; returns the
    extended arrays.
    """
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    low, high = directed.min(axis=1), directed.max(axis=1)
    # summed per undirected edge, 4 + direction (+-1) is 3 or 5 exactly for an edge used once
    code = np.where(directed[:, 0] < directed[:, 1], 5, 3).astype(np.int32)
    edges = coo_matrix((code, (low, high)), shape=(len(vertices),) * 2).tocsr()
    edges.sum_duplicates()
    once = edges.tocoo()
    single = (once.data == 3) | (once.data == 5)
    if not single.any():
        return vertices, faces
    forward = once.data[single] == 5
    a, b = once.row[single], once.col[single]
    boundary = np.stack([np.where(forward, a, b), np.where(forward, b, a)], axis=1).astype(np.int64)
    graph = coo_matrix(
        (np.ones(len(boundary), dtype=np.int8), (boundary[:, 0], boundary[:, 1])), shape=(len(vertices),) * 2
    )
    _, loop_of = connected_components(graph, directed=False)
    ring = _used(boundary, len(vertices))
    ring_loop = loop_of[ring]
    size = np.bincount(ring_loop)
    z_min = np.full(len(size), np.inf)
    z_max = np.full(len(size), -np.inf)
    np.minimum.at(z_min, ring_loop, vertices[ring, 2])
    np.maximum.at(z_max, ring_loop, vertices[ring, 2])
    sole = (size >= 3) & (z_min < floor_band_mm) & (z_max < FOOT_TOP_MM)
    hole = (size >= 3) & (size <= HOLE_MAX_VERTICES) & ~sole
    floor = sole if close_soles else np.zeros_like(sole)
    n = len(vertices)
    # one centre per closed loop: on the floor for floor openings, the ring's mean for holes
    closed_loops = np.flatnonzero(floor | hole)
    centre_of = np.full(len(size), -1, dtype=np.int64)
    centre_of[closed_loops] = n + np.arange(len(closed_loops))
    sums = np.zeros((len(size), 3))
    np.add.at(sums, ring_loop, vertices[ring])
    centres = sums[closed_loops] / size[closed_loops, None]
    centres[floor[closed_loops], 2] = 0.0
    # floor openings: every ring vertex gets a copy on the floor below it
    dropped = ring[floor[ring_loop]]
    below = np.full(len(vertices), -1, dtype=np.int64)
    below[dropped] = n + len(closed_loops) + np.arange(len(dropped))
    drop = vertices[dropped].copy()
    drop[:, 2] = 0.0
    u, v = boundary[:, 0], boundary[:, 1]
    edge_loop = loop_of[u]
    f, h = floor[edge_loop], hole[edge_loop]
    new_faces = [
        faces,
        np.stack([v[f], u[f], below[u[f]]], 1),
        np.stack([v[f], below[u[f]], below[v[f]]], 1),
        np.stack([centre_of[edge_loop[f]], below[v[f]], below[u[f]]], 1),
        np.stack([centre_of[edge_loop[h]], v[h], u[h]], 1),
    ]
    new_vertices = [vertices, centres, drop]
    return np.concatenate(new_vertices), np.concatenate(new_faces)


def _validate(subject: trimesh.Trimesh, rig: Rig) -> None:
    cfg = rig.tsdf
    v = subject.vertices
    height = float(v[:, 2].max())
    extent = max(float(np.ptp(v[:, 0])), float(np.ptp(v[:, 1])))  # column by column: 0.2 ms, not 6 ms
    if height < 0.5 * HEIGHT_RANGE_MM[0] and extent < EXTENT_RANGE_MM[0]:
        raise NoSubject(f"largest object is {height:.0f} mm tall and {extent:.0f} mm wide: clutter, not a person")
    margin = BOUNDARY_MARGIN_VOXELS * cfg.voxel_mm
    r = np.hypot(v[:, 0], v[:, 1])
    if r.max() > rig.ring_radius_mm - cfg.camera_clearance_mm:
        i = int(np.argmax(r))
        raise SubjectTooCloseToCameras(
            math.degrees(math.atan2(v[i, 1], v[i, 0])), float(v[i, 2]), float(r[i]), rig.ring_radius_mm,
            cfg.camera_clearance_mm,
        )
    if r.max() >= cfg.volume_radius_mm - margin:
        i = int(np.argmax(r))
        raise SubjectTouchesBoundary(
            "side", math.degrees(math.atan2(v[i, 1], v[i, 0])), float(v[i, 2]), float(r[i]), cfg.volume_radius_mm
        )
    if height >= cfg.volume_height_mm - margin:
        i = int(np.argmax(v[:, 2]))
        raise SubjectTouchesBoundary(
            "top", math.degrees(math.atan2(v[i, 1], v[i, 0])), height, float(r[i]), cfg.volume_height_mm
        )
    if not HEIGHT_RANGE_MM[0] <= height <= HEIGHT_RANGE_MM[1]:
        raise ImplausibleSubject("height", height, *HEIGHT_RANGE_MM)
    if not EXTENT_RANGE_MM[0] <= extent <= EXTENT_RANGE_MM[1]:
        raise ImplausibleSubject("horizontal extent", extent, *EXTENT_RANGE_MM)


def surface_rig(rig: Rig) -> Rig:
    """``rig`` whose TSDF voxel is its stored surface's (``tsdf.surface_voxel_mm``)."""
    return replace(rig, tsdf=replace(rig.tsdf, voxel_mm=rig.tsdf.surface_voxel_mm))


def fuse(frames: Sequence[PosedDepth], rig: Rig, *, validate: bool = True, surface: bool = False) -> TsdfResult:
    """Fuse a whole depth sweep into the subject's surface mesh (mm): :class:`TsdfFusion` with
    every frame at once, each camera's in time order; the planner's mesh, or with surface=True
    the stored surface (:meth:`TsdfFusion.surface`).

    validate=False skips the person-size and containment checks (analytic test shapes); a missing
    subject and too few frames are refused either way.
    """
    fusion = TsdfFusion(surface_rig(rig) if surface else rig)  # the stored surface: its voxel at once
    fusion.add(sorted(frames, key=lambda f: (f.camera_id, f.timestamp_s)))
    return fusion.surface(validate=validate) if surface else fusion.result(validate=validate)
