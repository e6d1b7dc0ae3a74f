"""The tbp command turns NumPy's huge-page advice off unless its environment asks for it."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from numpy._core.multiarray import _set_madvise_hugepage

from cli.pages import VARIABLE, numpy_page_advice


@pytest.fixture
def advice():
    """NumPy's advice as it was, restored after the test (setting it returns the old value)."""
    before = _set_madvise_hugepage(True)
    _set_madvise_hugepage(before)
    yield
    _set_madvise_hugepage(before)


def _current() -> bool:
    now = _set_madvise_hugepage(True)
    _set_madvise_hugepage(now)
    return now


def test_unset_means_off_here_and_in_the_processes_started_from_here(advice, monkeypatch) -> None:
    monkeypatch.delenv(VARIABLE, raising=False)
    _set_madvise_hugepage(True)
    assert numpy_page_advice() is False and _current() is False
    assert os.environ[VARIABLE] == "0"
    probe = "from numpy._core.multiarray import _set_madvise_hugepage as f; print(f(True))"
    child = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert child.stdout.strip() == "False"


def test_the_environment_can_turn_the_advice_back_on(advice, monkeypatch) -> None:
    monkeypatch.setenv(VARIABLE, "1")
    _set_madvise_hugepage(False)
    assert numpy_page_advice() is True and _current() is True


def test_a_malformed_value_is_named(advice, monkeypatch) -> None:
    monkeypatch.setenv(VARIABLE, "yes")
    with pytest.raises(ValueError, match=r"NUMPY_MADVISE_HUGEPAGE='yes'"):
        numpy_page_advice()


def test_the_tbp_command_sets_it_before_parsing(advice, monkeypatch) -> None:
    from cli import main

    monkeypatch.delenv(VARIABLE, raising=False)
    _set_madvise_hugepage(True)
    with pytest.raises(SystemExit):
        main(["--help"])
    assert _current() is False
