"""Focus calibration on the simulated phones, through the real phone driver: each phone's sweep
(daemon/jobs/focus_sweep.py, the procedure a rig's phones go through) runs over ADB against a simulated
phone that photographs a board on a stand in front of it (drivers/sim/focus_target.py), moved to
each distance the procedure asks for. Virtual time: a phone's ~250 pictures take no real waiting.

The simulated phones' lenses carry a seeded per-phone error (drivers/sim/phone.py), so the table
has something to recover; the truth is each phone's own lens.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from daemon.jobs.focus_sweep import FocusTable, SweepSettings, calibrate_focus
from drivers.phone.focus import FocusCalibration
from planner.calibration.focus_fit import CHECK_MM
from planner.calibration.target import CuboidTarget
from planner.rig import Rig

TEXTURE_PX_PER_MM = 4.0


@dataclass(frozen=True)
class PhoneFocusResult:
    """One phone: its measured table, the shared default table it replaces, and the focus error (mm)
    at CHECK_MM with each, against the phone's true lens; pictures: how many the sweeps took."""

    table: FocusTable
    previous: Any
    error_mm: np.ndarray
    default_error_mm: np.ndarray
    pictures: int

    @property
    def phone(self) -> str:
        return self.table.phone


def calibrate_sim_focus(rig: Rig, target: CuboidTarget, seed: int, out: Path, *,
                        settings: SweepSettings = SweepSettings(),
                        progress: Callable[[str, int, int], None] | None = None) -> list[PhoneFocusResult]:
    """Sweep every simulated phone of the rig (seeded as sim/rig.py seeds them) and write
    ``out/<phone id>.yaml`` focus tables (with ``out/<phone id>/``: sweeps and sharpest pictures)."""
    from sim.clock import run_virtual

    return run_virtual(_calibrate_all(rig, target, seed, out, settings, progress))


async def _calibrate_all(rig: Rig, target: CuboidTarget, seed: int, out: Path, settings: SweepSettings,
                         progress: Callable[[str, int, int], None] | None) -> list[PhoneFocusResult]:
    from drivers.adb.auth import AdbKey

    key = AdbKey.generate()
    out.mkdir(parents=True, exist_ok=True)
    results = []
    for index, phone in enumerate(rig.phones):
        async with focus_bench(rig, target, index, seed, key, settings.distances_mm[0]) as bench:
            table = await calibrate_focus(
                bench.camera, rig.optics, settings, bench.place_board, out, measured=f"simulated, seed {seed}",
                progress=None if progress is None else lambda done, total: progress(phone.id, done, total))
        measured = FocusCalibration(table.diopters, table.distance_mm, source=phone.id)
        lens = bench.phone.sharp_distance_mm
        error = np.array([lens(measured.diopters_for(x)) - x for x in CHECK_MM])
        default_error = np.array([lens(bench.default.diopters_for(x)) - x for x in CHECK_MM])
        results.append(PhoneFocusResult(table, bench.default, error, default_error, len(bench.phone.captures)))
    return results


@dataclass
class FocusBench:
    """A simulated phone with a board stand in front of it, and the phone driver connected to it
    (its focus table: the rig file's). ``place_board`` moves the stand, as the operator does."""

    phone: Any
    stand: Any
    camera: Any
    default: Any

    async def place_board(self, distance_mm: float) -> None:
        self.stand.distance_mm = distance_mm


@asynccontextmanager
async def focus_bench(rig: Rig, target: CuboidTarget, index: int, seed: int, key: Any,
                      distance_mm: float) -> AsyncIterator[FocusBench]:
    """Rig phone ``index`` (seeded as sim/rig.py seeds it) on a focus bench, the board at distance_mm."""
    from drivers.phone.camera import PhoneCamera
    from drivers.phone.focus import load_focus_calibration
    from drivers.sim.focus_target import BoardStand
    from drivers.sim.phone import SimulatedPhone
    from sim.rig import sim_phone_link

    phone = rig.phones[index]
    sim = SimulatedPhone(phone.serial, seed=seed * 100 + index, optics=rig.optics, known_keys=[key.public_blob()])
    sim.board = BoardStand(target.board_image(0, TEXTURE_PX_PER_MM).astype(np.float32), TEXTURE_PX_PER_MM,
                           distance_mm)
    tasks: list[asyncio.Task[Any]] = []
    default = load_focus_calibration(rig.resolve(phone.focus_calibration))
    camera = PhoneCamera(sim_phone_link(sim, tasks), phone, default, key=key)
    try:
        await camera.connect()
        yield FocusBench(sim, sim.board, camera, default)
    finally:
        await camera.close()
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
