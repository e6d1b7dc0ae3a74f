"""Errors of the shape estimate (depth sweep tagging and TSDF): one tree, each naming the values involved."""

from __future__ import annotations

from planner.picklable import PicklableError


class ShapeEstimateError(PicklableError):
    """Base of every depth-sweep and TSDF refusal."""


class FrameOutsideTrace(ShapeEstimateError):
    """A depth frame's timestamp lies outside the recorded beam trace, so its angle is unknown."""

    def __init__(self, camera_id: str, frame_number: int, time_s: float, start_s: float, end_s: float) -> None:
        self.camera_id, self.frame_number, self.time_s = camera_id, frame_number, time_s
        self.start_s, self.end_s = start_s, end_s
        super().__init__(
            f"depth camera {camera_id} frame {frame_number} at t={time_s:.4f} s is outside the beam "
            f"trace [{start_s:.4f}, {end_s:.4f}] s; its beam angle cannot be interpolated"
        )


class BadTrace(ShapeEstimateError):
    """The beam position trace cannot be interpolated (too short, times not increasing, not finite)."""


class UnknownDepthCamera(ShapeEstimateError):
    """A frame names a depth camera that the rig file does not describe."""

    def __init__(self, camera_id: str, known: list[str]) -> None:
        self.camera_id, self.known = camera_id, known
        super().__init__(f"frame from depth camera {camera_id!r}, rig knows {', '.join(known)}")


class TooFewFrames(ShapeEstimateError):
    """Not enough frames with depth to fuse a reliable shape."""

    def __init__(self, usable: int, needed: int, per_camera: dict[str, int]) -> None:
        self.usable, self.needed, self.per_camera = usable, needed, per_camera
        detail = ", ".join(f"{k}: {v}" for k, v in sorted(per_camera.items())) or "no frames"
        super().__init__(f"{usable} usable depth frames, need at least {needed} ({detail})")


class NoSubject(ShapeEstimateError):
    """Nothing but floor (or nothing at all) inside the scan volume."""

    def __init__(self, detail: str) -> None:
        self.detail = detail
        super().__init__(f"no subject in the scan volume: {detail}")


class SubjectTouchesBoundary(ShapeEstimateError):
    """The subject reaches the scan volume's side or top, so part of the body may be cut off."""

    def __init__(self, where: str, angle_deg: float, height_mm: float, radius_mm: float, limit_mm: float) -> None:
        self.where, self.angle_deg, self.height_mm = where, angle_deg, height_mm
        self.radius_mm, self.limit_mm = radius_mm, limit_mm
        super().__init__(
            f"subject touches the scan volume's {where} at azimuth {angle_deg:.0f} deg, height "
            f"{height_mm:.0f} mm (radius {radius_mm:.0f} mm; limit {limit_mm:.0f} mm): ask the "
            f"subject to stand on the marks with arms closer to the body"
        )


class SubjectTooCloseToCameras(ShapeEstimateError):
    """Skin within the clearance of the ring the phones ride on: the beam must not start."""

    def __init__(self, angle_deg: float, height_mm: float, radius_mm: float, ring_mm: float, clearance_mm: float) -> None:
        self.angle_deg, self.height_mm, self.radius_mm = angle_deg, height_mm, radius_mm
        self.ring_mm, self.clearance_mm = ring_mm, clearance_mm
        super().__init__(
            f"subject reaches {radius_mm:.0f} mm from the axis at azimuth {angle_deg:.0f} deg, height "
            f"{height_mm:.0f} mm: within {clearance_mm:.0f} mm of the camera ring ({ring_mm:.0f} mm); "
            f"ask the subject to stand on the marks with the arms closer to the body"
        )


class ImplausibleSubject(ShapeEstimateError):
    """The reconstructed subject is too small or too large to be a person."""

    def __init__(self, quantity: str, value_mm: float, low_mm: float, high_mm: float) -> None:
        self.quantity, self.value_mm, self.low_mm, self.high_mm = quantity, value_mm, low_mm, high_mm
        super().__init__(
            f"reconstructed subject {quantity} {value_mm:.0f} mm is outside the range of a person "
            f"[{low_mm:.0f}, {high_mm:.0f}] mm"
        )
