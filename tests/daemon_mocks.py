"""Mock-tier devices for the daemon's unit tests: instant to build, analytic, recording calls.

They implement the daemon's device protocols (daemon/rig/devices.py: Drive, Phone; checked by
tests/test_device_protocols.py) to exercise the capture executor alone, and answer with the drivers' own result and error types; the end-to-end
tests use the protocol-level simulators instead.
"""

from __future__ import annotations

import asyncio
import math
import threading
from collections.abc import AsyncIterator, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from drivers.motor.samples import BeamSample
from drivers.phone.camera import CaptureDone, ClockSample, FocusDone, PhoneInfo
from drivers.phone.errors import CaptureFailed, PhoneDisconnected, PullFailed
from drivers.sim.trapezoid import hold, position_move, velocity_ramp

OPERATION_ENABLED = 0x27
"""Statusword of a drive in OPERATION ENABLED (CiA 402)."""


class MockDrive:
    """A beam on an analytic trapezoidal trajectory, sampled at ``rate_hz`` on the loop clock."""

    def __init__(self, *, rate_hz: float = 200.0, speed_error: float = 0.0, max_accel: float = 60.0) -> None:
        self.name = "beam"
        self.rate_hz = rate_hz
        self.speed_error = speed_error
        self.max_accel = max_accel
        self.trajectory = hold(0.0, 0.0)
        self.offset = 0.0
        self.fault: Exception | None = None
        self.latest: BeamSample | None = None
        self.calls: list[tuple[str, tuple[float, ...]]] = []
        self._queues: list[asyncio.Queue[BeamSample]] = []
        self._task: asyncio.Task[None] | None = None
        self._closed = False

    @property
    def closed(self) -> bool:
        return self._closed

    def _now(self) -> float:
        return asyncio.get_running_loop().time()

    def _state(self) -> tuple[float, float]:
        p, v = self.trajectory.at(self._now())
        return p + self.offset, v

    async def connect(self) -> None:
        self._task = asyncio.create_task(self._stream())

    async def enable(self) -> None:
        self.calls.append(("enable", ()))

    async def set_zero(self, angle_deg: float = 0.0) -> None:
        p, _ = self._state()
        self.offset += angle_deg - p
        self.calls.append(("set_zero", (angle_deg,)))

    async def rotate(self, speed_deg_s: float, acceleration_deg_s2: float) -> None:
        self.calls.append(("rotate", (speed_deg_s, acceleration_deg_s2)))
        t = self._now()
        p, v = self.trajectory.at(t)
        target = speed_deg_s * (1.0 + self.speed_error)
        self.trajectory = velocity_ramp(t, p, v, target, acceleration_deg_s2, acceleration_deg_s2)

    async def stop(self, deceleration_deg_s2: float) -> None:
        self.calls.append(("stop", (deceleration_deg_s2,)))
        t = self._now()
        p, v = self.trajectory.at(t)
        self.trajectory = velocity_ramp(t, p, v, 0.0, deceleration_deg_s2, deceleration_deg_s2)

    async def quick_stop(self) -> None:
        await self.stop(self.max_accel)

    def sample_age_s(self) -> float:
        return math.inf if self.latest is None else self._now() - self.latest.time_s

    def heartbeat_age_s(self) -> float:
        return 0.0 if self._task is not None and not self._task.done() else math.inf

    def liveness(self) -> list[str]:
        running = self._task is not None and not self._task.done()
        return [] if running or self._task is None or self._closed else ["beam: sample stream ended"]

    async def move_to(self, angle_deg: float, speed_deg_s: float, acceleration_deg_s2: float) -> None:
        self.calls.append(("move_to", (angle_deg, speed_deg_s, acceleration_deg_s2)))
        t = self._now()
        p, v = self.trajectory.at(t)
        self.trajectory = position_move(t, p, v, angle_deg - self.offset, speed_deg_s,
                                        acceleration_deg_s2, acceleration_deg_s2)
        await asyncio.sleep(max(self.trajectory.end_time - t, 0.0) + 1.0 / self.rate_hz)

    async def reset_fault(self) -> None:
        self.fault = None

    async def close(self) -> None:
        self._closed = True
        if self._task is not None:
            self._task.cancel()

    async def samples(self) -> AsyncIterator[BeamSample]:
        queue: asyncio.Queue[BeamSample] = asyncio.Queue()
        self._queues.append(queue)
        while True:
            yield await queue.get()

    async def _stream(self) -> None:
        period = 1.0 / self.rate_hz
        while True:
            await asyncio.sleep(period)
            p, v = self._state()
            self.latest = BeamSample(self._now(), p, v, OPERATION_ENABLED)
            for q in self._queues:
                q.put_nowait(self.latest)


class MockPhone:
    """A phone with a lens that takes time to move and a seeded trigger latency with jitter.

    Faults: ``fail_after`` (the link drops after that many captures; ``reconnectable`` says if
    it comes back), ``freeze_after`` (after that many captures no request is ever answered, as
    when the camera HAL hangs, until ``frozen`` is set False), ``fail_captures_at`` (the
    captures, counted from 0, that answer CAPTURE_FAILED), ``fail_pulls`` (every pull fails)."""

    def __init__(self, serial: str, *, seed: int = 0, latency_s: float = 0.04, jitter_s: float = 0.002,
                 clock_offset_s: float = 1234.5, lens_s: float = 0.03) -> None:
        self.serial = serial
        self.name = f"phone-{serial}"
        self.rng = np.random.default_rng(seed)
        self.latency_s = latency_s
        self.jitter_s = jitter_s
        self.clock_offset_s = clock_offset_s
        self.lens_s = lens_s
        self.focus_mm = 0.0
        self.captures: list[int] = []
        self.fail_after: int | None = None
        self.freeze_after: int | None = None
        self.frozen = False
        self.fail_captures_at: set[int] = set()
        self.fail_pulls = False
        self._tries = 0
        self.connected = True
        self.reconnectable = True
        self.focus_table = None  # no calibration: the daemon falls back to the reported range
        self.info: PhoneInfo | None = None
        self.deleted: list[str] = []

    def _device_ns(self, host_s: float) -> int:
        return int(round((host_s + self.clock_offset_s) * 1e9))

    def _check(self) -> None:
        if self.fail_after is not None and len(self.captures) >= self.fail_after:
            self.connected = False
            self.fail_after = None
        if not self.connected:
            raise PhoneDisconnected(self.serial, "ready", "link lost")

    async def _answer(self) -> None:
        """A frozen phone never answers (the caller's timeout decides)."""
        if self.freeze_after is not None and len(self.captures) >= self.freeze_after:
            self.frozen, self.freeze_after = True, None
        while self.frozen:
            await asyncio.sleep(0.1)

    async def connect(self, timeout_s: float | None = None) -> None:
        if not self.reconnectable:
            raise PhoneDisconnected(self.serial, "connecting", "connection refused")
        self.connected = True

    async def set_focus_mm(self, focus_mm: float) -> FocusDone:
        self._check()
        await self._answer()
        await asyncio.sleep(self.lens_s)
        self.focus_mm = focus_mm
        now = asyncio.get_running_loop().time()
        return FocusDone(1000.0 / focus_mm, focus_mm, self._device_ns(now))

    async def set_lens_diopters(self, diopters: float) -> FocusDone:
        return await self.set_focus_mm(1000.0 / diopters)

    async def capture(self) -> CaptureDone:
        self._check()
        await self._answer()
        self._tries += 1
        if self._tries - 1 in self.fail_captures_at:
            raise CaptureFailed(self.serial, "ready", "CAPTURE_FAILED", "sensor busy", "capture")
        latency = self.latency_s + self.jitter_s * float(self.rng.standard_normal())
        await asyncio.sleep(latency)
        start = asyncio.get_running_loop().time()
        await asyncio.sleep(0.002 + 0.05)
        self.captures.append(self._device_ns(start))
        return CaptureDone(self._device_ns(start), 0.002, 1000.0 / max(self.focus_mm, 1.0),
                           f"/sdcard/tbp/{len(self.captures)}.jpg", 1000)

    async def clock_sample(self) -> ClockSample:
        self._check()
        await self._answer()
        loop = asyncio.get_running_loop()
        send = loop.time()
        await asyncio.sleep(0.001)
        device = self._device_ns(loop.time())
        await asyncio.sleep(0.001)
        return ClockSample(send, device, loop.time())

    async def pull(self, phone_path: str, dest: Path) -> tuple[int, str]:
        import hashlib

        if self.fail_pulls:
            raise PullFailed(self.serial, "ready", f"{phone_path}: device I/O error")
        data = b"x" * 1000
        dest.write_bytes(data)
        return len(data), hashlib.sha256(data).hexdigest()

    async def delete(self, phone_path: str) -> None:
        self._check()
        self.deleted.append(phone_path)

    async def close(self) -> None:
        self.connected = False


@contextmanager
def answering_daemon(sock: Path, status: dict[str, Any] | Exception) -> Iterator[None]:
    """A stand-in daemon answering ``status`` (or refusing it with the exception) on the control
    socket ``sock``, served by the real ControlServer from its own event loop in a thread (the
    command under test runs its own loop)."""
    from daemon.server.control import ControlServer

    class Daemon:
        def status(self) -> dict[str, Any]:
            if isinstance(status, Exception):
                raise status
            return status

    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    server = ControlServer(sock, Daemon())  # type: ignore[arg-type]
    asyncio.run_coroutine_threadsafe(server.start(), loop).result(10)
    try:
        yield
    finally:
        asyncio.run_coroutine_threadsafe(server.close(), loop).result(10)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(5)
