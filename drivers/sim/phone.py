"""A simulated rig phone: an adbd (drivers/sim/adbd.py) plus the capture agent, lens and sensor clock.

The agent starts only the way the real one does: the host runs ``CLASSPATH=<jar> app_process /
com.tbp.CaptureAgent ...`` on a shell stream; the jar must be on the phone (pushed, or
installed beforehand with ``agent_installed=True``). It then prints its READY line, listens on
``localabstract:tbp-capture`` and lives until that shell stream closes. Two agents can answer:
the Python twin (``agent_runtime="python"``, drivers/sim/phone_agent.py) or the real agent's JVM
build run with ``java`` (``"jvm"``, drivers/sim/jvm_agent.py, agent/); both drive this phone's
camera below, so the same faults act on either.

The camera, all on the event loop's clock: the lens travels for LENS_BASE_S + LENS_S_PER_DIOPTER *
|change| (times ``lens_slowdown``) and settles for LENS_SETTLE_S; a capture starts exposing
CAPTURE_LATENCY_S (+ seeded jitter) after the request and the JPEG is ready ENCODE_S after the
exposure. The sensor clock has its own offset and drift (seeded); a clock read happens after a
seeded one-way delay, so round trips are not zero. Each image is the subject ray
cast from ``pose(t)`` (time -> (4, 4) camera-to-world, provided by the sim wiring so the phone
knows nothing of the motor), its skin freckled as at a visit with ``lesion_changes`` (none by
default), and blurred by its distance from the focal plane; with a
``board`` (drivers/sim/focus_target.py: a board on a stand in front of the phone, for the focus
calibration's sweep) the picture is that board instead, and with a ``picture_source`` (the sim
wiring's calibration cuboid, seen from ``pose(t)``) it is what the source renders.

Faults: those of the adbd (refuse_auth, vanish(), disconnect_after_bytes) plus crash_agent()
(the agent process dies; adbd stays up, so a reconnect starts it again), lens_slowdown,
fail_captures (the next n captures fail as onCaptureFailed), answer_delay_s (every agent answer
is held back that long, as on a congested USB hub) and mute_agent (the camera HAL hangs: focus,
capture and clock requests go unanswered).
"""

from __future__ import annotations

import asyncio
import random
import weakref
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from drivers.phone import protocol
from drivers.sim.adbd import SimulatedAdbd
from drivers.sim.focus_target import BoardStand
from drivers.sim.jvm_agent import JvmRuntime
from drivers.sim.phone_agent import CaptureFailure, TwinRuntime
from drivers.sim.phone_render import PhoneRenderer, SubjectScene, empty_rig_picture, encode_jpeg
from drivers.sim.skin_texture import LesionChanges
from planner.rig import Optics, load_rig

PoseSource = Callable[[float], np.ndarray]
PictureSource = Callable[[np.ndarray | None, float, np.random.Generator], np.ndarray]
"""(camera-to-world pose at the exposure, sharpest distance of the lens in mm, noise) -> (H, W[, 3])
uint8: what the phone photographs when it is not the subject (the calibration cuboid)."""
_SCENES: weakref.WeakKeyDictionary[Any, Any] = weakref.WeakKeyDictionary()
AGENT_RUNTIMES = ("python", "jvm")
RENDER_SIZE = (192, 256)
"""(width, height) px of a simulated phone's pictures by default: 1/32 of the rig phone's sensor
side, about 1.5 mm/px on the skin (cheap; a finer render resolves smaller spots)."""


def _scene_for(subject: Any, lesion_changes: LesionChanges | None) -> SubjectScene:
    """One ray-casting scene per subject mesh and lesion changes, shared by every simulated phone."""
    scenes: dict[LesionChanges | None, SubjectScene] = _SCENES.setdefault(subject, {})
    scene = scenes.get(lesion_changes)
    if scene is None:
        scene = scenes[lesion_changes] = SubjectScene(subject, lesion_changes)
    return scene


@dataclass(frozen=True)
class Still:
    """One exposure: its start (loop s and sensor ns), exposure (s), focus used (diopters), the JPEG."""

    start_s: float
    sensor_timestamp_ns: int
    exposure_s: float
    focus_diopters: float
    jpeg: bytes


class SimulatedPhone(SimulatedAdbd):
    """One rig phone: adbd, capture agent, lens, sensor clock and camera."""

    LENS_BASE_S = 0.012
    LENS_S_PER_DIOPTER = 0.010
    LENS_SETTLE_S = 0.03
    CAPTURE_LATENCY_S = 0.045
    CAPTURE_JITTER_S = 0.003
    ENCODE_S = 0.12
    LINK_DELAY_S = 0.0003  # one way, USB/ADB and agent thread hand-off, before jitter
    EXPOSURE_RANGE_S = (1e-5, 0.5)  # SENSOR_INFO_EXPOSURE_TIME_RANGE
    ISO_RANGE = (50, 3200)  # SENSOR_INFO_SENSITIVITY_RANGE
    IMAGE_DIR = "/sdcard/DCIM/tbp"

    def __init__(self, serial: str, *, subject: Any | None = None, pose: PoseSource | None = None,
                 seed: int = 0, optics: Optics | None = None, known_keys: Iterable[bytes | str] = (),
                 accept_new_keys: bool = True, agent_installed: bool = True,
                 render_size: tuple[int, int] | None = RENDER_SIZE, min_focus_diopters: float = 10.0,
                 focus_calibration_quality: int = 1, timestamp_source: str = "realtime",
                 model: str = "TBP Simulated Phone", agent_runtime: str = "python",
                 agent_jar: Path | None = None, lesion_changes: LesionChanges | None = None) -> None:
        super().__init__(serial, properties={"ro.product.model": model}, known_keys=known_keys,
                         accept_new_keys=accept_new_keys, seed=seed)
        self.subject = subject
        self.lesion_changes = lesion_changes
        self.pose = pose
        self.seed = seed
        self.board: BoardStand | None = None
        self.picture_source: PictureSource | None = None
        self.optics = optics or load_rig().optics  # the default rig's phones
        self.render_size = render_size
        self.min_focus_diopters = min_focus_diopters
        self.focus_calibration_quality = focus_calibration_quality
        self.timestamp_source = timestamp_source
        rng = random.Random(seed * 7919 + 17)
        self.clock_offset_s = rng.uniform(1_000.0, 200_000.0)
        self.clock_drift_ppm = rng.uniform(-30.0, 30.0)
        # The lens focuses at 1000 / (offset + gain * commanded diopters) mm: a per-phone error
        # that `tbp calibrate focus` measures (about 0.1 D and 3 %, as uncalibrated Camera2 units).
        self.focus_offset_diopters = rng.gauss(0.0, 0.08)
        self.focus_gain = 1.0 + rng.gauss(0.0, 0.03)
        self._jitter = random.Random(seed * 104729 + 3)
        self.lens_diopters = 0.0
        self.lens_slowdown = 1.0
        self.fail_captures = 0
        self.mute_agent = False
        self.answer_delay_s = 0.0
        self.agent_version = protocol.PROTOCOL_VERSION  # what the Python twin's hello says
        self.captures: list[dict[str, Any]] = []
        self._renderer: PhoneRenderer | None = None
        self.agent = _agent_runtime(self, agent_runtime, agent_jar)
        if agent_installed:
            self.fs.write(protocol.AGENT_PATH, self.agent.installed_jar())
        self.commands["app_process"] = self.agent.app_process

    @property
    def agent_running(self) -> bool:
        """Whether an agent process runs (between app_process and its exit)."""
        result: bool = self.agent.running
        return result

    def crash_agent(self) -> None:
        """Fault: the agent process dies (its socket and shell stream close; adbd stays up)."""
        self.agent.crash()

    # ---------------------------------------------------------------- clock
    def sensor_ns(self, loop_time_s: float) -> int:
        """The phone's sensor clock (ns) at a host loop time: own offset and drift."""
        return int(round((self.clock_offset_s + loop_time_s * (1.0 + self.clock_drift_ppm * 1e-6)) * 1e9))

    def loop_time_of(self, sensor_ns: int) -> float:
        """Inverse of :meth:`sensor_ns`: ground truth for clock-sync tests."""
        return (sensor_ns * 1e-9 - self.clock_offset_s) / (1.0 + self.clock_drift_ppm * 1e-6)

    def _now_ns(self) -> int:
        return self.sensor_ns(asyncio.get_running_loop().time())

    # ---------------------------------------------------------------- camera (what either agent drives)
    def camera_info(self) -> dict[str, Any]:
        """The camera's characteristics and the manual exposure, as the agent's hello reports them."""
        width, height = self._image_size()
        return {"model": self.properties["ro.product.model"], "serial": self.serial,
                "min_focus_diopters": self.min_focus_diopters,
                "focus_distance_calibration": self.focus_calibration_quality,
                "timestamp_source": self.timestamp_source, "exposure_s": self.optics.exposure_s,
                "iso": self.optics.iso, "image_width": width, "image_height": height,
                "min_exposure_s": self.EXPOSURE_RANGE_S[0], "max_exposure_s": self.EXPOSURE_RANGE_S[1],
                "min_iso": self.ISO_RANGE[0], "max_iso": self.ISO_RANGE[1]}

    async def _hal(self) -> None:
        """The camera HAL's call: hangs for ever while the mute_agent fault is on."""
        if self.mute_agent:
            await asyncio.Event().wait()

    async def move_lens(self, diopters: float) -> tuple[float, int]:
        """Drive the lens to ``diopters``; (LENS_FOCUS_DISTANCE, SENSOR_TIMESTAMP) once it is still."""
        await self._hal()
        travel = self.LENS_BASE_S + self.LENS_S_PER_DIOPTER * abs(diopters - self.lens_diopters)
        await asyncio.sleep(travel * self.lens_slowdown + self.LENS_SETTLE_S)
        self.lens_diopters = float(diopters)
        return self.lens_diopters, self._now_ns()

    async def expose(self, exposure_s: float) -> Still:
        """One still at the current focus; CaptureFailure while the fail_captures fault lasts."""
        await self._hal()
        loop = asyncio.get_running_loop()
        latency = max(self.CAPTURE_LATENCY_S + self._jitter.gauss(0.0, self.CAPTURE_JITTER_S), 0.005)
        await asyncio.sleep(latency)
        start = loop.time()
        if self.fail_captures > 0:
            self.fail_captures -= 1
            raise CaptureFailure("CameraCaptureSession.CaptureCallback.onCaptureFailed reason 0")
        pose = self.pose(start + exposure_s / 2) if self.pose is not None else None
        focus_diopters = self.lens_diopters
        await asyncio.sleep(exposure_s)
        jpeg = await loop.run_in_executor(None, self._picture, pose, focus_diopters, len(self.captures))
        await asyncio.sleep(self.ENCODE_S)
        still = Still(start, self.sensor_ns(start), exposure_s, focus_diopters, jpeg)
        self.captures.append({"start_s": start, "sensor_timestamp_ns": still.sensor_timestamp_ns,
                              "exposure_s": exposure_s, "focus_diopters": focus_diopters, "size": len(jpeg)})
        return still

    async def read_clock(self) -> int:
        """The sensor clock, read one (jittered) link delay after the request, answered one later."""
        await self._hal()
        await asyncio.sleep(self.LINK_DELAY_S * (1.0 + self._jitter.random()))
        device_ns = self._now_ns()
        await asyncio.sleep(self.LINK_DELAY_S * (1.0 + self._jitter.random()))
        return device_ns

    # ---------------------------------------------------------------- pictures
    def sharp_distance_mm(self, diopters: float) -> float:
        """Where the lens is sharpest (mm) at a commanded focus (diopters): this phone's true lens."""
        measured = self.focus_offset_diopters + self.focus_gain * diopters
        return 1000.0 / measured if measured > 1e-4 else 1e7

    def _image_size(self) -> tuple[int, int]:
        return self.render_size or (self.optics.image_width_px // 32, self.optics.image_height_px // 32)

    def _picture(self, pose: np.ndarray | None, focus_diopters: float, index: int) -> bytes:
        if self.picture_source is not None:
            rng = np.random.default_rng([self.seed, index, 0x5CE7E])
            picture = self.picture_source(pose, self.sharp_distance_mm(focus_diopters), rng)
            return encode_jpeg(picture if picture.ndim == 3 else np.repeat(picture[:, :, None], 3, axis=2))
        if self.board is not None:
            rng = np.random.default_rng([self.seed, index, 0xB0A2D])
            return encode_jpeg(self.board.picture(self.sharp_distance_mm(focus_diopters), self.optics, rng))
        width, height = self._image_size()
        if self.subject is None or pose is None or self.render_size is None:
            return encode_jpeg(empty_rig_picture(width, height, seed=index))
        if self._renderer is None:
            self._renderer = PhoneRenderer(_scene_for(self.subject, self.lesion_changes), self.optics, width, height)
        return encode_jpeg(self._renderer.render(pose, self.sharp_distance_mm(focus_diopters)))


def _agent_runtime(phone: SimulatedPhone, runtime: str, jar: Path | None) -> Any:
    if runtime == "python":
        return TwinRuntime(phone)
    if runtime == "jvm":
        return JvmRuntime(phone, jar)
    raise ValueError(f"agent_runtime {runtime!r}: one of {', '.join(AGENT_RUNTIMES)}")
