"""ADB over USB bulk endpoints: interface matching, separate header/payload transfers, and a full
session through fake pyusb endpoints bridged to the simulated adbd (no hardware needed)."""

from __future__ import annotations

import asyncio
import os
import socket
from pathlib import Path
from types import SimpleNamespace

import pytest
import usb.core
import usb.util

from drivers.adb.auth import AdbKey
from drivers.adb.connection import AdbConnection
from drivers.adb.errors import ConnectionLost
from drivers.adb.message import A_CNXN, A_WRTE, HEADER_SIZE, AdbMessage, connect_message
from drivers.adb.usb import UsbTransport, adb_interface
from drivers.sim.adbd import SimulatedAdbd

KEY = AdbKey.generate("usb@host")


def _endpoint(address: int, attributes: int = 0x02) -> SimpleNamespace:
    return SimpleNamespace(bEndpointAddress=address, bmAttributes=attributes)


class _Interface(list):
    def __init__(self, cls: int, sub: int, proto: int, endpoints: list) -> None:
        super().__init__(endpoints)
        self.bInterfaceClass, self.bInterfaceSubClass, self.bInterfaceProtocol = cls, sub, proto
        self.bInterfaceNumber = 1


def test_adb_interface_matching() -> None:
    mtp = _Interface(0x06, 0x01, 0x01, [_endpoint(0x81), _endpoint(0x01)])
    adb = _Interface(0xFF, 0x42, 0x01, [_endpoint(0x83, 0x03), _endpoint(0x82), _endpoint(0x02)])
    found = adb_interface([[mtp, adb]])
    assert found is not None and found[0] is adb
    assert (found[1].bEndpointAddress, found[2].bEndpointAddress) == (0x82, 0x02)  # bulk only, not interrupt
    assert adb_interface([[mtp]]) is None
    assert adb_interface([[_Interface(0xFF, 0x42, 0x03, [_endpoint(0x81), _endpoint(0x01)])]]) is None  # fastboot


class _BridgedEndpoints:
    """Bulk IN/OUT endpoints whose transfers go over a blocking socket to the simulated adbd."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.sock.settimeout(0.05)
        self.wMaxPacketSize = 512
        self.zero_length_next = False
        self.split_next = False
        self.writes: list[int] = []
        self.fail_reads = False

    def write(self, data: bytes, timeout: int) -> int:
        self.writes.append(len(data))
        self.sock.sendall(bytes(data))
        return len(data)

    def read(self, size: int, timeout: int) -> bytes:
        if self.fail_reads:
            raise usb.core.USBError("No such device (it may have been disconnected)")
        if self.zero_length_next:  # a ZLP, then the payload split over two transfers
            self.zero_length_next = False
            self.split_next = True
            return b""
        if self.split_next and size > 1:
            self.split_next = False
            size //= 2
        data = b""
        while len(data) < size:
            try:
                chunk = self.sock.recv(size - len(data))
            except TimeoutError:
                if not data:
                    raise usb.core.USBTimeoutError("timeout") from None
                continue
            if not chunk:
                raise usb.core.USBError("pipe closed")
            data += chunk
        return data


@pytest.fixture
def no_release(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(usb.util, "release_interface", lambda device, number: None)
    monkeypatch.setattr(usb.util, "dispose_resources", lambda device: None)


async def _usb_session(device: SimulatedAdbd) -> tuple[UsbTransport, _BridgedEndpoints, asyncio.Task]:
    host_sock, device_sock = socket.socketpair()
    reader, writer = await asyncio.open_connection(sock=device_sock)
    task = asyncio.create_task(device.accept(reader, writer))
    endpoints = _BridgedEndpoints(host_sock)
    transport = UsbTransport(object(), SimpleNamespace(bInterfaceNumber=1), endpoints, endpoints, name="USB0001")
    return transport, endpoints, task


async def test_full_session_over_usb_endpoints(tmp_path: Path, no_release: None) -> None:
    device = SimulatedAdbd("USB0001", known_keys=[KEY.public_blob()])
    data = os.urandom(1_500_000)
    device.fs.write("/sdcard/a.jpg", data)
    transport, endpoints, task = await _usb_session(device)
    conn = AdbConnection(transport, KEY)
    await conn.connect()
    assert endpoints.writes[:2] == [HEADER_SIZE, len(AdbConnection.BANNER) + 1]  # header, then payload
    stream = await conn.open("shell:cat")
    endpoints.writes.clear()
    await stream.write(bytes(1024))  # whole 512-byte packets: a zero-length packet ends the transfer
    at = endpoints.writes.index(1024)  # (OKAYs for the shell's output may come in between)
    assert endpoints.writes[at - 1:at + 2] == [HEADER_SIZE, 1024, 0]
    await stream.close()
    assert await conn.shell("getprop ro.serialno") == b"USB0001\n"
    endpoints.zero_length_next = True
    assert await conn.shell("echo split") == b"split\n"
    async with await conn.sync() as sync:
        size, _ = await sync.pull("/sdcard/a.jpg", tmp_path / "a.jpg")
    assert size == len(data) and (tmp_path / "a.jpg").read_bytes() == data
    await conn.close()
    endpoints.sock.close()  # unplugging the cable is what ends the device's session
    await task


async def test_usb_error_is_connection_lost(no_release: None) -> None:
    device = SimulatedAdbd("USB0001", known_keys=[KEY.public_blob()])
    transport, endpoints, task = await _usb_session(device)
    endpoints.fail_reads = True  # unplugged: nothing was sent, so the next bulk read is the failing one
    with pytest.raises(ConnectionLost, match="USB error: .*disconnected"):
        await transport.recv()
    with pytest.raises(ConnectionLost):  # stays failed
        await transport.recv()
    await transport.close()
    await transport.close()
    with pytest.raises(ConnectionLost, match="transport closed"):
        await transport.send(_cnxn())
    endpoints.sock.close()
    await task


def _cnxn() -> AdbMessage:
    message = connect_message(b"host::")
    assert message.command == A_CNXN
    return message


async def test_open_names_missing_and_ambiguous_phones(monkeypatch: pytest.MonkeyPatch) -> None:
    import drivers.adb.usb as adb_usb
    from drivers.adb.errors import UsbDeviceNotFound

    monkeypatch.setattr(adb_usb, "adb_devices", lambda: iter([("AAA", object()), ("BBB", object())]))
    with pytest.raises(UsbDeviceNotFound, match="CCC .*no USB device with an ADB interface"):
        await UsbTransport.open("CCC")
    with pytest.raises(UsbDeviceNotFound, match=r"2 ADB devices attached; name one: \['AAA', 'BBB'\]"):
        await UsbTransport.open()


class _FloodingEndpoint:
    """A bulk IN endpoint of a phone that sends WRTE after WRTE, as fast as it is read."""

    wMaxPacketSize = 512

    def __init__(self) -> None:
        self.message = AdbMessage(A_WRTE, 1, 1, bytes(4096)).encode()
        self.pos = 0
        self.messages_read = 0

    def read(self, size: int, timeout: int) -> bytes:
        out = bytearray()
        while len(out) < size:
            take = min(size - len(out), len(self.message) - self.pos)
            out += self.message[self.pos:self.pos + take]
            self.pos += take
            if self.pos == len(self.message):
                self.pos = 0
                self.messages_read += 1
        return bytes(out)


async def test_a_flooding_phone_queues_at_most_queue_high_messages(no_release: None) -> None:
    flood = _FloodingEndpoint()
    transport = UsbTransport(object(), SimpleNamespace(bInterfaceNumber=1), flood, flood, name="FLOOD")
    await asyncio.sleep(0.3)  # nobody calls recv(): the reader thread must stop reading ahead
    assert transport._messages.qsize() <= UsbTransport.QUEUE_HIGH
    assert flood.messages_read <= UsbTransport.QUEUE_HIGH + 1
    assert (await transport.recv()).command == A_WRTE
    await asyncio.sleep(0.05)
    assert transport._messages.qsize() <= UsbTransport.QUEUE_HIGH  # one slot freed, one more read
    await transport.close()


async def test_closing_joins_the_threads_and_releases_the_interface_off_the_event_loop(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A write may wait out its 5 s timeout and a release is a control transfer: close() waits
    for them in a thread, never on the loop that carries the heartbeats."""
    import threading

    threads: dict[str, str] = {}
    monkeypatch.setattr(usb.util, "release_interface",
                        lambda device, number: threads.setdefault("release", threading.current_thread().name))
    monkeypatch.setattr(usb.util, "dispose_resources",
                        lambda device: threads.setdefault("dispose", threading.current_thread().name))
    device = SimulatedAdbd("USB0001", known_keys=[KEY.public_blob()])
    transport, endpoints, task = await _usb_session(device)
    shutdown = transport._writer.shutdown
    transport._writer.shutdown = lambda wait=True: (threads.setdefault("shutdown", threading.current_thread().name),
                                                    shutdown(wait))
    await transport.close()
    loop_thread = threading.current_thread().name
    assert set(threads) == {"release", "dispose", "shutdown"} and loop_thread not in threads.values()
    endpoints.sock.close()
    await task
