"""Per-phone focus calibration: commanded LENS_FOCUS_DISTANCE (diopters) -> measured sharpest distance.

Camera2 focus distances are approximate at best (LENS_INFO_FOCUS_DISTANCE_CALIBRATION 1 drifts,
0 is in arbitrary units), so each phone's table is measured on the rig and kept in
calibration_data/focus/*.yaml:

    points:            # commanded diopters (increasing) -> sharpest distance in mm (decreasing)
      - [0.5, 1950.0]
      - [1.0, 985.0]

Between points the table is interpolated linearly in measured diopters (1000 / mm), which is
nearly linear in commanded diopters for a voice-coil lens; the inverse is the same
piecewise-linear map read the other way, so both directions round-trip exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivers.phone.errors import FocusCalibrationError, FocusOutOfRange
from planner.schema.tables import FOCUS_FILE, MAX_DIOPTERS, MAX_DISTANCE_MM, MIN_DISTANCE_MM

MAX_FILE_BYTES = FOCUS_FILE.max_bytes


@dataclass(frozen=True)
class FocusCalibration:
    """A monotonic focus table. diopters: (n,) commanded, strictly increasing, >= 0;
    distance_mm: (n,) measured sharpest distance, strictly decreasing, mm."""

    diopters: np.ndarray
    distance_mm: np.ndarray
    source: str = "<memory>"

    def __post_init__(self) -> None:
        d = np.asarray(self.diopters, dtype=float)
        mm = np.asarray(self.distance_mm, dtype=float)
        object.__setattr__(self, "diopters", d)
        object.__setattr__(self, "distance_mm", mm)
        if d.ndim != 1 or d.shape != mm.shape or len(d) < 2:
            raise FocusCalibrationError(self.source, "points", f"need >= 2 [diopters, mm] pairs, got {len(d)}")
        if not (np.all(np.isfinite(d)) and np.all(np.isfinite(mm))):
            raise FocusCalibrationError(self.source, "points", "values must be finite numbers")
        if d.min() < 0 or d.max() > MAX_DIOPTERS:
            raise FocusCalibrationError(self.source, "points",
                                        f"diopters {d.min():g}..{d.max():g} outside [0, {MAX_DIOPTERS:g}]")
        if mm.min() < MIN_DISTANCE_MM or mm.max() > MAX_DISTANCE_MM:
            raise FocusCalibrationError(self.source, "points", f"distances {mm.min():g}..{mm.max():g} mm "
                                        f"outside [{MIN_DISTANCE_MM:g}, {MAX_DISTANCE_MM:g}] mm")
        if np.any(np.diff(d) <= 0):
            raise FocusCalibrationError(self.source, "points", "commanded diopters must strictly increase")
        if np.any(np.diff(mm) >= 0):
            raise FocusCalibrationError(self.source, "points",
                                        "sharpest distance must strictly decrease as diopters increase")

    @property
    def near_mm(self) -> float:
        """Nearest distance the table reaches (mm)."""
        return float(self.distance_mm[-1])

    @property
    def far_mm(self) -> float:
        """Farthest distance the table reaches (mm)."""
        return float(self.distance_mm[0])

    @property
    def max_diopters(self) -> float:
        return float(self.diopters[-1])

    def focus_mm(self, diopters: float) -> float:
        """Sharpest distance (mm) for a commanded focus (diopters within the table)."""
        measured = np.interp(diopters, self.diopters, 1000.0 / self.distance_mm)
        return float(1000.0 / measured)

    def diopters_for(self, focus_mm: float, *, device: str | None = None) -> float:
        """The focus to command (diopters) so the sharpest distance is focus_mm; FocusOutOfRange outside."""
        slack = 1e-9 * self.far_mm  # rounding at the ends is not out of range
        if not (math.isfinite(focus_mm) and self.near_mm - slack <= focus_mm <= self.far_mm + slack):
            raise FocusOutOfRange(device or self.source, "planning", float(focus_mm), self.near_mm, self.far_mm)
        measured = 1000.0 / self.distance_mm
        return float(np.interp(1000.0 / focus_mm, measured, self.diopters))


def load_focus_calibration(path: Path | str) -> FocusCalibration:
    """Read and validate a focus table file (see the module docstring; its table:
    planner/schema/tables.py)."""
    values, _ = FOCUS_FILE.load(path, FocusCalibrationError)
    table = np.array(values["points"], dtype=float)
    return FocusCalibration(table[:, 0], table[:, 1], source=str(path))
