"""Reading images at sub-pixel positions."""

from __future__ import annotations

import numpy as np


def bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(K, C) values of an (H, W, C) image at pixel coordinates u (across), v (down), origin
    at the image's top-left corner (pixel centres at +0.5); clamped at the edges."""
    h, w = image.shape[:2]
    x = np.clip(np.asarray(u, dtype=float) - 0.5, 0.0, w - 1.0)
    y = np.clip(np.asarray(v, dtype=float) - 0.5, 0.0, h - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), w - 2) if w > 1 else np.zeros(len(x), np.int64)
    y0 = np.minimum(np.floor(y).astype(np.int64), h - 2) if h > 1 else np.zeros(len(y), np.int64)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
    return top * (1 - fy) + bottom * fy
