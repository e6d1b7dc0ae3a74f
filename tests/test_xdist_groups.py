"""The suite's xdist groups hold with the installed pytest and pytest-xdist.

``./dev test`` runs on pytest-xdist workers with ``--dist loadgroup``: the tests of the shared
simulated scan share one worker (tests/conftest.py), which makes that scan once. A pytest that
keeps node ids where pytest-xdist cannot mark the group (pytest 9.2 with pytest-xdist 3.8) spreads
a group over the workers without a word; this test sees it.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

GROUPED = '''
import pytest


@pytest.mark.xdist_group("shared")
@pytest.mark.parametrize("i", range(6))
def test_grouped(i):
    assert i in range(6)
'''


def test_a_group_runs_on_one_worker(tmp_path: Path) -> None:
    (tmp_path / "test_grouped.py").write_text(GROUPED)
    (tmp_path / "pytest.ini").write_text("[pytest]\n")
    run = subprocess.run([sys.executable, "-m", "pytest", "-n", "2", "--dist", "loadgroup", "-v", "-p",
                          "no:cacheprovider", str(tmp_path)], cwd=tmp_path, capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    passed = re.findall(r"\[(gw\d+)\].*PASSED .*test_grouped\[\d\](@\w+)?", run.stdout)
    assert len(passed) == 6, run.stdout[-3000:]
    assert {group for _, group in passed} == {"@shared"}, "the group's suffix is missing: " + run.stdout[-3000:]
    assert len({worker for worker, _ in passed}) == 1, passed
