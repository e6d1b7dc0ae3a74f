"""The project's own ADB client: wire framing, host key and AUTH, streams, shell, sync, transports.

Transports: TCP and any asyncio reader/writer pair (drivers/adb/transport.py), USB bulk
endpoints through pyusb (drivers/adb/usb.py, real hardware only).
"""

from drivers.adb.auth import AdbKey
from drivers.adb.connection import AdbConnection, DeviceBanner
from drivers.adb.errors import (
    AdbError,
    AdbLimitExceeded,
    AdbProtocolError,
    AdbTimeout,
    AuthRefused,
    ConnectionLost,
    KeyFileError,
    StreamClosed,
    StreamRefused,
    SyncFail,
    UsbDeviceNotFound,
)
from drivers.adb.streams import AdbStream
from drivers.adb.sync import SyncClient, SyncStat
from drivers.adb.transport import AdbTransport, SocketTransport, StreamTransport, open_tcp
from drivers.adb.usb import UsbTransport

__all__ = [
    "AdbConnection", "AdbError", "AdbKey", "AdbLimitExceeded", "AdbProtocolError", "AdbStream", "AdbTimeout", "AdbTransport",
    "AuthRefused", "ConnectionLost", "DeviceBanner", "KeyFileError", "StreamClosed", "StreamRefused",
    "SocketTransport", "StreamTransport", "SyncClient", "SyncFail", "SyncStat", "UsbDeviceNotFound", "UsbTransport",
    "open_tcp",
]
