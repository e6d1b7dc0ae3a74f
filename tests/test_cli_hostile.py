"""User-facing commands given careless input (issue 14, probe 5): one line naming the problem, the
documented exit code, no traceback, and no long work before a refusal that could be known up front."""

from __future__ import annotations

import asyncio
import contextlib
import threading
from pathlib import Path

import numpy as np
import pytest

from cli import main as tbp
from drivers.depth.recording import INDEX, save_sweep
from planner.rig import load_rig
from planner.sweep import BeamTrace, PosedDepth, Sweep

RIG = load_rig()


def _one_line(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    # (JSON lines are the log of a daemon this test runs in a thread, not the command's output)
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("{")]
    assert len(lines) == 1, err
    return lines[0]


def _sweep(folder: Path, frames: int = 2, shape: tuple[int, int] = (720, 1280)) -> Path:
    posed = [PosedDepth(camera_id="depth0", frame_number=i, timestamp_s=0.1 * i, beam_angle_deg=float(i),
                        depth=np.full(shape, 900, np.uint16), depth_unit_mm=1.0,
                        intrinsics=RIG.depth_camera_model.intrinsic_matrix, camera_to_world=np.eye(4))
             for i in range(frames)]
    save_sweep(Sweep(tuple(posed), BeamTrace(np.array([0.0, 1.0]), np.array([0.0, 10.0]))), folder)
    return folder


@pytest.fixture
def no_fusion(monkeypatch: pytest.MonkeyPatch) -> None:
    """Refusals must come before the fusion: reaching it fails the test."""
    import planner.tsdf

    def fuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("the fusion ran before the refusal")

    monkeypatch.setattr(planner.tsdf, "fuse", fuse)


def test_reconstruct_a_truncated_frame_names_the_file(tmp_path: Path, capsys, no_fusion) -> None:
    frames = _sweep(tmp_path / "frames")
    victim = sorted(frames.glob("*.npz"))[1]
    victim.write_bytes(victim.read_bytes()[: victim.stat().st_size // 2])
    assert tbp(["reconstruct", "--frames", str(frames)]) == 1
    line = _one_line(capsys)
    assert victim.name in line and "truncated or corrupt" in line


def test_reconstruct_a_frame_larger_than_the_camera_is_refused_before_reading(tmp_path: Path, capsys,
                                                                           no_fusion) -> None:
    frames = _sweep(tmp_path / "frames", frames=1, shape=(2000, 2000))  # compresses to a few KB
    assert tbp(["reconstruct", "--frames", str(frames)]) == 1
    assert "more than the 921600 pixels allowed" in _one_line(capsys)


def test_reconstruct_frame_files_stay_in_the_sweep_folder(tmp_path: Path, capsys, no_fusion) -> None:
    frames = _sweep(tmp_path / "frames", frames=1)
    index = frames / INDEX
    index.write_text(index.read_text().replace('"file": "', '"file": "../'))
    assert tbp(["reconstruct", "--frames", str(frames)]) == 1
    assert "is not a file name in the sweep folder" in _one_line(capsys)


@pytest.mark.parametrize("out, problem", [("o.xyz", "cannot write '.xyz'; use one of .ply"),
                                          ("a-file/o.ply", "a-file is not a folder"),
                                          ("folder.ply", "is a folder")])
def test_reconstruct_refuses_an_output_it_cannot_write_before_any_work(tmp_path: Path, capsys, no_fusion,
                                                                       out: str, problem: str) -> None:
    frames = _sweep(tmp_path / "frames", frames=1)
    (tmp_path / "folder.ply").mkdir()
    (tmp_path / "a-file").write_text("x")
    assert tbp(["reconstruct", "--frames", str(frames), "--out", str(tmp_path / out)]) == 2
    assert problem in _one_line(capsys)


def test_commands_refuse_an_output_they_cannot_write_before_any_work(tmp_path: Path, capsys,
                                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    import analysis.evaluation
    import planner.plan

    def never(*args: object, **kwargs: object) -> None:
        raise AssertionError("the work ran before the refusal")

    monkeypatch.setattr(planner.plan, "plan_focus", never)
    monkeypatch.setattr(analysis.evaluation, "run_corpus", never)
    (tmp_path / "a-file").write_text("x")
    assert tbp(["plan", "--mesh", str(tmp_path / "m.ply"), "--json", str(tmp_path / "a-file" / "p.json")]) == 2
    assert "tbp plan: --json" in _one_line(capsys)
    assert tbp(["evaluate", "--bodies", "1", "--out", str(tmp_path / "a-file" / "ev")]) == 2
    assert "tbp evaluate: --out" in _one_line(capsys)
    import sim.body

    monkeypatch.setattr(sim.body, "generate_body", never)
    assert tbp(["body", "--out", str(tmp_path / "a-file" / "b.ply")]) == 2
    assert _one_line(capsys) == f"tbp body: --out {tmp_path / 'a-file' / 'b.ply'}: {tmp_path / 'a-file'} is not a folder"
    for action in ([], ["target"], ["focus"]):
        assert tbp(["calibrate", *action, "--sim", "--out", str(tmp_path / "a-file" / "cal")]) == 2
        assert _one_line(capsys) == f"tbp calibrate: --out {tmp_path / 'a-file' / 'cal'}: {tmp_path / 'a-file'} is not a folder"


@pytest.mark.parametrize("flag", ["--calibration-trials", "--sway-poses"])
def test_evaluate_refuses_a_negative_study_size_before_any_work(tmp_path: Path, capsys,
                                                                monkeypatch: pytest.MonkeyPatch, flag) -> None:
    import analysis.evaluation

    def never(*args: object, **kwargs: object) -> None:
        raise AssertionError("the work ran before the refusal")

    monkeypatch.setattr(analysis.evaluation, "run_corpus", never)
    assert tbp(["evaluate", "--bodies", "1", flag, "-1", "--out", str(tmp_path / "ev")]) == 2
    assert "--calibration-trials and --sway-poses must be >= 0" in _one_line(capsys)
    with pytest.raises(ValueError, match="0 or more"):
        analysis.evaluation.StudyOptions(**{flag.removeprefix("--").replace("-", "_"): -1})


def test_scans_on_a_store_that_does_not_exist(tmp_path: Path, capsys) -> None:
    assert tbp(["scans", "--store", str(tmp_path / "nonexistent"), "--check"]) == 2
    assert _one_line(capsys) == f"tbp scans: scan store {tmp_path / 'nonexistent'} does not exist"
    (tmp_path / "file").write_text("x")
    assert tbp(["scans", "--store", str(tmp_path / "file")]) == 2
    assert "is not a folder" in _one_line(capsys)


# ---------------------------------------------------------------------- tbp scan against a daemon


class _Daemon:
    """A control API handler: refuses scans (busy), or accepts one and then goes away."""

    def __init__(self, busy: bool) -> None:
        self.busy = busy
        self.gone = threading.Event()

    def status(self) -> dict:
        return {"state": "CAPTURING" if self.busy else "IDLE"}

    def scan(self, **args: object) -> dict:
        from daemon.errors import ScanBusy

        if self.busy:
            raise ScanBusy("CAPTURING", "a scan is already running")
        self.gone.set()
        return {"scan_id": "s1"}

    def abort(self) -> dict:
        return {}

    def reset(self) -> dict:
        return {}

    async def subscribe(self):
        while not self.gone.is_set():
            await asyncio.sleep(0.01)
        return  # the daemon stops: the subscription ends mid-scan
        yield


@contextlib.contextmanager
def _daemon_in_thread(sock: Path, handler: _Daemon):
    """A control server on its own loop in a thread, so `tbp scan` can run here with asyncio.run."""
    from daemon.server.control import ControlServer

    ready, stop = threading.Event(), threading.Event()

    async def serve() -> None:
        async with ControlServer(sock, handler):
            ready.set()
            while not stop.is_set():
                await asyncio.sleep(0.01)

    thread = threading.Thread(target=asyncio.run, args=(serve(),), daemon=True)
    thread.start()
    assert ready.wait(10)
    try:
        yield
    finally:
        stop.set()
        thread.join(10)


def test_scan_without_a_daemon_is_one_line_and_exit_2(tmp_path: Path, capsys) -> None:
    assert tbp(["scan", "--socket", str(tmp_path / "none.sock")]) == 2
    assert "rig daemon not reachable" in _one_line(capsys)


def test_scan_refused_by_a_busy_daemon_is_one_line_and_exit_1(tmp_path: Path, capsys) -> None:
    sock = tmp_path / "c.sock"
    with _daemon_in_thread(sock, _Daemon(busy=True)):
        assert tbp(["scan", "--socket", str(sock)]) == 1
    assert "refused: scan: ScanBusy: cannot start a scan in state CAPTURING" in _one_line(capsys)


def test_scan_whose_daemon_goes_away_is_one_line_and_exit_2(tmp_path: Path, capsys) -> None:
    sock = tmp_path / "c.sock"
    with _daemon_in_thread(sock, _Daemon(busy=False)):
        assert tbp(["scan", "--socket", str(sock)]) == 2
    assert "the daemon closed the subscription" in _one_line(capsys)


@pytest.mark.parametrize("extra, problem", [(["--subject", "missing.ply"], "no such file"),
                                            (["--rig", "missing.yaml"], "cannot read")])
def test_simulated_scan_with_unusable_input_is_one_line_and_exit_2(tmp_path: Path, capsys, extra, problem) -> None:
    extra = [str(tmp_path / e) if e.endswith((".ply", ".yaml")) else e for e in extra]
    assert tbp(["scan", "--sim", "--store", str(tmp_path / "s"), *extra]) == 2
    assert problem in _one_line(capsys)


@pytest.mark.parametrize("extra, problem", [(["--subject", "missing.ply"], "no such file"),
                                            (["--subject", "garbled.ply"], "cannot be read as a mesh"),
                                            (["--rig", "missing.yaml"], "cannot read")])
def test_the_simulated_daemon_with_unusable_input_is_one_line_and_exit_2(tmp_path: Path, capsys, extra,
                                                                        problem) -> None:
    (tmp_path / "garbled.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n")
    extra = [str(tmp_path / e) if e.endswith((".ply", ".yaml")) else e for e in extra]
    assert tbp(["daemon", "--sim", "--http", "off", "--store", str(tmp_path / "s"),
                "--socket", str(tmp_path / "control.sock"), *extra]) == 2
    line = _one_line(capsys)
    assert line.startswith("tbp daemon: ") and problem in line


@pytest.mark.parametrize("text, problem", [
    (None, "cannot read"),
    ("can: {interface: socketcan, channel: can0}\nphones: {}\ndepth_cameras: {}\npanel: null\n", "phones.cam0"),
    ("can: {interface: socketcan, channel: can0, bitrate: 500000}\nphones: {}\ndepth_cameras: {}\npanel: null\n",
     "can.bitrate"),
])
def test_the_real_daemon_with_an_unusable_hardware_file_exits_2_naming_the_key(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str | None, problem: str) -> None:
    """Exit status 2 is the unit's RestartPreventExitStatus: systemd does not restart into the same error."""
    hardware = tmp_path / "hardware.yaml"
    if text is not None:
        hardware.write_text(text)
    argv = ["daemon", "--hardware", str(hardware), "--store", str(tmp_path / "scans"),
            "--socket", str(tmp_path / "c.sock"), "--http", "off"]
    assert tbp(argv) == 2
    line = _one_line(capsys)
    assert line.startswith("tbp daemon: ") and str(hardware) in line and problem in line
    assert not (tmp_path / "c.sock").exists()  # refused before serving anything


@pytest.mark.parametrize("command", [["viewer", "--http", "127.0.0.1:0", "--cache", "{tmp}/cache"],
                                     ["export", "{tmp}/no-scan"]])
@pytest.mark.parametrize("url", ["pacs.clinic.example/dicom-web", "ftp://pacs/dicom-web", "http://"])
def test_an_archive_url_that_is_not_http_is_refused_before_any_work(tmp_path: Path, capsys, command, url) -> None:
    args = [part.replace("{tmp}", str(tmp_path)) for part in command]
    assert tbp([*args, "--dicomweb", url]) == 2
    line = _one_line(capsys)
    assert line.startswith(f"tbp {command[0]}: --dicomweb") and "http:// or https:// URL" in line
    assert not (tmp_path / "cache").exists()


def test_an_output_check_that_may_still_be_refused_makes_nothing(tmp_path: Path) -> None:
    from cli.outputs import output_problem

    out = tmp_path / "new" / "cal"
    assert output_problem("--out", out, folder=True, create=False) is None
    assert not (tmp_path / "new").exists()
    (tmp_path / "a-file").write_text("x")
    assert output_problem("--out", tmp_path / "a-file" / "cal", folder=True, create=False) == (
        f"--out {tmp_path / 'a-file' / 'cal'}: {tmp_path / 'a-file'} is not a folder")
    assert output_problem("--out", out, folder=True) is None and out.is_dir()
