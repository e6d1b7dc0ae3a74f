"""Why a scan stopped or the rig latched FAULT: typed causes, not sentences.

A cause names where it came from (an enum member), the device and the detail in words. Its
text (``device: detail``) is what a person reads in the logs, ``tbp status`` and the manifest,
beside the typed fields a program can match on.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Any, Self


class FaultSource(enum.Enum):
    """What latched a safety fault (the beam stops; only an operator reset clears it)."""

    ESTOP = "estop"
    """The panel's emergency stop was pressed."""
    PANEL_LOST = "panel_lost"
    """The panel's heartbeat stopped: the e-stop's state is unknown."""
    PANEL = "panel"
    """The panel did not take a command (status light, subject lights)."""
    DRIVE_FAULT = "drive_fault"
    """The drive reported a fault (EMCY, fault bit, its heartbeat from the host lost)."""
    DRIVE_ERROR = "drive_error"
    """A drive command failed (start-up, a scan step, the controlled stop of an abort)."""
    ENCODER_STALLED = "encoder_stalled"
    """No encoder sample while the beam was expected to move."""
    HOST_STALLED = "host_stalled"
    """The daemon's event loop stood still too long: the drive guard quick-stopped the beam."""
    SHUTDOWN = "shutdown"
    """A shutdown handler (quick stop, fault light) failed during a trip."""
    SCAN_FAILED = "scan_failed"
    """Closing a scan raised (e.g. too many open files): the rig stops and says why."""


class AbortSource(enum.Enum):
    """What stopped a scan without latching a fault (the beam decelerates, images are kept)."""

    STOP_BUTTON = "stop_button"
    """The panel's stop button."""
    CONTROL_API = "control_api"
    """``tbp abort`` (the control API)."""
    DAEMON_STOPPING = "daemon_stopping"
    """The daemon was asked to stop (systemd stop, Ctrl-C)."""
    STORE = "store"
    """The scan store cannot take more (disk full); images not pulled stay on the phones."""
    SCAN_ERROR = "scan_error"
    """A scan step raised a typed error (a depth camera stalled, the plan is infeasible...)."""


@dataclass(frozen=True)
class Cause:
    """Where a stop came from, the device involved and what happened, in words."""

    source: FaultSource | AbortSource
    device: str
    detail: str

    @property
    def text(self) -> str:
        return f"{self.device}: {self.detail}"

    def __str__(self) -> str:
        return self.text

    def as_dict(self) -> dict[str, str]:
        return {"source": self.source.value, "device": self.device, "detail": self.detail,
                "text": self.text}

    @classmethod
    def of_error(cls, source: Any, device: str, error: BaseException, context: str = "") -> Self:
        """A cause whose detail is the error's type and message (after ``context``, if any)."""
        described = f"{type(error).__name__}: {error}"
        return cls(source, device, f"{context}: {described}" if context else described)

    @staticmethod
    def from_dict(data: dict[str, Any]) -> Cause:
        """The cause :meth:`as_dict` wrote (a :class:`FaultCause` or an :class:`AbortCause`)."""
        value = data["source"]
        if value in _FAULT_VALUES:
            return FaultCause(FaultSource(value), str(data["device"]), str(data["detail"]))
        return AbortCause(AbortSource(value), str(data["device"]), str(data["detail"]))


@dataclass(frozen=True)
class FaultCause(Cause):
    """The cause of a latched safety fault."""

    source: FaultSource


@dataclass(frozen=True)
class AbortCause(Cause):
    """The cause of an aborted scan."""

    source: AbortSource


_FAULT_VALUES = frozenset(s.value for s in FaultSource)
