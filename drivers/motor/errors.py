"""The motor area's exception tree: every error names the device, its CiA 402 state and the values.

Faults that the drive reports (EMCY) or that the host detects (lost heartbeat) are latched by
:class:`~drivers.motor.drive.BeamDrive` until ``reset_fault()`` and raised again by every call that
waits on the drive, so a fault can never be missed by a caller that was busy elsewhere.
"""

from __future__ import annotations

from drivers.errors import DeviceGone
from drivers.motor.emcy import emcy_meaning
from drivers.motor.sdo_aborts import abort_meaning


class DriveError(Exception):
    """Base of the motor area's errors.

    Attributes:
        device: the drive's name (``beam``) or the CAN port's name.
        state: the CiA 402 state (or port state) when the error happened, as text.
    """

    def __init__(self, device: str, state: str, message: str) -> None:
        self.device = device
        self.state = state
        super().__init__(f"{device} [{state}]: {message}")


class CanBusError(DriveError, DeviceGone):
    """The CAN port is closed or the bus interface failed (device = port name)."""


class SdoError(DriveError):
    """An SDO transfer failed."""


class SdoAbort(SdoError):
    """The server answered an SDO request with an abort code (CiA 301 section 7.2.4.3.17)."""

    def __init__(self, device: str, state: str, index: int, subindex: int, code: int) -> None:
        self.index = index
        self.subindex = subindex
        self.code = code
        super().__init__(
            device,
            state,
            f"SDO abort 0x{code:08X} ({abort_meaning(code)}) on 0x{index:04X}:{subindex}",
        )


class SdoTimeout(SdoError):
    """No SDO response arrived within the client's timeout."""

    def __init__(self, device: str, state: str, index: int, subindex: int, timeout_s: float) -> None:
        self.index = index
        self.subindex = subindex
        self.timeout_s = timeout_s
        super().__init__(
            device, state, f"no SDO response for 0x{index:04X}:{subindex} within {timeout_s:g} s"
        )


class SdoProtocolError(SdoError):
    """The server's SDO response was malformed or did not match the request."""


class DriveFault(DriveError):
    """The drive reported a fault with an EMCY message (or its statusword shows FAULT).

    Attributes:
        code: the EMCY error code (u16), None when the statusword showed FAULT without any EMCY.
        meaning: the code's meaning from CiA 301 / CiA 402.
        register: the error register byte (0x1001) sent with the EMCY.
    """

    def __init__(self, device: str, state: str, code: int | None, register: int = 0) -> None:
        self.code = code
        self.register = register
        self.meaning = emcy_meaning(code) if code is not None else "statusword FAULT without EMCY"
        shown = f"0x{code:04X}" if code is not None else "none"
        super().__init__(
            device, state, f"drive fault, EMCY code {shown} ({self.meaning}), register 0x{register:02X}"
        )


class FollowingError(DriveFault):
    """The drive stopped because its position lagged the demand beyond the window (EMCY 0x8611)."""


class HeartbeatLost(DriveError, DeviceGone):
    """The drive's heartbeat did not arrive within the consumer time."""

    def __init__(self, device: str, state: str, silent_s: float, timeout_s: float) -> None:
        self.silent_s = silent_s
        self.timeout_s = timeout_s
        super().__init__(device, state, f"no heartbeat for {silent_s:.3f} s (consumer time {timeout_s:g} s)")


class HostStalled(DriveError):
    """The host's event loop did not run for longer than the rig allows: the drive guard quick-stopped
    the beam and stopped the host heartbeat (drivers/motor/guard.py)."""

    def __init__(self, device: str, state: str, stalled_s: float, limit_s: float) -> None:
        self.stalled_s = stalled_s
        self.limit_s = limit_s
        super().__init__(device, state, f"the host's event loop did not run for {stalled_s:.3f} s "
                                        f"(limit {limit_s:g} s): quick stop sent, host heartbeat stopped")


class DriveRebooted(DriveError):
    """The drive sent a boot-up message while connected: it reset and lost its configuration."""


class StateTransitionTimeout(DriveError):
    """The drive did not reach the requested CiA 402 state (or motion goal) in time."""

    def __init__(
        self, device: str, state: str, goal: str, controlword: int, statusword: int, timeout_s: float
    ) -> None:
        self.goal = goal
        self.controlword = controlword
        self.statusword = statusword
        self.timeout_s = timeout_s
        super().__init__(
            device,
            state,
            f"did not reach {goal} within {timeout_s:g} s after controlword 0x{controlword:04X} "
            f"(statusword 0x{statusword:04X})",
        )


class NmtTimeout(DriveError):
    """The drive did not answer an NMT command (no boot-up after a reset, no first TPDO)."""


class NmtStateLost(DriveError):
    """The drive's heartbeat says it left OPERATIONAL (another master, or its CAN error
    behaviour): its PDOs, and so the position stream, have stopped."""


class FrameError(DriveError):
    """A frame from the drive does not fit the configured protocol (PDO length, statusword)."""


class MotionInterrupted(DriveError):
    """A move ended short of its target: halted by stop() or by a quick stop."""


class DriveSettingError(DriveError):
    """The drive does not hold a value the rig requires of it (docs/motor.md lists them):
    bring-up stops there, because such a drive would not stop by itself when the host dies.

    Attributes:
        index, subindex: the object.
        setting: what the object is (``abort connection option code``).
        required: the value the rig writes.
    """

    def __init__(self, device: str, state: str, index: int, subindex: int, setting: str, required: int,
                 problem: str) -> None:
        self.index = index
        self.subindex = subindex
        self.setting = setting
        self.required = required
        super().__init__(device, state, f"{setting} 0x{index:04X}:{subindex} = {required}: {problem}")


class SettingRefused(DriveSettingError):
    """The drive answered the write (or its read-back) of a required setting with an SDO abort."""

    def __init__(self, device: str, state: str, index: int, subindex: int, setting: str, required: int,
                 code: int) -> None:
        self.code = code
        super().__init__(device, state, index, subindex, setting, required,
                         f"refused with SDO abort 0x{code:08X} ({abort_meaning(code)})")


class SettingMismatch(DriveSettingError):
    """The drive accepted a required setting but reads back another value."""

    def __init__(self, device: str, state: str, index: int, subindex: int, setting: str, written: int,
                 read: int) -> None:
        self.written = written
        self.read = read
        super().__init__(device, state, index, subindex, setting, written, f"written, but reads back {read}")


class DriveNotReady(DriveError):
    """A command needs another state (enabled, connected, stationary) than the drive is in."""


class MotionLimitError(DriveError):
    """A requested speed or acceleration is outside the rig's motor limits."""
