"""Thin-lens optics of the phone cameras: depth of field, focus intervals, resolution (SPEC 2).

All distances in mm along the optical axis. Functions are vectorised over NumPy arrays and
return float64 arrays (``inf`` where a far limit is unbounded).
"""

from __future__ import annotations

import math

import numpy as np

from planner.rig import Optics


def depth_of_field(
    s: np.ndarray | float, hyperfocal_mm: float, focal_length_mm: float
) -> tuple[np.ndarray, np.ndarray]:
    """Near and far sharp limits for focus distance ``s``.

    near(s) = s (H - f) / (H + s - 2 f); far(s) = s (H - f) / (H - s) for s < H, else inf.
    """
    s = np.asarray(s, dtype=float)
    h, f = hyperfocal_mm, focal_length_mm
    near = s * (h - f) / (h + s - 2 * f)
    with np.errstate(divide="ignore", invalid="ignore"):
        far = np.where(s < h, s * (h - f) / (h - s), np.inf)
    return near, far


def focus_interval(
    z: np.ndarray | float, hyperfocal_mm: float, focal_length_mm: float
) -> tuple[np.ndarray, np.ndarray]:
    """Closed interval [lo, hi] of focus distances s for which depth ``z`` is sharp.

    lo = z H / (H - f + z); hi = z (H - 2 f) / (H - f - z), or inf when z >= H - f.
    Equivalent to near(s) <= z <= far(s).
    """
    z = np.asarray(z, dtype=float)
    h, f = hyperfocal_mm, focal_length_mm
    lo = z * h / (h - f + z)
    with np.errstate(divide="ignore", invalid="ignore"):
        hi = np.where(z < h - f, z * (h - 2 * f) / (h - f - z), np.inf)
    return lo, hi


def in_depth_of_field(
    z: np.ndarray | float, s: np.ndarray | float, hyperfocal_mm: float, focal_length_mm: float
) -> np.ndarray:
    """(broadcast) bool: depth ``z`` is sharp when focused at ``s``."""
    lo, hi = focus_interval(z, hyperfocal_mm, focal_length_mm)
    s = np.asarray(s, dtype=float)
    return (lo <= s) & (s <= hi)


def mm_per_px(optics: Optics) -> float:
    """Object-space pixel pitch per mm of depth: 2 tan(HFOV / 2) / image width."""
    return 2.0 * math.tan(math.radians(optics.hfov_deg) / 2.0) / optics.image_width_px


def resolution_mm_per_px(z: np.ndarray | float, optics: Optics) -> np.ndarray:
    """Millimetres of surface per image pixel at depth ``z`` (mm): z * 2 tan(HFOV/2) / width."""
    return np.asarray(z, dtype=float) * mm_per_px(optics)
