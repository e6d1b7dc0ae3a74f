"""Focus calibration: sweep peaks, the lens fit, and the simulated phones' focus error recovered."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from planner.calibration.focus_fit import FocusFitError, FocusSweep, fit_focus_table, sweep_peak

GRID = np.round(np.arange(0.3, 10.01, 0.1), 2)


def _sweep(distance_mm: float, offset: float, gain: float, width: float = 0.35) -> FocusSweep:
    peak = (1000.0 / distance_mm - offset) / gain
    return FocusSweep(distance_mm, GRID, 100.0 * np.exp(-((GRID - peak) / width) ** 2) + 1.0)


@settings(max_examples=60, deadline=None)
@given(st.floats(0.8, 9.0), st.floats(0.2, 0.6))
def test_sweep_peak_lands_between_settings(peak: float, width: float) -> None:
    sweep = FocusSweep(500.0, GRID, np.exp(-((GRID - peak) / width) ** 2) + 1e-3)
    assert sweep_peak(sweep) == pytest.approx(peak, abs=0.02)


@settings(max_examples=30, deadline=None)
@given(st.floats(-0.15, 0.15), st.floats(0.94, 1.06))
def test_fit_recovers_a_linear_lens(offset: float, gain: float) -> None:
    sweeps = [_sweep(d, offset, gain) for d in (180.0, 250.0, 330.0, 450.0, 600.0, 900.0)]
    grid, mm, _ = fit_focus_table(sweeps, [1.0, 2.0, 3.0, 4.0, 5.0])
    assert np.allclose(1000.0 / mm, offset + gain * grid, atol=0.01)


def test_a_sweep_that_peaks_at_its_end_asks_for_a_wider_sweep() -> None:
    with pytest.raises(FocusFitError, match="widen the sweep"):
        sweep_peak(FocusSweep(150.0, GRID[:20], np.arange(1.0, 21.0)))


@pytest.mark.slow
def test_simulated_phones_focus_error_is_recovered(tmp_path: Path) -> None:
    from drivers.phone.focus import load_focus_calibration
    from planner.calibration.target import load_target
    from planner.rig import load_rig
    from sim.focus_calibration import calibrate_sim_focus

    results = calibrate_sim_focus(load_rig(), load_target(), seed=4, out=tmp_path)
    for r in results:
        assert np.abs(r.error_mm).max() < 3.0  # within the depth of field's few-mm margin
        assert np.abs(r.default_error_mm).max() > 3 * np.abs(r.error_mm).max()
        table = load_focus_calibration(tmp_path / f"{r.phone}.yaml")  # the driver reads it
        assert table.near_mm < 200.0 and table.far_mm > 1000.0
