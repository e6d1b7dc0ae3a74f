"""A stop is never lost: a cancel that lands just after a wait's result still cancels (the waits
of the beam and the capture), and scans stopped at random points in virtual time always end,
in bounded time, with the folder closed and every captured image verified
(tests/cancellation.py, the harness ``./dev bench safety`` runs 1,000 times)."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from daemon.jobs.capture import CaptureRunner, TriggerLatency
from daemon.rig.beam import BeamTracker
from daemon.rig.clocksync import ClockSync
from drivers.motor.samples import BeamSample
from planner.schedule import compile_plan, phone_timings, rig_profile
from sim.clock import run_virtual
from tests.cancellation import make_trials, run_trials, summary
from tests.daemon_mocks import MockDrive, MockPhone
from tests.daemon_rigs import RIG

TURNS = range(6)
"""Loop turns between a wait's result and the cancel: the result's callbacks take a few."""


class ManualDrive:
    """A drive whose encoder samples the test sends one by one."""

    name = "beam"

    def __init__(self) -> None:
        self.latest: BeamSample | None = None
        self._queue: asyncio.Queue[BeamSample] = asyncio.Queue()

    def send(self, angle_deg: float, speed_deg_s: float = 0.0) -> None:
        self._queue.put_nowait(BeamSample(asyncio.get_running_loop().time(), angle_deg, speed_deg_s, 0x27))

    async def samples(self) -> AsyncIterator[BeamSample]:
        while True:
            self.latest = await self._queue.get()
            yield self.latest


async def _cancel_after_result(wait: Callable[[], Awaitable[Any]], result: Callable[[], None], turns: int) -> None:
    """Start ``wait()``, give it its result, cancel it ``turns`` loop turns later: unless the wait
    finished before the cancel, the cancel must win (a wait that returned, raised something else
    or carried on lost it)."""
    task = asyncio.create_task(wait())
    for _ in range(3):
        await asyncio.sleep(0)
    assert not task.done()
    result()
    for _ in range(turns):
        await asyncio.sleep(0)
    if task.done():  # finished before the cancel: nothing to lose
        return
    task.cancel()
    try:
        async with asyncio.timeout(2.0):
            outcome = await asyncio.shield(task)
    except asyncio.CancelledError:
        assert task.cancelled()
        return
    except TimeoutError:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        outcome = "nothing: it carried on waiting"
    except Exception as exc:  # the wait went on after the cancel and failed later
        outcome = f"{type(exc).__name__}: {exc}"
    pytest.fail(f"the cancel {turns} turn(s) after the result was lost; the wait returned {outcome}")


@pytest.mark.parametrize("turns", TURNS)
def test_a_cancel_as_the_beam_reaches_the_angle_cancels_the_wait(turns: int) -> None:
    async def main() -> None:
        drive = ManualDrive()
        tracker = BeamTracker()
        await tracker.start(drive)
        drive.send(0.0, 10.0)
        await asyncio.sleep(0)
        await _cancel_after_result(lambda: tracker.wait_angle(10.0, 5.0), lambda: drive.send(10.0, 10.0), turns)
        await tracker.stop()

    run_virtual(main())


@pytest.mark.parametrize("turns", TURNS)
def test_a_cancel_as_a_sample_arrives_cancels_a_capture_waiting_for_the_beam(turns: int) -> None:
    """The trigger of a phone waits for samples while the beam stands still (before the rotation):
    a cancel landing with a sample must end that worker, not leave it waiting for the next."""

    async def main() -> None:
        drive = ManualDrive()
        tracker = BeamTracker()
        await tracker.start(drive)
        drive.send(-60.0)
        await asyncio.sleep(0)
        profile = rig_profile(RIG)
        schedule = compile_plan(np.full(RIG.n_poses, 500.0), RIG, phone_timings(RIG, trigger_latency_s=[0.04] * 7),
                                profile=profile)
        runner = CaptureRunner(RIG, schedule, drive, tracker, [None] * RIG.n_cameras,
                               [ClockSync(p.id) for p in RIG.phones], [TriggerLatency(0.04) for _ in RIG.phones])
        record = runner.records[0]
        await _cancel_after_result(lambda: runner._wait_fire(record, record.planned_angle_deg, 0.04, "retake"),
                                   lambda: drive.send(-60.0), turns)
        await tracker.stop()

    run_virtual(main())


class StubbornPhone(MockPhone):
    """A phone whose capture, once cancelled, ignores every cancel for ``stubborn_s`` more."""

    stubborn_s = 8.0
    capturing = False

    async def capture(self) -> Any:
        self.capturing = True
        try:
            return await super().capture()
        except asyncio.CancelledError:
            until = asyncio.get_running_loop().time() + self.stubborn_s
            while (left := until - asyncio.get_running_loop().time()) > 0:
                try:
                    await asyncio.sleep(left)
                except asyncio.CancelledError:
                    continue
            raise
        finally:
            self.capturing = False


def test_a_capture_worker_that_does_not_stop_is_named_and_left_behind() -> None:
    """The phones' workers of a pass are stopped with a bound: the pass ends on time and names
    the worker it left (cancelled) instead of waiting for it."""
    from daemon.jobs.phones import prepare_phones

    async def main() -> tuple[list[str], float]:
        drive = MockDrive()
        await drive.connect()
        tracker = BeamTracker()
        await tracker.start(drive)
        phones = [(StubbornPhone if i == 3 else MockPhone)(p.serial, seed=i) for i, p in enumerate(RIG.phones)]
        profile = rig_profile(RIG)
        await drive.move_to(profile.start_deg, 40.0, 60.0)
        prep = await prepare_phones(phones, RIG)
        schedule = compile_plan(np.full(RIG.n_poses, 500.0), RIG, phone_timings(RIG, trigger_latency_s=[0.04] * 7),
                                profile=profile)
        runner = CaptureRunner(RIG, schedule, drive, tracker, phones, prep.clocks, prep.latency)
        loop = asyncio.get_running_loop()
        rotation = asyncio.create_task(runner.main_pass())
        while runner.captured < 20 or not phones[3].capturing:
            await asyncio.sleep(0.005)
        rotation.cancel()
        stopped = loop.time()
        await asyncio.gather(rotation, return_exceptions=True)
        took = loop.time() - stopped
        await asyncio.sleep(StubbornPhone.stubborn_s)  # the phone lets go at last
        await tracker.stop()
        await drive.close()
        return runner.abandoned, took

    abandoned, took = run_virtual(main())
    assert abandoned == ["capture-3"]
    assert took == pytest.approx(CaptureRunner.WORKER_STOP_S, abs=0.05)


def test_stopping_the_tracker_does_not_swallow_its_callers_cancel() -> None:
    async def main() -> None:
        drive = ManualDrive()
        tracker = BeamTracker()
        await tracker.start(drive)
        stopping = asyncio.create_task(tracker.stop())
        await asyncio.sleep(0)
        stopping.cancel()
        with pytest.raises(asyncio.CancelledError):
            await stopping

    run_virtual(main())


@pytest.mark.slow
def test_scans_stopped_at_random_points_always_end_closed_with_every_image(tmp_path: Path) -> None:
    """200 scans on the short rig, each stopped once: abort, e-stop, the job's task cancelled,
    the daemon stopped, at rest and while the beam turns, some in the loop turns right after an
    encoder sample."""
    results = run_trials(make_trials(200, seed=28), tmp_path)
    bad = [r for r in results if not r.ok]
    assert not bad, "\n".join(f"{r.trial}: {r.state_at} -> {r.end_state} after {r.exit_s} s, "
                              f"{r.outcome}; lost {r.lost[:3]}; {r.problems[:2]}" for r in bad[:10])
    counts = summary(results)
    assert counts["runs"] == 200 and counts["hangs"] == 0 and counts["images_lost"] == 0
    assert counts["captured_before"] > 200  # stops landed while images were coming in
    assert {"PREPARING", "DEPTH_SWEEP", "CAPTURING"} <= set(counts["states"])
