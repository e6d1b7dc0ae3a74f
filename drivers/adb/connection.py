"""The host side of an ADB connection: CNXN/AUTH handshake, then services over multiplexed streams.

    conn = AdbConnection(await open_tcp("127.0.0.1", 5555), key)
    device = await conn.connect()
    print(await conn.shell("getprop ro.product.model"))
    async with await conn.sync() as sync:
        size, sha = await sync.pull("/sdcard/DCIM/img.jpg", Path("img.jpg"))
    await conn.close()
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field

import structlog

from drivers.adb.auth import TOKEN_SIZE, AdbKey
from drivers.adb.errors import AdbError, AdbProtocolError, AdbTimeout, AuthRefused, ConnectionLost
from drivers.adb.message import (
    A_AUTH,
    A_CNXN,
    A_VERSION_MIN,
    AUTH_RSAPUBLICKEY,
    AUTH_SIGNATURE,
    AUTH_TOKEN,
    MAX_PAYLOAD,
    AdbMessage,
    agreed,
    checksummed,
    connect_message,
    parse_banner,
)
from drivers.adb.streams import AdbStream, StreamMux
from drivers.adb.sync import SyncClient
from drivers.adb.transport import AdbTransport

log = structlog.get_logger("drivers.adb.connection")


@dataclass(frozen=True)
class DeviceBanner:
    """What the device said in its CNXN: kind ('device'), properties, features, version, max payload."""

    kind: str
    properties: dict[str, str]
    features: frozenset[str]
    version: int
    max_payload: int
    raw: bytes = field(repr=False, default=b"")


class AdbConnection:
    """One ADB link to one device. States: offline -> authorizing -> online -> closed | lost."""

    HANDSHAKE_TIMEOUT_S = 10.0
    AUTH_ACCEPT_TIMEOUT_S = 30.0  # the phone user taps "Allow USB debugging" once per host key
    BANNER = b"host::features=cmd"
    # Largest WRTE payload this host accepts. Every stream shares the link, so one payload holds
    # back a focus or capture command queued behind it: 256 KiB is ~6 ms on USB 2.0 (1 MiB, the
    # protocol's maximum, would be ~25 ms), and early credit keeps TCP pulls at full speed.
    MAX_PAYLOAD = 256 * 1024
    # Largest shell/exec output kept: the host runs short commands (getprop, ls); a device that
    # keeps writing is cut off here instead of filling the host's memory.
    MAX_COMMAND_OUTPUT = 1024 * 1024

    def __init__(self, transport: AdbTransport, key: AdbKey | None, *, name: str | None = None) -> None:
        self.transport = transport
        self.key = key
        self.name = name or transport.name
        self.state = "offline"
        self.device: DeviceBanner | None = None
        self.mux = StreamMux(transport, name=self.name)
        self._reader: asyncio.Task[None] | None = None

    async def connect(self) -> DeviceBanner:
        """CNXN, answer AUTH (signature first, then the public key), wait for the device's CNXN."""
        self.state = "authorizing"
        try:
            await self.transport.send(connect_message(self.BANNER, max_payload=self.MAX_PAYLOAD))
            banner = await self._authenticate()
        except AdbError:
            self.state = "lost"
            await self.transport.close()
            raise
        self.device = banner
        self.mux.max_payload = banner.max_payload
        self.mux.with_checksum = checksummed(banner.version)
        self.state = "online"
        self._reader = asyncio.create_task(self._run(), name=f"adb-{self.name}")
        log.info("adb_online", device=self.name, model=banner.properties.get("ro.product.model"),
                 max_payload=banner.max_payload, version=f"0x{banner.version:08X}")
        return banner

    async def _authenticate(self) -> DeviceBanner:
        sent_signature = sent_key = False
        timeout_s = self.HANDSHAKE_TIMEOUT_S
        while True:
            try:
                async with asyncio.timeout(timeout_s):
                    msg = await self.transport.recv(MAX_PAYLOAD)
            except TimeoutError:
                if sent_key:
                    raise AuthRefused(self.name, self.state, f"public key not accepted within {timeout_s:g} s") from None
                raise AdbTimeout(self.name, self.state, "CNXN or AUTH from the device", timeout_s) from None
            except ConnectionLost as exc:
                if sent_key:
                    raise AuthRefused(self.name, self.state, "device dropped the link after the public key") from exc
                raise
            if msg.command == A_CNXN:
                return self._banner(msg)
            if msg.command != A_AUTH or msg.arg0 != AUTH_TOKEN:
                raise AdbProtocolError(self.name, self.state, f"unexpected {msg.name}({msg.arg0}) during handshake")
            if self.key is None:
                raise AuthRefused(self.name, self.state, "device wants AUTH and no host key was given")
            if len(msg.payload) != TOKEN_SIZE:
                raise AdbProtocolError(self.name, self.state,
                                       f"AUTH token of {len(msg.payload)} bytes, expected {TOKEN_SIZE}")
            if not sent_signature:
                await self.transport.send(AdbMessage(A_AUTH, AUTH_SIGNATURE, 0, self.key.sign(bytes(msg.payload))))
                sent_signature = True
            elif not sent_key:
                await self.transport.send(AdbMessage(A_AUTH, AUTH_RSAPUBLICKEY, 0, self.key.public_key_payload()))
                sent_key = True
                timeout_s = self.AUTH_ACCEPT_TIMEOUT_S
                log.info("adb_public_key_sent", device=self.name, note="accept the key on the phone")
            else:
                raise AuthRefused(self.name, self.state, "device refused the signature and the public key")

    def _banner(self, msg: AdbMessage) -> DeviceBanner:
        version, max_payload = msg.arg0, msg.arg1
        if version < A_VERSION_MIN:
            raise AdbProtocolError(self.name, self.state, f"device protocol version 0x{version:08X} too old")
        kind, props = parse_banner(bytes(msg.payload))
        features = frozenset(f for f in props.pop("features", "").split(",") if f)
        version, size = agreed(version, max_payload, self.MAX_PAYLOAD)  # both directions use these
        return DeviceBanner(kind, props, features, version, size, bytes(msg.payload))

    async def _run(self) -> None:
        await self.mux.run()
        if self.state == "online":
            self.state = "lost"
            log.warning("adb_connection_lost", device=self.name, error=str(self.mux.lost))

    def _check_online(self) -> None:
        if self.mux.lost is not None:
            raise self.mux.lost
        if self.state != "online":
            raise ConnectionLost(self.name, self.state, "not connected")

    async def open(self, service: str) -> AdbStream:
        """Open a service stream (shell:, exec:, sync:, localabstract:NAME, ...)."""
        self._check_online()
        return await self.mux.open(service)

    async def shell(self, command: str, *, max_bytes: int | None = None) -> bytes:
        """Run a command through 'shell:' and return its output (stdout and stderr, as the phone sends it).

        At most ``max_bytes`` (default MAX_COMMAND_OUTPUT) are kept; more raises AdbLimitExceeded.
        """
        return await self._run_command(f"shell:{command}", max_bytes)

    async def exec(self, command: str, *, max_bytes: int | None = None) -> bytes:
        """Run a command through 'exec:' (raw, binary-safe stdout), bounded like :meth:`shell`."""
        return await self._run_command(f"exec:{command}", max_bytes)

    async def _run_command(self, service: str, max_bytes: int | None) -> bytes:
        stream = await self.open(service)
        try:
            return await stream.read_all(self.MAX_COMMAND_OUTPUT if max_bytes is None else max_bytes)
        finally:
            await stream.close()

    async def sync(self) -> SyncClient:
        """A sync-service session (STAT, RECV, SEND, LIST); use as an async context manager."""
        return SyncClient(await self.open("sync:"), device=self.name)

    @property
    def online(self) -> bool:
        return self.state == "online" and self.mux.lost is None

    async def close(self) -> None:
        """Close every stream and the transport; idempotent."""
        if self.state == "closed":
            return
        self.state = "closed"
        await self.mux.close()
        if self._reader is not None:
            self._reader.cancel()
            await asyncio.gather(self._reader, return_exceptions=True)
