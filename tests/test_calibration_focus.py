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
    assert any(np.abs(r.default_error_mm).max() > 20.0 for r in results)  # the lens errors are real
    for r in results:
        assert np.abs(r.error_mm).max() < 3.0  # within the depth of field's few-mm margin
        if np.abs(r.default_error_mm).max() > 5.0:  # a lens the shared table misses, recovered
            assert np.abs(r.default_error_mm).max() > 3 * np.abs(r.error_mm).max()
        table = load_focus_calibration(tmp_path / f"{r.phone}.yaml")  # the driver reads it
        assert table.near_mm < 200.0 and table.far_mm > 1000.0


def _bench_sweep(tmp_path: Path, distances: tuple[float, ...], fault=None):
    """One simulated phone on the focus bench, swept through the phone driver on virtual time;
    ``fault(bench, distance)`` runs as the board reaches each distance."""
    from daemon.jobs.focus_sweep import SweepSettings, calibrate_focus
    from drivers.adb.auth import AdbKey
    from planner.calibration.target import load_target
    from planner.rig import load_rig
    from sim.clock import run_virtual
    from sim.focus_calibration import focus_bench

    rig, settings = load_rig(), SweepSettings(distances_mm=distances)

    async def sweep():
        async with focus_bench(rig, load_target(), 0, 3, AdbKey.generate(), distances[0]) as bench:
            async def place(distance: float) -> None:
                await bench.place_board(distance)
                if fault is not None:
                    fault(bench, distance)

            try:
                return await calibrate_focus(bench.camera, rig.optics, settings, place, tmp_path,
                                             measured="test"), bench
            except Exception as exc:
                return exc, bench

    return run_virtual(sweep())


@pytest.mark.slow  # a focus sweep of the simulated phone at five board distances
def test_a_phone_is_swept_through_its_driver_and_left_clean(tmp_path: Path) -> None:
    from drivers.phone.focus import FocusCalibration, load_focus_calibration

    distances = (200.0, 300.0, 450.0, 700.0, 1000.0)
    table, bench = _bench_sweep(tmp_path, distances)
    lens = bench.phone.sharp_distance_mm
    measured = FocusCalibration(table.diopters, table.distance_mm)
    assert all(abs(lens(measured.diopters_for(x)) - x) < 3.0 for x in (200.0, 300.0, 500.0, 1000.0))
    assert load_focus_calibration(table.path).far_mm > 1000.0  # the driver reads the file
    # every picture was pulled, measured and deleted from the phone; the sharpest of each distance kept
    assert len(bench.phone.captures) == sum(len(s.diopters) for s in table.sweeps)
    assert not [p for p in bench.phone.fs.files if p.startswith(bench.phone.IMAGE_DIR)]
    assert sorted(p.name for p in (tmp_path / table.phone).glob("d*.jpg")) == [f"d{d:04.0f}.jpg" for d in distances]
    # each sweep is fine around its peak: the settings next to the peak are 0.1 D apart
    for sweep in table.sweeps:
        peak = int(np.argmax(sweep.sharpness))
        assert np.allclose(np.diff(sweep.diopters[peak - 1:peak + 2]), 0.1)


def test_a_phone_that_vanishes_mid_sweep_is_named_and_its_pictures_kept(tmp_path: Path) -> None:
    from drivers.phone.errors import PhoneError

    def unplug(bench, distance: float) -> None:
        if distance == 450.0:
            bench.phone.vanish()

    error, bench = _bench_sweep(tmp_path, (200.0, 300.0, 450.0), unplug)
    assert isinstance(error, PhoneError) and bench.phone.serial in str(error)
    assert (tmp_path / "cam0" / "d0200.jpg").is_file() and (tmp_path / "cam0" / "d0300.jpg").is_file()
    assert not (tmp_path / "cam0.yaml").exists()  # no table from an incomplete sweep


@settings(max_examples=80, deadline=None)
@given(peak=st.floats(0.3, 10.0), highest=st.floats(3.0, 12.0), coarse=st.floats(0.2, 1.0))
def test_sweep_settings_stay_in_the_lens_range_and_never_repeat(peak: float, highest: float, coarse: float) -> None:
    from daemon.jobs.focus_sweep import SweepSettings

    s = SweepSettings(coarse_step=coarse)
    first = s.coarse(highest)
    assert first[0] == s.lowest and first[-1] == highest  # the lens' own end, never past it
    assert np.all(np.diff(first) > 0) and np.all(np.diff(first) <= coarse + 1e-9)
    fine = s.fine(min(peak, highest), highest, first)
    assert np.all((fine >= s.lowest) & (fine <= highest))
    assert not any(np.isclose(first, d, atol=1e-6).any() for d in fine)


@pytest.mark.parametrize("kwargs, message", [
    ({"distances_mm": (200.0, 300.0)}, "at least 3"),
    ({"fine_step": 0.5, "coarse_step": 0.4}, "steps must satisfy"),
    ({"board_share": 0.0}, "board width"),
])
def test_bad_sweep_settings_are_refused(kwargs, message: str) -> None:
    from daemon.jobs.focus_sweep import SweepSettings

    with pytest.raises(ValueError, match=message):
        SweepSettings(**kwargs)


def test_an_unreadable_sweep_picture_is_named(tmp_path: Path) -> None:
    from daemon.jobs.focus_sweep import SweepPictureError, board_sharpness

    bad = tmp_path / "sweep.jpg"
    bad.write_bytes(b"not a jpeg")
    with pytest.raises(SweepPictureError, match="cam3: .*sweep.jpg is not a readable picture"):
        board_sharpness(bad, 0.5, "cam3")


@pytest.mark.parametrize("argv, message", [
    (["--phone", "nosuch"], "no phone 'nosuch' in the rig file"),
    (["--distances", "200,300", "--sim"], "at least 3 positive board distances"),
])
def test_focus_command_refuses_bad_arguments(tmp_path: Path, capsys, argv, message: str) -> None:
    from cli import main

    hardware = Path(__file__).resolve().parent.parent / "calibration_data" / "hardware.loopback.yaml"
    assert main(["calibrate", "focus", "--out", str(tmp_path), "--hardware", str(hardware), *argv]) == 2
    assert message in capsys.readouterr().err


def test_focus_command_names_a_phone_that_does_not_answer(tmp_path: Path, capsys) -> None:
    import re
    import socket

    from cli import main

    with socket.socket() as probe:  # a loopback port nothing listens on
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    loopback = Path(__file__).resolve().parent.parent / "calibration_data" / "hardware.loopback.yaml"
    hardware = tmp_path / "hardware.yaml"
    hardware.write_text(re.sub(r'cam2: \{tcp: "127.0.0.1:\d+"\}', f'cam2: {{tcp: "127.0.0.1:{port}"}}',
                               loopback.read_text()))
    assert f"127.0.0.1:{port}" in hardware.read_text()
    argv = ["calibrate", "focus", "--out", str(tmp_path / "out"), "--hardware", str(hardware), "--yes",
            "--phone", "cam2", "--socket", str(tmp_path / "no-daemon.sock"), "--state-dir", str(tmp_path)]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert "cam2:" in err
    assert not (tmp_path / "out" / "cam2.yaml").exists()


def test_focus_command_leaves_the_phones_to_a_running_daemon(tmp_path: Path, capsys) -> None:
    from cli import main
    from tests.daemon_mocks import answering_daemon

    sock = tmp_path / "control.sock"
    with answering_daemon(sock, {"state": "IDLE", "devices": []}):
        hardware = Path(__file__).resolve().parent.parent / "calibration_data" / "hardware.loopback.yaml"
        argv = ["calibrate", "focus", "--out", str(tmp_path / "out"), "--hardware", str(hardware), "--yes",
                "--socket", str(sock), "--state-dir", str(tmp_path)]
        assert main(argv) == 2
        assert "the daemon is running and owns the phones" in capsys.readouterr().err
        assert not (tmp_path / "out").exists()  # no phone was touched
