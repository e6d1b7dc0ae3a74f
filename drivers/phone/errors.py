"""The phone area's exception tree: every error names the phone (serial), its state and the values.

ADB-level failures are translated at the PhoneCamera boundary: a lost link becomes
:class:`PhoneDisconnected` (the original AdbError chained as its cause).
"""

from __future__ import annotations

from drivers.errors import DeviceGone


class PhoneError(Exception):
    """Base of the phone area's errors.

    Attributes:
        device: the phone's serial (or a calibration file's path for table errors).
        state: the camera's state when the error happened, as text.
    """

    def __init__(self, device: str, state: str, message: str) -> None:
        self.device = device
        self.state = state
        super().__init__(f"{device} [{state}]: {message}")


class PhoneDisconnected(PhoneError, DeviceGone):
    """The ADB link or the agent's stream dropped, or the phone cannot be reached."""


class PhoneUnauthorized(PhoneDisconnected):
    """The phone refused this host's ADB key: accept it on the phone ("Allow USB debugging")."""


class WrongPhone(PhoneError):
    """The device on this link reports another serial than the rig file's phone."""


class AgentMissing(PhoneError):
    """The capture agent is neither on the phone nor available locally to push."""


class AgentStartFailed(PhoneError):
    """app_process did not report the agent listening (its output is quoted)."""


class AgentProtocolError(PhoneError):
    """A line from (or to) the capture agent breaks the JSON-lines protocol."""


class AgentError(PhoneError):
    """The agent answered a request with an error code (docs/capture-agent-protocol.md)."""

    def __init__(self, device: str, state: str, code: str, message: str, op: str = "") -> None:
        self.code = code
        self.op = op
        super().__init__(device, state, f"{op or 'request'} failed: {code}: {message}")


class CaptureFailed(AgentError):
    """The camera could not take the picture (CAPTURE_FAILED, CAMERA_ERROR, STORAGE_FULL...)."""


class FocusFailed(AgentError):
    """The agent could not set the lens (FOCUS_* codes)."""


class RequestTimeout(PhoneError):
    """No answer to an agent request within its class-constant timeout."""

    def __init__(self, device: str, state: str, op: str, timeout_s: float) -> None:
        self.op = op
        self.timeout_s = timeout_s
        super().__init__(device, state, f"no answer to {op!r} within {timeout_s:g} s")


class FocusTimeout(RequestTimeout):
    """The lens did not report stationary in time."""


class CaptureTimeout(RequestTimeout):
    """The capture did not complete in time."""


class PullFailed(PhoneError):
    """The sync service refused or broke a pull (path and reason named)."""


class FocusCalibrationError(PhoneError):
    """A focus table file is malformed: device = the file, names the key and the problem."""

    def __init__(self, path: str, key: str, problem: str) -> None:
        self.path = path
        self.key = key
        self.problem = problem
        super().__init__(path, "calibration", f"{key}: {problem}")


class FocusOutOfRange(PhoneError):
    """A focus distance outside what the phone's calibrated lens range can reach."""

    def __init__(self, device: str, state: str, focus_mm: float, near_mm: float, far_mm: float) -> None:
        self.focus_mm = focus_mm
        self.near_mm = near_mm
        self.far_mm = far_mm
        super().__init__(device, state,
                         f"focus {focus_mm:.1f} mm outside the calibrated range [{near_mm:.1f}, {far_mm:.1f}] mm")
