"""Reading images at sub-pixel positions, image by image."""

from __future__ import annotations

import numpy as np


def bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(K, C) values of an (H, W, C) image at pixel coordinates u (across), v (down), origin
    at the image's top-left corner (pixel centres at +0.5); clamped at the edges. Computed in
    the image's float type (float32 images: float32 values, half the memory of float64)."""
    h, w = image.shape[:2]
    x = np.clip(np.asarray(u, dtype=float) - 0.5, 0.0, w - 1.0)
    y = np.clip(np.asarray(v, dtype=float) - 0.5, 0.0, h - 1.0)
    # x, y >= 0: truncation is the floor
    x0 = np.minimum(x.astype(np.int64), w - 2) if w > 1 else np.zeros(len(x), np.int64)
    y0 = np.minimum(y.astype(np.int64), h - 2) if h > 1 else np.zeros(len(y), np.int64)
    kind = image.dtype if image.dtype in (np.float32, np.float64) else np.dtype(float)
    fx, fy = (x - x0).astype(kind)[:, None], (y - y0).astype(kind)[:, None]
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    flat = image.reshape(h * w, -1)  # one flat index a corner: cheaper than a (row, column) pair

    def at(row: np.ndarray, column: np.ndarray) -> np.ndarray:
        return np.take(flat, row * w + column, axis=0)  # take: twice as fast as flat[index]

    top = at(y0, x0) * (1 - fx) + at(y0, x1) * fx
    bottom = at(y1, x0) * (1 - fx) + at(y1, x1) * fx
    return top * (1 - fy) + bottom * fy


def by_image(pose: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """Per image of samples' poses (K,) int: its pose and the indices of its samples, ascending."""
    order = np.argsort(pose, kind="stable")
    counts = np.bincount(pose)
    ends = np.cumsum(counts)
    return [(int(p), order[ends[p] - counts[p]:ends[p]]) for p in np.flatnonzero(counts)]
