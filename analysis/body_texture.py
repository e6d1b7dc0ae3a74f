"""The photographic body: a scan's mesh textured from its own images, stored as ``body.glb``.

Every texel of the mesh's atlas (analysis/atlas.py) takes its colour from the images that show
its skin point best, ranked as image navigation ranks them (planner.navigation.view_costs: the
plan's cost, in which an image that holds the point outside its depth of field pays the focus
term, so a sharp image always wins over a blurred one). Images within ``BLEND_MARGIN`` of the
best cost are blended, with weights falling to zero at that margin and towards each image's
border, so the texture has no seams where the best image changes. Each image's gain (per colour
channel) and the light's falloff with the incidence are fitted by least squares where images
share skin (analysis/exposure.py) and divided out before blending. Where the scan's surface is
off the skin, images seen from different sides disagree about where a spot is on it; each texel
is sampled at the offset along the surface's normal at which its images agree
(analysis/parallax.py), so small lesions stay in place and unsmeared.

The file is a glTF binary (metres, as glTF wants; the scan's mm divided by 1000) with one mesh,
its texture coordinates and a JPEG atlas, written into the scan folder through the store.
"""

from __future__ import annotations

import dataclasses
import io
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from analysis.atlas import Atlas, fill_gutters, unwrap
from analysis.exposure import Exposure, fit_exposure
from analysis.navigate import Navigator
from analysis.parallax import surface_offsets
from analysis.pixels import bilinear
from analysis.scan_views import ScanRecord, open_scan

#: Images whose cost is within this of a texel's best image are blended into it (the cost's
#: off-axis term grows by about this much across a fifth of an image).
BLEND_MARGIN = 0.05
#: The blend weight of an image rises from 0 at its border to 1 this share of its width inside.
EDGE_SHARE = 0.08
#: Poses this much above a corner's blend margin are tested at the triangle's texels too (the
#: cost changes across a triangle; a depth-of-field limit may cross it).
CANDIDATE_SLACK = 0.05
#: Images blended into a texel at most (the heaviest).
MAX_BLEND = 4
#: Images more than MAX_BLEND a triangle's corners offer its texels.
CANDIDATE_EXTRA = 2
#: Texel side as a share of the best image's pixel on the skin (finer than the pixel: the chart's
#: tilt and the resampling each lose a little).
TEXEL_PER_PIXEL = 0.7
#: Rings of neighbouring vertices the normals the light's falloff is measured against are averaged over.
SMOOTH_RINGS = 4
#: Texels per pass of the visibility test (bounds its temporary arrays).
TEXEL_BLOCK = 150_000
#: Largest atlas side, texels.
MAX_SIDE = 8192
JPEG_QUALITY = 92


class TextureError(ValueError):
    """The scan cannot be textured (no mesh, no image on disk), naming the scan and why."""


@dataclass(frozen=True)
class Samples:
    """The images that texture each texel: per blended pair the texel index (K,), pose (K,),
    pixel (K,) u and v (in the stored image's pixels), blend weight (K,), incidence (K,) (cos of
    the angle between the camera's ray and the skin's normal); per texel the best
    pose (T,) (-1: no image sees it), whether that image holds it sharp (T,) and its mm/px (T,)."""

    texel: np.ndarray
    pose: np.ndarray
    u: np.ndarray
    v: np.ndarray
    weight: np.ndarray
    incidence: np.ndarray
    best_pose: np.ndarray
    best_sharp: np.ndarray
    best_mm_px: np.ndarray


@dataclass(frozen=True)
class BodyTexture:
    """The textured body: atlas, texture (H, W, 3) uint8, per-texel samples, the images'
    exposure, each texel's offset (T,) mm along the surface's outward normal where the images
    were sampled (analysis/parallax.py) and where the time went (seconds per step)."""

    atlas: Atlas
    texture: np.ndarray
    samples: Samples
    exposure: Exposure
    offset_mm: np.ndarray
    seconds: dict[str, float]


def stored_image_size(scan: ScanRecord) -> tuple[int, int]:
    """(width, height) px of the scan's stored images (simulated phones store small ones)."""
    for image in scan.images:
        if scan.image_on_disk(image):
            with Image.open(scan.path / image.file) as picture:
                return picture.size
    raise TextureError(f"scan {scan.path}: no verified image on disk to texture from")


def choose_views(nav: Navigator, points: np.ndarray, normals: np.ndarray, image_size: tuple[int, int], *,
                 candidates: Any | None = None, margin: float = BLEND_MARGIN, most: int = MAX_BLEND,
                 smooth_normals: np.ndarray | None = None) -> Samples:
    """The blended images of texels at points (T, 3) mm with inward normals (T, 3): see
    :class:`Samples`. Ranked by the navigator's cost under the focus actually captured; images
    within ``margin`` of a texel's best are kept, at most ``most`` of them. candidates: a (T, P) sparse matrix whose
    non-zeros are the only poses to consider for each texel (None: every pose). smooth_normals:
    (T, 3) inward normals the incidence is measured against (default ``normals``)."""
    smooth_normals = normals if smooth_normals is None else smooth_normals
    from planner.navigation import pixel_of, view_costs
    from planner.optics import resolution_mm_per_px

    rig = nav.scan.rig
    optics = rig.optics
    scale = image_size[0] / optics.image_width_px
    available = np.isfinite(nav.focus_mm)
    focus = np.nan_to_num(nav.focus_mm, nan=-1.0)
    parts: list[tuple[np.ndarray, ...]] = []
    best_pose = np.full(len(points), -1, dtype=np.int64)
    best_sharp = np.zeros(len(points), dtype=bool)
    best_mm_px = np.full(len(points), np.nan)
    for start in range(0, len(points), TEXEL_BLOCK):
        chunk = slice(start, start + TEXEL_BLOCK)
        among = None
        if candidates is not None:
            block = candidates[chunk].tocoo()
            among = (block.col, block.row)
        table, cost, sharp = view_costs(nav.scene, rig, nav.poses, focus, points[chunk], normals[chunk], among=among)
        vis = table.vis
        keep = np.flatnonzero(available[vis.pose])
        point, pose, cost, sharp, depth = vis.point[keep], vis.pose[keep], cost[keep], sharp[keep], vis.depth[keep]
        if not len(point):
            continue
        lowest = np.full(len(points[chunk]), np.inf)
        np.minimum.at(lowest, point, cost)
        near = cost - lowest[point] < margin
        point, pose, cost, sharp, depth = point[near], pose[near], cost[near], sharp[near], depth[near]
        u, v = pixel_of(nav.poses, pose, points[chunk][point], rig)
        border = np.minimum.reduce([u, optics.image_width_px - u, v, optics.image_height_px - v])
        edge = np.clip(border / (EDGE_SHARE * optics.image_width_px), 1e-3, 1.0)
        weight = np.clip(1.0 - (cost - lowest[point]) / BLEND_MARGIN, 0.0, 1.0) * edge
        # at most ``most`` images a texel, the heaviest (smooth skin seen alike by many images)
        order = np.lexsort((cost, -weight, point))
        rank = np.arange(len(order)) - np.searchsorted(point[order], point[order])
        top = np.sort(order[rank < most])
        # each texel's best image (lowest cost, first on ties, as navigation orders them)
        order = np.lexsort((pose, cost, point))
        first = order[np.r_[True, point[order][1:] != point[order][:-1]]]
        best_pose[start + point[first]] = pose[first]
        best_sharp[start + point[first]] = sharp[first]
        best_mm_px[start + point[first]] = resolution_mm_per_px(depth[first], optics) / scale
        point, pose, u, v, weight = point[top], pose[top], u[top], v[top], weight[top]
        ray = points[chunk][point] - nav.poses.centres[pose]
        towards = smooth_normals[chunk][point]
        incidence = np.einsum("ij,ij->i", ray, towards) / np.maximum(
            np.linalg.norm(ray, axis=1) * np.linalg.norm(towards, axis=1), 1e-12)
        parts.append((start + point, pose, u * scale, v * scale, weight, incidence))
    if not parts:
        empty = np.zeros(0)
        return Samples(empty.astype(np.int64), empty.astype(np.int64), empty, empty, empty, empty,
                       best_pose, best_sharp, best_mm_px)
    texel, pose, u, v, weight, incidence = (np.concatenate(c) for c in zip(*parts))
    return Samples(texel.astype(np.int64), pose.astype(np.int64), u, v, weight, incidence, best_pose, best_sharp, best_mm_px)


def smooth_face_normals(vertices: np.ndarray, faces: np.ndarray, rings: int = SMOOTH_RINGS) -> np.ndarray:
    """(F, 3) inward unit normals averaged over ``rings`` rings of neighbouring vertices: the
    skin's direction under a TSDF surface's facets (the light's falloff follows the skin)."""
    from scipy import sparse

    corners = vertices[faces]
    area_normals = -np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    at_vertex = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(at_vertex, faces[:, k], area_normals)
    edges = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    n = len(vertices)
    ring = sparse.csr_matrix((np.ones(2 * len(edges)), (np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]])),
                             shape=(n, n)) + sparse.identity(n, format="csr")
    for _ in range(rings):
        at_vertex = ring @ at_vertex
    per_face = at_vertex[faces].sum(axis=1)
    return per_face / np.maximum(np.linalg.norm(per_face, axis=1, keepdims=True), 1e-12)


def candidate_poses(nav: Navigator, vertices: np.ndarray, faces: np.ndarray, image_size: tuple[int, int]) -> Any:
    """(F, P) sparse: the poses worth testing for the texels of each triangle, the best
    MAX_BLEND + CANDIDATE_EXTRA within BLEND_MARGIN + CANDIDATE_SLACK of the best image at any of
    its corners (testing every pose at every texel costs ten times more and finds the same images)."""
    from scipy import sparse

    normals = np.zeros_like(vertices)
    corners = vertices[faces]
    area_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    for k in range(3):
        np.add.at(normals, faces[:, k], -area_normals)  # inward, weighted by area
    ok = np.flatnonzero(np.linalg.norm(normals, axis=1) > 0)
    found = choose_views(nav, vertices[ok], normals[ok], image_size, margin=BLEND_MARGIN + CANDIDATE_SLACK,
                         most=MAX_BLEND + CANDIDATE_EXTRA)
    n_poses = nav.scan.rig.n_poses
    at_vertex = sparse.csr_matrix((np.ones(len(found.texel)), (ok[found.texel], found.pose)),
                                  shape=(len(vertices), n_poses))
    incidence = sparse.csr_matrix((np.ones(faces.size), (np.repeat(np.arange(len(faces)), 3), faces.ravel())),
                                  shape=(len(faces), len(vertices)))
    per_face = (incidence @ at_vertex).tocsr()
    per_face.data[:] = 1.0
    return per_face


def sample_images(scan: ScanRecord, samples: Samples) -> np.ndarray:
    """(K, 3) float RGB of every blended pair, bilinear at its pixel, one image in memory at a time."""
    colours = np.zeros((len(samples.pose), 3))
    order = np.argsort(samples.pose, kind="stable")
    poses, starts = np.unique(samples.pose[order], return_index=True)
    ends = np.r_[starts[1:], len(order)]
    for pose, a, b in zip(poses, starts, ends):
        image = scan.image_at(int(pose))
        if image is None or not scan.image_on_disk(image):
            raise TextureError(f"scan {scan.path}: pose {pose} has no image on disk")
        with Image.open(scan.path / image.file) as picture:
            pixels = np.asarray(picture.convert("RGB"), dtype=np.float32)
        mine = order[a:b]
        colours[mine] = bilinear(pixels, samples.u[mine], samples.v[mine])
    return colours


def blend(samples: Samples, colours: np.ndarray, exposure: Exposure, n_texels: int) -> tuple[np.ndarray, np.ndarray]:
    """Per texel (T, 3) the weighted mean of its samples' colours with their exposure (gain and
    light falloff) taken out, and (T,) whether any image gave it a colour."""
    corrected = colours / exposure.factor(samples.pose, samples.incidence)
    total = np.bincount(samples.texel, samples.weight, minlength=n_texels)
    out = np.zeros((n_texels, 3))
    for c in range(3):
        out[:, c] = np.bincount(samples.texel, samples.weight * corrected[:, c], minlength=n_texels)
    seen = total > 0
    out[seen] /= total[seen, None]
    return out, seen


def texture_scan(scan: ScanRecord, *, texel_mm: float | None = None, max_side: int = MAX_SIDE,
                 progress: Callable[[str], None] | None = None) -> BodyTexture:
    """Texture a scan's mesh from its images (see the module docstring). texel_mm None: from the
    images' resolution on the skin (TEXEL_PER_PIXEL of the median best image's mm/px)."""
    say = progress or (lambda _text: None)
    seconds: dict[str, float] = {}
    clock = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        seconds[name] = now - clock
        clock = now

    if "mesh" not in scan.manifest.files:
        raise TextureError(f"scan {scan.path}: no mesh (the scan ended before the depth sweep)")
    nav = Navigator(scan)
    if not np.isfinite(nav.focus_mm).any():
        raise TextureError(f"scan {scan.path}: no verified image on disk to texture from")
    size = stored_image_size(scan)
    mesh = nav.mesh
    vertices, faces = np.asarray(mesh.vertices, dtype=float), np.asarray(mesh.faces, dtype=np.int64)
    normals = -np.asarray(nav.scene.face_normals)
    lap("open")
    if texel_mm is None:
        probe = np.random.default_rng(0).choice(len(faces), min(len(faces), 4000), replace=False)
        probe = probe[np.linalg.norm(normals[probe], axis=1) > 0]
        best = choose_views(nav, vertices[faces[probe]].mean(axis=1), normals[probe], size).best_mm_px
        if not np.isfinite(best).any():
            raise TextureError(f"scan {scan.path}: no image sees the mesh")
        texel_mm = TEXEL_PER_PIXEL * float(np.nanmedian(best))
        lap("resolution")
    say(f"unwrapping {len(faces)} triangles at {texel_mm:.2f} mm per texel")
    atlas = unwrap(vertices, faces, texel_mm, max_side=max_side)
    lap("atlas")
    say(f"atlas {atlas.shape[1]} x {atlas.shape[0]}, {atlas.charts} charts, {len(atlas.texel_rc)} texels on the skin")
    per_face = candidate_poses(nav, vertices, faces, size)
    lap("candidates")
    texel_normals = normals[atlas.texel_face]
    facing = np.linalg.norm(texel_normals, axis=1) > 0  # texels of zero-area triangles stay unseen
    on = np.flatnonzero(facing)
    smooth = smooth_face_normals(vertices, faces)
    found = choose_views(nav, atlas.texel_point[on], texel_normals[on], size,
                         candidates=per_face[atlas.texel_face[on]], smooth_normals=smooth[atlas.texel_face[on]])
    samples = _widen(found, on, len(atlas.texel_rc))
    lap("views")
    say(f"{len(samples.pose)} image samples from {len(np.unique(samples.pose))} images")
    colours = sample_images(scan, samples)
    lap("sample")
    exposure = fit_exposure(samples.texel, samples.pose, samples.incidence, colours, samples.weight, scan.rig.n_poses)
    lap("exposure")
    outward = -smooth[atlas.texel_face]
    offset = surface_offsets(nav, atlas, samples.texel, samples.pose, samples.weight, samples.incidence, exposure,
                             outward, size)
    samples = _moved(nav, samples, atlas.texel_point + offset[:, None] * outward, size)
    colours = sample_images(scan, samples)
    lap("parallax")
    colour, seen = blend(samples, colours, exposure, len(atlas.texel_rc))
    texture = np.zeros((*atlas.shape, 3), dtype=np.uint8)
    filled = np.zeros(atlas.shape, dtype=bool)
    rows, cols = atlas.texel_rc[seen, 0], atlas.texel_rc[seen, 1]
    texture[rows, cols] = np.clip(np.rint(colour[seen]), 0, 255)
    filled[rows, cols] = True
    texture = fill_gutters(texture, filled)
    lap("blend")
    return BodyTexture(atlas, texture, samples, exposure, offset, seconds)


def _moved(nav: Navigator, samples: Samples, points: np.ndarray, image_size: tuple[int, int]) -> Samples:
    """The samples with their pixels where each texel's point is ``points`` (T, 3) mm."""
    from planner.navigation import pixel_of

    scale = image_size[0] / nav.scan.rig.optics.image_width_px
    u, v = np.empty(len(samples.pose)), np.empty(len(samples.pose))
    for start in range(0, len(samples.pose), TEXEL_BLOCK):  # bounds the projection's temporaries
        part = slice(start, start + TEXEL_BLOCK)
        u[part], v[part] = pixel_of(nav.poses, samples.pose[part], points[samples.texel[part]], nav.scan.rig)
    return dataclasses.replace(samples, u=u * scale, v=v * scale)


def _widen(found: Samples, texels: np.ndarray, n: int) -> Samples:
    """Samples of a subset of texels (indices ``texels``) re-indexed to all ``n`` texels."""
    best_pose = np.full(n, -1, dtype=np.int64)
    best_sharp = np.zeros(n, dtype=bool)
    best_mm_px = np.full(n, np.nan)
    best_pose[texels], best_sharp[texels], best_mm_px[texels] = found.best_pose, found.best_sharp, found.best_mm_px
    return Samples(texels[found.texel], found.pose, found.u, found.v, found.weight, found.incidence,
                   best_pose, best_sharp, best_mm_px)


def glb_bytes(body: BodyTexture, *, quality: int = JPEG_QUALITY) -> bytes:
    """The textured mesh as a glTF binary: positions in metres, UVs, a JPEG base colour texture."""
    import trimesh
    from trimesh.visual.material import PBRMaterial
    from trimesh.visual.texture import TextureVisuals

    buffer = io.BytesIO()
    Image.fromarray(body.texture, "RGB").save(buffer, format="JPEG", quality=quality)
    buffer.seek(0)
    image = Image.open(buffer)
    material = PBRMaterial(baseColorTexture=image, metallicFactor=0.0, roughnessFactor=0.9, doubleSided=False)
    uv = np.stack([body.atlas.uv[:, 0], 1.0 - body.atlas.uv[:, 1]], axis=1)  # trimesh: v up; glTF export flips it
    mesh = trimesh.Trimesh(vertices=body.atlas.vertices / 1000.0, faces=body.atlas.faces,
                           visual=TextureVisuals(uv=uv, material=material), process=False)
    return trimesh.Scene(mesh).export(file_type="glb")


def write_body(scan_dir: Path | str, *, rig_path: Path | str | None = None, texel_mm: float | None = None,
               progress: Callable[[str], None] | None = None) -> Path:
    """Texture the scan and store ``body.glb`` in its folder (listed in the manifest); its path.
    texel_mm: the atlas' texel (None: from the images' resolution on the skin)."""
    scan = open_scan(scan_dir, rig_path)
    body = texture_scan(scan, texel_mm=texel_mm, progress=progress)
    if progress is not None:
        progress("writing body.glb")
    return scan.folder.write_body(glb_bytes(body))


def report_and_body(scan_dir: Path | str, *, rig_path: Path | str | None = None,
                    texel_mm: float | None = None) -> Path:
    """The scan's QA report, then its textured body when it has a mesh and an image to texture
    it from (a scan stopped before its sweep or capture has none): the step after a scan (the
    daemon's ``qa_report`` hook); returns the report's page. The report is written first, so a
    texture that fails leaves it in place. texel_mm: the body's texel (None: from the images)."""
    from analysis.qa_report import generate_report

    page = generate_report(scan_dir, rig_path=rig_path)
    scan = open_scan(scan_dir, rig_path)
    if "mesh" in scan.manifest.files and any(scan.image_on_disk(i) for i in scan.images):
        write_body(scan_dir, rig_path=rig_path, texel_mm=texel_mm)
    return page


def read_atlas_texture(glb: bytes) -> Any:
    """The base colour texture of a body.glb as a PIL image (for checks and the benchmark)."""
    import trimesh

    scene = trimesh.load(io.BytesIO(glb), file_type="glb")
    mesh = next(iter(scene.geometry.values()))
    return mesh.visual.material.baseColorTexture
