"""The simulated phone photographing a flat board square-on at a known distance: what the focus
calibration's sweep sees. The board patch is scaled to the phone's pixels at that distance and
blurred by the thin-lens circle of confusion of the lens' true sharp distance (phone_render.py),
the optics' point spread and sensor noise.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter

from drivers.sim.phone_render import circle_of_confusion_mm
from planner.rig import Optics

PATCH_PX = 160
RENDER_SCALE = 1 / 8
"""The sweep's pictures are rendered at 1/8 of the sensor, and only the board's centre in detail
(the rest of the field would be wasted work)."""
SURROUND_GREY = 128.0


def board_patch(texture: np.ndarray, texture_px_per_mm: float, distance_mm: float, sharp_mm: float,
                optics: Optics, rng: np.random.Generator, psf_px: float = 0.6, noise: float = 2.0) -> np.ndarray:
    """(PATCH_PX, PATCH_PX) float32 grey: the centre of a board picture at distance_mm, lens sharp at sharp_mm."""
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
    result: np.ndarray = blurred + rng.standard_normal(blurred.shape).astype(np.float32) * np.float32(noise)
    return result


@dataclass
class BoardStand:
    """A board on a stand, square-on in front of one phone, its centre on the optical axis:
    ``distance_mm`` from the lens is where the operator (or a test) has put it. texture: the
    board's grey image at texture_px_per_mm."""

    texture: np.ndarray
    texture_px_per_mm: float
    distance_mm: float
    _surround: np.ndarray | None = field(default=None, repr=False, compare=False)

    def picture(self, sharp_mm: float, optics: Optics, rng: np.random.Generator) -> np.ndarray:
        """(H, W, 3) uint8, the phone's whole field at RENDER_SCALE, lens sharp at sharp_mm: the
        board's centre (PATCH_PX square, rendered) in the middle of a plain, noisy surround."""
        width, height = round(optics.image_width_px * RENDER_SCALE), round(optics.image_height_px * RENDER_SCALE)
        if self._surround is None or self._surround.shape != (height, width):  # the same noisy card every time
            card = np.random.default_rng(0x5C2D).standard_normal((height, width)).astype(np.float32)
            self._surround = np.float32(SURROUND_GREY) + np.float32(2.0) * card
        frame = self._surround.copy()
        patch = board_patch(self.texture, self.texture_px_per_mm, self.distance_mm, sharp_mm, optics, rng)
        ph, pw = patch.shape
        y0, x0 = (height - ph) // 2, (width - pw) // 2
        frame[y0:y0 + ph, x0:x0 + pw] = patch
        return np.repeat(np.clip(frame, 0, 255).astype(np.uint8)[:, :, None], 3, axis=2)
