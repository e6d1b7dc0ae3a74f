"""The event loop's lateness, per scan state (daemon/server/looplag.py)."""

from __future__ import annotations

import asyncio
import math
import subprocess
import sys
import time
import traceback
from pathlib import Path

import pytest
import structlog
from hypothesis import given
from hypothesis import strategies as st

from daemon.jobs.scan import ScanReport
from daemon.rig.states import ScanOutcome
from daemon.server.looplag import LoopLagMonitor, MachineTimes
from daemon.server.stallstacks import format_dump, place
from sim.loopback import UNIT, machine_caused, set_autogroup_nice, unit_cpu_weight, weight_nice


def test_a_blocked_loop_is_measured_and_logged_under_the_state_it_blocked_in() -> None:
    state = ["IDLE"]
    monitor = LoopLagMonitor(lambda: state[0], period_s=0.01, warn_s=0.05)

    async def scenario() -> None:
        task = asyncio.create_task(monitor.run())
        await asyncio.sleep(0.05)
        state[0] = "PLANNING"
        await asyncio.sleep(0.02)
        time.sleep(0.12)  # compute on the loop: what the worker process exists to prevent
        await asyncio.sleep(0.03)
        state[0] = "CAPTURING"
        await asyncio.sleep(0.03)
        task.cancel()

    with structlog.testing.capture_logs() as logs:
        asyncio.run(scenario())
    summary = monitor.summary()
    assert summary["PLANNING"]["max_ms"] >= 100.0
    assert summary["IDLE"]["max_ms"] < summary["PLANNING"]["max_ms"]
    stalls = [e for e in logs if e["event"] == "loop_lag"]
    assert stalls and all(e["lag_state"] == "PLANNING" for e in stalls)
    summaries = [e["lag_state"] for e in logs if e["event"] == "loop_lag_summary"]
    assert summaries == ["IDLE", "PLANNING"]  # each state summarised when the loop leaves it


def _hold_the_loop() -> None:
    time.sleep(0.15)


def _monitored(monitor: LoopLagMonitor, hold: bool) -> None:
    """Run ``monitor`` 0.1 s, the loop held by :func:`_hold_the_loop` in the middle if ``hold``."""

    async def scenario() -> None:
        task = asyncio.create_task(monitor.run())
        await asyncio.sleep(0.05)
        if hold:
            _hold_the_loop()
        await asyncio.sleep(0.05)
        task.cancel()

    asyncio.run(scenario())


def test_a_stall_leaves_every_threads_stack_taken_while_it_lasted(tmp_path: Path) -> None:
    stacks = tmp_path / "loop-stalls.txt"
    monitor = LoopLagMonitor(lambda: "CAPTURING", period_s=0.01, warn_s=0.05, tracebacks=stacks)
    with structlog.testing.capture_logs() as logs:
        _monitored(monitor, hold=True)
    text = stacks.read_text()
    assert "in _hold_the_loop" in text and "in scenario" in text  # taken during the stall, not after
    stalls = [e for e in logs if e["event"] == "loop_lag"]
    assert stalls and all(e["tracebacks"] == str(stacks) for e in stalls)
    # the loop thread's place in this stall's own dump: the code that held it, not its selector
    assert stalls[0]["loop_frame"].startswith("test_looplag.py:") and stalls[0]["loop_frame"].endswith(" in _hold_the_loop")
    assert stalls[0]["process_cpu_ms"] >= 0.0
    assert stalls[0]["stacks_after_ms"] >= 0.0


def test_the_dump_is_in_the_fault_handlers_layout_with_the_loop_thread_named() -> None:
    here = traceback.extract_stack()
    text = format_dump({0x7F0000000002: here, 0x7F0000000001: here}, 0x7F0000000001, "Loop stall")
    lines = text.splitlines()
    assert lines[0] == "Loop stall"
    assert "Thread 0x00007f0000000002 (most recent call first):" in lines
    assert "Loop thread 0x00007f0000000001 (most recent call first):" in lines
    first = lines[lines.index("Loop thread 0x00007f0000000001 (most recent call first):") + 1]
    assert first.startswith(f'  File "{__file__}", line ') and first.endswith(
        " in test_the_dump_is_in_the_fault_handlers_layout_with_the_loop_thread_named")  # most recent first
    me = place(sys._getframe())  # noqa: SLF001
    assert me.startswith("test_looplag.py:")
    assert me.endswith(" in test_the_dump_is_in_the_fault_handlers_layout_with_the_loop_thread_named")


CHURN = """
import asyncio, sys, threading, time
from pathlib import Path
from daemon.server.looplag import LoopLagMonitor

def deep(n):  # frames past one chunk of the interpreter's frame stack, allocated and freed
    return [object()] if n == 0 else deep(n - 1)

def churn():
    while True:
        deep(900)

async def main():
    for _ in range(3):
        threading.Thread(target=churn, daemon=True).start()
    task = asyncio.create_task(LoopLagMonitor(lambda: "CAPTURING", period_s=0.01, warn_s=0.02,
                                              tracebacks=Path(sys.argv[1])).run())
    end = time.monotonic() + 2.0
    while time.monotonic() < end:
        await asyncio.sleep(0.01)
        time.sleep(0.04)  # a stall past warn_s, the other threads running meanwhile
    task.cancel()

asyncio.run(main())
"""


@pytest.mark.realtime
def test_stall_dumps_never_crash_the_daemon_however_its_threads_stacks_change(tmp_path: Path) -> None:
    """The interpreter's fault handler, armed at every sample, reads other threads' frames without
    the interpreter lock and crashes this program within a second (SIGSEGV); the watcher takes
    the stacks under the lock."""
    stacks = tmp_path / "loop-stalls.txt"
    run = subprocess.run([sys.executable, "-c", CHURN, str(stacks)], cwd=Path(__file__).parents[1],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr[-3000:]
    assert stacks.read_text().count("Loop thread 0x") >= 5  # the stalls were dumped, not skipped


def test_an_unwritable_stall_file_is_logged_and_the_lag_still_measured(tmp_path: Path) -> None:
    stacks = tmp_path / "no-such-folder" / "loop-stalls.txt"
    monitor = LoopLagMonitor(lambda: "CAPTURING", period_s=0.01, warn_s=0.05, tracebacks=stacks)
    with structlog.testing.capture_logs() as logs:
        _monitored(monitor, hold=True)
    refused = [e for e in logs if e["event"] == "loop_stall_tracebacks_unwritable"]
    assert refused and refused[0]["path"] == str(stacks)
    stalls = [e for e in logs if e["event"] == "loop_lag"]
    assert stalls and all("tracebacks" not in e for e in stalls)
    assert monitor.summary()["CAPTURING"]["max_ms"] >= 100.0


def test_no_stack_is_taken_while_the_loop_keeps_time(tmp_path: Path) -> None:
    stacks = tmp_path / "loop-stalls.txt"
    _monitored(LoopLagMonitor(lambda: "IDLE", period_s=0.01, warn_s=0.5, tracebacks=stacks), hold=False)
    assert stacks.read_text() == ""


def test_a_stall_says_whether_the_loop_ran_code_or_was_blocked() -> None:
    """cpu_ms: the loop thread computing (code on the loop); neither it nor runqueue_ms: blocked
    (a system call, the interpreter lock); runqueue_ms: waiting for a CPU (a busy machine)."""
    state = ["IDLE"]
    monitor = LoopLagMonitor(lambda: state[0], period_s=0.01, warn_s=0.05)

    async def scenario() -> None:
        task = asyncio.create_task(monitor.run())
        await asyncio.sleep(0.05)
        state[0] = "PLANNING"
        await asyncio.sleep(0.02)
        started = time.thread_time()
        while time.thread_time() - started < 0.1:  # 100 ms of CPU on the loop
            pass
        await asyncio.sleep(0.03)
        state[0] = "STORING"
        await asyncio.sleep(0.02)
        time.sleep(0.12)  # a blocking call on the loop
        await asyncio.sleep(0.03)
        task.cancel()

    with structlog.testing.capture_logs() as logs:
        asyncio.run(scenario())
    stalls = {e["lag_state"]: e for e in logs if e["event"] == "loop_lag"}
    assert stalls["PLANNING"]["cpu_ms"] >= 100.0
    assert stalls["STORING"]["cpu_ms"] < stalls["STORING"]["lag_ms"] / 2
    assert "runqueue_ms" in stalls["STORING"]
    assert {"pressure_ms", "steal_ms"} <= set(stalls["STORING"])  # the machine's side of a blocked loop


def test_the_machines_contention_only_grows() -> None:
    machine = MachineTimes()
    try:
        first = machine.read()
        busy = time.thread_time()
        while time.thread_time() - busy < 0.02:
            pass
        second = machine.read()
    finally:
        machine.close()
    for before, after in zip(first, second, strict=True):
        assert (before is None) == (after is None)
        assert before is None or 0.0 <= before <= after


def _stall(lag: float, cpu: float | None, runqueue: float | None, pressure: float | None = None,
           steal: float | None = None, **more: object) -> dict:
    return {"event": "loop_lag", "lag_state": "CAPTURING", "lag_ms": lag, "cpu_ms": cpu, "runqueue_ms": runqueue,
            "pressure_ms": pressure, "steal_ms": steal, **more}


def test_a_stall_is_the_machines_only_when_the_machine_was_contended_and_the_loop_not_running() -> None:
    from sim.loopback import LoopbackRig

    lines = [
        _stall(60.0, 55.0, 1.0, pressure=60.0),  # code on the loop: its own, however busy the machine
        _stall(60.0, 1.0, 40.0),  # waited for a CPU itself
        _stall(50.6, 1.1, 0.9, pressure=30.0),  # blocked while tasks waited for CPUs (a lock holder)
        _stall(50.6, 1.1, 0.9, pressure=5.0, steal=25.0),  # blocked while the hypervisor ran another guest
        _stall(50.6, 1.1, 0.9, pressure=5.0),  # blocked on a quiet machine: a system call on the loop
        _stall(50.6, 1.1, None),  # an older kernel that reports nothing: its own
    ]
    rig = object.__new__(LoopbackRig)
    rig.daemon_lines = lambda: lines  # type: ignore[method-assign]
    own, starved = rig.loop_stalls()
    assert own == [lines[0], lines[4], lines[5]]
    assert starved == [lines[1], lines[2], lines[3]]


def _ci5(**fields: object) -> dict:
    """A stall seen on a loaded CI machine: 140 ms late, the loop thread ran 3.5 ms and waited
    57 ms for a CPU; tasks waited for CPUs 68.9 ms of it (just short of half)."""
    return {**_stall(140.0, 3.5, 57.0, pressure=68.9, steal=0.0), **fields}


def test_a_stall_is_the_machines_only_with_evidence_that_no_code_of_the_daemons_held_the_loop() -> None:
    # contention short of half the stall, and nothing else known: the daemon's own
    assert not machine_caused(_ci5())
    # the dump found the loop still in its selector's wait, and the daemon's threads idle: the machine's
    assert machine_caused(_ci5(loop_frame="selectors.py:468 in select", process_cpu_ms=9.0))
    # ... but not when another thread of the daemon ran most of the stall (holding the interpreter lock)
    assert not machine_caused(_ci5(loop_frame="selectors.py:468 in select", process_cpu_ms=90.0))
    # ... nor when the loop thread was in the daemon's own code or a system call of its own
    assert not machine_caused(_ci5(loop_frame="store.py:120 in write_manifest", process_cpu_ms=9.0))
    assert not machine_caused(_ci5(loop_frame=None, process_cpu_ms=9.0))
    # the loop's own code running is its own, whatever the machine and the dump
    assert not machine_caused(_ci5(cpu_ms=100.0, runqueue_ms=10.0, pressure_ms=140.0,
                                   loop_frame="selectors.py:468 in select", process_cpu_ms=100.0))
    # a CPU waited for, or contention over half the stall while blocked: the machine's
    assert machine_caused(_ci5(runqueue_ms=75.0))
    assert machine_caused(_ci5(pressure_ms=60.0, steal_ms=15.0))


@given(st.lists(st.tuples(st.sampled_from(["IDLE", "DEPTH_SWEEP", "PLANNING"]),
                          st.floats(0.0, 2.0, allow_nan=False)), min_size=1, max_size=200))
def test_per_state_figures_are_those_of_the_state_samples(samples: list[tuple[str, float]]) -> None:
    monitor = LoopLagMonitor(lambda: "IDLE", warn_s=10.0)
    for state, lag in samples:
        monitor.record(state, lag)
    summary = monitor.summary()
    for state in {s for s, _ in samples}:
        lags = sorted(lag for s, lag in samples if s == state)
        figures = summary[state]
        assert figures["samples"] == len(lags)
        assert figures["max_ms"] == round(max(lags) * 1000, 2)
        for key, q in (("p50_ms", 0.5), ("p99_ms", 0.99)):
            exact = lags[max(1, math.ceil(q * len(lags))) - 1] * 1000  # nearest rank
            # the histogram's answer: the bin's upper edge, at most 5 % (or the 0.05 ms floor) high
            assert exact - 0.01 <= figures[key] <= max(exact * 1.05, 0.05) + 0.01, (key, exact, figures)
    assert monitor.last_s == samples[-1][1]


@given(st.floats(0.0, 30.0), st.floats(0.0, 10.0), st.floats(0.0, 10.0), st.booleans())
def test_sweep_to_capture_counts_compute_once_on_either_clock(rig_s: float, tsdf_s: float, plan_s: float,
                                                              virtual: bool) -> None:
    """On the real loop the rig-time gap already contains the compute; on the virtual-time loop
    (clock frozen during compute) it is added back."""
    report = ScanReport("s", Path("/x"), ScanOutcome.COMPLETED, phase_s={"sweep_to_capture": rig_s},
                        compute_s={"tsdf": tsdf_s, "planning": plan_s}, compute_stops_clock=virtual)
    expected = rig_s + (tsdf_s + plan_s if virtual else 0.0)
    assert abs(report.sweep_to_capture_s - expected) < 1e-9


def test_the_startup_heap_is_frozen_so_full_collections_skip_it() -> None:
    import gc

    from daemon.server.looplag import freeze_startup_heap

    kept = [object() for _ in range(10)]  # alive at start-up: frozen with the rest
    try:
        frozen = freeze_startup_heap()
        assert frozen == gc.get_freeze_count() > len(kept)
        assert not any(o is kept for o in gc.get_objects())  # the collector no longer walks them
    finally:
        gc.unfreeze()


def test_a_long_collection_is_logged_as_a_gc_pause_under_its_state() -> None:
    import gc

    monitor = LoopLagMonitor(lambda: "CAPTURING", period_s=0.01, warn_s=0.0)  # every collection is "long"

    async def scenario() -> None:
        task = asyncio.create_task(monitor.run())
        await asyncio.sleep(0.02)
        gc.collect()
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)

    with structlog.testing.capture_logs() as logs:
        asyncio.run(scenario())
    pauses = [e for e in logs if e["event"] == "gc_pause"]
    assert any(e["generation"] == 2 and e["lag_state"] == "CAPTURING" and e["pause_ms"] >= 0 for e in pauses)
    assert monitor._collection not in gc.callbacks  # gone with the monitor


@given(st.integers(1, 10000), st.integers(1, 10000))
def test_a_larger_cpu_weight_is_a_lower_or_equal_nice_level(a: int, b: int) -> None:
    low, high = sorted((a, b))
    assert -20 <= weight_nice(high) <= weight_nice(low) <= 19
    assert weight_nice(100) == 0 and weight_nice(1000) == -10  # the kernel's table: 1024 -> 9548


def test_the_loopback_rig_gives_a_session_its_share_as_the_scheduler_weighs_it() -> None:
    """Each simulator and the daemon run in a session of their own; with autogroup scheduling the
    scheduler weighs the session, so that is where the unit's share must be set."""
    if not Path("/proc/self/autogroup").exists():
        pytest.skip("this kernel has no autogroup scheduling: nice levels are weighed per thread")
    child = subprocess.Popen(["sleep", "30"], start_new_session=True)
    try:
        assert set_autogroup_nice(child.pid, 7)
        assert Path(f"/proc/{child.pid}/autogroup").read_text().split()[-1] == "7"
        # A process in the kernel's first session (as under a CI runner) reads an empty line:
        # it is in the root group, which is no autogroup; the child's session is one of its own.
        own = Path("/proc/self/autogroup").read_text().split()[:1]
        assert Path(f"/proc/{child.pid}/autogroup").read_text().split()[:1] != own
    finally:
        child.kill()
        child.wait()
    assert weight_nice(unit_cpu_weight(UNIT)) < 0  # the unit asks for more than a default share
