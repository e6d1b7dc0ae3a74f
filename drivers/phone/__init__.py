"""Phone cameras: the capture agent's protocol, focus calibration tables and PhoneCamera over ADB."""

from drivers.phone.camera import CaptureDone, ClockSample, FocusDone, PhoneCamera, PhoneInfo
from drivers.phone.errors import (
    AgentError,
    AgentMissing,
    AgentProtocolError,
    AgentStartFailed,
    CaptureFailed,
    CaptureTimeout,
    FocusCalibrationError,
    FocusFailed,
    FocusOutOfRange,
    FocusTimeout,
    PhoneDisconnected,
    PhoneError,
    PhoneUnauthorized,
    PullFailed,
    RequestTimeout,
    WrongPhone,
)
from drivers.phone.focus import FocusCalibration, load_focus_calibration

__all__ = [
    "AgentError", "AgentMissing", "AgentProtocolError", "AgentStartFailed", "CaptureDone", "CaptureFailed",
    "CaptureTimeout", "ClockSample", "FocusCalibration", "FocusCalibrationError", "FocusDone", "FocusFailed",
    "FocusOutOfRange", "FocusTimeout", "PhoneCamera", "PhoneDisconnected", "PhoneError", "PhoneInfo",
    "PhoneUnauthorized", "PullFailed", "RequestTimeout", "WrongPhone", "load_focus_calibration",
]
