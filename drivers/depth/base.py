"""Depth frame type, the protocol every depth camera backend implements, and how one is found.

Real (RealSense, bag playback) and simulated cameras all yield ``DepthFrame`` objects stamped on the
host event-loop clock, so the sweep can tag each frame with the beam angle from the motor trace.
A :class:`DepthSource` says where the hardware file finds a camera, and a kind's
:class:`DepthFinder` tells whether it is there without streaming from it
(drivers/depth/kinds.py lists the kinds).
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

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


@dataclass(frozen=True)
class DepthSource:
    """Where the hardware file finds one rig depth camera: its kind (drivers/depth/kinds.py), its
    serial (the rig file's) and, for a kind that plays a file, the file."""

    kind: str
    serial: str
    path: Path | None = None

    @property
    def address(self) -> str:
        return f"{self.kind}:{self.serial if self.path is None else self.path}"


class DepthFinder(Protocol):
    """Tells whether a depth camera is there, without streaming from it (the bring-up's re-probes,
    ``tbp check``); one per kind for the daemon's life."""

    async def find(self, camera_id: str, source: DepthSource) -> str:
        """The camera's identity in words; a :class:`~drivers.depth.errors.DepthCameraError` naming
        ``camera_id`` when it cannot be found."""
        ...

    async def close(self) -> None:
        """Release what the finder holds (a probe process); idempotent."""
        ...
