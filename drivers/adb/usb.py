"""ADB over USB bulk endpoints through pyusb (real phones on the rig's USB hub).

The ADB interface is class 0xFF, subclass 0x42, protocol 0x01 with one bulk IN and one bulk OUT
endpoint; header and payload travel as separate bulk transfers. pyusb blocks, so this transport
owns two threads: a reader that turns IN transfers into messages for the event loop
(call_soon_threadsafe), and a single writer thread that serialises OUT transfers. This is a
real-hardware path only; simulated phones use socketpair or TCP transports.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import structlog
import usb.core
import usb.util

from drivers.adb.errors import AdbError, ConnectionLost, UsbDeviceNotFound
from drivers.adb.message import HEADER_SIZE, MAX_PAYLOAD, AdbMessage, decode_header, finish_message

log = structlog.get_logger("drivers.adb.usb")

ADB_CLASS, ADB_SUBCLASS, ADB_PROTOCOL = 0xFF, 0x42, 0x01
ENDPOINT_IN = 0x80
TRANSFER_BULK = 0x02


def adb_interface(device: Any) -> tuple[Any, Any, Any] | None:
    """(interface, bulk IN endpoint, bulk OUT endpoint) of a pyusb device's ADB interface, or None."""
    for config in device:
        for interface in config:
            if (interface.bInterfaceClass, interface.bInterfaceSubClass, interface.bInterfaceProtocol) != \
                    (ADB_CLASS, ADB_SUBCLASS, ADB_PROTOCOL):
                continue
            bulk = [e for e in interface if e.bmAttributes & 0x03 == TRANSFER_BULK]
            ep_in = next((e for e in bulk if e.bEndpointAddress & ENDPOINT_IN), None)
            ep_out = next((e for e in bulk if not e.bEndpointAddress & ENDPOINT_IN), None)
            if ep_in is not None and ep_out is not None:
                return interface, ep_in, ep_out
    return None


def adb_devices() -> Iterator[tuple[str, Any]]:
    """(serial, pyusb device) for every attached device with an ADB interface."""

    for device in usb.core.find(find_all=True):
        if adb_interface(device) is None:
            continue
        try:
            serial = usb.util.get_string(device, device.iSerialNumber) or ""
        except (usb.core.USBError, ValueError) as exc:  # no permission: udev rule missing
            log.warning("adb_usb_serial_unreadable", bus=device.bus, address=device.address, error=str(exc))
            continue
        yield serial, device


class UsbTransport:
    """ADB messages over a claimed USB ADB interface."""

    READ_POLL_MS = 200     # the reader thread checks for close() this often
    WRITE_TIMEOUT_MS = 5000
    QUEUE_HIGH = 8         # messages read ahead of recv(); the reader thread waits beyond this

    def __init__(self, device: Any, interface: Any, ep_in: Any, ep_out: Any, *, name: str) -> None:
        self.device = device
        self.interface = interface
        self.ep_in = ep_in
        self.ep_out = ep_out
        self.name = name
        self.closed = False
        self.max_payload = MAX_PAYLOAD
        self._loop = asyncio.get_running_loop()
        self._messages: asyncio.Queue[AdbMessage | AdbError] = asyncio.Queue()
        self._writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"adb-usb-out-{name}")
        self._stop = threading.Event()
        self._slots = threading.Semaphore(self.QUEUE_HIGH)  # bounds what a flooding phone can queue
        self._reader = threading.Thread(target=self._read_loop, name=f"adb-usb-in-{name}", daemon=True)
        self._reader.start()

    @classmethod
    async def open(cls, serial: str | None = None) -> UsbTransport:
        """Claim the ADB interface of the phone with this serial (the only phone when None).

        Enumeration and claiming block on control transfers, so they run off the event loop
        (which keeps serving the beam drive meanwhile)."""
        loop = asyncio.get_running_loop()
        name, device, found = await loop.run_in_executor(None, cls._find_and_claim, serial)
        return cls(device, found[0], found[1], found[2], name=name)

    @staticmethod
    def _find_and_claim(serial: str | None) -> tuple[str, Any, tuple[Any, Any, Any]]:

        found = [(s, d) for s, d in adb_devices() if serial is None or s == serial]
        if not found:
            raise UsbDeviceNotFound(serial or "usb", "searching",
                                    "no USB device with an ADB interface (ff/42/01) matches")
        if len(found) > 1:
            raise UsbDeviceNotFound(serial or "usb", "searching",
                                    f"{len(found)} ADB devices attached; name one: {[s for s, _ in found]}")
        name, device = found[0]
        endpoints = adb_interface(device)
        if endpoints is None:  # unplugged between the two looks
            raise UsbDeviceNotFound(name, "searching", "the ADB interface disappeared")
        usb.util.claim_interface(device, endpoints[0].bInterfaceNumber)
        return name, device, endpoints

    def _read_exact(self, size: int) -> bytes:
        """size bytes from bulk IN, across several transfers if the phone splits them; the
        zero-length packet that ends a payload of whole packets is skipped."""

        parts: list[bytes] = []
        have = 0
        while have < size:
            if self._stop.is_set():
                raise ConnectionLost(self.name, "closed", "transport closed")
            try:
                data = bytes(self.ep_in.read(size - have, timeout=self.READ_POLL_MS))
            except usb.core.USBTimeoutError:
                continue
            parts.append(data)
            have += len(data)
        return b"".join(parts)

    def _read_loop(self) -> None:

        while not self._stop.is_set():
            if not self._slots.acquire(timeout=self.READ_POLL_MS / 1000):
                continue
            try:
                header = decode_header(self._read_exact(HEADER_SIZE), device=self.name,
                                       max_payload=self.max_payload)
                payload = self._read_exact(header.data_length) if header.data_length else b""
                item: AdbMessage | AdbError = finish_message(header, payload, device=self.name)
            except AdbError as exc:
                item = exc
            except usb.core.USBError as exc:  # unplugged, reset, or stalled endpoint
                item = ConnectionLost(self.name, "receiving", f"USB error: {exc}")
            self._loop.call_soon_threadsafe(self._messages.put_nowait, item)
            if isinstance(item, AdbError):
                return

    def _write(self, message: AdbMessage, with_checksum: bool) -> None:
        self.ep_out.write(message.header(with_checksum=with_checksum), timeout=self.WRITE_TIMEOUT_MS)
        if message.payload:
            self.ep_out.write(message.payload, timeout=self.WRITE_TIMEOUT_MS)
            if len(message.payload) % self.ep_out.wMaxPacketSize == 0:
                # a payload filling whole packets ends with a zero-length packet, or the phone's
                # bulk read waits for more (adb's own host side does the same)
                self.ep_out.write(b"", timeout=self.WRITE_TIMEOUT_MS)

    async def send(self, message: AdbMessage, *, with_checksum: bool = True) -> None:

        if self.closed:
            raise ConnectionLost(self.name, "closed", f"cannot send {message.name}: transport closed")
        try:
            await self._loop.run_in_executor(self._writer, self._write, message, with_checksum)
        except usb.core.USBError as exc:
            raise ConnectionLost(self.name, "sending", f"{message.name}: USB error: {exc}") from exc

    async def recv(self, max_payload: int = MAX_PAYLOAD) -> AdbMessage:
        self.max_payload = max_payload
        item = await self._messages.get()
        if isinstance(item, AdbError):
            self._messages.put_nowait(item)  # every later recv() fails the same way
            raise item
        self._slots.release()
        return item

    async def close(self) -> None:
        """Stop both threads and release the interface; idempotent. Joining the threads (a write
        may wait out its WRITE_TIMEOUT_MS) and releasing the interface (control transfers) run in
        a thread: the event loop carries the heartbeats."""
        if self.closed:
            return
        self.closed = True
        self._stop.set()
        await self._loop.run_in_executor(None, self._release)

    def _release(self) -> None:

        self._reader.join()
        self._writer.shutdown(wait=True)
        try:
            usb.util.release_interface(self.device, self.interface.bInterfaceNumber)
            usb.util.dispose_resources(self.device)
        except usb.core.USBError as exc:  # already unplugged: nothing left to release
            log.info("adb_usb_release_failed", device=self.name, error=str(exc))
