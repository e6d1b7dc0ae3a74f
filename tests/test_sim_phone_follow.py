"""``tbp sim phone --follow-beam``: a phone process posed at the angle ``tbp sim motor`` reports.

Both simulators run as their own processes on loopback; the test drives the beam as the daemon
does (BeamDrive over python-can's socketcand interface) and photographs through ``tbp phone
check`` (ADB over TCP). Real time; nothing asserts on durations.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import can
import numpy as np
import pytest
from PIL import Image

from cli import main
from drivers.motor import BeamDrive, PythonCanPort
from planner.rig import load_rig

RIG = load_rig()
BODY_SEED = 2
CAMERA = "cam3"


@contextlib.contextmanager
def _process(*argv: str, ready: str) -> Iterator[tuple[subprocess.Popen[str], re.Match[str]]]:
    """``tbp ARGV`` in its own process; yields it and the match of ``ready`` on its first line."""
    with subprocess.Popen([sys.executable, "-c", "import sys; from cli import main; sys.exit(main())", *argv],
                          stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True) as proc:
        try:
            line = proc.stdout.readline() if proc.stdout else ""
            match = re.search(ready, line)
            assert match, line
            yield proc, match
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()


def _reference(angle_deg: float, diopters: float) -> np.ndarray:
    """The picture the simulated phone takes of the same body from cam3 at this beam angle."""
    import io

    from drivers.sim.phone import SimulatedPhone
    from sim.body import make_body
    from sim.rig import phone_pose_source

    index = [p.id for p in RIG.phones].index(CAMERA)
    phone = SimulatedPhone("REF", subject=make_body(seed=BODY_SEED), optics=RIG.optics)
    jpeg = phone._picture(phone_pose_source(RIG, index, lambda _t: angle_deg)(0.0), diopters, 0)
    return np.asarray(Image.open(io.BytesIO(jpeg)).convert("L"), dtype=float)


def _similarity(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.corrcoef(a.ravel(), b.ravel())[0, 1])


async def _move_beam(bridge_port: int, angle_deg: float) -> None:
    """As the daemon does: connect over socketcand (bring-up starts the position TPDOs), enable, move."""
    bus = await asyncio.to_thread(can.Bus, interface="socketcand", host="127.0.0.1", port=bridge_port,
                                  channel="can0")
    drive = BeamDrive(PythonCanPort(bus, name="socketcand"), RIG.motor)
    try:
        await drive.connect()
        await drive.enable()
        await drive.move_to(angle_deg, RIG.motor.max_speed_deg_s, RIG.motor.max_acceleration_deg_s2)
    finally:
        await drive.close()


@pytest.mark.slow
@pytest.mark.realtime
def test_a_phone_following_the_beam_photographs_at_the_angle_the_drive_reports(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    from drivers.phone.camera import PhoneCamera

    # The simulated phone ray casts the body within the capture, on this machine's CPU: ~0.2 s,
    # 1.8 s on a 2-core machine busy with other work, where a phone's own processor would not
    # wait for the host's. The capture still has to answer, from where the beam stood.
    monkeypatch.setattr(PhoneCamera, "CAPTURE_TIMEOUT_S", 30.0)
    with _process("sim", "motor", "--port", "0", ready=r"socketcand 127\.0\.0\.1:(\d+) channel can0") as (_, m):
        bridge = int(m.group(1))
        with _process("sim", "phone", "--port", "0", "--serial", "TBPSIM03", "--camera", CAMERA,
                      "--body-seed", str(BODY_SEED), "--follow-beam", f"127.0.0.1:{bridge}",
                      ready=r"adbd\) on 127\.0\.0\.1:(\d+)") as (phone_proc, p):
            assert phone_proc.stdout is not None
            assert "following the beam's position on socketcand" in phone_proc.stdout.readline()
            asyncio.run(_move_beam(bridge, 90.0))
            code = main(["phone", "check", "--tcp", f"127.0.0.1:{p.group(1)}", "--camera", CAMERA,
                         "--state-dir", str(tmp_path / "state"), "--out", str(tmp_path)])
            out = capsys.readouterr().out
            assert code == 0, out
    diopters = float(re.search(r"focus  *450\.0 mm -> ([0-9.]+) D", out).group(1))
    shot = np.asarray(Image.open(tmp_path / f"{CAMERA}-check.jpg").convert("L"), dtype=float)
    at_90, at_0 = _reference(90.0, diopters), _reference(0.0, diopters)
    assert _similarity(at_90, at_0) < 0.9  # the two poses see the body differently
    assert _similarity(shot, at_90) > 0.99  # JPEG noise only: the phone stood where the beam was
    assert _similarity(shot, at_90) > _similarity(shot, at_0) + 0.05


def test_follow_beam_is_refused_without_a_body_and_with_a_bad_address(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["sim", "phone", "--port", "0", "--follow-beam", "127.0.0.1"])
    assert "expected HOST:PORT" in capsys.readouterr().err
    with pytest.raises(SystemExit, match="--follow-beam needs --body-seed"):
        main(["sim", "phone", "--port", "0", "--follow-beam", "127.0.0.1:29536"])
