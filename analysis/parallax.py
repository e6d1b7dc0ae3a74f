"""Where the scan's surface is off the skin, the images disagree about where a spot is on it.

A camera sees a skin point along its ray; a surface ``d`` mm above or below the skin meets that
ray ``d tan(angle)`` along the surface from the skin point's place on it (the angle between the
ray and the surface's normal), so images from different sides put one spot in different places
and a texture sampled where each ray meets the TSDF's surface smears and moves small lesions.
This module finds, per texel, the offset along the surface's normal at which the images agree
(a plane sweep over offsets, the colour differences between images summed over the atlas around
each texel), and the images are sampled at that offset: each image then puts the skin point seen
there on the texel that lies over it. The sweep compares more images than a texel blends (every
candidate image near its best, analysis/texel_views.py SWEEP_MARGIN), so skin one image textures
has its offset measured too; images seeing the skin squarely weigh most.

The offset is estimated twice: broadly (differences summed over centimetres, clear on almost
any skin) and locally (over a couple of millimetres, clear where the skin has texture of its
own, such as a lesion). The surface's distance from the skin changes by a millimetre over a few,
so a texel takes the local offset where the texels around have a clear one, else the broad one.
Where the images agree equally at every offset (plain skin, or a texel one image textures) the
offset is spread from the texels around that have a clear one, else zero.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy import ndimage

from analysis.pixels import bilinear, by_image
from analysis.texel_views import squarely
from planner.cores import each

if TYPE_CHECKING:
    from analysis.atlas import Atlas
    from analysis.exposure import Exposure
    from analysis.navigate import Navigator

#: Offsets along the surface's outward normal tried, mm (the TSDF surface is within ~3 mm of the skin).
OFFSETS_MM = np.arange(-3.0, 3.01, 0.5)
#: The sweep runs on the texels of a grid of about this pitch, mm (the offset changes over millimetres).
GRID_MM = 2.0
#: Colour differences are summed over a Gaussian of this sigma (mm) around each texel.
WINDOW_MM = 4.0
#: Offsets are spread over a Gaussian of this sigma (mm), weighted by how clear each one is.
SPREAD_MM = 8.0
#: A texel's offset counts when its best offset's difference is below this share of the mean.
CLEAR = 0.5
#: The local estimate: differences summed over a Gaussian of this sigma (mm) and clear offsets
#: spread over one of this sigma (mm). The TSDF surface's distance from the skin changes by a
#: millimetre over a few (averaging it over 8 mm is off by about 0.4 mm at half the skin),
#: and a lesion's own texture fixes the offset under it.
LOCAL_WINDOW_MM = 1.5
LOCAL_SPREAD_MM = 1.5
#: A local offset counts when its best offset's difference is below this share of the mean
#: (stricter than CLEAR: a couple of millimetres of plain skin agree nearly as well at every offset).
LOCAL_CLEAR = 0.3
#: The broad offset's weight against the share of clear local offsets around a texel (0..1).
LOCAL_TRUST = 0.05
_LUMINANCE = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)


def surface_offsets(nav: Navigator, atlas: Atlas, texel: np.ndarray, pose: np.ndarray, weight: np.ndarray,
                    incidence: np.ndarray, exposure: Exposure, outward: np.ndarray,
                    image_size: tuple[int, int]) -> np.ndarray:
    """(T,) offset (mm) along each texel's outward normal (its triangle's, ``outward`` (F, 3)) at
    which the images of the sweep's samples agree best: texel, pose, weight, incidence, (K,)
    each as analysis.texel_views.Samples, of texels of :func:`sweep_grid` (texel_views' sweep),
    weighted :func:`analysis.texel_views.squarely`; 0 where no texel around has a clear one."""
    n_texels = len(atlas.texel_point)
    step = _grid_step(atlas)
    rows, cols = atlas.texel_rc[:, 0], atlas.texel_rc[:, 1]
    count = np.bincount(texel, minlength=n_texels)
    swept = np.flatnonzero(count[texel] >= 2)
    grid_shape = (atlas.shape[0] // step + 1, atlas.shape[1] // step + 1)
    if not len(swept):
        return np.zeros(n_texels)
    values = _sweep(nav, atlas, texel[swept], pose[swept], incidence[swept], exposure, outward, image_size)
    # per texel and offset: the weighted variance of its images' luminance
    w = squarely(weight[swept], incidence[swept])
    t = texel[swept]
    total = np.bincount(t, w, minlength=n_texels)
    cost = np.zeros((len(OFFSETS_MM), *grid_shape), dtype=np.float32)
    seen = np.zeros(grid_shape, dtype=np.float32)
    g_rows, g_cols = rows // step, cols // step
    have = np.flatnonzero(total > 0)
    seen[g_rows[have], g_cols[have]] = 1.0
    for level in range(len(OFFSETS_MM)):
        lum = values[:, level]
        mean = np.bincount(t, w * lum, minlength=n_texels)[have] / total[have]
        square = np.bincount(t, w * lum * lum, minlength=n_texels)[have] / total[have]
        cost[level, g_rows[have], g_cols[have]] = np.maximum(square - mean * mean, 0.0)
    field = offset_field(cost, seen, atlas.texel_mm * step)
    result: np.ndarray = field[g_rows, g_cols].astype(np.float64)
    return result


def sweep_grid(atlas: Atlas) -> np.ndarray:
    """(T,) bool: the texels the sweep runs on, one every GRID_MM across the atlas' rows and
    columns."""
    step = _grid_step(atlas)
    on: np.ndarray = (atlas.texel_rc[:, 0] % step == 0) & (atlas.texel_rc[:, 1] % step == 0)
    return on


def _grid_step(atlas: Atlas) -> int:
    return max(int(round(GRID_MM / atlas.texel_mm)), 1)


def offset_field(cost: np.ndarray, seen: np.ndarray, cell_mm: float) -> np.ndarray:
    """(H, W) offset (mm) of every cell of a grid of pitch ``cell_mm`` from its cost (L, H, W)
    at each of OFFSETS_MM (the images' disagreement; cells no texel holds, ``seen`` (H, W) 0,
    are not counted). The local estimate (differences summed over LOCAL_WINDOW_MM, its offsets
    clear by LOCAL_CLEAR spread over LOCAL_SPREAD_MM) where it is clear near the cell, else the
    broad one (WINDOW_MM, CLEAR, SPREAD_MM); the two are weighted by the local estimate's clear
    share around the cell against LOCAL_TRUST. 0 where neither has a clear offset around."""
    broad, confidence = _spread(*_best_offsets(cost, seen, WINDOW_MM / cell_mm), SPREAD_MM / cell_mm)
    broad = np.where(confidence > 1e-3, broad, 0.0)
    local, near = _spread(*_best_offsets(cost, seen, LOCAL_WINDOW_MM / cell_mm, LOCAL_CLEAR), LOCAL_SPREAD_MM / cell_mm)
    field: np.ndarray = np.where(near > 1e-3, (near * local + LOCAL_TRUST * broad) / (near + LOCAL_TRUST), broad)
    return field


def _best_offsets(cost: np.ndarray, seen: np.ndarray, sigma: float,
                  clear: float = CLEAR) -> tuple[np.ndarray, np.ndarray]:
    """Each cell's offset (H, W) mm at the lowest of its cost (L, H, W) summed over a Gaussian
    of ``sigma`` cells, and whether that offset is clear (its cost below ``clear`` of the mean)."""
    norm = np.maximum(ndimage.gaussian_filter(seen, sigma), 1e-6)
    summed = np.stack([ndimage.gaussian_filter(level, sigma) / norm for level in cost])
    best = np.argmin(summed, axis=0)
    offset = OFFSETS_MM[best] + _parabola(summed, best) * (OFFSETS_MM[1] - OFFSETS_MM[0])
    lowest = np.take_along_axis(summed, best[None], axis=0)[0]
    return offset, (seen > 0) & (lowest < clear * summed.mean(axis=0))


def _spread(offset: np.ndarray, clear: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """The clear offsets (H, W) averaged over a Gaussian of ``sigma`` cells, and the clear share
    around each cell (the Gaussian's weight of clear cells; near 0: no clear offset around)."""
    share = ndimage.gaussian_filter(clear.astype(np.float32), sigma)
    total = ndimage.gaussian_filter(np.where(clear, offset, 0.0).astype(np.float32), sigma)
    return total / np.maximum(share, 1e-6), share


def _parabola(cost: np.ndarray, best: np.ndarray) -> np.ndarray:
    """Sub-step position (-0.5..0.5 steps) of the minimum of the parabola through the best
    offset's cost and its two neighbours' (0 at the ends of the sweep)."""
    last = len(cost) - 1
    inner = np.clip(best, 1, last - 1)
    c0, c1, c2 = (np.take_along_axis(cost, (inner + k)[None], axis=0)[0] for k in (-1, 0, 1))
    curvature = c0 - 2 * c1 + c2
    shift = np.where(curvature > 0, 0.5 * (c0 - c2) / np.where(curvature > 0, curvature, 1.0), 0.0)
    return np.where((best > 0) & (best < last), np.clip(shift, -0.5, 0.5), 0.0)


def _sweep(nav: Navigator, atlas: Atlas, texel: np.ndarray, pose: np.ndarray, incidence: np.ndarray,
           exposure: Exposure, outward: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """(K, L) exposure-corrected luminance of each sample's image at its texel's point moved by
    each of OFFSETS_MM along its triangle's ``outward`` (F, 3); one image in memory at a time on
    each thread (two where a core is spare)."""
    from planner.navigation import pixel_of

    scan = nav.scan
    scale = image_size[0] / scan.rig.optics.image_width_px
    values = np.zeros((len(texel), len(OFFSETS_MM)), dtype=np.float32)
    factor = (exposure.factor(pose, incidence) @ _LUMINANCE).astype(np.float32)  # luminance gain, roughly

    def sweep(group: tuple[int, np.ndarray]) -> None:
        p, mine = group
        lum = scan.pixels_at(p) @ _LUMINANCE
        points, normal = atlas.texel_point[texel[mine]], outward[atlas.texel_face[texel[mine]]]
        # every offset in one call (level-major, as (L, n)): fewer, larger array operations
        moved = (points[None] + OFFSETS_MM[:, None, None] * normal[None]).reshape(-1, 3)
        u, v = pixel_of(nav.poses, np.full(len(moved), p), moved, scan.rig)
        sampled = bilinear(lum[:, :, None], u * scale, v * scale)[:, 0].reshape(len(OFFSETS_MM), len(mine))
        values[mine] = sampled.T / factor[mine, None]

    each(sweep, by_image(pose), name="parallax")
    return values
