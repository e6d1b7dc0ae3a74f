"""The capture agent's Java build (agent/build.sh): the core's JUnit tests, and the Camera2 backend
compiled against the Android API stubs, so that a typo or a wrong signature fails here."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from tests.agent_jar import AGENT, jdk_missing

pytestmark = [pytest.mark.slow, pytest.mark.skipif(jdk_missing() is not None, reason=str(jdk_missing()))]


def _build(step: str, out: Path, agent: Path = AGENT, **env: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["bash", str(agent / "build.sh"), step, str(out)], capture_output=True, text=True,
                          env={**os.environ, **env}, timeout=600)


@pytest.mark.skipif(not Path("/usr/share/java/junit4.jar").is_file(), reason="apt-get install junit4")
def test_the_cores_unit_tests_pass(tmp_path: Path) -> None:
    result = _build("test", tmp_path)
    assert result.returncode == 0, result.stdout + result.stderr
    assert re.search(r"^OK \(\d+ tests\)", result.stdout, re.MULTILINE), result.stdout


def test_the_camera2_backend_compiles_against_the_stubs(tmp_path: Path) -> None:
    result = _build("check", tmp_path)
    assert result.returncode == 0, result.stdout + result.stderr
    assert not (tmp_path / "classes" / "android-check").exists()  # compile only: nothing of it is kept


@pytest.mark.parametrize("wrong, right", [
    ("CaptureResult.LENS_STATE)", "CaptureResult.LENS_STATES)"),  # a typo
    ("session.capture(still.build(), stillCallback, handler)", "session.capture(still.build(), stillCallback)"),
])
def test_a_wrong_camera2_call_fails_the_check(tmp_path: Path, wrong: str, right: str) -> None:
    agent = tmp_path / "agent"
    shutil.copytree(AGENT, agent, ignore=shutil.ignore_patterns("build"))
    backend = agent / "src/android/com/tbp/agent/android/Camera2Backend.java"
    text = backend.read_text()
    assert wrong in text
    backend.write_text(text.replace(wrong, right, 1))
    result = _build("check", tmp_path / "out", agent=agent)
    assert result.returncode != 0
    assert "Camera2Backend.java" in result.stderr + result.stdout


def test_the_core_and_the_simulator_build_import_nothing_of_android() -> None:
    for folder in ("src/core", "src/jvm"):
        for source in (AGENT / folder).rglob("*.java"):
            assert not re.search(r"^import (static )?android\.", source.read_text(), re.MULTILINE), source


def test_the_dex_jar_needs_the_android_sdk(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k != "ANDROID_HOME"}
    result = subprocess.run(["bash", str(AGENT / "build.sh"), "dex", str(tmp_path)], capture_output=True, text=True,
                            env=env, timeout=60)
    assert result.returncode != 0 and "ANDROID_HOME" in result.stderr
