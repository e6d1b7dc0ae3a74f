"""The focus calibration's sweep of one phone through its driver (``tbp calibrate focus``).

A board stands square-on in front of the phone, its centre on the optical axis, at each of a few
known distances in turn (``place_board`` is awaited before each: the operator moves the stand and
confirms). At each distance the lens setting itself (Camera2's LENS_FOCUS_DISTANCE, diopters, not
the focus table's millimetres) is stepped coarsely over the lens' range, then finely around the
sharpest coarse setting; every picture is pulled (daemon/jobs/pulls.py: verified, retried), measured
(variance of the Laplacian over the centre of the picture that the board covers at that distance,
so the background's blur does not count) and deleted from the phone. The sharpest picture of each
distance is kept in ``workdir`` for the report. ``planner/calibration/focus_fit.py`` turns the
sweeps into the phone's focus table. The same code sweeps a real phone and a simulated one.
"""

from __future__ import annotations

import json
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import structlog

from daemon.errors import DaemonError
from daemon.jobs.pulls import Pull, pull_verified
from daemon.rig.devices import Phone
from drivers.phone.camera import PhoneInfo
from planner.calibration.detect import sharpness
from planner.calibration.focus_fit import DISTANCES_MM, TABLE_DIOPTERS, FocusSweep, fit_focus_table, table_yaml
from planner.rig import Optics

log = structlog.get_logger(__name__)


class SweepPictureError(DaemonError, ValueError):
    """A sweep picture the host cannot read (named: phone, file)."""

    def __init__(self, phone: str, path: Path) -> None:
        self.phone, self.path = phone, path
        super().__init__(f"focus sweep of {phone}: {path} is not a readable picture")


class SweepPhoneNotConnected(DaemonError, RuntimeError):
    """The focus sweep was handed a phone that has not connected (it knows no lens range yet)."""

    def __init__(self, phone: str) -> None:
        self.phone = phone
        super().__init__(f"focus sweep of {phone}: the phone is not connected (connect it first)")


@dataclass(frozen=True)
class SweepSettings:
    """Distances of the board (mm, nearest first) and the lens settings swept at each (diopters):
    every ``coarse_step`` from ``lowest`` to the lens' closest focus, then every ``fine_step``
    within ``fine_span`` of the sharpest coarse setting. ``board_width_mm``: the board's narrower
    side; the centre square measured is ``board_share`` of what it covers in the picture."""

    distances_mm: tuple[float, ...] = DISTANCES_MM
    lowest: float = 0.3
    coarse_step: float = 0.4
    fine_step: float = 0.1
    fine_span: float = 0.5
    board_width_mm: float = 280.0
    board_share: float = 0.8

    def __post_init__(self) -> None:
        if len(self.distances_mm) < 3 or min(self.distances_mm) <= 0:
            raise ValueError(f"need at least 3 positive board distances, got {self.distances_mm}")
        if not 0 < self.fine_step <= self.coarse_step or self.fine_span < self.fine_step:
            raise ValueError(f"steps must satisfy 0 < fine ({self.fine_step}) <= coarse ({self.coarse_step}) "
                             f"and fine span ({self.fine_span}) >= fine step")
        if not (self.board_width_mm > 0 and 0 < self.board_share <= 1):
            raise ValueError(f"board width {self.board_width_mm} mm and share {self.board_share}: need "
                             "a positive width and a share in (0, 1]")

    def coarse(self, highest: float) -> np.ndarray:
        """Coarse settings from ``lowest`` up to ``highest`` (the lens' closest focus), both included."""
        steps = np.arange(self.lowest, highest - 1e-6, self.coarse_step)
        return np.append(steps, highest)

    def fine(self, peak: float, highest: float, done: np.ndarray) -> np.ndarray:
        """Fine settings around ``peak`` within the lens' range, leaving out those already in ``done``."""
        around = peak + self.fine_step * np.arange(-int(self.fine_span / self.fine_step + 1e-9),
                                                    int(self.fine_span / self.fine_step + 1e-9) + 1)
        around = around[(around >= self.lowest) & (around <= highest)]
        return np.array([d for d in around if not np.any(np.isclose(done, d, atol=1e-6))])


def board_sharpness(path: Path, width_share: float, phone: str) -> float:
    """Sharpness of the centre square of a picture file whose side is ``width_share`` of the
    picture's width (at most its shorter side)."""
    grey = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if grey is None:
        raise SweepPictureError(phone, path)
    h, w = grey.shape
    side = int(np.clip(width_share * w, 8, min(h, w)))
    y0, x0 = (h - side) // 2, (w - side) // 2
    return sharpness(grey[y0:y0 + side, x0:x0 + side])


async def sweep_phone(camera: Phone, optics: Optics, settings: SweepSettings,
                      place_board: Callable[[float], Awaitable[None]], workdir: Path,
                      progress: Callable[[int, int], None] | None = None) -> list[FocusSweep]:
    """Sweep a connected phone (lens: ``optics``) at every distance of ``settings``; one
    FocusSweep per distance.

    Phone errors (a phone that vanishes, a capture that fails, a picture that cannot be pulled
    whole: ImagePullFailed) propagate, naming the phone."""
    phone = camera.name
    highest = float(_info(camera).min_focus_diopters)
    workdir.mkdir(parents=True, exist_ok=True)
    coarse = settings.coarse(highest)
    fine_guess = int(2 * settings.fine_span / settings.fine_step)
    total, done = len(settings.distances_mm) * (len(coarse) + fine_guess), 0
    sweeps = []
    for distance in settings.distances_mm:
        await place_board(distance)
        measured: dict[float, float] = {}
        best = -1.0
        keep = workdir / f"d{distance:04.0f}.jpg"
        # the centre square measured: board_share of the board's width at this distance
        width_share = (settings.board_share * settings.board_width_mm * optics.focal_length_px
                       / (optics.image_width_px * distance))

        async def measure(diopters: float) -> None:
            nonlocal best, done
            await camera.set_lens_diopters(diopters)
            shot = await camera.capture()
            picture = workdir / "sweep.jpg"
            await pull_verified(Pull(shot.path, phone, None, shot.path, picture, camera.pull, shot.size_bytes))
            await camera.delete(shot.path)
            value = board_sharpness(picture, width_share, phone)
            measured[float(diopters)] = value
            if value > best:
                best = value
                picture.replace(keep)
            done += 1
            if progress is not None:
                progress(min(done, total), total)

        for d in coarse:
            await measure(float(d))
        peak = max(measured, key=measured.__getitem__)
        for d in settings.fine(peak, highest, np.array(list(measured))):
            await measure(float(d))
        diopters = np.array(sorted(measured))
        sweeps.append(FocusSweep(distance, diopters, np.array([measured[d] for d in diopters])))
        log.info("focus_sweep.distance", phone=phone, distance_mm=distance, pictures=len(diopters),
                 sharpest_diopters=peak)
    (workdir / "sweep.jpg").unlink(missing_ok=True)
    return sweeps


def _info(camera: Phone) -> PhoneInfo:
    """What a connected phone reported (its lens range, its model)."""
    if camera.info is None:
        raise SweepPhoneNotConnected(camera.name)
    return camera.info


@dataclass(frozen=True)
class FocusTable:
    """One phone's measured focus table (commanded diopters -> sharpest distance, mm), the fit's
    RMS residual (diopters), the sweeps it came from and the file it was written to."""

    phone: str
    diopters: np.ndarray
    distance_mm: np.ndarray
    rms_diopters: float
    sweeps: list[FocusSweep]
    path: Path


async def calibrate_focus(camera: Phone, optics: Optics, settings: SweepSettings,
                          place_board: Callable[[float], Awaitable[None]], out: Path, *, measured: str,
                          progress: Callable[[int, int], None] | None = None) -> FocusTable:
    """Sweep a connected phone, fit its focus table and write ``out/<phone>.yaml`` (the format the
    phone driver reads; ``measured`` says when and how), with the sweeps' numbers and the sharpest
    picture of each distance in ``out/<phone>/``. Raises FocusFitError when the sweeps do not
    determine a table (named: phone, distance, problem)."""
    phone = camera.name
    sweeps = await sweep_phone(camera, optics, settings, place_board, out / phone, progress)
    (out / phone / "sweeps.json").write_text(json.dumps([
        {"distance_mm": s.distance_mm, "diopters": s.diopters.tolist(), "sharpness": s.sharpness.tolist()}
        for s in sweeps], indent=1))
    grid, mm, rms = fit_focus_table(sweeps, TABLE_DIOPTERS, phone)
    path = out / f"{phone}.yaml"
    path.write_text(table_yaml(_info(camera).model, measured, grid, mm))
    return FocusTable(phone, grid, mm, rms, sweeps, path)
