"""Focus calibration on the simulated phones: each phone sweeps its focus over a board placed at
known distances (the procedure an operator runs with a board on a stand), the sharpness peaks
give the phone's focus table (planner/calibration/focus_fit.py).

The simulated phones' lenses carry a seeded per-phone error (drivers/sim/phone.py), so the table
has something to recover; the truth is each phone's own lens.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from planner.calibration.focus_fit import FocusSweep, fit_focus_table, table_yaml
from planner.calibration.target import CuboidTarget
from planner.rig import Rig

DISTANCES_MM = (180.0, 220.0, 270.0, 330.0, 420.0, 550.0, 750.0, 1100.0)
SWEEP_DIOPTERS = np.round(np.arange(0.3, 10.01, 0.1), 2)
TABLE_DIOPTERS = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 5.0, 6.0, 7.0, 8.0)
CHECK_MM = (200.0, 250.0, 300.0, 400.0, 500.0, 700.0, 1000.0)
"""Planned focus distances at which the table's error is reported (the rig plans 200-1000 mm)."""


@dataclass(frozen=True)
class PhoneFocusResult:
    """One phone: its table, the fit residual (D) and the focus error (mm) at CHECK_MM with the
    measured table and with the shared default table, both against the phone's true lens."""

    phone: str
    diopters: np.ndarray
    distance_mm: np.ndarray
    rms_diopters: float
    error_mm: np.ndarray
    default_error_mm: np.ndarray


def calibrate_sim_focus(rig: Rig, target: CuboidTarget, seed: int, out: Path) -> list[PhoneFocusResult]:
    """Sweep every simulated phone of the rig (phones seeded as sim/rig.py seeds them), write
    ``out/<phone id>.yaml`` focus tables; returns the per-phone results."""
    from drivers.phone.focus import FocusCalibration, load_focus_calibration
    from drivers.sim.focus_target import board_patch, sharpness
    from drivers.sim.phone import SimulatedPhone

    out.mkdir(parents=True, exist_ok=True)
    texture_ppm = 4.0
    texture = target.board_image(0, texture_ppm).astype(np.float32)
    results = []
    for i, phone in enumerate(rig.phones):
        sim = SimulatedPhone(phone.serial, seed=seed * 100 + i, optics=rig.optics)
        rng = np.random.default_rng([seed, i, 0xF0C])
        sweeps = []
        for distance in DISTANCES_MM:
            values = [sharpness(board_patch(texture, texture_ppm, distance, sim.sharp_distance_mm(d), rig.optics, rng))
                      for d in SWEEP_DIOPTERS]
            sweeps.append(FocusSweep(distance, SWEEP_DIOPTERS, np.array(values)))
        grid, mm, rms = fit_focus_table(sweeps, TABLE_DIOPTERS, phone.id)
        (out / f"{phone.id}.yaml").write_text(table_yaml("TBP Simulated Phone", f"simulated, seed {seed}", grid, mm))
        table = FocusCalibration(grid, mm, source=phone.id)
        default = load_focus_calibration(rig.resolve(phone.focus_calibration))
        check = np.array(CHECK_MM)
        error = np.array([sim.sharp_distance_mm(table.diopters_for(x)) - x for x in check])
        default_error = np.array([sim.sharp_distance_mm(default.diopters_for(x)) - x for x in check])
        results.append(PhoneFocusResult(phone.id, grid, mm, rms, error, default_error))
    return results
