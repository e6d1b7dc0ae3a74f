"""Focus calibration of one phone: from sharpness measured over focus sweeps of a board at known
distances to the phone's focus table (commanded diopters -> sharpest distance, drivers/phone/focus.py).

For each distance the sweep's sharpness peaks at the commanded setting that focuses there; a
parabola through the peak and its neighbours (in log sharpness) places it between settings. A
voice-coil lens is close to linear in diopters, so the measured diopters 1000 / distance are
fitted as a quadratic in the commanded ones (least squares over all distances), which smooths
the peaks' noise; the table is that fit sampled on the commanded grid.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from planner.picklable import PicklableError

DISTANCES_MM = (180.0, 220.0, 270.0, 330.0, 420.0, 550.0, 750.0, 1100.0)
"""Where the board stands for the sweeps: the rig plans focus from 200 to 1000 mm."""
TABLE_DIOPTERS = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 5.0, 6.0, 7.0, 8.0)
"""Commanded settings at which the fitted lens is written into the focus table."""
CHECK_MM = (200.0, 250.0, 300.0, 400.0, 500.0, 700.0, 1000.0)
"""Planned focus distances at which a table's error is reported (the rig plans 200-1000 mm)."""


class FocusFitError(PicklableError, ValueError):
    """The sweeps do not determine a focus table (named: phone, distance, problem)."""

    def __init__(self, phone: str, problem: str) -> None:
        self.phone, self.problem = phone, problem
        super().__init__(f"focus calibration of {phone}: {problem}")


@dataclass(frozen=True)
class FocusSweep:
    """Sharpness (any positive measure) of a board at distance_mm for each commanded setting (diopters)."""

    distance_mm: float
    diopters: np.ndarray
    sharpness: np.ndarray


def sweep_peak(sweep: FocusSweep, phone: str = "phone") -> float:
    """The commanded diopters at which the sweep is sharpest (parabolic interpolation in log sharpness)."""
    d, s = np.asarray(sweep.diopters, dtype=float), np.asarray(sweep.sharpness, dtype=float)
    if len(d) < 3 or np.any(np.diff(d) <= 0) or np.any(~np.isfinite(s)) or np.any(s <= 0):
        raise FocusFitError(phone, f"sweep at {sweep.distance_mm:g} mm: need >= 3 increasing settings with "
                            "positive sharpness")
    i = int(np.argmax(s))
    if i == 0 or i == len(d) - 1:
        raise FocusFitError(phone, f"sweep at {sweep.distance_mm:g} mm peaks at the end of the swept range "
                            f"({d[i]:g} D): widen the sweep")
    y = np.log(s[i - 1:i + 2])
    x = d[i - 1:i + 2]
    a, b, _ = np.polyfit(x - x[1], y, 2)
    if a >= 0:
        return float(x[1])
    return float(x[1] - b / (2 * a))


def fit_focus_table(sweeps: Sequence[FocusSweep], grid_diopters: Sequence[float], phone: str = "phone"
                    ) -> tuple[np.ndarray, np.ndarray, float]:
    """(grid diopters, sharpest distance mm at each, RMS fit residual in diopters) from the sweeps."""
    if len(sweeps) < 3:
        raise FocusFitError(phone, f"{len(sweeps)} distances measured; need at least 3")
    commanded = np.array([sweep_peak(s, phone) for s in sweeps])
    measured = 1000.0 / np.array([s.distance_mm for s in sweeps])
    degree = 2 if len(sweeps) >= 5 else 1
    coeffs = np.polyfit(commanded, measured, degree)
    rms = float(np.sqrt(np.mean((np.polyval(coeffs, commanded) - measured) ** 2)))
    grid = np.asarray(grid_diopters, dtype=float)
    fitted = np.polyval(coeffs, grid)
    if np.any(fitted <= 0) or np.any(np.diff(fitted) <= 0):
        raise FocusFitError(phone, "the fitted lens is not monotonic over the grid: check the sweeps")
    return grid, 1000.0 / fitted, rms


def table_yaml(phone_model: str, measured: str, diopters: np.ndarray, distance_mm: np.ndarray) -> str:
    """A focus table file (drivers/phone/focus.py's format)."""
    lines = ["# Focus table measured by `tbp calibrate focus`: commanded LENS_FOCUS_DISTANCE (diopters)",
             "# -> distance of the sharpest board (mm).", f"phone_model: {phone_model}", f"measured: {measured}",
             "points:"]
    lines += [f"  - [{d:.4g}, {mm:.1f}]" for d, mm in zip(diopters, distance_mm)]
    return "\n".join(lines) + "\n"
