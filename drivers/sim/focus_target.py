"""The simulated phone photographing a flat board square-on at a known distance: what the focus
calibration's sweep sees. The board patch is scaled to the phone's pixels at that distance and
blurred by the thin-lens circle of confusion of the lens' true sharp distance (phone_render.py),
the optics' point spread and sensor noise.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter

from drivers.sim.phone_render import circle_of_confusion_mm
from planner.rig import Optics

PATCH_PX = 160
RENDER_SCALE = 1 / 8
"""The sweep's pictures are rendered at 1/8 of the sensor (the whole field would be wasted work)."""


def board_patch(texture: np.ndarray, texture_px_per_mm: float, distance_mm: float, sharp_mm: float,
                optics: Optics, rng: np.random.Generator, psf_px: float = 0.6, noise: float = 2.0) -> np.ndarray:
    """(PATCH_PX, PATCH_PX) float32 grey: the centre of a board picture at distance_mm, lens sharp at sharp_mm."""
    import cv2

    focal_px = optics.focal_length_px * RENDER_SCALE
    px_per_mm = focal_px / distance_mm
    scale = px_per_mm / texture_px_per_mm
    h, w = texture.shape
    side = int(np.ceil(PATCH_PX / scale)) + 2
    y0, x0 = (h - side) // 2, (w - side) // 2
    crop = texture[y0:y0 + side, x0:x0 + side].astype(np.float32)
    patch = cv2.resize(crop, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)[:PATCH_PX, :PATCH_PX]
    pixel_mm = optics.focal_length_mm / focal_px
    coc_px = float(circle_of_confusion_mm(np.array(distance_mm), sharp_mm, optics)) / pixel_mm
    blurred = gaussian_filter(patch, np.hypot(psf_px, coc_px / 2), truncate=3.0)
    return blurred + rng.standard_normal(blurred.shape).astype(np.float32) * np.float32(noise)


def sharpness(picture: np.ndarray) -> float:
    """Variance of the Laplacian (what the pipeline's blur check uses too)."""
    import cv2

    return float(cv2.Laplacian(picture.astype(np.float32), cv2.CV_32F).var())
