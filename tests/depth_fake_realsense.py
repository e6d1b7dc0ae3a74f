"""A fake ``pyrealsense2`` at its API boundary, for the live RealSense driver tests (no camera here;
recordings are played back with the real pyrealsense2, tests/test_depth_playback.py).

``FakeRealSense`` holds scripted devices; ``module()`` builds the module object a
test injects as ``sys.modules["pyrealsense2"]``. Streaming runs on a thread, as librealsense's
does, calling the pipeline's frame callback; timestamps come from a device clock that runs from
an arbitrary origin. With an infrared stream enabled every frame comes in a frameset with the left
imager's Y8 picture (``infrared_image``), as a pipeline's syncer delivers them.
"""

from __future__ import annotations

import enum
import threading
import time
import types
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np


class stream(enum.Enum):  # noqa: N801 - pyrealsense2's spelling
    depth = 1
    color = 2
    infrared = 3


class format(enum.Enum):  # noqa: N801,A001
    z16 = 1
    rgb8 = 2
    y8 = 3


class option(enum.Enum):  # noqa: N801
    emitter_enabled = 1
    laser_power = 2


class camera_info(enum.Enum):  # noqa: N801
    serial_number = 1
    product_line = 2
    firmware_version = 3


class timestamp_domain(enum.Enum):  # noqa: N801
    hardware_clock = 0
    system_time = 1
    global_time = 2


@dataclass
class intrinsics:  # noqa: N801
    width: int
    height: int
    ppx: float
    ppy: float
    fx: float
    fy: float


@dataclass
class FakeDevice:
    """A scripted camera.

    frames: how many frames it delivers; stop_after: it goes silent after this many;
    period_s: real time between frames; device_ms0: its clock's reading at the first frame;
    device_period_ms: clock step per frame (None: follows real elapsed time).
    """

    serial: str
    depth_scale: float = 0.001
    intrinsics: intrinsics = field(default_factory=lambda: intrinsics(1280, 720, 641.5, 359.25, 912.0, 911.0))
    frames: int = 10
    stop_after: int | None = None
    period_s: float = 0.002
    device_ms0: float = 123_456.0
    device_period_ms: float | None = None
    domain: timestamp_domain = timestamp_domain.hardware_clock
    dtype: Any = np.uint16
    size: tuple[int, int] | None = None  # (height, width); None: as configured
    fail_start: str | None = None
    start_delay_s: float = 0.0
    options: set[option] = field(default_factory=lambda: {option.emitter_enabled, option.laser_power})
    infrared_missing: set[int] = field(default_factory=set)  # framesets that come without infrared
    stopped: threading.Event = field(default_factory=threading.Event)
    # what the driver asked for
    configured: list[tuple[Any, ...]] = field(default_factory=list)
    options_set: list[tuple[option, float]] = field(default_factory=list)
    delivered: int = 0

    def get_info(self, info: camera_info) -> str:
        return {camera_info.serial_number: self.serial, camera_info.product_line: "D400",
                camera_info.firmware_version: "5.16.0.1"}[info]

    def first_depth_sensor(self) -> FakeDevice:
        return self

    def get_depth_scale(self) -> float:
        return self.depth_scale

    def supports(self, which: option) -> bool:
        return which in self.options

    def set_option(self, which: option, value: float) -> None:
        if which not in self.options:
            raise RuntimeError(f"object doesn't support option #{which.value}")
        self.options_set.append((which, value))


class FakeDepthFrame:
    def __init__(self, number: int, device_ms: float, data: np.ndarray, domain: timestamp_domain):
        self._number, self._ms, self._data, self._domain = number, device_ms, data, domain

    def is_frameset(self) -> bool:
        return False

    def is_depth_frame(self) -> bool:
        return True

    def as_depth_frame(self) -> FakeDepthFrame:
        return self

    def __bool__(self) -> bool:
        return True

    def get_data(self) -> np.ndarray:
        return self._data

    def get_width(self) -> int:
        return self._data.shape[1]

    def get_height(self) -> int:
        return self._data.shape[0]

    def get_timestamp(self) -> float:
        return self._ms

    def get_frame_number(self) -> int:
        return self._number

    def get_frame_timestamp_domain(self) -> timestamp_domain:
        return self._domain


class FakeInfraredFrame(FakeDepthFrame):
    def is_depth_frame(self) -> bool:
        return False


class FakeNoFrame:
    """What a frameset hands out for a stream it does not hold: an empty frame, false."""

    def __bool__(self) -> bool:
        return False


class FakeFrameset:
    def __init__(self, depth: FakeDepthFrame, infrared: dict[int, FakeInfraredFrame] | None = None) -> None:
        self._depth = depth
        self._infrared = infrared or {}

    def is_frameset(self) -> bool:
        return True

    def as_frameset(self) -> FakeFrameset:
        return self

    def get_depth_frame(self) -> FakeDepthFrame:
        return self._depth

    def get_infrared_frame(self, index: int = 0) -> FakeInfraredFrame | FakeNoFrame:
        if index == 0:  # the SDK's "first infrared frame"
            return next(iter(self._infrared.values()), FakeNoFrame())
        return self._infrared.get(index, FakeNoFrame())


def depth_value(frame_number: int) -> int:
    """The depth (units) every pixel of scripted frame ``frame_number`` holds."""
    return 1000 + frame_number


def infrared_image(frame_number: int, height: int, width: int) -> np.ndarray:
    """(height, width) uint8 left infrared picture of scripted frame ``frame_number``: a ramp, every
    pixel and every frame different from its neighbours."""
    return ((np.arange(height * width) + 7 * frame_number) % 251).astype(np.uint8).reshape(height, width)


class FakeRealSense:
    """The scripted world behind the fake module: connected devices."""

    def __init__(self) -> None:
        self.devices: list[FakeDevice] = []
        self.contexts_made = 0
        self.contexts_destroyed = 0
        self.query_threads: list[str] = []  # the thread each query_devices() ran on

    def module(self) -> types.ModuleType:
        world = self
        rs = types.ModuleType("pyrealsense2")
        for enum_type in (stream, format, option, camera_info, timestamp_domain, intrinsics):
            setattr(rs, enum_type.__name__, enum_type)

        class context:  # noqa: N801
            def __init__(self) -> None:
                world.contexts_made += 1

            def __del__(self) -> None:  # librealsense joins its device watcher here (~100 ms, GIL held)
                world.contexts_destroyed += 1

            def query_devices(self) -> list[FakeDevice]:
                world.query_threads.append(threading.current_thread().name)
                return list(world.devices)

        class config:  # noqa: N801
            def __init__(self) -> None:
                self.serial: str | None = None
                self.streams: list[tuple[Any, ...]] = []

            def enable_device(self, serial: str) -> None:
                self.serial = serial

            def enable_stream(self, *args: Any) -> None:
                self.streams.append(args)

        class stream_profile:  # noqa: N801
            def __init__(self, device: FakeDevice) -> None:
                self._device = device

            def as_video_stream_profile(self) -> stream_profile:
                return self

            def get_intrinsics(self) -> intrinsics:
                return self._device.intrinsics

        class pipeline_profile:  # noqa: N801
            def __init__(self, device: FakeDevice) -> None:
                self._device = device

            def get_device(self) -> FakeDevice:
                return self._device

            def get_stream(self, kind: stream) -> stream_profile:
                assert kind is stream.depth
                return stream_profile(self._device)

        class pipeline:  # noqa: N801
            def __init__(self, ctx: Any = None) -> None:
                self._stop = threading.Event()
                self._thread: threading.Thread | None = None

            def start(self, cfg: config, callback: Callable[[Any], None]) -> pipeline_profile:
                device = next(d for d in world.devices if d.serial == cfg.serial)
                time.sleep(device.start_delay_s)  # opening the USB device takes a while
                if device.fail_start:
                    raise RuntimeError(device.fail_start)
                self._device = device
                device.configured = list(cfg.streams)
                self._thread = threading.Thread(target=self._run, args=(device, cfg, callback))
                self._thread.start()
                return pipeline_profile(device)

            def _run(self, device: FakeDevice, cfg: config, callback: Callable[[Any], None]) -> None:
                if device.size is not None:
                    height, width = device.size
                else:
                    _, width, height, _, _ = cfg.streams[0]
                buffer = np.zeros((height, width), dtype=device.dtype)  # reused, as the SDK does
                infrared = [s for s in cfg.streams if s[0] is stream.infrared]
                infrared_buffer = np.zeros((height, width), dtype=np.uint8)
                started = time.monotonic()
                for k in range(device.frames):
                    if device.stop_after is not None and k >= device.stop_after:
                        self._stop.wait()
                    if self._stop.is_set():
                        return
                    buffer[...] = depth_value(k)
                    step = device.device_period_ms
                    ms = device.device_ms0 + (k * step if step is not None
                                              else (time.monotonic() - started) * 1000.0)
                    frame = FakeDepthFrame(k, ms, buffer, device.domain)
                    if infrared:
                        infrared_buffer[...] = infrared_image(k, height, width)
                        index = infrared[0][1]
                        found = {} if k in device.infrared_missing else {
                            index: FakeInfraredFrame(k, ms, infrared_buffer, device.domain)}
                        callback(FakeFrameset(frame, found))
                    else:
                        callback(FakeFrameset(frame) if k % 2 else frame)
                    buffer[...] = 0  # the next use of the buffer overwrites the frame
                    infrared_buffer[...] = 0
                    device.delivered += 1
                    time.sleep(device.period_s)

            def stop(self) -> None:
                self._stop.set()
                if self._thread is not None:
                    self._thread.join()
                    self._device.stopped.set()

        rs.context, rs.config, rs.pipeline = context, config, pipeline
        return rs
