"""One fault latch: the state machine's FAULT and its causes, which the safety monitor latches and
reads (daemon/rig/states.py, daemon/rig/safety.py). Whatever trips, resets and job steps come in whatever
order, the monitor and the machine tell the same story, and only a reset that saw no new trip
clears it."""

from __future__ import annotations

import asyncio

import pytest
from hypothesis import settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, precondition, rule

from daemon.errors import FaultLatched, IllegalTransition
from daemon.faults import FaultCause, FaultSource
from daemon.rig.safety import SafetyMonitor
from daemon.rig.states import ScanState, ScanStateMachine

CAUSES = st.builds(FaultCause, st.sampled_from(list(FaultSource)), st.sampled_from(["beam", "panel", "scan"]),
                   st.sampled_from(["e-stop pressed", "EMCY 0x5441", "stalled"]))


class LatchMachine(RuleBasedStateMachine):
    """The real monitor and machine against a model: latched or not, and the causes in order."""

    def __init__(self) -> None:
        super().__init__()
        self.loop = asyncio.new_event_loop()
        self.machine = ScanStateMachine()
        self.safety = SafetyMonitor(self.machine)
        self.handler_fails = False
        self.safety.add_handler("quick stop", self._handler)
        self.latched = False
        self.causes: list[FaultCause] = []

    async def _handler(self) -> None:
        if self.handler_fails:
            raise RuntimeError("drive did not answer")

    def teardown(self) -> None:
        self.loop.close()

    @rule(fails=st.booleans())
    def shutdown_handler_fails(self, fails: bool) -> None:
        self.handler_fails = fails

    @rule(cause=CAUSES)
    def trip(self, cause: FaultCause) -> None:
        first = not self.latched
        self.loop.run_until_complete(self.safety.trip(cause))
        self.latched = True
        self.causes.append(cause)
        if first and self.handler_fails:
            self.causes.append(FaultCause(FaultSource.SHUTDOWN, "quick stop",
                                          "shutdown handler failed: RuntimeError: drive did not answer"))

    @rule(again=st.one_of(st.none(), CAUSES))
    def reset(self, again: FaultCause | None) -> None:
        """The operator's reset; ``again``: a trip while it recovers (the e-stop pressed again)."""

        async def recover() -> None:
            if again is not None:
                await self.safety.trip(again)

        if again is None:
            self.loop.run_until_complete(self.safety.reset("operator", recover))
            self.latched, self.causes = False, []
            return
        first = not self.latched
        with pytest.raises(FaultLatched):
            self.loop.run_until_complete(self.safety.reset("operator", recover))
        self.latched = True
        self.causes.append(again)
        if first and self.handler_fails:
            self.causes.append(FaultCause(FaultSource.SHUTDOWN, "quick stop",
                                          "shutdown handler failed: RuntimeError: drive did not answer"))

    @rule(to=st.sampled_from([s for s in ScanState if s is not ScanState.FAULT]))
    def job_step(self, to: ScanState) -> None:
        """A job asks for a state: refused while latched (nothing but the reset leaves FAULT)."""
        if self.machine.allowed(to):
            assert not self.latched
            self.machine.transition(to, "job step")
        else:
            with pytest.raises(IllegalTransition):
                self.machine.transition(to, "job step")

    @precondition(lambda self: self.machine.state is not ScanState.IDLE)
    @rule()
    def job_ends(self) -> None:
        """A job ends as RigJob does: STORING then IDLE, unless a fault is latched (FAULT stays)."""
        if self.safety.latched:
            return
        for to in (ScanState.ABORTING, ScanState.STORING, ScanState.IDLE):
            if self.machine.allowed(to):
                self.machine.transition(to, "job end")
        assert self.machine.state is ScanState.IDLE

    @invariant()
    def one_story(self) -> None:
        assert self.safety.latched is self.machine.fault_latched is self.latched
        assert (self.machine.state is ScanState.FAULT) is bool(self.machine.fault_causes) is self.latched
        assert self.safety.causes == self.machine.fault_causes == self.causes


TestFaultLatch = LatchMachine.TestCase
TestFaultLatch.settings = settings(max_examples=150, stateful_step_count=30, deadline=None)


def test_a_trip_while_the_reset_recovers_stays_latched() -> None:
    """The e-stop pressed again while the drive is re-enabled: the reset refuses, FAULT stays
    with the new cause beside the old one."""
    machine = ScanStateMachine()
    safety = SafetyMonitor(machine)
    pressed = FaultCause(FaultSource.ESTOP, "panel", "e-stop pressed")

    async def main() -> None:
        await safety.trip(pressed)

        async def recover() -> None:
            await safety.trip(pressed)

        with pytest.raises(FaultLatched, match="e-stop pressed; panel: e-stop pressed"):
            await safety.reset("operator", recover)

    asyncio.run(main())
    assert machine.state is ScanState.FAULT and safety.causes == [pressed, pressed]
