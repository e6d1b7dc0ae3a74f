"""``tbp phone check`` against ``tbp sim phone`` running as its own process."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from cli import main

pytestmark = pytest.mark.realtime  # a simulated phone in its own process


@pytest.fixture
def sim_phone_port() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "import sys; from cli import main; sys.exit(main())",
                             "sim", "phone", "--port", "0", "--serial", "TBPSIM03"], stdout=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert "127.0.0.1:" in line, line
        yield int(line.rsplit(":", 1)[1])
    finally:
        proc.terminate()
        proc.wait(timeout=20)


def test_check_a_phone_end_to_end(sim_phone_port: int, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    code = main(["phone", "check", "--tcp", f"127.0.0.1:{sim_phone_port}", "--camera", "cam3",
                 "--state-dir", str(tmp_path / "state"), "--out", str(tmp_path / "out")])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "TBPSIM03" in out and "lens still after" in out and out.rstrip().endswith("OK")
    assert (tmp_path / "out" / "cam3-check.jpg").stat().st_size > 0
    assert (tmp_path / "state" / "adbkey.pub").exists()


def test_check_reports_the_typed_error(sim_phone_port: int, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    code = main(["phone", "check", "--tcp", f"127.0.0.1:{sim_phone_port}", "--camera", "cam1",
                 "--state-dir", str(tmp_path / "state"), "--out", str(tmp_path)])
    assert code == 1
    assert "FAILED: WrongPhone" in capsys.readouterr().err


def test_check_a_phone_that_photographs_a_body(tmp_path: Path, capsys: pytest.CaptureFixture,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    import numpy as np
    from PIL import Image

    from drivers.phone.camera import PhoneCamera

    # The simulated phone ray casts the body within the capture, on this machine's CPU: ~0.2 s,
    # 1.8 s on a 2-core machine busy with other work, where a phone's own processor would not
    # wait for the host's. The capture still has to answer, with the body in the picture.
    monkeypatch.setattr(PhoneCamera, "CAPTURE_TIMEOUT_S", 30.0)
    proc = subprocess.Popen([sys.executable, "-c", "import sys; from cli import main; sys.exit(main())",
                             "sim", "phone", "--port", "0", "--serial", "TBPSIM03", "--body-seed", "2"],
                            stdout=subprocess.PIPE, text=True)
    try:
        port = int(proc.stdout.readline().rsplit(":", 1)[1])
        code = main(["phone", "check", "--tcp", f"127.0.0.1:{port}", "--camera", "cam3",
                     "--state-dir", str(tmp_path / "state"), "--out", str(tmp_path)])
        assert code == 0, capsys.readouterr()
        image = np.asarray(Image.open(tmp_path / "cam3-check.jpg"))
        assert image[image.shape[0] // 2, image.shape[1] // 2, 0] > 120  # the body fills the middle
    finally:
        proc.terminate()
        proc.wait(timeout=20)


@pytest.mark.realtime
def test_check_pushes_the_agents_jvm_build_and_runs_it(agent_jvm_jar: Path, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture) -> None:
    proc = subprocess.Popen([sys.executable, "-c", "import sys; from cli import main; sys.exit(main())", "sim",
                             "phone", "--port", "0", "--serial", "TBPSIM03", "--agent-runtime", "jvm"],
                            stdout=subprocess.PIPE, text=True)
    try:
        port = int(proc.stdout.readline().rsplit(":", 1)[1])
        check = ["phone", "check", "--tcp", f"127.0.0.1:{port}", "--camera", "cam3",
                 "--state-dir", str(tmp_path / "state"), "--out", str(tmp_path / "out")]
        assert main(check) == 1  # nothing on the phone and no jar to push
        assert "FAILED: AgentMissing" in capsys.readouterr().err
        assert main([*check, "--agent-jar", str(agent_jvm_jar)]) == 0
        out = capsys.readouterr().out
        assert f"agent pushed ({agent_jvm_jar.stat().st_size} bytes)" in out and out.rstrip().endswith("OK")
        assert (tmp_path / "out" / "cam3-check.jpg").stat().st_size > 0
        assert main([*check, "--agent-jar", str(agent_jvm_jar)]) == 0  # the phone's copy is this build
        assert "the phone's agent" in capsys.readouterr().out
    finally:
        proc.terminate()
        proc.wait(timeout=20)
