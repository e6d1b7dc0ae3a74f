"""The scan state machine: states, the table of allowed transitions, and status events.

The table is data, so a reviewer can read the whole life of a scan in one place and a test can
walk every edge. Leaving FAULT is only possible through :meth:`ScanStateMachine.reset`
(Klipper's latched shutdown): a scan, a retry or a restart can never clear a fault by itself.
The machine is the rig's one fault latch: FAULT and its causes are held here, and the safety
monitor (daemon/rig/safety.py) latches and reads them through it, keeping no copy of its own.
Every transition is logged with its cause and published to the subscribers (the control API
streams them to clients).
"""

from __future__ import annotations

import asyncio
import enum
from collections import deque
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from typing import Any

import structlog

from daemon.errors import IllegalTransition
from daemon.faults import Cause, FaultCause
from daemon.utc import utc_stamp

log = structlog.get_logger("daemon.rig.states")


class ScanState(enum.Enum):
    IDLE = "IDLE"
    PREPARING = "PREPARING"
    DEPTH_SWEEP = "DEPTH_SWEEP"
    RECONSTRUCTING = "RECONSTRUCTING"
    PLANNING = "PLANNING"
    CAPTURING = "CAPTURING"
    RETAKING = "RETAKING"
    CALIBRATING = "CALIBRATING"
    STORING = "STORING"
    ABORTING = "ABORTING"
    FAULT = "FAULT"


class ScanOutcome(enum.Enum):
    """How a job ended, a scan or a calibration rotation (recorded in its folder).

    COMPLETED: every step ran and every planned image is in the folder. PARTIAL: every step ran
    (the rotation and its retakes finished) but planned images are missing (a scan's report
    counts them per phone and reason). ABORTED: stopped by the operator, the daemon's stop or
    an error. FAULTED: stopped by the safety latch.
    """

    COMPLETED = "COMPLETED"
    PARTIAL = "PARTIAL"
    ABORTED = "ABORTED"
    FAULTED = "FAULTED"


S = ScanState

SCAN_STEPS = (S.PREPARING, S.DEPTH_SWEEP, S.RECONSTRUCTING, S.PLANNING, S.CAPTURING, S.RETAKING)
"""A scan's states in order, each run by its step (daemon/jobs/scan_steps.py); a step that has
nothing for the next state to do (no missed capture to retake) skips it."""

_ACTIVE = (*SCAN_STEPS, S.CALIBRATING)

TRANSITIONS: dict[ScanState, frozenset[ScanState]] = {
    S.IDLE: frozenset({S.PREPARING, S.CALIBRATING, S.FAULT}),
    S.PREPARING: frozenset({S.DEPTH_SWEEP, S.ABORTING, S.FAULT}),
    S.DEPTH_SWEEP: frozenset({S.RECONSTRUCTING, S.ABORTING, S.FAULT}),
    S.RECONSTRUCTING: frozenset({S.PLANNING, S.ABORTING, S.FAULT}),
    S.PLANNING: frozenset({S.CAPTURING, S.ABORTING, S.FAULT}),
    S.CAPTURING: frozenset({S.RETAKING, S.STORING, S.ABORTING, S.FAULT}),
    S.RETAKING: frozenset({S.STORING, S.ABORTING, S.FAULT}),
    S.CALIBRATING: frozenset({S.STORING, S.ABORTING, S.FAULT}),  # the stop-and-go calibration rotation
    S.STORING: frozenset({S.IDLE, S.FAULT}),
    S.ABORTING: frozenset({S.STORING, S.IDLE, S.FAULT}),
    S.FAULT: frozenset({S.IDLE}),
}
"""Allowed transitions. FAULT -> IDLE exists only for :meth:`ScanStateMachine.reset`."""

ACTIVE_STATES = frozenset(_ACTIVE)
"""States in which the beam may move under the scan's control."""

SCAN_STATES = frozenset({*_ACTIVE, S.STORING, S.ABORTING})
"""States only a running scan may be in: every one is left by the scan itself."""


def state_groups() -> dict[str, list[str]]:
    """The status answer's state lists, in the table's order: ``active`` (the beam may move, an
    abort is taken) and ``job`` (a scan or calibration rotation runs: START is refused)."""
    return {"active": [s.value for s in ScanState if s in ACTIVE_STATES],
            "job": [s.value for s in ScanState if s in SCAN_STATES]}


@dataclass(frozen=True)
class StatusEvent:
    """One status event: a state transition or a progress report.

    Attributes:
        kind: "transition" or "progress".
        state: the state after the event.
        previous: the state before a transition (same as ``state`` for progress).
        cause: why: in words, or a typed :class:`Cause` (every FAULT, every abort).
        time_s: event-loop clock, s (durations between events; virtual in simulated scans).
        scan_id: the scan the event belongs to, or None outside a scan.
        data: extra key-value facts (counts, angles); JSON-serialisable.
        utc: calendar time of the event, ISO 8601 UTC (what a person reads as a clock time).
        seq: the machine's running event number (a client joining the stream's history to
            the live events drops the ones it already has).
    """

    kind: str
    state: ScanState
    previous: ScanState
    cause: str | Cause
    time_s: float
    scan_id: str | None = None
    data: dict[str, Any] = field(default_factory=dict)
    utc: str = ""
    seq: int = 0

    def as_dict(self) -> dict[str, Any]:
        """JSON-able; ``cause`` is the text, ``source`` and ``device`` are set for typed causes."""
        typed = self.cause if isinstance(self.cause, Cause) else None
        return {
            "kind": self.kind,
            "state": self.state.value,
            "previous": self.previous.value,
            "cause": str(self.cause),
            "source": None if typed is None else typed.source.value,
            "device": None if typed is None else typed.device,
            "time_s": self.time_s,
            "scan_id": self.scan_id,
            "data": dict(self.data),
            "utc": self.utc,
            "seq": self.seq,
        }


class ScanStateMachine:
    """Holds the rig's scan state; refuses transitions outside :data:`TRANSITIONS`.

    Subscribers each get their own bounded queue; a slow subscriber loses its oldest events
    rather than stalling the scan.
    """

    QUEUE_SIZE = 256
    RECENT_SIZE = 200
    """Events kept in :attr:`recent` (a console opened later shows them)."""
    COUNTER_CAUSES = frozenset({"captured", "verified"})
    """Per-image progress counts: the console's bars carry them, :attr:`recent` keeps none."""

    def __init__(self, *, name: str = "rig") -> None:
        self.name = name
        self.state = ScanState.IDLE
        self.scan_id: str | None = None
        self._fault_causes: list[FaultCause] = []
        self.faults_latched = 0
        """Fault causes latched since the machine was made (a reset does not lower it)."""
        self.history: list[StatusEvent] = []
        self.recent: deque[StatusEvent] = deque(maxlen=self.RECENT_SIZE)
        """The latest transitions and progress events other than the per-image counts."""
        self.entered_s = 0.0
        """Event-loop time of the last transition (when the current state began)."""
        self.started_s = 0.0
        """Event-loop time the machine last left IDLE (when the current job began)."""
        self.counts: dict[str, int] = {}
        """The latest per-image count of each of :data:`COUNTER_CAUSES` since the machine last
        left IDLE (the running or last job's images captured and verified so far)."""
        self._seq = 0
        self._subscribers: set[asyncio.Queue[StatusEvent]] = set()
        self._changed = asyncio.Event()

    @property
    def fault_latched(self) -> bool:
        return self.state is ScanState.FAULT

    @property
    def fault_causes(self) -> list[FaultCause]:
        """The latched fault's causes in the order they came (a copy; empty outside FAULT)."""
        return list(self._fault_causes)

    def allowed(self, to: ScanState) -> bool:
        return to in TRANSITIONS[self.state] and not (
            self.state is ScanState.FAULT and to is ScanState.IDLE
        )

    def transition(self, to: ScanState, cause: str | Cause, **data: Any) -> StatusEvent:
        """Move to ``to``; raises :class:`IllegalTransition` if the table forbids it.

        A request for the current state is refused too, except FAULT -> FAULT, which only
        adds the new cause to the latched ones (every fault handler reports). FAULT takes a
        :class:`FaultCause` and nothing else.
        """
        if to is ScanState.FAULT:
            if not isinstance(cause, FaultCause):
                raise TypeError(f"FAULT needs a FaultCause, got {type(cause).__name__}: {cause!r}")
            self._fault_causes.append(cause)
            self.faults_latched += 1
            if self.state is ScanState.FAULT:
                return self._emit("progress", ScanState.FAULT, cause, data)
        if not self.allowed(to):
            raise IllegalTransition(self.state.value, to.value, cause)
        return self._emit("transition", to, cause, data)

    def reset(self, cause: str) -> StatusEvent:
        """Clear a latched FAULT (the operator's explicit reset); only valid in FAULT."""
        if self.state is not ScanState.FAULT:
            raise IllegalTransition(self.state.value, ScanState.IDLE.value, f"reset: {cause}")
        self._fault_causes = []
        return self._emit("transition", ScanState.IDLE, f"reset: {cause}", {})

    def progress(self, cause: str, **data: Any) -> StatusEvent:
        """Publish a progress event without changing state."""
        return self._emit("progress", self.state, cause, data)

    def subscribe(self) -> AsyncIterator[StatusEvent]:
        """Status events from now on, until the subscriber stops iterating."""
        queue: asyncio.Queue[StatusEvent] = asyncio.Queue(self.QUEUE_SIZE)
        self._subscribers.add(queue)
        return self._drain(queue)

    async def _drain(self, queue: asyncio.Queue[StatusEvent]) -> AsyncIterator[StatusEvent]:
        try:
            while True:
                yield await queue.get()
        finally:
            self._subscribers.discard(queue)

    async def wait_for(self, *states: ScanState) -> ScanState:
        """Wait until the machine is in one of ``states``."""
        while self.state not in states:
            self._changed.clear()
            await self._changed.wait()
        return self.state

    def _emit(self, kind: str, to: ScanState, cause: str | Cause, data: dict[str, Any]) -> StatusEvent:
        try:
            now = asyncio.get_running_loop().time()
        except RuntimeError:
            now = 0.0
        self._seq += 1
        name = str(cause)
        counter = name in self.COUNTER_CAUSES
        event = StatusEvent(kind, to, self.state, cause, now, self.scan_id, data, utc=utc_stamp(), seq=self._seq)
        if kind == "transition":
            log.info("scan_transition", rig=self.name, previous=self.state.value,
                     state=to.value, cause=name, scan_id=self.scan_id, **data)
        else:
            log.debug("scan_progress", rig=self.name, state=to.value, cause=name, **data)
        self.state = to
        if kind == "transition":
            self.entered_s = now
            if event.previous is ScanState.IDLE:
                self.started_s = now
                self.counts = {}
        elif counter and isinstance(data.get(name), int):
            self.counts[name] = data[name]
        self.history.append(event)
        if kind == "transition" or not counter:
            self.recent.append(event)
        if len(self.history) > 4 * self.QUEUE_SIZE:
            del self.history[: self.QUEUE_SIZE]
        for queue in self._subscribers:
            if queue.full():
                queue.get_nowait()
            queue.put_nowait(event)
        self._changed.set()
        return event
