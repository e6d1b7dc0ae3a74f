"""The scan state machine: the transition table, the latched fault, status events."""

from __future__ import annotations

import asyncio

import pytest

from daemon.errors import IllegalTransition
from daemon.faults import AbortCause, AbortSource, FaultCause, FaultSource
from daemon.rig.states import TRANSITIONS, ScanState, ScanStateMachine

S = ScanState
ESTOP = FaultCause(FaultSource.ESTOP, "panel", "e-stop pressed")
DRIVE = FaultCause(FaultSource.DRIVE_FAULT, "beam", "DriveFault: over-current")

HAPPY_PATH = [
    ScanState.PREPARING,
    ScanState.DEPTH_SWEEP,
    ScanState.RECONSTRUCTING,
    ScanState.PLANNING,
    ScanState.CAPTURING,
    ScanState.RETAKING,
    ScanState.STORING,
    ScanState.IDLE,
]


def test_happy_path_is_allowed() -> None:
    machine = ScanStateMachine()
    for state in HAPPY_PATH:
        machine.transition(state, "test")
    assert machine.state is ScanState.IDLE
    assert [e.state for e in machine.history] == HAPPY_PATH


EDGES = {
    (S.IDLE, S.PREPARING),
    (S.PREPARING, S.DEPTH_SWEEP), (S.DEPTH_SWEEP, S.RECONSTRUCTING),
    (S.RECONSTRUCTING, S.PLANNING), (S.PLANNING, S.CAPTURING),
    (S.CAPTURING, S.RETAKING), (S.CAPTURING, S.STORING), (S.RETAKING, S.STORING),
    (S.STORING, S.IDLE),
    (S.IDLE, S.CALIBRATING), (S.CALIBRATING, S.STORING),  # the calibration rotation
    *((s, S.ABORTING) for s in (S.PREPARING, S.DEPTH_SWEEP, S.RECONSTRUCTING, S.PLANNING,
                                 S.CAPTURING, S.RETAKING, S.CALIBRATING)),
    (S.ABORTING, S.STORING), (S.ABORTING, S.IDLE),
    *((s, S.FAULT) for s in S if s is not S.FAULT),
}
"""The life of a scan, written out by hand (not read back from the table under test). FAULT ->
IDLE is only :meth:`ScanStateMachine.reset`; FAULT -> FAULT only adds a cause."""


def test_the_table_is_exactly_the_written_edges() -> None:
    table = {(a, b) for a, targets in TRANSITIONS.items() for b in targets}
    assert table == EDGES | {(S.FAULT, S.IDLE)}


@pytest.mark.parametrize("start", list(ScanState))
def test_disallowed_transitions_raise(start: ScanState) -> None:
    for to in ScanState:
        machine = ScanStateMachine()
        machine.state = start
        cause = ESTOP if to is S.FAULT else "test"
        if (start, to) in EDGES:
            machine.transition(to, cause)
            assert machine.state is to and machine.history[-1].kind == "transition"
        elif start is S.FAULT and to is S.FAULT:
            machine.transition(to, cause)
            assert machine.state is S.FAULT and machine.history[-1].kind == "progress"
        else:
            with pytest.raises(IllegalTransition) as info:
                machine.transition(to, cause)
            assert info.value.current == start.value and info.value.requested == to.value
            assert machine.state is start and machine.history == []


def test_fault_takes_a_typed_cause_only() -> None:
    machine = ScanStateMachine()
    with pytest.raises(TypeError, match="FaultCause"):
        machine.transition(S.FAULT, "e-stop pressed")
    with pytest.raises(TypeError, match="FaultCause"):
        machine.transition(S.FAULT, AbortCause(AbortSource.STOP_BUTTON, "panel", "stop button"))
    assert machine.state is S.IDLE and machine.fault_causes == []


def test_fault_is_latched_until_reset() -> None:
    machine = ScanStateMachine()
    machine.transition(ScanState.PREPARING, "start")
    machine.transition(ScanState.FAULT, ESTOP)
    machine.transition(ScanState.FAULT, DRIVE)
    assert machine.fault_causes == [ESTOP, DRIVE]
    event = machine.history[-1].as_dict()
    assert event["cause"] == "beam: DriveFault: over-current"
    assert (event["source"], event["device"]) == ("drive_fault", "beam")
    with pytest.raises(IllegalTransition):
        machine.transition(ScanState.IDLE, "scan finished")
    with pytest.raises(IllegalTransition):
        machine.transition(ScanState.PREPARING, "new scan")
    machine.reset("operator")
    assert machine.state is ScanState.IDLE and machine.fault_causes == []
    with pytest.raises(IllegalTransition):
        machine.reset("again")


def test_a_cause_survives_its_json_form() -> None:
    for cause in (ESTOP, AbortCause(AbortSource.STORE, "store", "StoreFull: disk full")):
        data = cause.as_dict()
        assert data["text"] == str(cause)
        back = type(cause).from_dict(data)
        assert back == cause and type(back) is type(cause)


async def test_subscribers_receive_events_in_order() -> None:
    machine = ScanStateMachine()
    events = machine.subscribe()
    received: list[ScanState] = []

    async def collect() -> None:
        async for event in events:
            received.append(event.state)
            if event.state is ScanState.IDLE:
                return

    task = asyncio.create_task(collect())
    await asyncio.sleep(0)
    for state in HAPPY_PATH:
        machine.transition(state, "test", step=state.value)
    await asyncio.wait_for(task, 1.0)
    assert received == HAPPY_PATH
    assert machine.history[0].as_dict()["data"] == {"step": "PREPARING"}


async def test_wait_for_state() -> None:
    machine = ScanStateMachine()
    waiter = asyncio.create_task(machine.wait_for(ScanState.DEPTH_SWEEP))
    await asyncio.sleep(0)
    machine.transition(ScanState.PREPARING, "x")
    await asyncio.sleep(0)
    assert not waiter.done()
    machine.transition(ScanState.DEPTH_SWEEP, "y")
    assert await asyncio.wait_for(waiter, 1.0) is ScanState.DEPTH_SWEEP


def test_the_scan_steps_follow_the_table() -> None:
    """Each scan step hands over to the next one the table allows; RETAKING may be skipped."""
    from daemon.rig.states import SCAN_STEPS

    assert SCAN_STEPS[0] in TRANSITIONS[S.IDLE]
    for state, after in zip(SCAN_STEPS, SCAN_STEPS[1:]):
        assert after in TRANSITIONS[state], (state, after)
    assert S.STORING in TRANSITIONS[SCAN_STEPS[-1]] and S.STORING in TRANSITIONS[S.CAPTURING]


def test_the_status_carries_the_state_lists_the_console_reads() -> None:
    """The console (web/static/console.js) keeps no state list of its own: it reads these."""
    from pathlib import Path

    from daemon.rig.states import ACTIVE_STATES, SCAN_STATES, state_groups

    groups = state_groups()
    assert set(groups["active"]) == {s.value for s in ACTIVE_STATES}
    assert set(groups["job"]) == {s.value for s in SCAN_STATES}
    assert groups["active"][:2] == ["PREPARING", "DEPTH_SWEEP"] and "ABORTING" not in groups["active"]
    console = (Path(__file__).parents[1] / "web" / "static" / "console.js").read_text()
    assert '"RECONSTRUCTING"' not in console and "s.states" in console
