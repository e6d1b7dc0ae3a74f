"""Reading images at sub-pixel positions, image by image."""

from __future__ import annotations

import numpy as np

CUBIC_A = -0.5
"""Keys' cubic convolution parameter: -0.5 reproduces quadratics (Catmull-Rom)."""


def _cubic_weights(f: np.ndarray) -> np.ndarray:
    """(K, 4) Keys weights of the taps at -1, 0, 1, 2 for fractional offsets f (K,) in [0, 1]."""
    a = CUBIC_A
    t = np.stack([1.0 + f, f, 1.0 - f, 2.0 - f], axis=1)
    near = ((a + 2.0) * t - (a + 3.0)) * t * t + 1.0
    far = ((a * t - 5.0 * a) * t + 8.0 * a) * t - 4.0 * a
    return np.where(t <= 1.0, near, far)


def bicubic(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(K, C) values of an (H, W, C) image at pixel coordinates u (across), v (down), origin at
    the image's top-left corner (pixel centres at +0.5): Keys' cubic convolution over the 4 x 4
    pixels around, edges replicated, each value clamped to the range of its 2 x 2 nearest
    pixels (no ringing past what the image holds there). Bilinear interpolation averages a
    spot one pixel across with its surroundings by up to half at a half-pixel offset; the cubic
    keeps more of it. Computed in the image's float type (float32 images: float32 values)."""
    h, w = image.shape[:2]
    x = np.clip(np.asarray(u, dtype=float) - 0.5, 0.0, w - 1.0)
    y = np.clip(np.asarray(v, dtype=float) - 0.5, 0.0, h - 1.0)
    x0, y0 = x.astype(np.int64), y.astype(np.int64)  # x, y >= 0: truncation is the floor
    kind = image.dtype if image.dtype in (np.float32, np.float64) else np.dtype(float)
    wx, wy = _cubic_weights(x - x0).astype(kind), _cubic_weights(y - y0).astype(kind)
    flat = image.reshape(h * w, -1)  # one flat index a pixel: cheaper than a (row, column) pair
    columns = [np.clip(x0 + i, 0, w - 1) for i in (-1, 0, 1, 2)]
    out = np.zeros((len(x), flat.shape[1]), dtype=kind)
    low = np.full_like(out, np.inf)
    high = np.full_like(out, -np.inf)
    for j, dy in enumerate((-1, 0, 1, 2)):
        row = np.clip(y0 + dy, 0, h - 1) * w
        across = np.zeros_like(out)
        for i, column in enumerate(columns):
            value = np.take(flat, row + column, axis=0).astype(kind, copy=False)  # take: faster than flat[index]
            across += wx[:, i:i + 1] * value
            if dy in (0, 1) and i in (1, 2):
                np.minimum(low, value, out=low)
                np.maximum(high, value, out=high)
        out += wy[:, j:j + 1] * across
    clipped: np.ndarray = np.clip(out, low, high)
    return clipped


def by_image(pose: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """Per image of samples' poses (K,) int: its pose and the indices of its samples, ascending."""
    order = np.argsort(pose, kind="stable")
    counts = np.bincount(pose)
    ends = np.cumsum(counts)
    return [(int(p), order[ends[p] - counts[p]:ends[p]]) for p in np.flatnonzero(counts)]
