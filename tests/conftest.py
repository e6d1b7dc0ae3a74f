"""Shared test set-up."""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest
import structlog
from hypothesis import settings

# Property tests draw the same examples on every run (a CI run never fails on a draw the last
# one did not make); HYPOTHESIS_PROFILE=explore draws new ones when hunting for bugs.
settings.register_profile("ci", derandomize=True, print_blob=True)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Tiers that follow from a test's fixtures (before ``-m`` selects): a test of the shared
    simulated scan (``web_store``) is slow."""
    for item in items:
        if "web_store" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.slow)


@pytest.fixture(autouse=True)
def _structlog_defaults() -> Iterator[None]:
    """A CLI run in-process binds structlog to pytest's captured stdout, which closes after the
    test; put the defaults back so later tests never log into a closed stream."""
    yield
    structlog.reset_defaults()


@pytest.fixture(scope="session")
def web_store(tmp_path_factory: pytest.TempPathFactory):
    """A store with one small simulated scan (capsule subject, QA report), shared by the web tests."""
    from analysis.qa_report import generate_report
    from sim.run import run_sim_scan
    from tests.daemon_rigs import PLAN_POINTS, capsule_subject

    root = tmp_path_factory.mktemp("web-store")
    run_sim_scan(store=root, seed=1, plan_points=PLAN_POINTS, depth_decimation=4, subject=capsule_subject(),
                 panel=False, qa_report=generate_report)
    return root
