"""The scan state machine: the transition table, the latched fault, status events."""

from __future__ import annotations

import asyncio

import pytest

from daemon.errors import IllegalTransition
from daemon.states import TRANSITIONS, ScanState, ScanStateMachine

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


def test_every_state_appears_in_the_table() -> None:
    assert set(TRANSITIONS) == set(ScanState)
    for targets in TRANSITIONS.values():
        assert targets <= set(ScanState)


@pytest.mark.parametrize("start", list(ScanState))
def test_disallowed_transitions_raise(start: ScanState) -> None:
    for to in ScanState:
        machine = ScanStateMachine()
        machine.state = start
        if to in TRANSITIONS[start] and not (start is ScanState.FAULT and to is ScanState.IDLE):
            machine.transition(to, "ok")
            assert machine.state is to
        elif to is ScanState.FAULT and start is ScanState.FAULT:
            machine.transition(to, "again")
            assert machine.state is ScanState.FAULT
        else:
            with pytest.raises(IllegalTransition) as info:
                machine.transition(to, "bad")
            assert info.value.current == start.value and info.value.requested == to.value
            assert machine.state is start


def test_fault_is_latched_until_reset() -> None:
    machine = ScanStateMachine()
    machine.transition(ScanState.PREPARING, "start")
    machine.transition(ScanState.FAULT, "estop")
    machine.transition(ScanState.FAULT, "drive fault")
    assert machine.fault_causes == ["estop", "drive fault"]
    with pytest.raises(IllegalTransition):
        machine.transition(ScanState.IDLE, "scan finished")
    with pytest.raises(IllegalTransition):
        machine.transition(ScanState.PREPARING, "new scan")
    machine.reset("operator")
    assert machine.state is ScanState.IDLE and machine.fault_causes == []
    with pytest.raises(IllegalTransition):
        machine.reset("again")


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
