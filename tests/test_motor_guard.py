"""The drive guard: its decisions as properties of time, and its thread against a stalled loop."""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.motor import nmt
from drivers.motor.guard import GuardLogic, GuardTiming, GuardTrip, GuardTripKind, ThreadedGuard, quick_stop_message
from drivers.motor.port import RealtimePort

TIMING = GuardTiming(heartbeat_period_s=0.05, drive_timeout_s=0.35, host_stall_s=0.5)
DRIVE_PERIOD_S = 0.1


def run(timing: GuardTiming, until: float, *, tick: Callable[[float], float] = lambda t: 0.01,
        paused: Callable[[float], bool] = lambda t: False, loop_runs: Callable[[float], bool] = lambda t: True,
        drive_talks: Callable[[float], bool] = lambda t: True,
        delivery_s: float = 0.005) -> tuple[list[float], list[tuple[float, GuardTrip]], list[float]]:
    """Step a guard from 0 to ``until`` s: the guard wakes every ``tick(t)``; while ``paused(t)`` the
    whole process stands (no step, no feed, no frame handled); the loop feeds every feed period
    while ``loop_runs(t)``; the drive sends a heartbeat every 100 ms while ``drive_talks(t)``, each
    handled ``delivery_s`` later or at the end of a pause. Returns heartbeat times, trips, quick stops."""
    logic = GuardLogic(timing, 0.0)
    heartbeats: list[float] = []
    trips: list[tuple[float, GuardTrip]] = []
    stops: list[float] = []
    pending: list[float] = []
    next_drive, next_feed, t = DRIVE_PERIOD_S, timing.feed_period_s, 0.0
    while t < until:
        if not paused(t):
            while next_drive <= t:
                if drive_talks(next_drive):
                    pending.append(next_drive + delivery_s)
                next_drive += DRIVE_PERIOD_S
            for at in [p for p in pending if p <= t]:
                logic.drive_heartbeat(t if paused(at) else at)
                pending.remove(at)
            while next_feed <= t:
                if loop_runs(next_feed):
                    logic.feed(t if paused(next_feed) else next_feed)
                next_feed += timing.feed_period_s
            actions = logic.step(t)
            if actions.heartbeat:
                heartbeats.append(t)
            if actions.quick_stop:
                stops.append(t)
            if actions.trip is not None:
                trips.append((t, actions.trip))
        t += tick(t)
    return heartbeats, trips, stops


def gaps(times: list[float]) -> list[float]:
    return [b - a for a, b in zip(times, times[1:])]


@given(st.lists(st.floats(0.001, 0.03), min_size=1, max_size=20))
def test_a_healthy_host_and_drive_never_trip_and_heartbeats_keep_their_period(jitter: list[float]) -> None:
    heartbeats, trips, stops = run(TIMING, 5.0, tick=lambda t: jitter[int(t * 100) % len(jitter)])
    assert trips == [] and stops == []
    assert max(gaps(heartbeats)) <= TIMING.heartbeat_period_s + max(jitter) + 1e-9


@given(start=st.floats(0.5, 3.0), pause=st.floats(0.0, 0.25))
def test_a_whole_process_pause_of_up_to_250_ms_trips_nothing(start: float, pause: float) -> None:
    """A garbage collection holds the guard, the receive thread and the loop alike."""
    heartbeats, trips, _ = run(TIMING, 5.0, paused=lambda t: start <= t < start + pause)
    assert trips == []
    # The drive's consumer (350 ms) never misses: the longest silence is one period plus the pause.
    assert max(gaps(heartbeats)) <= TIMING.heartbeat_period_s + pause + 0.021
    assert max(gaps(heartbeats)) < TIMING.drive_timeout_s


@given(start=st.floats(0.5, 3.0), tick=st.floats(0.001, 0.02))
def test_a_stuck_loop_trips_host_stalled_within_its_limit_and_silences_the_heartbeat(start: float, tick: float) -> None:
    heartbeats, trips, stops = run(TIMING, 5.0, tick=lambda t: tick, loop_runs=lambda t: t < start)
    assert len(trips) == 1 and len(stops) == 1
    at, trip = trips[0]
    assert trip.kind is GuardTripKind.HOST_STALLED
    assert TIMING.host_stall_s < trip.silent_s <= TIMING.host_stall_s + tick + 1e-9
    assert start - TIMING.feed_period_s - 1e-9 <= at - trip.silent_s <= start + 1e-9  # the last feed
    assert stops == [at]
    assert all(h < at for h in heartbeats)  # the drive's consumer then stops it too


@given(start=st.floats(0.5, 3.0), tick=st.floats(0.001, 0.02))
def test_a_silent_drive_trips_within_the_timeout(start: float, tick: float) -> None:
    _, trips, stops = run(TIMING, 5.0, tick=lambda t: tick, drive_talks=lambda t: t < start)
    assert [trip.kind for _, trip in trips] == [GuardTripKind.DRIVE_SILENT]
    at, trip = trips[0]
    assert TIMING.drive_timeout_s < trip.silent_s <= TIMING.drive_timeout_s + tick + 1e-9
    assert start - DRIVE_PERIOD_S <= at - trip.silent_s <= start + 0.006  # the last heartbeat handled
    assert len(stops) == 1


@given(start=st.floats(0.5, 3.0), pause=st.floats(1.0, 2.0))
def test_a_frozen_process_trips_host_stalled_the_moment_it_wakes(start: float, pause: float) -> None:
    _, trips, _ = run(TIMING, 5.0, paused=lambda t: start <= t < start + pause)
    assert len(trips) == 1
    at, trip = trips[0]
    assert trip.kind is GuardTripKind.HOST_STALLED and start + pause <= at <= start + pause + 0.011


def test_a_trip_holds_until_rearmed_then_heartbeats_resume() -> None:
    logic = GuardLogic(TIMING, 0.0)
    assert logic.step(0.0).heartbeat
    actions = logic.step(0.6)  # neither fed nor heard from
    assert actions.quick_stop and actions.trip is not None and not actions.heartbeat
    for t in (0.7, 0.8, 5.0):
        later = logic.step(t)
        assert not (later.heartbeat or later.quick_stop or later.trip)
    logic.rearm(5.0)
    assert logic.step(5.0).heartbeat and logic.trip is None


@given(st.lists(st.floats(0.0, 3.0), max_size=6), st.floats(0.5, 4.0))
def test_stepping_only_when_due_acts_as_stepping_every_millisecond(feeds: list[float], silent_from: float) -> None:
    """The loop guard sleeps until :meth:`GuardLogic.next_due`; it must miss nothing a tight loop sees."""
    def simulate(event_driven: bool) -> list[tuple[float, bool, bool]]:
        logic = GuardLogic(TIMING, 0.0)
        out, t = [], 0.0
        events = sorted([(f, "feed") for f in feeds] + [(k * 0.1, "hb") for k in range(1, 40) if k * 0.1 < silent_from])
        while t < 4.0:
            while events and events[0][0] <= t:
                at, kind = events.pop(0)
                (logic.feed if kind == "feed" else logic.drive_heartbeat)(at)
            a = logic.step(t)
            if a.heartbeat or a.quick_stop:
                out.append((round(t, 6), a.heartbeat, a.quick_stop))
            nxt = t + 0.001
            if event_driven:
                nxt = min(logic.next_due(t + 1e-9), events[0][0] if events else 4.0, 4.0)
                nxt = max(nxt, t + 1e-9)
            t = nxt
        return out

    tight, driven = simulate(False), simulate(True)
    stops = ([t for t, _, q in tight if q], [t for t, _, q in driven if q])
    assert len(stops[0]) == len(stops[1]) <= 1
    if stops[0]:
        assert stops[1][0] <= stops[0][0] + 1e-9  # it trips no later than a millisecond loop
    beats = [t for t, h, _ in driven if h]
    assert beats[0] == 0.0 and max(gaps(beats), default=0.0) <= TIMING.heartbeat_period_s + 1e-9
    end = stops[1][0] if stops[1] else 4.0
    assert beats[-1] >= end - TIMING.heartbeat_period_s - 1e-9  # heartbeats until the trip


def test_timing_refuses_a_stall_limit_below_the_feed_period() -> None:
    with pytest.raises(ValueError, match="host_stall_s"):
        GuardTiming(heartbeat_period_s=0.05, drive_timeout_s=0.35, host_stall_s=0.04)
    with pytest.raises(ValueError, match="drive_timeout_s"):
        GuardTiming(heartbeat_period_s=0.05, drive_timeout_s=float("nan"), host_stall_s=0.5)


class FakeRealtimePort:
    """A port whose urgent frames are recorded with the monotonic time they were queued."""

    def __init__(self) -> None:
        self.sent: list[tuple[float, can.Message]] = []
        self.taps: list[Callable[[can.Message, float], None]] = []
        self.lock = threading.Lock()

    def send_urgent(self, msg: can.Message) -> None:
        with self.lock:
            self.sent.append((time.monotonic(), msg))

    def tap(self, callback: Callable[[can.Message, float], None]) -> Callable[[], None]:
        self.taps.append(callback)
        return lambda: self.taps.remove(callback)

    def stopped_threads(self) -> list[str]:
        return []

    def receive(self, msg: can.Message) -> None:
        for callback in list(self.taps):
            callback(msg, time.monotonic())

    def frames(self, cob_id: int) -> list[float]:
        with self.lock:
            return [at for at, m in self.sent if m.arbitration_id == cob_id]


@pytest.mark.realtime
async def test_the_guard_thread_quick_stops_a_loop_that_blocks_and_tells_the_loop_once() -> None:
    """The loop blocks in a call that releases the interpreter lock (as a socket send would): the
    guard's thread goes on, sends the quick stop and stops the host heartbeat; the loop hears once."""
    port = FakeRealtimePort()
    assert isinstance(port, RealtimePort)
    # The rig's own stall limit (motor.host_stall_ms 500): a loaded 2-core test machine has held a
    # worker's loop 200 ms between two feeds, which a tighter limit would rightly call a stall.
    timing = GuardTiming(heartbeat_period_s=0.02, drive_timeout_s=30.0, host_stall_s=0.5)
    trips: list[GuardTrip] = []
    guard = ThreadedGuard(port, 5, 0x7F, timing, trips.append, loop=asyncio.get_running_loop())
    beats = nmt.heartbeat_cob_id(0x7F)
    stop_id = quick_stop_message(5).arbitration_id
    try:
        fed = 0
        fed_until = time.monotonic() + 10.0  # a deadline, not a duration: a descheduled thread beats late
        while (fed < 10 or not port.frames(beats)) and time.monotonic() < fed_until:
            guard.feed()
            fed += 1
            await asyncio.sleep(0.02)
        assert trips == [] and port.frames(beats)
        # The loop is stuck from here (time.sleep holds it); the guard's thread is not. It stays
        # stuck until the quick stop is sent, then long enough past it for a repeat to show.
        stuck_until = time.monotonic() + 10.0
        while not port.frames(stop_id) and time.monotonic() < stuck_until:
            time.sleep(0.01)
        time.sleep(timing.host_stall_s)
        stops = port.frames(stop_id)
        assert len(stops) == 1
        assert all(at < stops[0] for at in port.frames(beats))
        heard_until = time.monotonic() + 10.0
        while not trips and time.monotonic() < heard_until:  # the loop runs again: the trip reaches it
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.05)
        assert [t.kind for t in trips] == [GuardTripKind.HOST_STALLED] and trips[0].silent_s > 0.5
        assert port.sent[-1][1].arbitration_id == stop_id
        assert quick_stop_message(5).data == bytes([0x02, 0x00])
    finally:
        await guard.stop()


@pytest.mark.realtime
async def test_drive_heartbeats_stamped_in_the_receive_thread_outlast_a_slow_loop() -> None:
    """The drive's heartbeats are counted when the port's thread receives them, so a loop that falls
    behind handling them does not make a drive on time look silent."""
    port = FakeRealtimePort()
    timing = GuardTiming(heartbeat_period_s=0.02, drive_timeout_s=0.35, host_stall_s=5.0)  # the rig's 350 ms
    trips: list[GuardTrip] = []
    guard = ThreadedGuard(port, 5, 0x7F, timing, trips.append, loop=asyncio.get_running_loop())
    stop = threading.Event()

    def drive() -> None:
        while not stop.wait(0.02):
            port.receive(can.Message(arbitration_id=nmt.heartbeat_cob_id(5), data=b"\x05"))

    talker = threading.Thread(target=drive, daemon=True)
    talker.start()
    try:
        guard.feed()
        time.sleep(1.0)  # the loop handles nothing for 1 s; the guard still hears the drive
        guard.feed()
        await asyncio.sleep(0.05)
        assert trips == [] and guard.heartbeat_age_s() < 0.35
        stop.set()
        talker.join()
        fed_until = time.monotonic() + 5.0
        while not trips and time.monotonic() < fed_until:  # the loop on time, the drive silent
            guard.feed()
            await asyncio.sleep(0.02)
        assert [t.kind for t in trips] == [GuardTripKind.DRIVE_SILENT]
    finally:
        stop.set()
        await guard.stop()
