"""The virtual-time event loop that simulated scans run on."""

from __future__ import annotations

import asyncio
import math
import socket
import threading

import pytest
from hypothesis import given
from hypothesis import strategies as st

from sim.clock import Pace, TasksLeftPending, VirtualTimeLoop, VirtualTimeStall, run_virtual


def test_sleep_advances_the_virtual_clock_exactly():
    async def main() -> tuple[float, float]:
        loop = asyncio.get_running_loop()
        start = loop.time()
        await asyncio.sleep(3600.0)
        return start, loop.time()

    start, end = run_virtual(main())
    assert start == 0.0
    assert end == pytest.approx(3600.0, abs=1e-9)


async def _interleaved(log: list[tuple[float, str]]) -> None:
    loop = asyncio.get_running_loop()

    async def ticker(name: str, period: float, count: int) -> None:
        for _ in range(count):
            await asyncio.sleep(period)
            log.append((round(loop.time(), 9), name))

    await asyncio.gather(ticker("heartbeat", 0.1, 30), ticker("pdo", 0.005, 500), ticker("slow", 0.7, 4))


def test_the_same_program_gives_the_same_timeline_at_any_time_scale():
    fast: list[tuple[float, str]] = []
    paced: list[tuple[float, str]] = []
    run_virtual(_interleaved(fast))
    run_virtual(_interleaved(paced), time_scale=1000.0)
    assert fast == paced
    assert [name for _, name in fast].count("heartbeat") == 30


def test_timeouts_fire_on_virtual_time():
    async def main() -> float:
        loop = asyncio.get_running_loop()
        with pytest.raises(TimeoutError):
            async with asyncio.timeout(2.5):
                await asyncio.Event().wait()
        return loop.time()

    assert run_virtual(main()) == pytest.approx(2.5)


def test_clock_stands_still_while_an_executor_job_runs():
    release = threading.Event()

    def job() -> str:
        release.wait(5.0)
        return "planned"

    async def main() -> list[str]:
        order: list[str] = []

        async def timer() -> None:
            await asyncio.sleep(10.0)
            order.append("timer")

        async def compute() -> None:
            result = await asyncio.get_running_loop().run_in_executor(None, job)
            order.append(result)

        timer_task = asyncio.create_task(timer())
        compute_task = asyncio.create_task(compute())
        await asyncio.sleep(0)
        threading.Timer(0.05, release.set).start()
        await asyncio.gather(timer_task, compute_task)
        return order

    assert run_virtual(main()) == ["planned", "timer"]


def test_socketpair_bytes_arrive_without_a_time_jump():
    async def main() -> tuple[bytes, float]:
        loop = asyncio.get_running_loop()
        a, b = socket.socketpair()
        reader, a_writer = await asyncio.open_connection(sock=a)
        _, writer = await asyncio.open_connection(sock=b)

        async def send_later() -> None:
            await asyncio.sleep(5.0)
            writer.write(b"frame")
            await writer.drain()

        sender = asyncio.create_task(send_later())
        data = await reader.readexactly(5)
        arrived = loop.time()
        await sender
        writer.close()
        a_writer.close()
        return data, arrived

    data, arrived = run_virtual(main())
    assert data == b"frame"
    assert arrived == pytest.approx(5.0)


def test_a_deadlocked_simulation_is_reported_instead_of_hanging():
    async def main() -> None:
        await asyncio.Event().wait()

    with pytest.raises(VirtualTimeStall, match="virtual time stalled"):
        run_virtual(main(), idle_real_timeout=0.05)


def test_time_scale_must_be_positive():
    with pytest.raises(ValueError, match="time_scale"):
        VirtualTimeLoop(time_scale=0.0)


def test_a_task_left_pending_fails_the_run_naming_it():
    device_tasks: list[asyncio.Task[object]] = []  # held, as a driver holds its reader task

    async def leaky() -> None:
        device_tasks.append(asyncio.create_task(asyncio.Event().wait(), name="forgotten-watch"))
        await asyncio.sleep(1.0)

    with pytest.raises(TasksLeftPending, match="forgotten-watch"):
        run_virtual(leaky())

    async def tidy() -> str:
        task = asyncio.create_task(asyncio.sleep(5.0), name="finished")
        await task
        return "done"

    assert run_virtual(tidy()) == "done"


def _epoll_wait(seconds: float) -> float:
    """What a wait costs on epoll, which waits whole milliseconds (rounded up)."""
    return math.ceil(seconds * 1000.0) / 1000.0


@given(st.lists(st.floats(1e-6, 0.2), min_size=1, max_size=400), st.floats(1.0, 100.0))
def test_a_paced_clock_keeps_its_scale_with_jumps_shorter_than_the_selector_waits(
        jumps: list[float], scale: float) -> None:
    pace, now = Pace(scale), 0.0
    for jump in jumps:
        wait = pace.wait(jump, now)
        assert wait >= 0.0
        now += _epoll_wait(wait)
    assert abs(now - sum(jumps) / scale) <= 0.001 + 1e-9
    # Waited jump by jump, the same timeline would cost up to a millisecond per jump.
    assert sum(_epoll_wait(j / scale) for j in jumps) >= now - 0.001


@given(st.floats(0.06, 30.0), st.floats(0.01, 2.0), st.floats(1.0, 50.0))
def test_a_paced_clock_that_fell_behind_paces_on_from_there_instead_of_racing(
        stall_s: float, after_s: float, scale: float) -> None:
    pace = Pace(scale, slack_s=0.05)
    now = _epoll_wait(pace.wait(1.0, 0.0))  # on time
    now += stall_s  # the loop could not run (a compute job, a loaded machine)
    resumed = now
    for _ in range(10):
        now += _epoll_wait(pace.wait(after_s / 10, now))
    assert abs((now - resumed) - after_s / scale) <= 0.001 + 1e-9


def test_real_io_that_ends_a_wait_early_restarts_the_pace_there() -> None:
    pace = Pace(10.0)
    assert pace.wait(1.0, 0.0) == pytest.approx(0.1)
    pace.restart(0.03)  # a control-socket client woke the loop 30 ms in
    assert pace.wait(1.0, 0.03) == pytest.approx(0.1)


def test_a_time_scale_set_while_running_paces_the_jumps_after_it(monkeypatch: pytest.MonkeyPatch) -> None:
    waits: list[tuple[float, float]] = []
    wait = Pace.wait

    def recorded(self: Pace, jump_s: float, now: float) -> float:
        waits.append((self.time_scale, jump_s))
        return wait(self, jump_s, now)

    monkeypatch.setattr(Pace, "wait", recorded)

    async def main() -> None:
        loop = asyncio.get_running_loop()
        await asyncio.sleep(1.0)  # as fast as possible: no pace
        loop.time_scale = 1000.0
        await asyncio.sleep(0.5)
        loop.time_scale = None
        await asyncio.sleep(2.0)

    run_virtual(main())
    assert waits == [(1000.0, pytest.approx(0.5))]
