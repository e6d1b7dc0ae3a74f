"""The photographic body: a scan's mesh textured from its own images, stored as ``body.glb``.

Every texel of the mesh's atlas (analysis/atlas.py) takes its colour from the images that show
its skin point best, blended across seams (analysis/texel_views.py). Each image's gain (per colour
channel) and the light's falloff with the incidence are fitted by least squares where images
share skin (analysis/exposure.py) and divided out before blending. Images are read one at a
time on each thread and samples blended in bounded blocks, so memory grows with the samples
(about 22 bytes each, 32-bit) and not with copies of them. Where a core is spare (a command run
by hand, or the daemon's compute worker after a scan, in STORING: daemon/offload/worker.py
on_every_core) the atlas, the view choice, the image sampling and the blend run two blocks or
images at once (planner/cores.py), with the same result as one.

The file is a glTF binary (metres, as glTF wants; the scan's mm divided by 1000) with one mesh,
its texture coordinates and a JPEG atlas, written into the scan folder through the store.
"""

from __future__ import annotations

import io
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from analysis.atlas import Atlas, seam_gutters, unwrap
from analysis.exposure import MAX_EQUATIONS, Exposure, fit_exposure
from analysis.navigate import Navigator
from analysis.pixels import bicubic, by_image
from analysis.scan_views import ScanRecord, open_scan, picture_size
from analysis.texel_views import Samples, candidate_poses, choose_views, runs, squarely, texel_views
from planner.cores import each, heap_for_large_arrays

#: Texel side as a share of the best image's pixel on the skin (finer than the pixel: the chart's
#: tilt and the resampling each lose a little).
TEXEL_PER_PIXEL = 0.7
#: Rings of neighbouring vertices the normals the light's falloff is measured against are averaged over.
SMOOTH_RINGS = 4
#: Samples per pass of the blending (bounds its temporary arrays).
SAMPLE_BLOCK = 1 << 21
#: Largest atlas side, texels.
MAX_SIDE = 8192
#: The texel grows until the mesh's area is at most this many texels (the atlas holds about 7/8 of
#: that: its charts are projected). The texture's time and memory follow its texels (about 250
#: bytes a texel at the peak): at the bound about 3.1 GiB and under a minute on two cores, whatever
#: the mesh's tessellation and however well its charts pack.
MAX_TEXELS = 15_000_000
JPEG_QUALITY = 92


class TextureError(ValueError):
    """The scan cannot be textured (no mesh, no image on disk), naming the scan and why."""


@dataclass(frozen=True)
class BodyTexture:
    """The textured body: atlas, texture (H, W, 3) uint8, per-texel samples, the images'
    exposure, where the time went (seconds per step), and the gutter
    texels that hold the skin continuing over their chart's edge (analysis/atlas.py
    seam_gutters): (G, 2) row, column and (G, 3) mm the surface point each was taken from."""

    atlas: Atlas
    texture: np.ndarray
    samples: Samples
    exposure: Exposure
    seconds: dict[str, float]
    gutter_rc: np.ndarray
    gutter_point: np.ndarray


def stored_image_size(scan: ScanRecord) -> tuple[int, int]:
    """(width, height) px of the scan's stored images (simulated phones store small ones)."""
    for image in scan.images:
        if scan.image_on_disk(image):
            return picture_size(scan.path / image.file)
    raise TextureError(f"scan {scan.path}: no verified image on disk to texture from")


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


def sample_images(scan: ScanRecord, samples: Samples) -> np.ndarray:
    """(K, 3) float32 RGB of every blended pair, bicubic at its pixel; images read one at a
    time on each thread (:func:`planner.cores.each`)."""
    colours = np.empty((len(samples.pose), 3), dtype=np.float32)

    def sample(group: tuple[int, np.ndarray]) -> None:
        pose, mine = group
        colours[mine] = bicubic(scan.pixels_at(pose), samples.u[mine], samples.v[mine])

    each(sample, by_image(samples.pose), name="sample")
    return colours


def blend(samples: Samples, colours: np.ndarray, exposure: Exposure, n_texels: int) -> tuple[np.ndarray, np.ndarray]:
    """Per texel (T, 3) the weighted mean of its samples' colours (K, 3) with their exposure
    (gain and light falloff) taken out, weighted by :func:`analysis.texel_views.squarely`, and
    (T,) whether any image gave it a colour; samples in
    blocks of about SAMPLE_BLOCK that end where a texel's samples end (samples grouped by
    texel), each summed over the texels it spans: a short range no other block writes, so
    blocks run two at once where a core is spare."""
    total = np.zeros(n_texels)
    out = np.zeros((n_texels, 3))
    texels = samples.texel
    cuts = np.unique(np.r_[0, np.searchsorted(texels, texels[SAMPLE_BLOCK::SAMPLE_BLOCK]), len(texels)])

    def add(block: tuple[int, int]) -> None:
        part = slice(*block)
        texel = texels[part]
        weight = squarely(samples.weight[part], samples.incidence[part])
        low = int(texel.min())
        span = int(texel.max()) - low + 1
        corrected = colours[part] / exposure.factor(samples.pose[part], samples.incidence[part])
        total[low:low + span] += np.bincount(texel - low, weight, minlength=span)
        for c in range(3):
            out[low:low + span, c] += np.bincount(texel - low, weight * corrected[:, c], minlength=span)

    each(add, zip(cuts[:-1].tolist(), cuts[1:].tolist()), name="blend")
    seen = total > 0
    out[seen] /= total[seen, None]
    return out, seen


def texture_scan(scan: ScanRecord, *, texel_mm: float | None = None, max_side: int = MAX_SIDE,
                 progress: Callable[[str], None] | None = None) -> BodyTexture:
    """Texture a scan's mesh from its images (see the module docstring). texel_mm None: from the
    images' resolution on the skin (TEXEL_PER_PIXEL of the median best image's mm/px)."""
    say = progress or (lambda _text: None)
    heap_for_large_arrays()
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
    budget_mm = math.sqrt(float(mesh.area) / MAX_TEXELS)
    if budget_mm > texel_mm:
        say(f"{texel_mm:.2f} mm per texel would need more than {MAX_TEXELS / 1e6:g} M texels: {budget_mm:.2f} mm")
        texel_mm = budget_mm
    say(f"unwrapping {len(faces)} triangles at {texel_mm:.2f} mm per texel")
    atlas = unwrap(vertices, faces, texel_mm, max_side=max_side)
    lap("atlas")
    say(f"atlas {atlas.shape[1]} x {atlas.shape[0]}, {atlas.charts} charts, {len(atlas.texel_rc)} texels on the skin")
    per_face = candidate_poses(nav, vertices, faces, size)
    lap("candidates")
    smooth = smooth_face_normals(vertices, faces)
    samples = texel_views(nav, atlas, normals, smooth, per_face, size)
    lap("views")
    say(f"{len(samples.pose)} image samples from {np.count_nonzero(np.bincount(samples.pose))} images")
    colours = sample_images(scan, samples)
    lap("sample")
    fit = _overlapping(samples, 2 * MAX_EQUATIONS)
    exposure = fit_exposure(samples.texel[fit], samples.pose[fit], samples.incidence[fit], colours[fit],
                            samples.weight[fit], scan.rig.n_poses)
    del fit
    lap("exposure")
    colour, seen = blend(samples, colours, exposure, len(atlas.texel_rc))
    del colours
    texture = np.zeros((*atlas.shape, 3), dtype=np.uint8)
    filled = np.zeros(atlas.shape, dtype=bool)
    rows, cols = atlas.texel_rc[seen, 0], atlas.texel_rc[seen, 1]
    texture[rows, cols] = np.clip(np.rint(colour[seen]), 0, 255)
    filled[rows, cols] = True
    del colour, rows, cols
    lap("blend")
    texture, gutter_rc, gutter_point = seam_gutters(atlas, texture, filled, nav.scene.closest_faces)
    lap("gutters")
    return BodyTexture(atlas, texture, samples, exposure, seconds, gutter_rc, gutter_point)


def _overlapping(samples: Samples, equations: int) -> np.ndarray:
    """The indices of the samples the exposure fit reads: every sample when the texels two or
    more images texture hold at most ``equations`` overlaps, else those of a random share (fixed
    seed) of those texels holding about that many, so the fit's size is bounded whatever the
    atlas' size."""
    starts, counts = runs(samples.texel)
    shared = np.flatnonzero(counts >= 2)
    total = int((counts[shared] - 1).sum())
    if total <= equations:
        return np.arange(len(samples.texel))
    group = shared[np.sort(np.random.default_rng(0).choice(len(shared), len(shared) * equations // total, replace=False))]
    size = counts[group]
    index: np.ndarray = np.repeat(starts[group] - (np.cumsum(size) - size), size) + np.arange(size.sum())
    return index


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
        progress("steps: " + ", ".join(f"{name} {seconds:.1f} s" for name, seconds in body.seconds.items()))
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
