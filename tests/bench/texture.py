"""The photographic body (issue 30 item 1) on simulated people, whose skin is known.

For each body and render scale: a default simulated scan (no QA report) whose phones render at
the scale times 192 x 256 px (``render_scale``, sim/rig.py SimOptions; 1 is the default scan,
about 1.6 mm/px on the skin at the best image, 2 about 0.8 mm/px, 4 about 0.4 mm/px; the rig's
phones hold 32), then ``tbp texture`` on it in a child process (wall time and peak RSS, goals
<= 60 s and <= 4 GiB), the step after a scan as the daemon runs it (QA report and body in its
compute worker, wall time, goal <= 60 s), the scan in the viewer (headless Chromium on loopback,
fresh server each time: first paint of the QA map's mesh, goal <= 1.5 s; the skin with the
preview atlas; the full atlas on the screen, goal <= 5 s), then against the simulated truth (the
body mesh, its skin coordinates and the freckles drivers/sim/skin_texture.py paints on it):

- colour: mean CIEDE2000 of the texels whose best image holds them sharp, against the skin's
  albedo (the simulated phones light it with a falloff over the incidence, which the texture
  takes out), split by how far the scan's surface is from the true skin there; goal <= 3;
- the surface off the skin: how far the scan's surface is from the true skin along its normal
  (median, 90th percentile, mean);
- lesions: the freckles of the dark layer whose disc on the skin is >= 1.5 mm across and that
  the images hold sharp; found when a simple spot detector on the atlas (a difference of
  Gaussians: darker at the spot's scale than the skin around it, a local maximum; on the charts'
  texels and the gutter texels that hold the skin over a chart's edge, each at the surface point
  its colour was taken from) has a spot within 1 mm of it on the true skin; goal >= 95 %. The
  detector is checked on the skin's own albedo at the same texels, where it finds nearly all. The
  misses are split by the disc's width in the best image's pixels, the disc, the best image's
  mm/px, the scan surface's distance from the skin, the heaviest image's angle to the skin, and
  the distance from an atlas chart's edge and from a hole in the scan's mesh: found / detected
  1-3 mm off / not detected. A 1.5 mm disc spans about one pixel at scale 1, two at 2 and four at 4: the goal
  means something from scale 2 on;
- the textured surface more than 10 mm off the true skin (the TSDF's webbing between limbs);
- resolution: the texture's texel on the skin (mm, from each triangle's area on the skin and in
  the atlas) against the best image's mm/px at that texel, median ratio; goal <= 1.5.

A table of every body and scale ends the output.

    python -m tests.bench texture    (TBP_TEXTURE_SEEDS=0,3 for other bodies, TBP_TEXTURE_SCALES=1,2,4
                                      for other render scales; default bodies 0, scales 1 and 2;
                                      scale 4's scan renders for 3-6 min a body)
"""

from __future__ import annotations

import logging
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import structlog
from scipy import ndimage

#: The environment ``tbp texture`` runs in, as the bench was started: a simulated scan sets this
#: process' numeric libraries to one thread, as the daemon does, and a command run by hand has both cores.
_ENVIRONMENT = dict(os.environ)
SEEDS = tuple(int(s) for s in os.environ.get("TBP_TEXTURE_SEEDS", "0").split(","))
SCALES = tuple(int(s) for s in os.environ.get("TBP_TEXTURE_SCALES", "1,2").split(","))
GOAL_S = 60.0
GOAL_GIB = 4.0
GOAL_DELTA_E = 3.0
GOAL_PAINT_MS = 1500
GOAL_FULL_MS = 5000
VIEWER_LOADS = 3
GOAL_LESIONS = 0.95
GOAL_RESOLUTION = 1.5
LESION_MM = 1.5
MATCH_MM = 1.0
#: Darkness (1 - luminance / the skin around) a detected spot must reach.
SPOT_DARKNESS = 0.06
#: The skin around a spot: Gaussian of this sigma (mm) over the atlas' filled texels.
BACKGROUND_MM = 4.0
#: A spot's scale: Gaussian of this sigma (mm), half the smallest lesion counted.
SPOT_MM = LESION_MM / 2
#: Bands of distance from an atlas chart's edge (mm) the lesions are split by.
EDGE_BANDS_MM = (0, 2, 4, 8, np.inf)
#: Bands of distance from an open edge of the scan's mesh (mm): a hole, where the webbing between
#: an arm and the torso was carved away or no depth frame saw the skin, and the soles.
HOLE_BANDS_MM = (0, 3, 6, 10, 20, np.inf)


def srgb_to_lab(rgb: np.ndarray) -> np.ndarray:
    """(N, 3) sRGB 0..255 -> CIELAB (D65)."""
    c = np.asarray(rgb, dtype=float) / 255.0
    linear = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    m = np.array([[0.4124564, 0.3575761, 0.1804375], [0.2126729, 0.7151522, 0.0721750],
                  [0.0193339, 0.1191920, 0.9503041]])
    xyz = linear @ m.T / np.array([0.95047, 1.0, 1.08883])
    f = np.where(xyz > (6 / 29) ** 3, np.cbrt(xyz), xyz / (3 * (6 / 29) ** 2) + 4 / 29)
    return np.stack([116 * f[:, 1] - 16, 500 * (f[:, 0] - f[:, 1]), 200 * (f[:, 1] - f[:, 2])], axis=1)


def delta_e00(lab1: np.ndarray, lab2: np.ndarray) -> np.ndarray:
    """(N,) CIEDE2000 colour difference of CIELAB colours (N, 3) (Sharma, Wu, Dalal 2005)."""
    l1, a1, b1 = lab1.T
    l2, a2, b2 = lab2.T
    c_bar = (np.hypot(a1, b1) + np.hypot(a2, b2)) / 2
    g = 0.5 * (1 - np.sqrt(c_bar**7 / (c_bar**7 + 25.0**7)))
    a1p, a2p = (1 + g) * a1, (1 + g) * a2
    c1p, c2p = np.hypot(a1p, b1), np.hypot(a2p, b2)
    h1p = np.degrees(np.arctan2(b1, a1p)) % 360
    h2p = np.degrees(np.arctan2(b2, a2p)) % 360
    dl, dc = l2 - l1, c2p - c1p
    dh = h2p - h1p
    dh = np.where(dh > 180, dh - 360, np.where(dh < -180, dh + 360, dh))
    dh = np.where(c1p * c2p == 0, 0.0, dh)
    dhh = 2 * np.sqrt(c1p * c2p) * np.sin(np.radians(dh / 2))
    l_bar, cp_bar = (l1 + l2) / 2, (c1p + c2p) / 2
    hsum = h1p + h2p
    h_bar = np.where(np.abs(h1p - h2p) > 180, np.where(hsum < 360, hsum + 360, hsum - 360), hsum) / 2
    h_bar = np.where(c1p * c2p == 0, hsum, h_bar)
    t = (1 - 0.17 * np.cos(np.radians(h_bar - 30)) + 0.24 * np.cos(np.radians(2 * h_bar))
         + 0.32 * np.cos(np.radians(3 * h_bar + 6)) - 0.20 * np.cos(np.radians(4 * h_bar - 63)))
    sl = 1 + 0.015 * (l_bar - 50) ** 2 / np.sqrt(20 + (l_bar - 50) ** 2)
    sc, sh = 1 + 0.045 * cp_bar, 1 + 0.015 * cp_bar * t
    rt = (-2 * np.sqrt(cp_bar**7 / (cp_bar**7 + 25.0**7))
          * np.sin(np.radians(60 * np.exp(-(((h_bar - 275) / 25) ** 2)))))
    return np.sqrt((dl / sl) ** 2 + (dc / sc) ** 2 + (dhh / sh) ** 2 + rt * (dc / sc) * (dhh / sh))


class Truth:
    """The simulated body: closest skin point, its skin coordinates, albedo and normal."""

    def __init__(self, mesh) -> None:
        from planner.visibility import RayScene

        self.mesh = mesh
        skin = mesh.vertex_attributes.get("skin_mm")
        self.skin = np.asarray(mesh.vertices if skin is None else skin, dtype=float)
        self.scene = RayScene(mesh)

    def at(self, points: np.ndarray) -> dict[str, np.ndarray]:
        """For points (N, 3) mm: the closest true skin point, its distance, skin coordinates,
        smooth outward normal and albedo (N, 3) 0..255."""
        from drivers.sim.phone_render import SKIN_RGB
        from drivers.sim.skin_texture import pigment, pigmented

        closest, face = self.scene.closest_faces(points)
        corners = np.asarray(self.mesh.vertices, dtype=float)[self.mesh.faces[face]]
        weights = _barycentric(closest, corners)
        skin = np.einsum("nk,nkj->nj", weights, self.skin[self.mesh.faces[face]])
        normal = np.einsum("nk,nkj->nj", weights, np.asarray(self.mesh.vertex_normals)[self.mesh.faces[face]])
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-9)
        albedo = pigmented(np.tile(SKIN_RGB.astype(np.float32), (len(points), 1)), pigment(skin))
        return {"point": closest, "distance": np.linalg.norm(closest - points, axis=1), "skin": skin,
                "normal": normal, "albedo": albedo}


def _barycentric(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    v0, v1, v2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], p - tri[:, 0]
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
    den = np.where(d00 * d11 - d01 * d01 == 0, 1.0, d00 * d11 - d01 * d01)
    w1, w2 = (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den
    return np.stack([1 - w1 - w2, w1, w2], axis=1)


def lesions(truth: Truth) -> tuple[np.ndarray, np.ndarray]:
    """The dark layer's freckles on the skin at least LESION_MM across: their points on the
    true skin (K, 3) mm and disc diameters (K,) mm."""
    from drivers.sim.skin_texture import LAYERS, layer_spots
    from planner.sampling import sample_surface

    layer = LAYERS[0]
    dense = sample_surface(truth.mesh, int(truth.mesh.area / 4.0), seed=5)  # a sample per 4 mm^2
    skin = truth.at(dense.points)["skin"]
    cells = np.unique(np.floor(skin / layer.cell_mm).astype(np.int64), axis=0)
    _, centre, radius, _ = layer_spots(cells, layer)
    # the ball's centre in skin coordinates -> the closest skin point (the unswayed body: skin = world)
    on = truth.at(centre.astype(float))
    disc = 2 * np.sqrt(np.maximum(radius**2 - on["distance"] ** 2, 0.0))
    keep = disc >= LESION_MM
    return on["point"][keep], disc[keep]


def detect_spots(texture: np.ndarray, filled: np.ndarray, texel_mm: float) -> np.ndarray:
    """(D, 2) float row, column of dark spots in an atlas (H, W, 3) uint8: a difference of
    Gaussians over the filled texels, the luminance smoothed over SPOT_MM against the skin around
    (BACKGROUND_MM); its local maxima above SPOT_DARKNESS, refined to the darkness-weighted
    centroid of their 3 x 3 texels. Smoothed at the spot's scale, a flat disc's darkness peaks at
    its centre (the texels' own darkness peaks anywhere on it)."""
    from scipy import ndimage

    luminance = texture.astype(float) @ np.array([0.2126, 0.7152, 0.0722])
    inside = ndimage.binary_erosion(filled, iterations=1)
    weight = filled.astype(float)

    def smoothed(sigma_mm: float) -> np.ndarray:
        sigma = sigma_mm / texel_mm
        total = ndimage.gaussian_filter(np.where(filled, luminance, 0.0), sigma)
        return total / np.maximum(ndimage.gaussian_filter(weight, sigma), 1e-6)

    dark = np.where(inside, 1.0 - smoothed(SPOT_MM) / np.maximum(smoothed(BACKGROUND_MM), 1.0), 0.0)
    peaks = (dark >= SPOT_DARKNESS) & (dark == ndimage.maximum_filter(dark, size=3))
    rows, cols = np.nonzero(peaks)
    offsets = np.array([(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1)])
    r = np.clip(rows[:, None] + offsets[:, 0], 0, dark.shape[0] - 1)
    c = np.clip(cols[:, None] + offsets[:, 1], 0, dark.shape[1] - 1)
    w = np.maximum(dark[r, c], 0.0) * filled[r, c]
    total = np.maximum(w.sum(axis=1), 1e-9)
    return np.stack([(w * r).sum(axis=1) / total, (w * c).sum(axis=1) / total], axis=1) + 0.5  # centres at +0.5


#: ``tbp texture`` in a child process that says its own peak RSS last on stderr: VmHWM, the
#: high-water mark of its own memory (ru_maxrss carries the parent's over the fork and exec).
_TEXTURE_CHILD = ("import sys\nfrom cli import main\ncode = main(sys.argv[1:])\n"
                  "peak = next(line for line in open('/proc/self/status') if line.startswith('VmHWM:')).split()[1]\n"
                  "print(f'peak_rss_kib {peak}', file=sys.stderr)\nsys.exit(code)")


def _one(seed: int, scale: int, root: Path) -> dict[str, float]:
    from drivers.sim.phone import RENDER_SIZE
    from sim.run import run_sim_scan

    started = time.perf_counter()
    report = run_sim_scan(store=root / f"s{seed}x{scale}", seed=seed, panel=False, render_scale=scale,
                          depth_decimation=1)  # the depth cameras at the rig's resolution
    print(f"body {seed}, phones at {RENDER_SIZE[0] * scale} x {RENDER_SIZE[1] * scale} px (render scale {scale}): "
          f"simulated scan {report.outcome.value} in {time.perf_counter() - started:.0f} s", flush=True)
    return measure(report.folder, seed)


def measure(folder: Path, seed: int) -> dict[str, float]:
    """Texture the scan in ``folder`` of the simulated body ``seed``, print its figures and
    return the headline ones."""
    from scipy.spatial import cKDTree

    from analysis.body_texture import texture_scan
    from analysis.scan_views import open_scan
    from sim.rig import default_subject

    env = {**_ENVIRONMENT, "PYTHONPATH": os.pathsep.join([str(Path(__file__).resolve().parents[2]),
                                                          _ENVIRONMENT.get("PYTHONPATH", "")])}
    started = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", _TEXTURE_CHILD, "texture", str(folder)], check=False, env=env,
                          capture_output=True, text=True)
    texture_s = time.perf_counter() - started
    *lines, last = done.stderr.strip().splitlines() or [""]
    peak_gib = float(last.removeprefix("peak_rss_kib ")) / 2**20 if last.startswith("peak_rss_kib ") else float("nan")
    if done.returncode != 0:
        print(done.stderr[-2000:])
        raise SystemExit(f"tbp texture failed on body {seed}")
    size_mb = (folder / "body.glb").stat().st_size / 1e6
    print(f"  tbp texture {texture_s:.1f} s (goal <= {GOAL_S:.0f}), peak RSS {peak_gib:.2f} GiB "
          f"(goal <= {GOAL_GIB:.0f}), body.glb {size_mb:.1f} MB")
    for line in lines:
        print(f"    {line}")
    daemon_s = _after_scan_in_worker(folder)
    print(f"  the daemon's step after the scan (its QA report, then its body) in its compute worker: "
          f"{daemon_s:.1f} s (goal <= {GOAL_S:.0f})")
    viewer = _viewer_times(folder)
    if viewer:
        print(f"  the viewer on loopback (headless Chromium, software WebGL; median of {VIEWER_LOADS} fresh servers): "
              f"first paint {viewer['first']:.0f} ms (goal <= {GOAL_PAINT_MS}), the skin (preview atlas) "
              f"{viewer['preview']:.0f} ms, the full atlas ({viewer['size']}) {viewer['full']:.0f} ms "
              f"(goal <= {GOAL_FULL_MS}), max {viewer['full_max']:.0f} ms")

    # The same texture again in-process, for its per-texel records (deterministic).
    body = texture_scan(open_scan(folder))
    atlas, samples = body.atlas, body.samples
    truth = Truth(default_subject(seed))
    at = truth.at(atlas.texel_point)
    rows, cols = atlas.texel_rc[:, 0], atlas.texel_rc[:, 1]
    sharp = samples.best_sharp & (at["distance"] < 5.0)
    got = body.texture[rows, cols].astype(float)
    de = delta_e00(srgb_to_lab(at["albedo"][sharp]), srgb_to_lab(got[sharp]))
    close = at["distance"][sharp] < 2.0
    print(f"  colour on sharp skin ({100 * sharp.mean():.1f} % of the texels): mean CIEDE2000 {de.mean():.2f} against "
          f"the albedo (goal <= {GOAL_DELTA_E:.0f}), median {np.median(de):.2f}, 90th percentile "
          f"{np.percentile(de, 90):.2f}; where the scan's surface is within 2 mm of the skin ({100 * close.mean():.0f} %) "
          f"mean {de[close].mean():.2f}, elsewhere {de[~close].mean():.2f}")

    signed = np.einsum("ij,ij->i", atlas.texel_point - at["point"], at["normal"])[sharp]  # + outside the skin
    print(f"  surface off the skin on sharp texels: median {np.median(np.abs(signed)):.2f} mm, 90th percentile "
          f"{np.percentile(np.abs(signed), 90):.2f} mm (mean {signed.mean():+.2f})")

    # lesions
    # the atlas' textured texels and its gutter texels that hold the skin over a chart's edge,
    # each mapped to the surface point its colour was taken from
    filled = np.zeros(atlas.shape, dtype=bool)
    filled[rows, cols] = samples.best_pose >= 0
    filled[body.gutter_rc[:, 0], body.gutter_rc[:, 1]] = True
    index = np.full(atlas.shape, -1, dtype=np.int64)
    index[rows, cols] = np.arange(len(rows))
    index[body.gutter_rc[:, 0], body.gutter_rc[:, 1]] = len(rows) + np.arange(len(body.gutter_rc))
    lesion_points, disc = lesions(truth)
    texels = cKDTree(atlas.texel_point)
    _, nearest = texels.query(lesion_points)
    held = samples.best_sharp[nearest] & (np.linalg.norm(atlas.texel_point[nearest] - lesion_points, axis=1) < 5.0)
    surface_points = np.r_[atlas.texel_point, body.gutter_point]

    def found_at(texture: np.ndarray) -> tuple[np.ndarray, int]:
        """Each held lesion's distance (mm) to the nearest spot detected on ``texture``, and the spots."""
        spots = detect_spots(texture, filled, atlas.texel_mm)
        near = index[np.clip(np.rint(spots[:, 0] - 0.5).astype(int), 0, atlas.shape[0] - 1),
                     np.clip(np.rint(spots[:, 1] - 0.5).astype(int), 0, atlas.shape[1] - 1)]
        spots = spots[near >= 0]
        if not len(spots):
            return np.full(held.sum(), np.inf), 0
        # the spot's point on the scan's surface: its texel's point moved by the sub-texel offset
        # along the chart (approximated by the neighbouring texels' points)
        points = truth.at(_subtexel_points(spots, index, surface_points))["point"]
        return cKDTree(points).query(lesion_points[held])[0], len(spots)

    distance, n_spots = found_at(body.texture)
    found = distance <= MATCH_MM
    print(f"  lesions >= {LESION_MM} mm held sharp: {held.sum()} of {len(held)}; found within {MATCH_MM} mm: "
          f"{found.sum()} ({100 * found.mean():.1f} %, goal >= {100 * GOAL_LESIONS:.0f} %); within 2 mm "
          f"{100 * (distance <= 2.0).mean():.1f} %; spots detected {n_spots}; median disc {np.median(disc):.1f} mm")
    # the detector itself, on the skin's own albedo at the same texels and gutter texels
    albedo = body.texture.copy()
    albedo[rows, cols] = np.clip(np.rint(at["albedo"]), 0, 255)
    albedo[body.gutter_rc[:, 0], body.gutter_rc[:, 1]] = np.clip(np.rint(truth.at(body.gutter_point)["albedo"]), 0, 255)
    ideal, ideal_spots = found_at(albedo)
    del albedo
    print(f"  the detector on the skin's own albedo there: {100 * (ideal <= MATCH_MM).mean():.1f} % found within "
          f"{MATCH_MM} mm, {ideal_spots} spots")
    where = nearest[held]
    textured = np.zeros(atlas.shape, dtype=bool)
    textured[rows, cols] = True
    from_edge = ndimage.distance_transform_edt(textured)[rows[where], cols[where]] * atlas.texel_mm
    from_hole = _from_open_edge(atlas, atlas.texel_point[where])
    lesion_breakdown(distance, disc[held], samples.best_mm_px[where], at["distance"][where], _squarest_angle(samples, where),
                     from_edge, from_hole)
    for name, value, bands in (("the chart's edge", from_edge, EDGE_BANDS_MM), ("the mesh's open edge", from_hole, HOLE_BANDS_MM)):
        cells = ", ".join(f"{low:g}-{high:g}: {100 * (ideal[inside] <= MATCH_MM).mean():.0f} %"
                          for low, high, inside in _bands(value, bands))
        print(f"    the detector on the albedo, by mm from {name} (found): {cells}")

    # resolution: each triangle's skin area over its atlas area -> mm per texel on the skin
    tri = atlas.vertices[atlas.faces]
    skin_area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    uv = atlas.uv[atlas.faces] * np.array([atlas.shape[1], atlas.shape[0]])
    e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    uv_area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        texel_on_skin = np.sqrt(skin_area / uv_area)[atlas.texel_face]
    off = np.isfinite(texel_on_skin) & (at["distance"] > 10.0)
    print(f"  surface more than 10 mm off the true skin (the TSDF's webbing; its texture is not skin): "
          f"{np.sum(texel_on_skin[off] ** 2) / 100:.0f} cm^2, {100 * off.mean():.2f} % of the texels")
    ratio = texel_on_skin / samples.best_mm_px
    ok = np.isfinite(ratio) & sharp
    print(f"  resolution: texel {atlas.texel_mm:.2f} mm on the chart, median {np.median(texel_on_skin[ok]):.2f} mm on the "
          f"skin; best image median {np.nanmedian(samples.best_mm_px[ok]):.2f} mm/px; texel / pixel median "
          f"{np.median(ratio[ok]):.2f}, 95th percentile {np.percentile(ratio[ok], 95):.2f} (goal <= {GOAL_RESOLUTION})")
    return {"found": 100 * found.mean(), "found2": 100 * (distance <= 2.0).mean(), "delta_e": de.mean(),
            "mm_px": float(np.nanmedian(samples.best_mm_px[ok])), "ratio": float(np.median(ratio[ok])),
            "ideal": 100 * (ideal <= MATCH_MM).mean(), "seconds": texture_s, "daemon_s": daemon_s, "gib": peak_gib,
            "full_ms": viewer["full"] if viewer else float("nan")}


def _viewer_times(folder: Path) -> dict[str, Any] | None:
    """The scan in the viewer, each time from a fresh server and browser: ms from navigation to
    the first paint (the QA map's mesh), to the skin (the textured body with its preview atlas)
    and to the full atlas on the screen; None (said) without Chromium."""
    from tests.web_browser import chromium, chromium_missing, serve_in_thread, wait_for

    reason = chromium_missing()
    if reason:
        print(f"  the viewer: skipped ({reason})")
        return None
    loads = []
    for _ in range(VIEWER_LOADS):
        with serve_in_thread(folder.parent) as url, chromium() as driver:
            driver.get(f"{url}/scans/{folder.name}")
            wait_for(driver, "window.tbpViewer && (window.tbpViewer.textureLevel === 'full' || window.tbpViewer.error)", 120.0)
            loads.append(driver.execute_script("const v = window.tbpViewer; return {error: v.error, first: v.firstPaintMs, "
                                               "preview: v.timing.bodyBuiltMs, full: v.timing.fullTextureMs, size: v.textureSize}"))
    failed = next((x["error"] for x in loads if x["error"]), None)
    if failed:
        raise SystemExit(f"the viewer failed on {folder.name}: {failed}")
    size = loads[0]["size"]
    return {**{k: float(np.median([x[k] for x in loads])) for k in ("first", "preview", "full")},
            "full_max": max(x["full"] for x in loads), "size": f"{size['width']} x {size['height']} texels"}


def _after_scan_in_worker(folder: Path) -> float:
    """Seconds of the step after a scan as the daemon runs it in STORING (daemon/server/serve.py):
    analysis/body_texture.py report_and_body in a compute worker of its own (a batch job, one
    numeric thread, its loops on every core: daemon/offload/worker.py on_every_core), started
    and warmed up first."""
    from analysis.body_texture import report_and_body
    from daemon.offload.worker import compute_pool, on_every_core

    with compute_pool() as pool:
        pool.submit(int).result()
        started = time.perf_counter()
        pool.submit(on_every_core, report_and_body, folder).result()
        return time.perf_counter() - started


def lesion_breakdown(distance: np.ndarray, disc: np.ndarray, mm_px: np.ndarray, surface_mm: np.ndarray,
                     angle_deg: np.ndarray, from_edge_mm: np.ndarray, from_hole_mm: np.ndarray) -> None:
    """Print where the held lesions are lost: per bin of the disc's width in the best image's
    pixels, of its width across in the heaviest blended image (the disc foreshortened by that
    image's angle to the skin, in the best image's pixels), of the disc (mm), of the best image's
    mm/px, of the scan surface's distance from the true skin there, of the angle between the
    heaviest blended image's ray and the skin's normal (a surface d off the skin moves a spot
    d tan(angle)), of the distance from the atlas chart's edge (mm) and of the distance from an
    open edge of the scan's mesh (mm, a hole), the share found within
    MATCH_MM, detected but off (the nearest spot MATCH_MM..3 mm away) and not detected (no spot
    within 3 mm). All (K,) per lesion."""
    across = disc * np.cos(np.radians(np.nan_to_num(angle_deg, nan=90.0))) / mm_px  # foreshortened
    splits = (("disc px", disc / mm_px, (0, 1.5, 2.5, 4, np.inf)),
              ("disc px across (foreshortened by the angle)", across, (0, 1, 2, 3, np.inf)),
              ("disc mm", disc, (1.5, 2.5, 3.5, 4.5, np.inf)),
              ("mm/px", mm_px, (0, *np.round(np.nanpercentile(mm_px, [33, 67]), 2), np.inf)),
              ("surface off mm", surface_mm, (0, 1, 2, np.inf)), ("angle deg", angle_deg, (0, 20, 35, 50, 65, 90.01)),
              ("mm from the chart's edge", from_edge_mm, EDGE_BANDS_MM),
              ("mm from the mesh's open edge (a hole)", from_hole_mm, HOLE_BANDS_MM))
    for name, value, edges in splits:
        cells = []
        for low, high, inside in _bands(value, edges):
            d = distance[inside]
            cells.append(f"{low:g}-{high:g}: {inside.sum()} {100 * (d <= MATCH_MM).mean():.0f}/"
                         f"{100 * ((d > MATCH_MM) & (d <= 3.0)).mean():.0f}/{100 * (d > 3.0).mean():.0f}")
        print(f"    by {name} (n found/off/undetected %): " + "; ".join(cells))


def _bands(value: np.ndarray, edges: Any) -> list[tuple[float, float, np.ndarray]]:
    """Each band [low, high) of ``edges`` that holds a value (K,): low, high and which (K,) bool."""
    bands = [(low, high, (value >= low) & (value < high)) for low, high in zip(edges[:-1], edges[1:])]
    return [(low, high, inside) for low, high, inside in bands if inside.any()]


def _from_open_edge(atlas: Any, points: np.ndarray) -> np.ndarray:
    """(K,) mm from points (K, 3) to the nearest vertex on an open edge of the atlas' source mesh
    (an edge of one triangle: a hole, or the mesh's rim); inf where the mesh is closed."""
    from scipy.spatial import cKDTree

    faces = atlas.source_vertex[atlas.faces]
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    unique, count = np.unique(edges, axis=0, return_counts=True)
    rim = np.unique(unique[count == 1])
    if not len(rim):
        return np.full(len(points), np.inf)
    source = np.zeros((int(atlas.source_vertex.max()) + 1, 3))
    source[atlas.source_vertex] = atlas.vertices
    distance: np.ndarray = cKDTree(source[rim]).query(points)[0]
    return distance


def _squarest_angle(samples: Any, texels: np.ndarray) -> np.ndarray:
    """(K,) angle (deg) between the heaviest blended image's ray and the skin's normal at texels
    (K,) (samples are grouped by texel, heaviest first); NaN where no image textures one."""
    first = np.searchsorted(samples.texel, texels)
    has = first < len(samples.texel)
    has[has] = samples.texel[first[has]] == texels[has]
    angle = np.full(len(texels), np.nan)
    angle[has] = np.degrees(np.arccos(np.clip(np.abs(samples.incidence[first[has]]), 0.0, 1.0)))
    return angle


def _subtexel_points(spots: np.ndarray, index: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(D, 3) surface points of sub-texel atlas positions (D, 2) (row, column; texel centres at
    +0.5): bilinear over the filled texels around each."""
    r = spots[:, 0] - 0.5
    c = spots[:, 1] - 0.5
    r0, c0 = np.floor(r).astype(int), np.floor(c).astype(int)
    total = np.zeros((len(spots), 3))
    weight = np.zeros(len(spots))
    for dr in (0, 1):
        for dc in (0, 1):
            rr = np.clip(r0 + dr, 0, index.shape[0] - 1)
            cc = np.clip(c0 + dc, 0, index.shape[1] - 1)
            w = (1 - np.abs(r - (r0 + dr))) * (1 - np.abs(c - (c0 + dc)))
            i = index[rr, cc]
            w = np.where(i >= 0, w, 0.0)
            total += w[:, None] * points[np.maximum(i, 0)]
            weight += w
    return total / np.maximum(weight, 1e-9)[:, None]


def run() -> None:
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    rows = []
    with tempfile.TemporaryDirectory(prefix="tbp-texture-bench-") as root:
        for seed in SEEDS:
            for scale in SCALES:
                rows.append((seed, scale, _one(seed, scale, Path(root))))
                shutil.rmtree(Path(root) / f"s{seed}x{scale}")
    print(f"{'body':>4} {'scale':>5} {'mm/px':>6} {'found <= 1 mm':>14} {'<= 2 mm':>8} {'on albedo':>9} {'dE00':>5} {'texel/px':>8} "
          f"{'texture s':>9} {'daemon s':>8} {'GiB':>5} {'full atlas ms':>13}")
    for seed, scale, r in rows:
        print(f"{seed:>4} {scale:>5} {r['mm_px']:>6.2f} {r['found']:>13.1f}% {r['found2']:>7.1f}% {r['ideal']:>8.1f}% {r['delta_e']:>5.2f} "
              f"{r['ratio']:>8.2f} {r['seconds']:>9.1f} {r['daemon_s']:>8.1f} {r['gib']:>5.2f} {r['full_ms']:>13.0f}")
    print(f"peak memory of this process (max RSS) {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")


if __name__ == "__main__":
    run()
