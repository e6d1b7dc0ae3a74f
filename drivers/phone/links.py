"""Transport factories for PhoneCamera: how to reach a real phone (USB or wireless debugging).

PhoneCamera calls its factory on every connect(), so a replugged or re-enumerated phone is found
again by serial. The simulated rig passes its own factory (a socketpair to a SimulatedPhone).
"""

from __future__ import annotations

from drivers.adb.transport import AdbTransport, open_tcp
from drivers.adb.usb import UsbTransport
from drivers.phone.camera import TransportFactory


def usb_link(serial: str) -> TransportFactory:
    """The phone with this USB serial (ro.serialno), on whichever USB port it is plugged into."""

    async def connect() -> AdbTransport:
        return await UsbTransport.open(serial)

    return connect


def tcp_link(host: str, port: int = 5555) -> TransportFactory:
    """A phone in wireless debugging / ``adb tcpip`` mode, or a ``tbp sim phone`` process."""

    async def connect() -> AdbTransport:
        return await open_tcp(host, port)

    return connect
