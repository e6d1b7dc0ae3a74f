"""Carrying a mark the last millimetres on the pictures: the skin around it, matched between scans.

The meshes alone carry a mark to within a few millimetres (analysis/registration.py), but on
flat skin (a back, a thigh) nothing in the shape holds it in place along the skin. The skin
itself does: freckles, naevi, pores. Around the mark, a small square of skin is resampled from
the earlier scan's sharpest pictures onto the skin's tangent plane (a rectified patch, in mm,
so the camera's distance and angle drop out); around the carried point, a larger square is
resampled from the later scan's pictures the same way, turned by the local registration's
rotation. Normalised cross-correlation of the two (after taking out the shading's slow
gradient) finds the offset along the skin; the carried point moves by it only when the match
is distinct and the pictures agree, otherwise the shape's answer stands.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

STEP_MM = 0.5
"""Sample spacing of the rectified patches."""
TEMPLATE_HALF_MM = 10.0
SEARCH_MM = 8.0
"""How far along the skin the pictures may move a carried mark."""
MIN_SCORE = 0.45
"""Lowest normalised cross-correlation a match needs."""
MIN_MARGIN = 0.1
"""A match must beat the best one elsewhere (beyond 2 mm) by this much: repeated skin is no match."""
AGREE_MM = 1.5
"""Two pictures agree when their offsets are this close; a match needs two that agree, or"""
SURE_SCORE, SURE_MARGIN = 0.75, 0.15
"""one picture alone this clear."""
VIEWS = 3
"""Pictures tried per scan, best first (navigation's ranking)."""
SHADING_SIGMA_MM = 3.0
MIN_CONTRAST = 2.0
"""Grey-level spread (after the shading is taken out) below which a patch is blank skin."""
NORMAL_RADIUS_MM = 6.0
RISE_MM = 15.0
"""The rectified patch is the skin met by rays along the normal from this far above the plane."""


@dataclass(frozen=True)
class PictureMatch:
    """The carried point moved along the later scan's skin, and the match's score."""

    point_mm: np.ndarray
    score: float


def tangent_frame(normal: np.ndarray, along: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane normal to ``normal``; the first as close to ``along``
    (default: horizontal, across the vertical) as the plane allows."""
    n = normal / np.linalg.norm(normal)
    if along is None:
        along = np.cross([0.0, 0.0, 1.0], n)
        if np.linalg.norm(along) < 1e-6:  # the top of the head: any direction will do
            along = np.array([1.0, 0.0, 0.0])
    e1 = along - n * float(np.dot(along, n))
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


@lru_cache(maxsize=16)
def _grey(path: Path, least_width_px: int) -> np.ndarray | None:
    """The picture in grey levels (H, W) uint8, decoded at the smallest JPEG scale that is at
    least ``least_width_px`` wide (a rig's 40-megapixel picture is far finer than the patches
    need); None when it cannot be read."""
    from PIL import Image

    try:
        with Image.open(path) as image:
            image.draft("L", (least_width_px, least_width_px * image.height // max(image.width, 1)))
            return np.asarray(image.convert("L"))
    except (OSError, ValueError, Image.DecompressionBombError):
        return None


class ScanPictures:
    """One scan's mesh, poses and pictures, resampled onto the skin's tangent plane."""

    def __init__(self, navigator: Any) -> None:
        self.navigator = navigator
        self.scene = navigator.scene
        self.rig = navigator.scan.rig
        self._vertices: Any = None

    def normal(self, point: np.ndarray) -> np.ndarray:
        """Outward unit normal of the skin at ``point``: of the plane through the mesh within
        NORMAL_RADIUS_MM (one triangle of a scanned mesh tilts by tens of degrees)."""
        from scipy.spatial import cKDTree

        _, faces = self.scene.closest_faces(point[None, :])
        outward = self.scene.face_normals[int(np.asarray(faces).reshape(-1)[0])]
        if self._vertices is None:
            self._vertices = cKDTree(np.asarray(self.navigator.mesh.vertices, dtype=float))
        near = self._vertices.data[self._vertices.query_ball_point(point, NORMAL_RADIUS_MM)]
        if len(near) < 6:
            return outward
        _, _, axes = np.linalg.svd(near - near.mean(axis=0), full_matrices=False)
        normal = axes[2]
        return normal if normal @ outward >= 0 else -normal

    def skin(self, point: np.ndarray, e1: np.ndarray, e2: np.ndarray, half_mm: float) -> np.ndarray:
        """(S, S, 3) points of the skin under a square grid on the tangent plane at ``point``,
        found along the normal (NaN where the skin is not within RISE_MM of the plane)."""
        steps = np.arange(-half_mm, half_mm + STEP_MM / 2, STEP_MM)
        a, b = np.meshgrid(steps, steps, indexing="ij")
        normal = np.cross(e1, e2)
        above = point + a.reshape(-1, 1) * e1 + b.reshape(-1, 1) * e2 + RISE_MM * normal
        down = np.repeat(-normal[None, :], len(above), axis=0)
        t = self.scene.first_hits(above, down)
        t[t > 2 * RISE_MM] = np.nan
        return (above - t[:, None] * normal).reshape(len(steps), len(steps), 3)

    def towards_camera(self, view: dict[str, Any], point: np.ndarray) -> np.ndarray:
        direction = self.navigator.poses.centres[view["pose"]] - point
        return direction / np.linalg.norm(direction)

    def views(self, point: np.ndarray) -> list[dict[str, Any]]:
        """The best views of the point that are in focus, best first."""
        answer = self.navigator.query(point=point, count=VIEWS)
        return [v for v in answer["views"] if v["in_focus"]]

    def sample(self, view: dict[str, Any], grid: np.ndarray) -> np.ndarray:
        """The picture's grey levels at the grid's skin points (NaN: outside it, or hidden)."""
        from scipy.ndimage import map_coordinates

        from planner.navigation import pixel_of

        optics = self.rig.optics
        # pixels of at most half a patch step at the view's depth
        least = int(np.ceil(optics.image_width_px * min(1.0, 2.0 * view["resolution_mm_px"] / STEP_MM)))
        image = _grey(self.navigator.scan.path / view["file"], least)
        values = np.full(grid.shape[:2], np.nan, dtype=np.float32).reshape(-1)
        points = grid.reshape(-1, 3)
        known = np.flatnonzero(np.isfinite(points).all(axis=1))  # where the skin was found
        if image is None or not len(known):
            return values.reshape(grid.shape[:2])
        points = points[known]
        u, v = pixel_of(self.navigator.poses, np.full(len(points), view["pose"]), points, self.rig)
        scale = image.shape[1] / optics.image_width_px
        u, v = u * scale - 0.5, v * scale - 0.5  # pixel centres at .5
        inside = (u >= 0) & (v >= 0) & (u <= image.shape[1] - 1) & (v <= image.shape[0] - 1)
        centre = self.navigator.poses.centres[view["pose"]]
        seen = inside & ~np.asarray(self.scene.occluded(np.repeat(centre[None, :], len(points), axis=0), points, 2.0),
                                    dtype=bool)
        values[known[seen]] = map_coordinates(image.astype(np.float32), [v[seen], u[seen]], order=1)
        return values.reshape(grid.shape[:2])


def _detail(patch: np.ndarray) -> np.ndarray:
    """The patch without its slow shading gradient; NaN where the picture had nothing."""
    from scipy.ndimage import gaussian_filter

    known = np.isfinite(patch)
    filled = np.where(known, patch, 0.0)
    sigma = SHADING_SIGMA_MM / STEP_MM
    weight = gaussian_filter(known.astype(float), sigma)
    smooth = gaussian_filter(filled, sigma) / np.maximum(weight, 1e-6)
    return np.where(known, patch - smooth, np.nan)


def ncc_map(template: np.ndarray, search: np.ndarray, min_overlap: float = 0.6) -> np.ndarray:
    """Normalised cross-correlation of ``template`` (T, T) at every offset inside ``search``
    (S, S), S >= T: (S - T + 1, S - T + 1). NaN pixels of either are left out of each sum (masked
    NCC, Padfield 2012); an offset where under ``min_overlap`` of the template's pixels meet known
    search pixels scores -1."""
    from scipy.signal import fftconvolve

    def correlate(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return fftconvolve(a, b[::-1, ::-1], mode="valid")

    mask_t = np.isfinite(template).astype(float)
    mask_s = np.isfinite(search).astype(float)
    t = np.where(mask_t > 0, template, 0.0)
    s = np.where(mask_s > 0, search, 0.0)
    count = correlate(mask_s, mask_t)
    enough = count >= min_overlap * template.size
    count = np.maximum(count, 1.0)
    sum_s, sum_t = correlate(s, mask_t), correlate(mask_s, t)
    var_s = correlate(s * s, mask_t) - sum_s ** 2 / count
    var_t = correlate(mask_s, t * t) - sum_t ** 2 / count
    covariance = correlate(s, t) - sum_s * sum_t / count
    scale = np.sqrt(np.maximum(var_s, 0.0) * np.maximum(var_t, 0.0))
    scores = covariance / np.maximum(scale, 1e-9)
    return np.where(enough & (scale > 1e-6), np.clip(scores, -1.0, 1.0), -1.0)


def _consensus(found: list[tuple[float, float, float, float]]) -> tuple[float, float, float] | None:
    """The offset the later pictures agree on: the best match and those within AGREE_MM of it,
    when at least two pictures agree, or one alone when it is unmistakable; None otherwise."""
    if not found:
        return None
    offsets = np.array([f[:2] for f in found])
    scores = np.array([f[2] for f in found])
    best = int(np.argmax(scores))
    agree = np.hypot(*(offsets - offsets[best]).T) <= AGREE_MM
    alone = scores[best] >= SURE_SCORE and found[best][3] >= SURE_MARGIN
    if agree.sum() < 2 and not alone:
        return None
    a, b = np.average(offsets[agree], axis=0, weights=scores[agree])
    return float(a), float(b), float(scores[best])


def _peak(scores: np.ndarray) -> tuple[float, float, float, float]:
    """(row, column) of the best score to a fraction of a cell, the score, and the best score
    more than 2 mm away from it."""
    i, j = np.unravel_index(int(np.argmax(scores)), scores.shape)
    best = float(scores[i, j])

    def vertex(m: float, c: float, p: float) -> float:
        denominator = m - 2 * c + p
        return 0.0 if denominator >= 0 else float(np.clip(0.5 * (m - p) / denominator, -0.5, 0.5))

    di = vertex(scores[i - 1, j], best, scores[i + 1, j]) if 0 < i < scores.shape[0] - 1 else 0.0
    dj = vertex(scores[i, j - 1], best, scores[i, j + 1]) if 0 < j < scores.shape[1] - 1 else 0.0
    rows, cols = np.indices(scores.shape)
    far = np.hypot(rows - i, cols - j) * STEP_MM > 2.0
    runner_up = float(scores[far].max()) if far.any() else -1.0
    return i + di, j + dj, best, runner_up


class PictureMatcher:
    """Moves points carried from an earlier scan onto a later one by matching the skin's pictures."""

    def __init__(self, earlier: Any, later: Any) -> None:
        self.earlier = ScanPictures(earlier)
        self.later = ScanPictures(later)

    def refine(self, mark: np.ndarray, carried: np.ndarray, rotation: np.ndarray) -> PictureMatch | None:
        """``mark`` on the earlier mesh, ``carried`` its place on the later mesh by the shapes,
        ``rotation`` (3, 3) the local fit's turn from the earlier to the later scan: the carried
        point moved to where the pictures match, or None when they do not tell.

        A match must hold both ways: the later scan's skin at the matched point, looked for in
        the earlier scan's pictures, must be found back at the mark."""
        e1, e2 = tangent_frame(self.earlier.normal(mark))
        forward = _locate(_templates(self.earlier, mark, e1, e2, rotation), self.later, carried,
                          *tangent_frame(self.later.normal(carried), rotation @ e1))
        if forward is None:
            return None
        moved, later_e1, later_e2, score = forward
        back = _locate(_templates(self.later, moved, later_e1, later_e2, rotation.T), self.earlier, mark, e1, e2)
        if back is None or np.linalg.norm(back[0] - mark) > AGREE_MM:
            return None
        return PictureMatch(moved, score)


@dataclass(frozen=True)
class _Template:
    """The rectified skin around a point in one picture, and the direction it was seen from
    (unit, towards the camera, turned into the other scan's frame)."""

    patch: np.ndarray
    towards_camera: np.ndarray


def _templates(pictures: ScanPictures, point: np.ndarray, e1: np.ndarray, e2: np.ndarray,
               rotation: np.ndarray) -> list[_Template]:
    """The skin around ``point`` in the scan's best pictures, rectified (blank skin left out: it
    matches anything)."""
    grid = pictures.skin(point, e1, e2, TEMPLATE_HALF_MM)
    templates = []
    for view in pictures.views(point):
        patch = _detail(pictures.sample(view, grid))
        if np.isfinite(patch).mean() >= 0.6 and np.nanstd(patch) > MIN_CONTRAST:
            templates.append(_Template(patch, rotation @ pictures.towards_camera(view, point)))
    return templates


def _locate(templates: list[_Template], pictures: ScanPictures, centre: np.ndarray, e1: np.ndarray,
            e2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
    """Where the templates' skin is within SEARCH_MM of ``centre`` in the scan's pictures: the
    skin point, the frame searched in and the best score; None when the pictures do not agree.

    Each picture is searched with the template seen from the nearest direction: where the
    scanned surface is off the skin by a millimetre, pictures from different directions see
    the skin shifted against each other, pictures from the same direction alike."""
    if not templates:
        return None
    grid = pictures.skin(centre, e1, e2, TEMPLATE_HALF_MM + SEARCH_MM)
    found = []  # per picture: (offset along e1, along e2, score, margin)
    for view in pictures.views(centre):
        towards = pictures.towards_camera(view, centre)
        template = max(templates, key=lambda t: float(t.towards_camera @ towards))
        row, col, score, runner_up = _peak(ncc_map(template.patch, _detail(pictures.sample(view, grid))))
        middle = SEARCH_MM / STEP_MM
        a, b = (row - middle) * STEP_MM, (col - middle) * STEP_MM
        if score >= MIN_SCORE and score - runner_up >= MIN_MARGIN and max(abs(a), abs(b)) < SEARCH_MM - STEP_MM:
            found.append((a, b, score, score - runner_up))  # (a peak on the rim is no peak)
    chosen = _consensus(found)
    if chosen is None:
        return None
    a, b, score = chosen
    point = pictures.skin(centre + a * e1 + b * e2, e1, e2, 0.0)[0, 0]
    if not np.isfinite(point).all():
        return None
    return point, e1, e2, score  # the frame the match was found in, for the check back
