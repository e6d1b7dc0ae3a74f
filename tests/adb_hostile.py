"""Hostile ADB devices for the hardening tests: a simulated adbd that does what a broken or
malicious phone could do on the wire (issue 14, probe 3).

Shell commands: ``yes`` writes for ever (within flow control), ``flood`` writes WRTEs without
waiting for OKAY (ignoring flow control). Sync: a RECV of any path under ``/sdcard/endless/``
sends DATA chunks for ever, ``LIST /sdcard/endless`` lists for ever, ``LIST /sdcard/hugename``
announces a 4 GiB name and a RECV of ``/sdcard/longfail`` answers a FAIL claiming a 4 GiB reason.
"""

from __future__ import annotations

import struct

from drivers.adb.errors import AdbError
from drivers.adb.message import A_WRTE, AdbMessage
from drivers.adb.streams import AdbStream
from drivers.adb.sync import SYNC_DATA_MAX
from drivers.sim.adbd import SimulatedAdbd

ENDLESS_DIR = "/sdcard/endless"
_CHUNK = bytes(SYNC_DATA_MAX)
_DATA = struct.pack("<4sI", b"DATA", SYNC_DATA_MAX) + _CHUNK


class HostileAdbd(SimulatedAdbd):
    """A simulated adbd whose answers never end or break the protocol's bounds."""

    def __init__(self, serial: str, **options: object) -> None:
        super().__init__(serial, **options)  # type: ignore[arg-type]
        self.commands["yes"] = self._yes
        self.commands["flood"] = self._flood
        self.sent_bytes = 0

    async def _yes(self, argv: list[str], env: dict[str, str], stream: AdbStream) -> None:
        line = b"y\n" * (32 * 1024)
        while True:
            await stream.write(line)
            self.sent_bytes += len(line)

    async def _flood(self, argv: list[str], env: dict[str, str], stream: AdbStream) -> None:
        payload = bytes(stream.mux.max_payload)
        while True:  # no wait for OKAY between WRTEs
            await stream.mux.send(AdbMessage(A_WRTE, stream.local_id, stream.remote_id, payload))
            self.sent_bytes += len(payload)

    async def _sync_recv(self, stream: AdbStream, path: str) -> None:
        if path == "/sdcard/longfail":
            await stream.write(struct.pack("<4sI", b"FAIL", 0xFFFFFFFF) + b"no")
            return
        if not path.startswith(ENDLESS_DIR + "/"):
            await super()._sync_recv(stream, path)
            return
        batch = _DATA * max(stream.mux.max_payload // len(_DATA), 1)
        try:
            while True:
                await stream.write(batch)
                self.sent_bytes += len(batch)
        except AdbError:
            return  # the host closed the session

    async def _sync_list(self, stream: AdbStream, path: str) -> None:
        if path == "/sdcard/hugename":
            await stream.write(struct.pack("<4sIIII", b"DENT", 0o100644, 1, 0, 0xFFFFFFFF) + b"x")
            return
        if path != ENDLESS_DIR:
            await super()._sync_list(stream, path)
            return
        name = b"x.jpg"
        dent = struct.pack("<4sIIII", b"DENT", 0o100644, 1, 0, len(name)) + name
        batch = dent * 1000
        try:
            while True:
                await stream.write(batch)
        except AdbError:
            return
