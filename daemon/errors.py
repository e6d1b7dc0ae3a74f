"""The daemon's exception tree: scan sequencing, capture and safety errors.

Driver errors (``DriveError``, ``PhoneError``, ``AdbError``...) keep their own trees; the daemon
wraps them only where it adds the scan state, and always keeps the original as ``__cause__``.
"""

from __future__ import annotations

from collections.abc import Sequence


class DaemonError(Exception):
    """Base of every error the daemon itself raises."""


class IllegalTransition(DaemonError):
    """The scan state machine was asked for a transition its table does not allow."""

    def __init__(self, current: str, requested: str, cause: str) -> None:
        self.current = current
        self.requested = requested
        self.cause = cause
        super().__init__(
            f"scan state machine: transition {current} -> {requested} is not allowed (cause: {cause})"
        )


class ScanBusy(DaemonError):
    """A scan was requested while another one runs or a fault is latched."""

    def __init__(self, state: str, reason: str) -> None:
        self.state = state
        self.reason = reason
        super().__init__(f"cannot start a scan in state {state}: {reason}")


class FaultLatched(DaemonError):
    """The rig is in a latched FAULT; only an explicit reset clears it."""

    def __init__(self, causes: Sequence[str]) -> None:
        self.causes = list(causes)
        super().__init__("rig fault latched (reset required): " + "; ".join(self.causes))


class ScanAborted(DaemonError):
    """The operator (stop button or control API) aborted the scan; captured data is kept."""

    def __init__(self, state: str, cause: str) -> None:
        self.state = state
        self.cause = cause
        super().__init__(f"scan aborted in state {state}: {cause}")


class SafetyTrip(DaemonError):
    """A safety source (e-stop, drive fault, lost heartbeat, panel lost) tripped during a scan."""

    def __init__(self, source: str, detail: str) -> None:
        self.source = source
        self.detail = detail
        super().__init__(f"safety trip from {source}: {detail}")


class BeamTimeout(DaemonError):
    """The beam did not reach an angle in the time the motion profile allows."""

    def __init__(self, device: str, target_deg: float, angle_deg: float | None, timeout_s: float) -> None:
        self.device = device
        self.target_deg = target_deg
        self.angle_deg = angle_deg
        self.timeout_s = timeout_s
        now = "no encoder sample" if angle_deg is None else f"at {angle_deg:.3f} deg"
        super().__init__(
            f"{device}: beam did not reach {target_deg:.3f} deg within {timeout_s:g} s ({now})"
        )


class SweepFailed(DaemonError):
    """The depth sweep produced too few frames or none from a camera."""

    def __init__(self, camera: str, frames: int, needed: int) -> None:
        self.camera = camera
        self.frames = frames
        self.needed = needed
        super().__init__(f"depth camera {camera}: {frames} frames in the sweep, needed {needed}")


class CaptureMissed(DaemonError):
    """One pose was not captured at its angle (phone error, lens late, beam already past)."""

    def __init__(self, camera: str, angle_index: int, angle_deg: float, reason: str) -> None:
        self.camera = camera
        self.angle_index = angle_index
        self.angle_deg = angle_deg
        self.reason = reason
        super().__init__(f"{camera}: capture at angle {angle_index} ({angle_deg:.2f} deg) missed: {reason}")
