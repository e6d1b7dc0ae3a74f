"""Depth camera errors: one tree, each naming the camera and the values involved."""

from __future__ import annotations


class DepthCameraError(Exception):
    """Base of every depth camera failure; names the camera."""

    def __init__(self, camera_id: str, problem: str) -> None:
        self.camera_id = camera_id
        self.problem = problem
        super().__init__(f"depth camera {camera_id}: {problem}")


class DepthStreamStalled(DepthCameraError):
    """A streaming camera delivered no frame within the timeout, or its stream ended early."""

    def __init__(self, camera_id: str, frames: int, waited_s: float | None) -> None:
        self.frames, self.waited_s = frames, waited_s
        if waited_s is None:
            problem = f"stream ended after {frames} frames while the sweep was still running"
        else:
            problem = f"no frame for {waited_s:.2f} s after {frames} frames"
        super().__init__(camera_id, problem)


class RecordingUnreadable(DepthCameraError):
    """A depth recording or its beam-angle file is missing, malformed or does not match."""

    def __init__(self, camera_id: str, path: object, problem: str) -> None:
        self.path = str(path)
        super().__init__(camera_id, f"{path}: {problem}")


class InfraredUnavailable(DepthCameraError):
    """A camera asked for its infrared image cannot stream one (why: ``reason``)."""

    def __init__(self, camera_id: str, reason: str) -> None:
        self.reason = reason
        super().__init__(camera_id, f"no infrared stream: {reason}")
