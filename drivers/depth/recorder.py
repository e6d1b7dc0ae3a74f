"""Write depth frames into a RealSense recording with pyrealsense2's own software device and recorder.

The file is what librealsense itself records from a camera (a ROS2 bag, ``.db3``, since SDK
2.58), so playback goes through exactly the SDK path a recording from the rig's cameras takes.
Used to record the simulated depth cameras (``tbp depth record --sim``) for bench and
hardware-in-the-loop tests. The recording is written under a temporary name and renamed when
complete, so its path never holds half a recording.

The SDK stamps each message with the wall-clock time it was written, and real-time playback
paces frames by those stamps; frames written faster than the camera's rate therefore replay
correctly only with real time off (``BagPlayback``'s default for a recording with beam angles).
"""

from __future__ import annotations

import gc
import os
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from drivers.depth.errors import RecordingUnreadable
from drivers.depth.realsense import import_pyrealsense2

SUFFIX = ".db3"
DEVICE_NAME = "tbp-rig recorded depth camera"


class DepthRecorder:
    """One depth stream into ``path`` (must end in ``.db3``): ``with DepthRecorder(...) as r: r.write(...)``.

    width, height: pixels; intrinsics: (3, 3) pinhole K in pixels; depth_unit_mm: mm per depth
    unit; fps: the stream's nominal rate (metadata: the frames' own timestamps give their spacing);
    serial: reported as the recorded device's serial number.
    """

    def __init__(self, path: Path | str, *, camera_id: str, width: int, height: int,
                 intrinsics: np.ndarray, depth_unit_mm: float, fps: float, serial: str = "") -> None:
        self.path = Path(path)
        if self.path.suffix != SUFFIX:
            raise RecordingUnreadable(camera_id, self.path, f"pyrealsense2 records ROS2 bags: the name must end "
                                      f"in {SUFFIX}")
        self.camera_id = camera_id
        self.width, self.height = int(width), int(height)
        self.intrinsics = np.asarray(intrinsics, dtype=float)
        self.depth_unit_mm = float(depth_unit_mm)
        self.fps = fps
        self.serial = serial
        self.frames_written = 0
        self._partial = self.path.with_name(f".{self.path.stem}.partial{SUFFIX}")
        self._parts: dict[str, Any] = {}

    def __enter__(self) -> DepthRecorder:
        self.open()
        return self

    def __exit__(self, kind: type[BaseException] | None, *_: object) -> None:
        self.close(keep=kind is None)

    def open(self) -> None:
        """Create the software camera and start recording it."""
        rs = import_pyrealsense2(self.camera_id)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._partial.unlink(missing_ok=True)
        device = rs.software_device()
        device.register_info(rs.camera_info.name, DEVICE_NAME)
        device.register_info(rs.camera_info.serial_number, self.serial or self.camera_id)
        sensor = device.add_sensor("Stereo Module")
        profile = sensor.add_video_stream(self._stream(rs), True)
        sensor.add_read_only_option(rs.option.depth_units, self.depth_unit_mm / 1000.0)
        recorder = rs.recorder(str(self._partial), device)
        sensor.open(profile)
        sensor.start(lambda _frame: None)
        self._parts = {"rs": rs, "device": device, "sensor": sensor, "recorder": recorder,
                       "profile": profile.as_video_stream_profile()}

    def _stream(self, rs: ModuleType) -> Any:
        k = self.intrinsics
        intrinsics = rs.intrinsics()
        intrinsics.width, intrinsics.height = self.width, self.height
        intrinsics.fx, intrinsics.fy, intrinsics.ppx, intrinsics.ppy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
        intrinsics.model = rs.distortion.none
        intrinsics.coeffs = [0.0] * 5
        stream = rs.video_stream()
        stream.type, stream.index, stream.uid = rs.stream.depth, 0, 0
        stream.width, stream.height, stream.fps = self.width, self.height, int(round(self.fps))
        stream.bpp, stream.fmt, stream.intrinsics = 2, rs.format.z16, intrinsics
        return stream

    def write(self, frame_number: int, device_ms: float, depth: np.ndarray) -> None:
        """Record one (H, W) uint16 depth image stamped ``device_ms`` on the camera's clock."""
        if not self._parts:
            raise RecordingUnreadable(self.camera_id, self.path, "write() before open() or after close()")
        if depth.dtype != np.uint16 or depth.shape != (self.height, self.width):
            raise RecordingUnreadable(self.camera_id, self.path, f"frame {frame_number} is {depth.dtype} "
                                      f"{depth.shape}, the stream is uint16 ({self.height}, {self.width})")
        rs = self._parts["rs"]
        frame = rs.software_video_frame()
        frame.pixels = np.ascontiguousarray(depth)
        frame.stride, frame.bpp = self.width * 2, 2
        frame.timestamp = float(device_ms)
        frame.domain = rs.timestamp_domain.hardware_clock
        frame.frame_number = int(frame_number)
        frame.profile = self._parts["profile"]
        frame.depth_units = self.depth_unit_mm / 1000.0
        self._parts["sensor"].on_video_frame(frame)
        self.frames_written += 1

    def close(self, *, keep: bool = True) -> None:
        """Finish the file (the SDK writes it out when its recorder is released); rename it into place."""
        parts, self._parts = self._parts, {}
        if not parts:
            return
        sensor = parts.pop("sensor")
        sensor.stop()
        sensor.close()
        del sensor
        parts.clear()
        gc.collect()  # the recorder's destructor closes the bag; nothing else may still hold it
        if keep and self.frames_written:
            os.replace(self._partial, self.path)
        else:
            self._partial.unlink(missing_ok=True)
