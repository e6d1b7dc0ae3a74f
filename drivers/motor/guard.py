"""The drive guard: the host's heartbeat, the watch on the drive's heartbeat and the quick stop,
kept apart from the event loop's timing.

Three stop paths, from the one that needs the least of the host to the one that needs the most:

* **The host is frozen** (SIGSTOP, a swap storm, a C call holding the interpreter lock): nothing of
  the process runs, so nothing sends the host heartbeat; the drive's heartbeat consumer (0x1016)
  times out and the drive stops itself on its abort connection option (0x6007, docs/motor.md).
  When the process runs again the guard, having itself stood still longer than ``host_stall_s``,
  trips too, so the host latches why.
* **The event loop is stuck but the process runs** (a blocking send, an fsync, a C call that releases
  the interpreter lock): the loop stops feeding the guard; after ``host_stall_s`` the guard sends
  the quick stop (the controlword by RPDO: one frame, no SDO lock, no reply) and stops the host
  heartbeat, so the drive also faults on its own consumer timeout.
* **The drive falls silent**: its heartbeat stays away ``drive_timeout_s``; the guard sends the
  quick stop and stops the host heartbeat (a drive that still listens stops either way).

Every trip is latched by :class:`GuardLogic` until :meth:`GuardLogic.rearm` (the operator's reset):
no host heartbeat, no second quick stop, and the event loop is told once.

The logic is a pure function of time (:class:`GuardLogic`), run by one of two runners:
:class:`ThreadedGuard` on a real CAN port (its own thread, ``time.monotonic``, frames sent through
the port's urgent lane and received frames stamped in the port's receive thread, so a stalled loop
neither delays the heartbeat nor makes a drive heartbeat that arrived on time look late), and
:class:`LoopGuard` on an in-process bus in virtual time (the loop's clock; nothing there can stall
the loop but the test that means to).

A pause of the whole process (a garbage collection) delays the guard, the port's threads and the
loop alike. After such a pause the guard watches ``settle_s`` before judging, so heartbeats that
arrived during the pause and are still queued in the receive thread are counted first; a silence
longer than the limit plus ``pause_allowance_s`` trips at once whatever happened.
"""

from __future__ import annotations

import abc
import asyncio
import enum
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import can
import structlog

from drivers.motor import cia402, nmt
from drivers.motor.bringup import controlword_pdo
from drivers.motor.errors import CanBusError
from drivers.motor.port import RealtimePort
from planner.rig import Motor

log = structlog.get_logger(__name__)


class GuardTripKind(enum.Enum):
    HOST_STALLED = "host_stalled"
    """The event loop did not feed the guard for longer than ``host_stall_s``."""
    DRIVE_SILENT = "drive_silent"
    """The drive's heartbeat stayed away longer than ``drive_timeout_s``."""


@dataclass(frozen=True)
class GuardTrip:
    """Why the guard stopped the beam: what went silent, for how long, against which limit (s)."""

    kind: GuardTripKind
    silent_s: float
    limit_s: float

    def __str__(self) -> str:
        what = ("the event loop did not run" if self.kind is GuardTripKind.HOST_STALLED
                else "no heartbeat from the drive")
        return f"{what} for {self.silent_s:.3f} s (limit {self.limit_s:g} s): quick stop sent"


@dataclass(frozen=True)
class GuardTiming:
    """The guard's periods and limits, s.

    heartbeat_period_s: host heartbeat period (the rig's ``motor.host_heartbeat_ms``).
    drive_timeout_s: the drive's heartbeat is lost after this silence (``motor.heartbeat_timeout_ms``).
    host_stall_s: the loop is stuck after this long without feeding the guard (``motor.host_stall_ms``).
    feed_period_s: how often the loop feeds the guard.
    tick_s: the threaded guard's cycle.
    pause_s: a guard wake-up this late means the whole process was paused.
    settle_s: after such a pause, how long the guard watches before judging.
    pause_allowance_s: a silence this much beyond its limit trips even right after a pause.
    """

    heartbeat_period_s: float
    drive_timeout_s: float
    host_stall_s: float
    feed_period_s: float = 0.05
    tick_s: float = 0.01
    pause_s: float = 0.1
    settle_s: float = 0.05
    pause_allowance_s: float = 0.3

    def __post_init__(self) -> None:
        for name in ("heartbeat_period_s", "drive_timeout_s", "host_stall_s", "feed_period_s", "tick_s",
                     "pause_s", "settle_s", "pause_allowance_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"guard timing {name} must be a positive number of seconds, got {value!r}")
        if self.host_stall_s <= self.feed_period_s:
            raise ValueError(f"guard timing host_stall_s {self.host_stall_s:g} s must exceed "
                             f"feed_period_s {self.feed_period_s:g} s")

    @classmethod
    def of(cls, motor: Motor) -> GuardTiming:
        """The rig's motor section as guard timing."""
        return cls(heartbeat_period_s=motor.host_heartbeat_ms / 1000,
                   drive_timeout_s=motor.heartbeat_timeout_ms / 1000,
                   host_stall_s=motor.host_stall_ms / 1000)


@dataclass(frozen=True)
class GuardActions:
    """What one :meth:`GuardLogic.step` asks of its runner."""

    heartbeat: bool = False
    quick_stop: bool = False
    trip: GuardTrip | None = None


class GuardLogic:
    """The guard's decisions as a pure function of the times it is given (s, one clock).

    ``feed`` (the loop runs), ``drive_heartbeat`` and ``sample`` (frames from the drive) record
    when things happened; :meth:`step` says what to send and whether the guard trips. A trip is
    latched until :meth:`rearm`.
    """

    def __init__(self, timing: GuardTiming, now: float) -> None:
        self.timing = timing
        self.last_feed = now
        self.last_drive_heartbeat = now
        self.last_sample: float | None = None
        self.trip: GuardTrip | None = None
        self._next_heartbeat = now
        self._last_step = now
        self._awake_since = now - timing.settle_s

    def feed(self, now: float) -> None:
        self.last_feed = max(self.last_feed, now)

    def drive_heartbeat(self, now: float) -> None:
        self.last_drive_heartbeat = max(self.last_drive_heartbeat, now)

    def sample(self, now: float) -> None:
        self.last_sample = now if self.last_sample is None else max(self.last_sample, now)

    def rearm(self, now: float) -> None:
        """Clear a trip (the operator's reset): heartbeats resume, every silence is measured from now."""
        self.trip = None
        self.last_feed = self.last_drive_heartbeat = self._last_step = now
        self._next_heartbeat = now

    def step(self, now: float) -> GuardActions:
        """The actions due at ``now``."""
        t = self.timing
        own_gap = now - self._last_step
        if own_gap > t.pause_s:
            self._awake_since = now  # the guard itself did not run: let queued frames arrive first
        self._last_step = max(self._last_step, now)
        settled = now - self._awake_since >= t.settle_s
        trip: GuardTrip | None = None
        if self.trip is None:
            if own_gap > t.host_stall_s:  # the whole process stood still, the guard with it
                trip = self.trip = GuardTrip(GuardTripKind.HOST_STALLED, own_gap, t.host_stall_s)
            for kind, last, limit in ((GuardTripKind.HOST_STALLED, self.last_feed, t.host_stall_s),
                                      (GuardTripKind.DRIVE_SILENT, self.last_drive_heartbeat, t.drive_timeout_s)):
                silent = now - last
                if trip is None and (silent > limit + t.pause_allowance_s or (settled and silent > limit)):
                    trip = self.trip = GuardTrip(kind, silent, limit)
        heartbeat = self.trip is None and now >= self._next_heartbeat
        if heartbeat:
            self._next_heartbeat += t.heartbeat_period_s
            if self._next_heartbeat <= now:  # fell behind (a pause): one now, then on period again
                self._next_heartbeat = now + t.heartbeat_period_s
        return GuardActions(heartbeat=heartbeat, quick_stop=trip is not None, trip=trip)

    def next_due(self, now: float) -> float:
        """The earliest time at which :meth:`step` may act, given no new observation (inf: tripped)."""
        t = self.timing
        if self.trip is not None:
            return math.inf
        due = min(self._next_heartbeat, self.last_feed + t.host_stall_s,
                  self.last_drive_heartbeat + t.drive_timeout_s)
        if now - self._awake_since < t.settle_s:
            due = min(due, self._awake_since + t.settle_s)
        return max(now, due)


def heartbeat_message(host_node_id: int) -> can.Message:
    """The host's heartbeat (NMT OPERATIONAL)."""
    return can.Message(arbitration_id=nmt.heartbeat_cob_id(host_node_id),
                       data=nmt.heartbeat_frame(nmt.NmtState.OPERATIONAL), is_extended_id=False)


def quick_stop_message(node_id: int) -> can.Message:
    """The quick stop as the controlword on the drive's RPDO1 (configured by drivers/motor/bringup.py)."""
    return controlword_pdo(node_id, cia402.QUICK_STOP)


class DriveGuard(Protocol):
    """What the drive sees of either runner."""

    logic: GuardLogic

    @property
    def alive(self) -> bool:
        """The guard still runs (its thread or task)."""

    def feed(self) -> None:
        """The event loop runs (called from the loop)."""

    def rearm(self) -> None:
        """Clear a trip (the operator's reset): the host heartbeat resumes."""

    def heartbeat_age_s(self) -> float:
        """Seconds since the drive's last heartbeat, on the guard's own clock."""

    def sample_age_s(self) -> float:
        """Seconds since the drive's last position sample (inf: none yet), on the guard's own clock."""

    async def stop(self) -> None:
        """Stop producing heartbeats and watching (the drive's own consumer watches on)."""


def _observer(node_id: int, logic: GuardLogic) -> Callable[[int, float], None]:
    heartbeat, position = nmt.heartbeat_cob_id(node_id), nmt.tpdo_cob_id(1, node_id)

    def observe(cob_id: int, now: float) -> None:
        if cob_id == heartbeat:
            logic.drive_heartbeat(now)
        elif cob_id == position:
            logic.sample(now)

    return observe


class _GuardRunner(abc.ABC):
    """What both runners share: the logic on one clock (``_now``), the frames they send, the
    observer of the drive's frames, and how a trip is reported."""

    def __init__(self, node_id: int, host_node_id: int, timing: GuardTiming,
                 on_trip: Callable[[GuardTrip], None], name: str) -> None:
        self.timing = timing
        self.logic = GuardLogic(timing, self._now())
        self.name = name
        self.send_failures = 0
        self._on_trip = on_trip
        self._heartbeat = heartbeat_message(host_node_id)
        self._quick_stop = quick_stop_message(node_id)
        self._observe = _observer(node_id, self.logic)

    @abc.abstractmethod
    def _now(self) -> float:
        """The runner's clock, s."""

    def feed(self) -> None:
        self.logic.feed(self._now())

    def rearm(self) -> None:
        self.logic.rearm(self._now())

    def heartbeat_age_s(self) -> float:
        return self._now() - self.logic.last_drive_heartbeat

    def sample_age_s(self) -> float:
        last = self.logic.last_sample
        return math.inf if last is None else self._now() - last

    def _log_trip(self, trip: GuardTrip) -> None:
        log.error("drive_guard_tripped", drive=self.name, kind=trip.kind.value,
                  silent_s=round(trip.silent_s, 3), limit_s=trip.limit_s)


class ThreadedGuard(_GuardRunner):
    """The guard on its own thread, for a real CAN port (:class:`RealtimePort`), on ``time.monotonic``.

    ``on_trip(trip)`` is called on the event loop (``loop``), once per trip.
    """

    def __init__(self, port: RealtimePort, node_id: int, host_node_id: int, timing: GuardTiming,
                 on_trip: Callable[[GuardTrip], None], *, loop: asyncio.AbstractEventLoop,
                 name: str = "beam") -> None:
        super().__init__(node_id, host_node_id, timing, on_trip, name)
        self.port = port
        self._loop = loop
        self._stopping = threading.Event()
        self._untap = port.tap(lambda msg, at: self._observe(msg.arbitration_id, at))
        self._thread = threading.Thread(target=self._run, name=f"{name}-guard", daemon=True)
        self._thread.start()

    def _now(self) -> float:
        return time.monotonic()

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    async def stop(self) -> None:
        """Stop the thread (it exits within one tick; the loop does not wait for it)."""
        self._stopping.set()
        self._untap()

    def _run(self) -> None:
        while not self._stopping.wait(self.timing.tick_s):
            actions = self.logic.step(time.monotonic())
            if actions.quick_stop:
                self._send(self._quick_stop)
            if actions.heartbeat:
                self._send(self._heartbeat)
            if actions.trip is not None:
                self._log_trip(actions.trip)
                try:
                    self._loop.call_soon_threadsafe(self._on_trip, actions.trip)
                except RuntimeError:  # the loop is closed: the process is ending, the drive stops itself
                    return

    def _send(self, msg: can.Message) -> None:
        try:
            self.port.send_urgent(msg)
        except CanBusError:  # the port is closed or broken: its reader latches the link fault
            self.send_failures += 1


class LoopGuard(_GuardRunner):
    """The guard as a task of the event loop, for an in-process bus in virtual time (the loop's clock)."""

    def __init__(self, send: Callable[[can.Message], Any], node_id: int, host_node_id: int,
                 timing: GuardTiming, on_trip: Callable[[GuardTrip], None], *, name: str = "beam") -> None:
        self._loop = asyncio.get_running_loop()
        super().__init__(node_id, host_node_id, timing, on_trip, name)
        self._send = send
        self._wake = asyncio.Event()
        self._task = asyncio.create_task(self._run(), name=f"{name}-guard")

    def _now(self) -> float:
        return self._loop.time()

    def observe(self, cob_id: int, now: float) -> None:
        """A frame from the drive, handled on the loop at loop time ``now`` (an observation only
        moves a deadline later, so the guard's task need not wake)."""
        self._observe(cob_id, now)

    def rearm(self) -> None:
        super().rearm()
        self._wake.set()

    @property
    def alive(self) -> bool:
        return not self._task.done()

    async def stop(self) -> None:
        self._task.cancel()
        await asyncio.gather(self._task, return_exceptions=True)

    async def _send_frame(self, msg: can.Message) -> None:
        try:
            await self._send(msg)
        except CanBusError:  # the port is closed or broken: the drive's reader latches the link fault
            self.send_failures += 1

    async def _run(self) -> None:
        while True:
            actions = self.logic.step(self._loop.time())
            if actions.quick_stop:
                await self._send_frame(self._quick_stop)
            if actions.heartbeat:
                await self._send_frame(self._heartbeat)
            if actions.trip is not None:
                self._log_trip(actions.trip)
                self._on_trip(actions.trip)
            due = self.logic.next_due(self._loop.time())
            self._wake.clear()
            if math.isfinite(due):
                try:
                    async with asyncio.timeout_at(due + 1e-6):
                        await self._wake.wait()
                except TimeoutError:
                    pass
            else:
                await self._wake.wait()
