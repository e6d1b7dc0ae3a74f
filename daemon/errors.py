"""The daemon's exception tree: every error the daemon raises derives from :class:`DaemonError`.

Here: scan sequencing, capture and safety errors. Elsewhere in the daemon, under the same root:
the scan store's ``StoreError`` (daemon/records/atomic.py: ``StoreFull``, ``StoreWriteError``,
``ManifestError``, ``ScanFileError``, ``ImagePullFailed``, ``VerifyFailed``), the control API's
``ControlError`` (daemon/server/control.py) and ``ClockSyncError`` (daemon/rig/clocksync.py).
Driver errors (``DriveError``, ``PhoneError``, ``AdbError``...) keep their own trees; the daemon
wraps them only where it adds the scan state, and always keeps the original as ``__cause__``.
"""

from __future__ import annotations

from collections.abc import Sequence

from daemon.faults import Cause, FaultCause


class DaemonError(Exception):
    """Base of every error the daemon itself raises."""


class IllegalTransition(DaemonError):
    """The scan state machine was asked for a transition its table does not allow."""

    def __init__(self, current: str, requested: str, cause: str | Cause) -> None:
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


class ScanRefused(DaemonError):
    """A scan could not be started: its folder cannot be created (store full, missing or not
    writable, a malformed scan id). Nothing was started and nothing is left on disk; the store's
    error is the ``__cause__``."""

    def __init__(self, scan_id: object, reason: str) -> None:
        self.scan_id = scan_id
        self.reason = reason
        super().__init__(f"scan not started: {reason}")


class DevicesMissing(DaemonError):
    """Devices of the rig did not answer at bring-up; names each with its address and what to check."""

    def __init__(self, summary: str) -> None:
        self.summary = summary
        super().__init__(summary)


class CalibrationRefused(ScanRefused):
    """The installed calibration cannot be used: unreadable, or for other cameras than the rig's."""

    def __init__(self, scan_id: object, path: str, reason: str) -> None:
        self.path = path
        super().__init__(scan_id, f"calibration {path}: {reason}")


class FaultLatched(DaemonError):
    """The rig is in a latched FAULT; only an explicit reset clears it."""

    def __init__(self, causes: Sequence[FaultCause]) -> None:
        self.causes = list(causes)
        super().__init__("rig fault latched (reset required): " + "; ".join(map(str, self.causes)))


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


class PhoneDropped(CaptureMissed):
    """A pose not tried: its phone was dropped for the rest of the scan after failing
    ``failures`` captures in a row (``why``: the first error of that run)."""

    def __init__(self, camera: str, angle_index: int, angle_deg: float, failures: int, why: str) -> None:
        self.failures = failures
        self.why = why
        super().__init__(camera, angle_index, angle_deg,
                         f"phone dropped after {failures} failed captures in a row (first: {why})")
