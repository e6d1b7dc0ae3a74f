"""The ADB area's exception tree: every error names the device (serial or address), its state and values.

Connection-level failures (:class:`ConnectionLost`, :class:`AuthRefused`) end the whole
:class:`~drivers.adb.connection.AdbConnection`; stream-level ones (:class:`StreamRefused`,
:class:`StreamClosed`, :class:`SyncFail`) end only the stream they happened on.
"""

from __future__ import annotations

from drivers.errors import DeviceGone


class AdbError(Exception):
    """Base of the ADB area's errors.

    Attributes:
        device: the phone's serial, or the transport's address before the handshake.
        state: the connection or stream state when the error happened, as text.
    """

    def __init__(self, device: str, state: str, message: str) -> None:
        self.device = device
        self.state = state
        super().__init__(f"{device} [{state}]: {message}")


class AdbProtocolError(AdbError):
    """A malformed message: bad magic, checksum, length, a command out of sequence, a WRTE beyond
    the stream's flow-control window, or an AUTH token of the wrong length."""


class ConnectionLost(AdbError, DeviceGone):
    """The transport closed or failed (cable pulled, adbd restarted, Wi-Fi dropped)."""


class AdbTimeout(AdbError):
    """The device did not answer within a class-constant timeout; names the wait and its limit."""

    def __init__(self, device: str, state: str, waiting_for: str, timeout_s: float) -> None:
        self.waiting_for = waiting_for
        self.timeout_s = timeout_s
        super().__init__(device, state, f"no {waiting_for} within {timeout_s:g} s")


class AuthRefused(AdbError):
    """The device refused both the signature and the public key (the phone user said no)."""


class StreamRefused(AdbError):
    """The device refused to open a service (no such service, agent not listening)."""

    def __init__(self, device: str, state: str, service: str) -> None:
        self.service = service
        super().__init__(device, state, f"service {service!r} refused")


class AdbLimitExceeded(AdbError):
    """The device sent more than a configured limit allows (command output, a file, a listing).

    The stream it arrived on is closed; the connection stays up. Attributes: what (the stream or
    path), limit (the configured bound) and unit.
    """

    def __init__(self, device: str, state: str, what: str, limit: int, unit: str = "bytes") -> None:
        self.what = what
        self.limit = limit
        self.unit = unit
        super().__init__(device, state, f"{what}: more than the limit of {limit} {unit}")


class StreamClosed(AdbError):
    """The peer closed a stream while it was still being written or read."""


class SyncFail(AdbError):
    """The sync service answered FAIL, or broke its own framing (path and reason named)."""

    def __init__(self, device: str, state: str, path: str, reason: str) -> None:
        self.path = path
        self.reason = reason
        super().__init__(device, state, f"sync on {path!r} failed: {reason}")


class KeyFileError(AdbError):
    """The host key files (adbkey / adbkey.pub) are missing, unreadable or malformed."""


class UsbDeviceNotFound(AdbError):
    """No USB device with an ADB interface (class 0xFF, subclass 0x42, protocol 0x01) matched."""
