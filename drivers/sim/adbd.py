"""A simulated adbd: the device half of the ADB protocol over any reader/writer pair.

It answers the host's CNXN with AUTH TOKEN, checks signatures against its known host keys
(RSA PKCS#1 v1.5 over the token as a SHA-1 digest, like adbd), accepts or refuses a new public
key, then serves 'shell:'/'exec:' commands (getprop, echo, ls, rm, plus commands a subclass
adds), 'sync:' on an in-memory file system and 'localabstract:NAME' streams to listeners a
subclass registers. Any standard ADB client (Debian's adb) can talk to it over TCP.

Faults: refuse_auth (no key is accepted), vanish() (links drop, reconnects are refused until
reappear()), disconnect_after_bytes (the link drops in the middle of a RECV).
"""

from __future__ import annotations

import asyncio
import os
import posixpath
import random
import shlex
import stat as statmod
import struct
from collections.abc import Awaitable, Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import structlog

from drivers.adb.auth import BLOB_SIZE, TOKEN_SIZE, decode_public_blob, parse_public_key_text, verify_token_signature
from drivers.adb.errors import AdbError, ConnectionLost
from drivers.adb.message import (
    A_AUTH,
    A_CNXN,
    A_VERSION_MIN,
    AUTH_RSAPUBLICKEY,
    AUTH_SIGNATURE,
    AUTH_TOKEN,
    MAX_PAYLOAD,
    MAX_PAYLOAD_LEGACY,
    AdbMessage,
    agreed,
    checksummed,
    connect_message,
)
from drivers.adb.streams import AdbStream, ServiceHandler, StreamMux
from drivers.adb.sync import SYNC_DATA_MAX, data_chunks
from drivers.adb.transport import StreamTransport

log = structlog.get_logger("drivers.sim.adbd")

_ID_LEN = struct.Struct("<4sI")
Command = Callable[[list[str], dict[str, str], AdbStream], Awaitable[None]]


@dataclass
class SimFile:
    data: bytes
    mode: int
    mtime: int


class MemoryFileSystem:
    """Files by absolute path; directories exist implicitly as prefixes (plus a few fixed ones).

    A folder may be mounted from the host (:meth:`mount`): its files are then real files, as when
    the capture agent runs under the JVM and writes the images itself.
    """

    ROOTS = ("/", "/data", "/data/local", "/data/local/tmp", "/sdcard", "/sdcard/DCIM")

    def __init__(self) -> None:
        self.files: dict[str, SimFile] = {}
        self.mounts: dict[str, Path] = {}
        self._framed: dict[str, bytes] = {}

    def mount(self, path: str, folder: Path) -> None:
        """Serve ``path`` and everything under it from the host folder ``folder``."""
        self.mounts[posixpath.normpath(path)] = Path(folder)

    def _host(self, path: str) -> Path | None:
        """The host file behind a phone path inside a mount, else None."""
        for prefix, folder in self.mounts.items():
            if path == prefix:
                return folder
            if path.startswith(prefix + "/"):
                return folder / path[len(prefix) + 1:]
        return None

    def write(self, path: str, data: bytes, *, mode: int = 0o644, mtime: int = 0) -> None:
        path = posixpath.normpath(path)
        host = self._host(path)
        if host is not None:
            host.parent.mkdir(parents=True, exist_ok=True)
            host.write_bytes(data)
            host.chmod(mode & 0o777)
            os.utime(host, (mtime, mtime))
            return
        self.files[path] = SimFile(bytes(data), statmod.S_IFREG | (mode & 0o7777), mtime)
        self._framed.pop(path, None)

    def framed(self, path: str) -> bytes | None:
        """The file as a sync RECV answer (DATA chunks then DONE), built once per file version."""
        path = posixpath.normpath(path)
        if self._host(path) is not None:
            data = self.read(path)
            return None if data is None else data_chunks(data) + _ID_LEN.pack(b"DONE", 0)
        f = self.files.get(path)
        if f is None:
            return None
        if path not in self._framed:
            self._framed[path] = data_chunks(f.data) + _ID_LEN.pack(b"DONE", 0)
        return self._framed[path]

    def read(self, path: str) -> bytes | None:
        path = posixpath.normpath(path)
        host = self._host(path)
        if host is not None:
            return host.read_bytes() if host.is_file() else None
        f = self.files.get(path)
        return None if f is None else f.data

    def remove(self, path: str) -> bool:
        path = posixpath.normpath(path)
        host = self._host(path)
        if host is not None:
            if not host.is_file():
                return False
            host.unlink()
            return True
        self._framed.pop(path, None)
        return self.files.pop(path, None) is not None

    def is_dir(self, path: str) -> bool:
        path = posixpath.normpath(path)
        host = self._host(path)
        if host is not None:
            return host.is_dir()
        prefix = path.rstrip("/") + "/"
        return path in self.ROOTS or any(p.startswith(prefix) for p in [*self.files, *self.mounts])

    def stat(self, path: str) -> tuple[int, int, int]:
        """(mode, size, mtime); all 0 when the path does not exist."""
        path = posixpath.normpath(path)
        host = self._host(path)
        if host is not None:
            try:
                st = host.stat()
            except OSError:
                return 0, 0, 0
            return st.st_mode, st.st_size if statmod.S_ISREG(st.st_mode) else 4096, int(st.st_mtime)
        f = self.files.get(path)
        if f is not None:
            return f.mode, len(f.data), f.mtime
        if self.is_dir(path):
            return statmod.S_IFDIR | 0o771, 4096, 0
        return 0, 0, 0

    def list(self, path: str) -> list[str]:
        path = posixpath.normpath(path)
        host = self._host(path)
        if host is not None:
            return sorted(p.name for p in host.iterdir()) if host.is_dir() else []
        prefix = path.rstrip("/") + "/"
        names = {p[len(prefix):].split("/", 1)[0] for p in [*self.files, *self.mounts] if p.startswith(prefix)}
        names |= {r[len(prefix):].split("/", 1)[0] for r in self.ROOTS if r.startswith(prefix) and r != prefix}
        return sorted(n for n in names if n)


class SimulatedAdbd:
    """The adbd of one simulated phone. accept(reader, writer) serves one link until it drops."""

    HANDSHAKE_TIMEOUT_S = 10.0

    def __init__(self, serial: str, *, properties: dict[str, str] | None = None,
                 known_keys: Iterable[bytes | str] = (), accept_new_keys: bool = True,
                 seed: int = 0) -> None:
        self.serial = serial
        self.properties = {
            "ro.product.name": "tbpsim", "ro.product.model": "TBP Simulated Phone",
            "ro.product.device": "tbpsim", "ro.serialno": serial, "ro.build.version.sdk": "34",
            **(properties or {}),
        }
        self.known_keys: list[bytes] = [self._blob(k) for k in known_keys]
        self.accept_new_keys = accept_new_keys
        self.refuse_auth = False
        self.vanished = False
        self.disconnect_after_bytes: int | None = None
        self.fs = MemoryFileSystem()
        self.commands: dict[str, Command] = {"getprop": self._getprop, "echo": self._echo,
                                             "ls": self._ls, "rm": self._rm}
        self.listeners: dict[str, ServiceHandler] = {}
        self.links: dict[StreamMux, StreamTransport] = {}  # each live link's mux and its transport
        self.connections = 0
        self._sessions: set[asyncio.Task[None]] = set()
        self._rng = random.Random(seed)

    @staticmethod
    def _blob(key: bytes | str) -> bytes:
        """A known key as the raw RSAPublicKey struct, from the struct itself or adbkey.pub text."""
        if isinstance(key, bytes) and len(key) == BLOB_SIZE:
            decode_public_blob(key)
            return key
        return parse_public_key_text(key)

    # ---------------------------------------------------------------- faults
    def vanish(self) -> None:
        """Drop every link now and refuse reconnects (phone unplugged, crashed or out of battery)."""
        self.vanished = True
        for transport in list(self.links.values()):
            transport.writer.transport.abort()

    def reappear(self) -> None:
        self.vanished = False

    async def shut_down(self) -> None:
        """Drop every link and wait until their sessions (and what they run, the agent) have ended."""
        for transport in list(self.links.values()):
            transport.writer.transport.abort()
        await asyncio.gather(*self._sessions, return_exceptions=True)

    # ---------------------------------------------------------------- link
    async def accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Serve one host link (socketpair or TCP) until it closes."""
        session = asyncio.current_task()
        if session is not None:
            self._sessions.add(session)
            session.add_done_callback(self._sessions.discard)
        transport = StreamTransport(reader, writer, name=self.serial)
        if self.vanished:
            writer.transport.abort()
            return
        mux = StreamMux(transport, name=self.serial, resolver=self.resolve)
        try:
            async with asyncio.timeout(self.HANDSHAKE_TIMEOUT_S):
                version, max_payload = await self._handshake(transport)
        except (AdbError, TimeoutError) as exc:
            log.info("sim_adbd_handshake_failed", serial=self.serial, error=repr(exc))
            await transport.close()
            return
        mux.max_payload = max_payload
        mux.with_checksum = checksummed(version)
        self.links[mux] = transport
        self.connections += 1
        try:
            await mux.run()
        finally:
            self.links.pop(mux, None)
            await mux.close()  # the session ends once its services (the agent's shell) have

    async def _handshake(self, transport: StreamTransport) -> tuple[int, int]:
        msg = await transport.recv(MAX_PAYLOAD_LEGACY)
        if msg.command != A_CNXN or msg.arg0 < A_VERSION_MIN:
            raise ConnectionLost(self.serial, "handshake", f"expected CNXN, got {msg.name}({msg.arg0:#x})")
        version, max_payload = agreed(msg.arg0, msg.arg1, MAX_PAYLOAD)
        while True:
            token = self._rng.randbytes(TOKEN_SIZE)
            await transport.send(AdbMessage(A_AUTH, AUTH_TOKEN, 0, token))
            reply = await transport.recv(MAX_PAYLOAD_LEGACY)
            if reply.command != A_AUTH:
                raise ConnectionLost(self.serial, "auth", f"expected AUTH, got {reply.name}")
            if reply.arg0 == AUTH_SIGNATURE:
                if not self.refuse_auth and any(verify_token_signature(k, token, bytes(reply.payload))
                                                for k in self.known_keys):
                    break
            elif reply.arg0 == AUTH_RSAPUBLICKEY:
                if self.refuse_auth or not self.accept_new_keys:
                    raise ConnectionLost(self.serial, "auth", "user refused the host's public key")
                self.known_keys.append(parse_public_key_text(bytes(reply.payload)))
                break
            else:
                raise ConnectionLost(self.serial, "auth", f"AUTH type {reply.arg0}")
        features = "cmd"
        props = ";".join(f"{k}={self.properties[k]}" for k in
                         ("ro.product.name", "ro.product.model", "ro.product.device"))
        await transport.send(connect_message(f"device::{props};features={features}".encode(),
                                             version=version, max_payload=MAX_PAYLOAD))
        return version, max_payload

    # ---------------------------------------------------------------- services
    def resolve(self, service: str) -> ServiceHandler | None:
        if service.startswith(("shell:", "exec:")):
            command = service.split(":", 1)[1]
            return lambda stream: self._shell(command, stream)
        if service == "sync:":
            return self._sync
        if service.startswith("localabstract:"):
            return self.listeners.get(service.split(":", 1)[1])
        return None

    async def _shell(self, command: str, stream: AdbStream) -> None:
        try:
            words = shlex.split(command)
        except ValueError as exc:
            await stream.write(f"/system/bin/sh: syntax error: {exc}\n".encode())
            return
        env: dict[str, str] = {}
        while words and "=" in words[0] and not words[0].startswith("="):
            key, _, value = words.pop(0).partition("=")
            env[key] = value
        if not words:
            return
        handler = self.commands.get(posixpath.basename(words[0]))
        if handler is None:
            await stream.write(f"/system/bin/sh: {words[0]}: inaccessible or not found\n".encode())
            return
        await handler(words, env, stream)

    async def _getprop(self, argv: list[str], env: dict[str, str], stream: AdbStream) -> None:
        if len(argv) > 1:
            await stream.write(self.properties.get(argv[1], "").encode() + b"\n")
        else:
            await stream.write("".join(f"[{k}]: [{v}]\n" for k, v in sorted(self.properties.items())).encode())

    async def _echo(self, argv: list[str], env: dict[str, str], stream: AdbStream) -> None:
        await stream.write((" ".join(argv[1:]) + "\n").encode())

    async def _ls(self, argv: list[str], env: dict[str, str], stream: AdbStream) -> None:
        out = []
        for path in argv[1:] or ["/"]:
            if self.fs.read(path) is not None:
                out.append(path)
            elif self.fs.is_dir(path):
                out.extend(self.fs.list(path))
            else:
                out.append(f"ls: {path}: No such file or directory")
        await stream.write("".join(line + "\n" for line in out).encode())

    async def _rm(self, argv: list[str], env: dict[str, str], stream: AdbStream) -> None:
        missing = [p for p in argv[1:] if not p.startswith("-") and not self.fs.remove(p)]
        if missing and "-f" not in argv:
            await stream.write("".join(f"rm: {p}: No such file or directory\n" for p in missing).encode())

    # ---------------------------------------------------------------- sync
    async def _sync(self, stream: AdbStream) -> None:
        while True:
            try:
                header = await stream.readexactly(8)
            except AdbError:
                return
            ident, length = _ID_LEN.unpack(header)
            if ident == b"QUIT":
                return
            path = (await stream.readexactly(length)).decode("utf-8", "replace")
            if ident == b"STAT":
                await stream.write(struct.pack("<4sIII", b"STAT", *self.fs.stat(path)))
            elif ident == b"LIST":
                await self._sync_list(stream, path)
            elif ident == b"RECV":
                await self._sync_recv(stream, path)
            elif ident == b"SEND":
                await self._sync_send(stream, path)
            else:
                await self._sync_fail(stream, f"unknown sync request {ident!r}")
                return

    async def _sync_fail(self, stream: AdbStream, reason: str) -> None:
        raw = reason.encode()
        await stream.write(_ID_LEN.pack(b"FAIL", len(raw)) + raw)

    async def _sync_list(self, stream: AdbStream, path: str) -> None:
        out = []
        for name in self.fs.list(path):
            mode, size, mtime = self.fs.stat(posixpath.join(path, name))
            out.append(struct.pack("<4sIIII", b"DENT", mode, size, mtime, len(name.encode())) + name.encode())
        out.append(struct.pack("<4sIIII", b"DONE", 0, 0, 0, 0))
        await stream.write(b"".join(out))

    async def _sync_recv(self, stream: AdbStream, path: str) -> None:
        framed = self.fs.framed(path)
        if framed is None:
            await self._sync_fail(stream, f"remote object '{path}' does not exist")
            return
        view = memoryview(framed)
        frame = SYNC_DATA_MAX + 8
        batch = max(stream.mux.max_payload // frame, 1) * frame
        limit = self.disconnect_after_bytes
        if limit is not None:  # the fault: the link drops once `limit` file bytes are on their way
            cut = (limit // SYNC_DATA_MAX) * frame
            await stream.write(view[:cut])
            log.info("sim_adbd_fault_disconnect", serial=self.serial, path=path, after_bytes=limit)
            self.links[stream.mux].writer.transport.abort()
            return
        for start in range(0, len(view), batch):
            await stream.write(view[start:start + batch])

    async def _sync_send(self, stream: AdbStream, spec: str) -> None:
        path, _, mode_text = spec.rpartition(",")
        try:
            mode = int(mode_text)
        except ValueError:
            path, mode = spec, 0o644
        parts = []
        while True:
            ident, length = _ID_LEN.unpack(await stream.readexactly(8))
            if ident == b"DATA":
                if length > SYNC_DATA_MAX:
                    await self._sync_fail(stream, f"DATA chunk of {length} bytes > {SYNC_DATA_MAX}")
                    return
                parts.append(await stream.readexactly(length))
            elif ident == b"DONE":
                self.fs.write(path, b"".join(parts), mode=mode, mtime=length)
                await stream.write(_ID_LEN.pack(b"OKAY", 0))
                return
            else:
                await self._sync_fail(stream, f"unexpected {ident!r} during SEND")
                return
