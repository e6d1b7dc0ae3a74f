"""Latched shutdown: e-stop, drive fault and lost heartbeat stop the beam and latch FAULT.

Modelled on Klipper's shutdown: the first trip runs every registered handler (quick stop of the
drive, the panel's fault light...), each under its own timeout and even if another one fails;
the failures become further fault causes instead of log lines. Only :meth:`SafetyMonitor.reset`,
the operator's explicit reset, clears the latch. The latch itself is the state machine's FAULT
and its causes (daemon/rig/states.py): the monitor latches through it and reads it, so the two can
never tell different stories.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from typing import Any

import structlog

from daemon.errors import FaultLatched
from daemon.faults import FaultCause, FaultSource
from daemon.rig.hardware import RigHardware
from daemon.rig.states import ScanState, ScanStateMachine
from daemon.tasks import stop_tasks
from drivers.motor.errors import HostStalled

log = structlog.get_logger("daemon.rig.safety")

Handler = Callable[[], Awaitable[Any]]


class SafetyMonitor:
    """Watches the drive and runs the shutdown handlers on a trip; the latch is ``machine``'s.

    Args:
        machine: the scan state machine; a trip moves it to FAULT from any state.

    :meth:`start` watches the rig's drive every ``POLL_S`` (its ``fault``, its samples' age), the
    one the device set holds at each look: a drive renewed on a fresh link is watched at once.
    """

    POLL_S = 0.02
    HANDLER_TIMEOUT_S = 2.0
    STALE_SAMPLE_S = 0.5
    """No encoder sample for this long while the stream is expected means the drive is gone."""

    def __init__(self, machine: ScanStateMachine) -> None:
        self.machine = machine
        self.expect_samples = False
        self._handlers: list[tuple[str, Handler]] = []
        self._listeners: list[Callable[[FaultCause], None]] = []
        self._watch: asyncio.Task[None] | None = None
        self._handled = asyncio.Event()
        self._handled.set()

    def add_handler(self, name: str, handler: Handler) -> None:
        """A shutdown action, run on every trip in registration order (concurrently)."""
        self._handlers.append((name, handler))

    def on_trip(self, listener: Callable[[FaultCause], None]) -> None:
        """Called synchronously with the cause as soon as a trip happens (cancel the scan)."""
        self._listeners.append(listener)

    @property
    def watching(self) -> bool:
        """The drive watch runs (False before the drive first came up, or once it ended)."""
        return self._watch is not None and not self._watch.done()

    @property
    def latched(self) -> bool:
        """A fault is latched: the machine is in FAULT."""
        return self.machine.fault_latched

    @property
    def causes(self) -> list[FaultCause]:
        """The latched fault's causes (the machine's; empty when none is latched)."""
        return self.machine.fault_causes

    def check(self) -> None:
        """Raise :class:`FaultLatched` if a fault is latched (before moving anything)."""
        if self.latched:
            raise FaultLatched(self.causes)

    async def trip(self, cause: FaultCause) -> None:
        """Latch a fault and run every shutdown handler; a second trip only adds its cause."""
        first = not self.latched
        if first:
            self._handled.clear()
        self.machine.transition(ScanState.FAULT, cause)
        log.error("safety_trip", source=cause.source.value, device=cause.device,
                  detail=cause.detail, first=first, loop_s=asyncio.get_running_loop().time())
        if not first:
            return
        for listener in self._listeners:
            listener(cause)
        results = await asyncio.gather(
            *(self._run(name, handler) for name, handler in self._handlers), return_exceptions=True
        )
        for (name, _), result in zip(self._handlers, results):
            if isinstance(result, BaseException):
                failure = FaultCause.of_error(FaultSource.SHUTDOWN, name, result, "shutdown handler failed")
                self.machine.transition(ScanState.FAULT, failure)
        self._handled.set()

    async def settled(self) -> None:
        """Wait until the shutdown handlers of the current trip have all finished."""
        await self._handled.wait()

    async def _run(self, name: str, handler: Handler) -> None:
        async with asyncio.timeout(self.HANDLER_TIMEOUT_S):
            await handler()

    async def reset(self, cause: str, recover: Handler) -> None:
        """Clear the latch after ``recover`` (fault reset, re-enable) succeeded.

        A trip while ``recover`` runs (the e-stop pressed again, the drive failing to enable)
        is not cleared with the faults the operator saw: the reset raises :class:`FaultLatched`
        with every cause, and the latch stays."""
        seen = self.machine.faults_latched
        await recover()
        if self.machine.faults_latched != seen:
            raise FaultLatched(self.causes)
        if self.latched:
            self.machine.reset(cause)

    # ------------------------------------------------------------------ drive watch

    def start(self, devices: RigHardware) -> None:
        """Watch ``devices``' drive (idempotent)."""
        if self._watch is None:
            self._watch = asyncio.create_task(self._watch_drive(devices), name="safety-watch")

    async def stop(self) -> None:
        """Stop watching the drive (bounded; a cancel of the caller is not swallowed)."""
        watch, self._watch = self._watch, None
        if watch is not None:
            await stop_tasks([watch], self.HANDLER_TIMEOUT_S)

    async def _watch_drive(self, devices: RigHardware) -> None:
        reported: BaseException | None = None
        while True:
            await asyncio.sleep(self.POLL_S)
            drive = devices.drive
            device = drive.name
            fault = drive.fault
            if fault is not None and fault is not reported:
                # Also while latched: a drive fault after the first trip is one more cause to read.
                reported = fault
                source = FaultSource.HOST_STALLED if isinstance(fault, HostStalled) else FaultSource.DRIVE_FAULT
                await self.trip(FaultCause.of_error(source, device, fault))
                continue
            if self.latched:
                continue
            latest = drive.latest
            if self.expect_samples and latest is not None:
                # Stamped where the frame was received (the drive guard's thread on a real bus),
                # so a loop that falls behind does not make a live encoder look stalled.
                age = drive.sample_age_s()
                if age > self.STALE_SAMPLE_S:
                    await self.trip(FaultCause(
                        FaultSource.ENCODER_STALLED, device,
                        f"encoder stream stalled: last sample {age:.3f} s ago at "
                        f"{latest.angle_deg:.3f} deg (limit {self.STALE_SAMPLE_S:g} s)",
                    ))
