"""One phone's focus calibration as a picture: the sweeps and the fitted lens (``<phone>.png``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from planner.calibration.focus_fit import sweep_peak


def write_focus_figure(table: Any, previous: Any, path: Path) -> Path:
    """Left: each distance's sharpness over the commanded settings (each sweep scaled to its peak)
    with the interpolated peak; right: the fitted lens (commanded diopters -> sharpest distance)
    through the measured peaks, beside the table the phone used before. ``table``: a
    daemon.jobs.focus_sweep.FocusTable; ``previous``: the phone's FocusCalibration before."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (sweeps_ax, lens_ax) = plt.subplots(1, 2, figsize=(12, 4.2))
    colours = plt.get_cmap("viridis")(np.linspace(0, 0.9, len(table.sweeps)))
    peaks = []
    for sweep, colour in zip(table.sweeps, colours):
        peak = sweep_peak(sweep, table.phone)
        peaks.append(peak)
        sweeps_ax.plot(sweep.diopters, sweep.sharpness / sweep.sharpness.max(), ".-", color=colour, ms=3,
                       label=f"{sweep.distance_mm:g} mm")
        sweeps_ax.axvline(peak, color=colour, lw=0.6, ls=":")
    sweeps_ax.set_xlabel("commanded focus (LENS_FOCUS_DISTANCE), diopters")
    sweeps_ax.set_ylabel("sharpness of the board, share of the sweep's peak")
    sweeps_ax.set_title(f"{table.phone}: focus sweeps over a board at known distances")
    sweeps_ax.legend(fontsize=7, ncol=2)
    grid = np.linspace(table.diopters.min(), table.diopters.max(), 200)
    lens_ax.plot(grid, np.interp(grid, table.diopters, table.distance_mm), label="measured table (fit)")
    lens_ax.plot(peaks, [s.distance_mm for s in table.sweeps], "o", ms=4, label="sweep peaks")
    before = [previous.focus_mm(d) for d in grid]
    lens_ax.plot(grid, before, "--", color="grey", label="table before")
    lens_ax.set_yscale("log")
    lens_ax.set_xlabel("commanded focus, diopters")
    lens_ax.set_ylabel("sharpest distance, mm")
    lens_ax.set_title(f"fit residual {table.rms_diopters:.4f} D")
    lens_ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
