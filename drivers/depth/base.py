"""Depth frame type and the protocol every depth camera backend implements.

Real (RealSense, bag playback) and simulated cameras all yield ``DepthFrame`` objects stamped on the
host event-loop clock, so the sweep can tag each frame with the beam angle from the motor trace.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import AsyncIterator, Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class DepthFrame:
    """One depth image.

    depth: (H, W) uint16 in units of ``depth_unit_mm``; 0 means no measurement (hole).
    timestamp_s: host event-loop clock when the frame arrived.
    device_timestamp_ms: the camera's own clock (for diagnostics, not for tagging).
    intrinsics: (3, 3) pinhole K in pixels for this image.
    beam_angle_deg: the beam angle recorded with the frame when it is played back from a sweep
        recording (the sweep poses it there); None for a live camera, whose frame the sweep tags
        with the live encoder's angle at ``timestamp_s``.
    infrared: (H, W) uint8, the left infrared imager's picture, pixel-aligned with ``depth`` (the
        depth image is in the left imager's frame, so ``intrinsics`` are its intrinsics too); None
        unless the camera was started with ``infrared`` on.
    """

    camera_id: str
    frame_number: int
    timestamp_s: float
    device_timestamp_ms: float
    depth: np.ndarray
    depth_unit_mm: float
    intrinsics: np.ndarray
    beam_angle_deg: float | None = None
    infrared: np.ndarray | None = None

    def depth_mm(self) -> np.ndarray:
        """(H, W) float32 depth in mm, 0 where there is no measurement."""
        return self.depth.astype(np.float32) * np.float32(self.depth_unit_mm)


@runtime_checkable
class DepthCamera(Protocol):
    """A streaming depth camera: start it, iterate frames, stop it.

    A live camera's ``frames()`` ends only after ``stop()``; a recording's also ends at its end.

    infrared: set before ``start()``. When True every frame carries ``infrared`` (the left infrared
    imager's picture, for calibration) and the projector (emitter) is switched off so its pattern
    does not cover the target; a camera that cannot stream infrared raises InfraredUnavailable
    from ``start()``.
    """

    id: str
    infrared: bool

    async def start(self) -> None:
        """Open the device and start streaming."""
        ...

    def frames(self) -> AsyncIterator[DepthFrame]:
        """Frames in arrival order, stamped on the event-loop clock."""
        ...

    async def stop(self) -> None:
        """Stop streaming and release the device (idempotent)."""
        ...
