"""Getting the phones ready for a capture rotation: clock mapping and trigger latency.

Before the beam moves, every phone gets a few clock round trips (its sensor clock mapped to the
host event-loop clock) and a few warm-up captures with the beam at rest, which measure the
trigger latency (command sent -> exposure start) that the capture triggers compensate. A phone
that fails here is marked not ready; its poses are retaken after the main rotation if it
comes back.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Sequence
from dataclasses import dataclass

import structlog

from daemon.jobs.capture import TriggerLatency
from daemon.rig.clocksync import ClockSync
from daemon.rig.devices import Phone
from planner.rig import Rig

log = structlog.get_logger("daemon.jobs.phones")


@dataclass
class PhonePrep:
    """Per phone, in rig order: clock mapping, latency estimate, focus range (mm), readiness."""

    clocks: list[ClockSync]
    latency: list[TriggerLatency]
    min_focus_mm: list[float]
    max_focus_mm: list[float]
    ready: list[bool]
    errors: list[str | None]


DEFAULT_MIN_FOCUS_MM = 100.0
"""A phone's nearest focus when it has neither a focus table nor a reported minimum."""


def focus_range_mm(phone: Phone) -> tuple[float, float]:
    """Nearest and farthest focus (mm) of a phone: its focus table, else its reported minimum."""
    table = phone.focus_table
    if table is not None:
        return float(table.near_mm), float(table.far_mm)
    diopters = phone.info.min_focus_diopters if phone.info is not None else None
    near = 1000.0 / float(diopters) if diopters else DEFAULT_MIN_FOCUS_MM
    return near, math.inf


class PhonePreparer:
    """Clock round trips and warm-up captures for every phone, concurrently."""

    CLOCK_SAMPLES = 8
    CLOCK_SPACING_S = 0.2
    """Clock pings spread out: a drift fit over a few ms of pings would be all jitter."""
    WARMUP_CAPTURES = 2
    STEP_TIMEOUT_S = 2.0

    def __init__(self, phones: Sequence[Phone], rig: Rig) -> None:
        self.phones = list(phones)
        self.rig = rig

    async def run(self) -> PhonePrep:
        n = len(self.phones)
        prep = PhonePrep(
            clocks=[ClockSync(self.rig.phones[c].id) for c in range(n)],
            latency=[TriggerLatency() for _ in range(n)],
            min_focus_mm=[focus_range_mm(p)[0] for p in self.phones],
            max_focus_mm=[focus_range_mm(p)[1] for p in self.phones],
            ready=[False] * n,
            errors=[None] * n,
        )
        await asyncio.gather(*(self._one(c, prep) for c in range(n)))
        return prep

    async def _one(self, c: int, prep: PhonePrep) -> None:
        phone, loop = self.phones[c], asyncio.get_running_loop()
        try:
            for i in range(self.CLOCK_SAMPLES):
                if i:
                    await asyncio.sleep(self.CLOCK_SPACING_S)
                async with asyncio.timeout(self.STEP_TIMEOUT_S):
                    prep.clocks[c].add(await phone.clock_sample())
            for _ in range(self.WARMUP_CAPTURES):
                fired = loop.time()
                async with asyncio.timeout(self.STEP_TIMEOUT_S):
                    done = await phone.capture()
                prep.latency[c].update(prep.clocks[c].to_host(done.sensor_timestamp_ns) - fired)
        except Exception as exc:  # the phone's typed error is kept; its poses go to the retake pass
            prep.errors[c] = f"{type(exc).__name__}: {exc}"
            log.warning("phone_prepare_failed", camera=self.rig.phones[c].id, error=prep.errors[c])
            return
        prep.ready[c] = True
        log.info("phone_prepared", camera=self.rig.phones[c].id,
                 latency_s=round(prep.latency[c].value_s, 5))


async def prepare_phones(phones: Sequence[Phone], rig: Rig) -> PhonePrep:
    return await PhonePreparer(phones, rig).run()


async def keep_clocks_synced(phones: Sequence[Phone], prep: PhonePrep, period_s: float = 1.0) -> None:
    """Ping every ready phone's clock each ``period_s`` until cancelled (tracks drift).

    A phone that stops answering is left alone: its capture requests report the typed error.
    """
    active = [c for c, ready in enumerate(prep.ready) if ready]

    async def one(c: int) -> None:
        while True:
            await asyncio.sleep(period_s)
            try:
                async with asyncio.timeout(PhonePreparer.STEP_TIMEOUT_S):
                    prep.clocks[c].add(await phones[c].clock_sample())
            except Exception as exc:  # recorded on the phone; its captures carry the real error
                prep.errors[c] = f"clock sync stopped: {type(exc).__name__}: {exc}"
                return

    await asyncio.gather(*(one(c) for c in active))
