"""Shared test set-up."""

from __future__ import annotations

import gc
import os
from collections.abc import Iterator
from pathlib import Path

import pytest
import structlog
from hypothesis import settings

from daemon.offload.worker import one_numeric_thread

# Property tests draw the same examples on every run (a CI run never fails on a draw the last
# one did not make); HYPOTHESIS_PROFILE=explore draws new ones when hunting for bugs. No deadline:
# a property holds or not whatever the machine's load (tests never assert on wall-clock time).
settings.register_profile("ci", derandomize=True, print_blob=True, deadline=None)
settings.register_profile("explore", derandomize=False, deadline=None)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

# One BLAS and OpenMP thread per test process and per process a test starts: the suite runs one
# pytest-xdist worker per core, and a library splitting its loops over every core on a machine
# whose cores are all busy waits at each barrier for the half that shares a busy core.
one_numeric_thread()


LOOPBACK_RIGS = frozenset({"test_loopback_rig.py", "test_loopback_safety.py"})
"""Tests of a whole rig on this machine (sim/loopback.py): one xdist group, so one runs at a time,
started first. A loopback rig's daemon, drive and compute worker get the CPU before other work,
as the unit gives them on a rig PC, which has one rig: two at once starve each other's daemon
past its heartbeats (here a drive lost the host's for 0.35 s)."""


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Tiers, xdist groups and order (before ``-m`` selects): a test of the shared simulated scan
    (``web_store``) is slow, and all of them run on one xdist worker, which makes that scan once."""
    for item in items:
        if "web_store" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.xdist_group("web_store"))
            item.add_marker(pytest.mark.slow)
        if item.path.name in LOOPBACK_RIGS:
            item.add_marker(pytest.mark.xdist_group("loopback_rig"))
    # The loopback rigs' tests start first: they take minutes at the beam's real speeds, one after
    # the other on one worker, while the other workers take the rest. Then the slow tests (whole
    # scans, rotations, worker processes), so a phase ends on short tests on every worker instead
    # of one worker starting a minutes-long test while the others run out of work. (pytest-xdist
    # hands out its groups largest first, then single tests in this order.)
    items.sort(key=lambda item: (item.path.name not in LOOPBACK_RIGS, item.get_closest_marker("slow") is None))


def pytest_runtest_setup(item: pytest.Item) -> None:
    """A realtime test runs with the heap the earlier tests left frozen, as the daemon freezes its
    own after start-up (daemon/server/looplag.py): a full collection then walks only what the test
    made, not the whole run's objects, which paused the loop past a drive's 0.5 s host guard late in
    a CI run. Its teardown thaws them."""
    if item.get_closest_marker("realtime") is not None:
        gc.freeze()


@pytest.hookimpl(trylast=True)
def pytest_runtest_teardown(item: pytest.Item) -> None:
    if item.get_closest_marker("realtime") is not None:
        gc.unfreeze()


@pytest.fixture(autouse=True)
def _structlog_defaults() -> Iterator[None]:
    """A CLI run in-process binds structlog to pytest's captured stdout, which closes after the
    test; put the defaults back so later tests never log into a closed stream."""
    from daemon.logs import close_logging

    yield
    close_logging()
    structlog.reset_defaults()


def _tree(root: Path) -> dict[str, tuple[int, int]]:
    """Every file under ``root``: relative path -> (size, mtime ns)."""
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns) for p in root.rglob("*") if p.is_file()}


@pytest.fixture(scope="session")
def agent_jvm_jar(request: pytest.FixtureRequest):
    """The capture agent's JVM build, built once per version of agent/ (tests/agent_jar.py);
    the test is skipped when no JDK is installed."""
    from tests.agent_jar import session_jar

    return session_jar(request)


@pytest.fixture(scope="session")
def web_store(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """A store with one small simulated scan of the complete simulated rig (capsule subject, QA
    report) for a synthetic patient, shared read-only by the web, browser and scan report tests (a
    test that writes works on a copy); the session fails if any test changed it."""
    from analysis.qa_report import generate_report
    from daemon.clinic.patient import ScanSubject
    from sim.run import run_sim_scan
    from tests.daemon_rigs import PLAN_POINTS, capsule_subject

    root = tmp_path_factory.mktemp("web-store")
    patient = ScanSubject.from_args({"patient_id": "SYN-0001", "patient_name": "Testperson^Capsule"})
    run_sim_scan(store=root, seed=1, plan_points=PLAN_POINTS, depth_decimation=4, subject=capsule_subject(),
                 panel=False, qa_report=generate_report, patient=patient)
    made = _tree(root)
    yield root
    assert _tree(root) == made, "a test changed the shared web_store: copy it first (see test_web.scan_store)"
