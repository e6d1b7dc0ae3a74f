"""``tbp calibrate``: printable target, clear refusals."""

from __future__ import annotations

from pathlib import Path

import pytest

from cli import main


def test_target_writes_every_face(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["calibrate", "target", "--out", str(tmp_path)]) == 0
    assert len(list(tmp_path.glob("face_*.pdf"))) == 4 and len(list(tmp_path.glob("face_*.png"))) == 4
    assert "face_plus_x.pdf" in capsys.readouterr().out


def test_unreadable_captures_file_is_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "captures.json").write_text('{"captures": [{"camera": "cam0"}]}')
    assert main(["calibrate", "--pictures", str(tmp_path / "captures.json"), "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert "captures[0]" in err and "encoder_deg" in err


def test_sim_and_pictures_exclude_each_other(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["calibrate", "--sim", "--pictures", str(tmp_path / "c.json"), "--out", str(tmp_path)]) == 2
    assert "--sim or --pictures" in capsys.readouterr().err


def test_on_the_rig_it_needs_the_daemon(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    sock = tmp_path / "no.sock"
    assert main(["calibrate", "--out", str(tmp_path / "o"), "--socket", str(sock)]) == 1
    err = capsys.readouterr().err
    assert str(sock) in err and "not reachable" in err
    assert not (tmp_path / "o" / "calibration.yaml").exists()


def test_bad_target_file_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "t.yaml").write_text("name: x\n")
    assert main(["calibrate", "target", "--target", str(tmp_path / "t.yaml"), "--out", str(tmp_path)]) == 2
    assert "t.yaml" in capsys.readouterr().err
