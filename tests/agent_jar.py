"""The capture agent's JVM jar for the tests: built by agent/build.sh once per version of its sources.

Tests take it as the ``agent_jvm_jar`` fixture (tests/conftest.py); a test that needs the JVM is
skipped with the reason when no JDK is installed (``./dev`` installs one).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest

AGENT = Path(__file__).resolve().parents[1] / "agent"
JAR_NAME = "tbp-capture-agent-jvm.jar"


def jdk_missing() -> str | None:
    """Why the JVM agent cannot be built and run here, or None."""
    missing = [tool for tool in ("javac", "jar", "java") if shutil.which(tool) is None]
    return f"no {', '.join(missing)}: apt-get install default-jdk-headless" if missing else None


def sources_digest() -> str:
    """A hash of everything the JVM jar is built from."""
    digest = hashlib.sha256()
    files = [AGENT / "build.sh", *sorted((AGENT / "src" / "core").rglob("*.java")),
             *sorted((AGENT / "src" / "jvm").rglob("*.java"))]
    for path in files:
        digest.update(str(path.relative_to(AGENT)).encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()[:16]


def build_jvm_jar(cache: Path) -> Path:
    """The JVM jar for the current sources, built into ``cache/<digest>/`` unless already there."""
    out = cache / sources_digest()
    jar = out / JAR_NAME
    if jar.is_file():
        return jar
    cache.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(dir=cache, prefix=".build-"))
    result = subprocess.run(["bash", str(AGENT / "build.sh"), "jar", str(scratch)], capture_output=True, text=True)
    if result.returncode != 0:
        shutil.rmtree(scratch, ignore_errors=True)
        raise RuntimeError(f"agent/build.sh jar failed:\n{result.stdout}\n{result.stderr}")
    shutil.rmtree(scratch / "classes")
    try:
        os.rename(scratch, out)
    except OSError:  # another session built the same sources meanwhile
        shutil.rmtree(scratch, ignore_errors=True)
    return jar


def session_jar(request: pytest.FixtureRequest) -> Path:
    """The capture agent's JVM build (core + simulator platform), cached in pytest's cache folder."""
    reason = jdk_missing()
    if reason is not None:
        pytest.skip(reason)
    return build_jvm_jar(Path(request.config.cache.mkdir("tbp-agent-jar")))
