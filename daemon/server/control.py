"""The daemon's local control API: JSON lines over a Unix socket.

Requests, one JSON object a line: ``{"id": 1, "cmd": "status"|"scan"|"calibrate"|"abort"|"reset"|
"subscribe", "args": {...}}`` (``calibrate`` starts a calibration rotation: the cuboid in place). Replies: ``{"id": 1, "ok": true, "result": {...}}`` or
``{"id": 1, "ok": false, "error": {"type": "ScanRefused", "message": "..."}}``.
``subscribe`` replies with the current status and then streams ``{"event": {...}}`` lines
(state changes, progress, faults) until the client hangs up; that connection carries
nothing else. The socket is mode 0660 (optionally owned by a group) so only the daemon's
user and the operators' group can drive the rig; a stale socket left by a killed daemon is
removed, a live one is refused.

Bounded, never silent (see :class:`ControlServer`): requests and subscriptions have pools of
their own, and ``status``, ``abort`` and ``reset`` are served even when both are full; a
subscriber that stops reading is dropped, one that sends anything is answered and hung up on; a
connection idle for IDLE_TIMEOUT_S is closed, a line is at most MAX_LINE bytes, and a request that
is not JSON, nested too deeply or not an object gets a ``ProtocolError`` reply on a connection that
stays open. Every refusal is a typed error line: ``ProtocolError``, ``TooManyConnections``,
``TooManySubscribers``, ``SubscriberTooSlow``.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import enum
import grp
import inspect
import json
import os
import socket
import stat
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any, Protocol

import structlog

from daemon.errors import DaemonError
from daemon.server.subscriber import Ended, Subscriber, close_events, hang_up, peer_of
from drivers.noise import NoiseLog

DEFAULT_SOCKET = Path("/run/tbp-rig/control.sock")
SOCKET_ENV = "TBP_CONTROL_SOCKET"
GROUP_ENV = "TBP_CONTROL_GROUP"
COMMANDS = ("status", "scan", "calibrate", "abort", "reset", "subscribe")

log = structlog.get_logger(__name__)


def default_socket() -> Path:
    """$TBP_CONTROL_SOCKET, else /run/tbp-rig/control.sock (systemd RuntimeDirectory)."""
    return Path(os.environ.get(SOCKET_ENV, str(DEFAULT_SOCKET)))


def default_group() -> str | None:
    """$TBP_CONTROL_GROUP (the operators' group the socket is given to), else None."""
    return os.environ.get(GROUP_ENV) or None


class ControlError(DaemonError):
    """Base of the control API's errors."""


class SocketInUse(ControlError):
    """Another daemon is listening on the control socket."""


class DaemonUnavailable(ControlError):
    """The client cannot reach the daemon (no socket, refused, timed out, hung up)."""

    def __init__(self, path: Path | str, reason: str) -> None:
        self.path = str(path)
        self.reason = reason
        super().__init__(f"rig daemon not reachable at {self.path}: {reason}")


class CommandFailed(ControlError):
    """The daemon refused or failed a command; carries the daemon's error type and message."""

    def __init__(self, cmd: str, error_type: str, message: str) -> None:
        self.cmd = cmd
        self.error_type = error_type
        self.message = message
        super().__init__(f"{cmd}: {error_type}: {message}")


class ProtocolError(ControlError):
    """A line on the control socket is not a valid request or reply."""


class ControlHandler(Protocol):
    """What the daemon core provides; each method may be sync or async and returns a dict."""

    def status(self) -> Any: ...

    def scan(self, **args: Any) -> Any: ...

    def calibrate(self, **args: Any) -> Any: ...

    def abort(self) -> Any: ...

    def reset(self) -> Any: ...

    def subscribe(self) -> AsyncIterator[Any]: ...


def to_jsonable(value: Any) -> Any:
    """Status objects, dataclasses and enums as plain JSON values."""
    if hasattr(value, "as_dict"):
        return to_jsonable(value.as_dict())
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return to_jsonable(dataclasses.asdict(value))
    if isinstance(value, enum.Enum):
        return value.value if isinstance(value.value, (str, int, float)) else value.name
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, float) and value != value:
        return None
    if hasattr(value, "item"):
        return value.item()
    return value


def _line(obj: dict[str, Any]) -> bytes:
    return (json.dumps(to_jsonable(obj), separators=(",", ":"), default=str) + "\n").encode()


async def _resolve(value: Any) -> Any:
    return await value if inspect.isawaitable(value) else value


class ControlServer:
    """Serves the control API on ``path`` for ``handler``; use ``async with``.

    Three pools of connections, each bounded, so that no kind of client can lock the operator
    out of ``status``, ``abort`` and ``reset``:

    * requests: at most MAX_CONNECTIONS at once; one idle for IDLE_TIMEOUT_S, or not reading its
      replies for as long, is closed;
    * subscriptions: at most MAX_SUBSCRIBERS, counted apart (a subscription leaves the request
      pool), each with a send queue of MAX_PENDING_EVENTS (daemon/server/subscriber.py);
    * overflow: a connection beyond MAX_CONNECTIONS is read for one request (at most RESERVED of
      them wait REFUSE_WAIT_S for it; beyond, only a request already received is read): ``status``,
      ``abort`` and ``reset`` are served there, ``subscribe`` goes to its own pool, anything else
      is told ``TooManyConnections``.
    """

    MAX_LINE = 64 * 1024
    # Operators' clients use one connection per request plus a few `status --follow`; each is a
    # file descriptor, and the daemon needs its descriptors for phones, pulls and the store
    # (the unit's LimitNOFILE is sized with these bounds, tests/test_systemd_units.py). A
    # subscriber that stops reading costs at most MAX_PENDING_EVENTS lines (an event is about
    # 250 bytes) and the transport's 64 KiB.
    MAX_CONNECTIONS = 16
    MAX_SUBSCRIBERS = 32
    MAX_PENDING_EVENTS = 256
    IDLE_TIMEOUT_S = 10.0  # a client writes its request as soon as it connects
    RESERVED = 16
    BACKLOG = 16
    REFUSE_WAIT_S = 0.5
    HANG_UP_GRACE_S = 1.0
    URGENT = ("status", "abort", "reset")
    MAX_DESCRIPTORS = MAX_CONNECTIONS + MAX_SUBSCRIBERS + RESERVED + BACKLOG
    """Descriptors the control socket holds at most, beyond those closed as soon as accepted."""

    def __init__(self, path: Path | str, handler: ControlHandler, *, group: str | None = None,
                 mode: int = 0o660) -> None:
        self.path = Path(path)
        self.handler = handler
        self.group = group
        self.mode = mode
        self._server: asyncio.Server | None = None
        self._connections: set[asyncio.Task[None]] = set()
        self._subscribers: set[asyncio.Task[None]] = set()
        self._overflow = 0
        self._refused_log = NoiseLog(log, "control_connection_refused", period_s=10.0)
        self._dropped_log = NoiseLog(log, "control_subscriber_dropped", period_s=10.0)
        self._sent_data_log = NoiseLog(log, "control_subscriber_sent_data", period_s=10.0)

    async def __aenter__(self) -> ControlServer:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def start(self) -> None:
        self._remove_stale()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # backlog: asyncio also accepts up to this many connections in one go before any of
        # them is served; the default (100) let a flood of clients take 100 descriptors at once.
        self._server = await asyncio.start_unix_server(
            self._serve, path=str(self.path), limit=self.MAX_LINE, backlog=self.BACKLOG
        )
        os.chmod(self.path, self.mode)
        if self.group is not None:
            try:
                gid = grp.getgrnam(self.group).gr_gid
            except KeyError:
                await self.close()
                raise ControlError(f"control socket {self.path}: no group {self.group!r}") from None
            os.chown(self.path, -1, gid)
        log.info("control_listening", path=str(self.path), mode=oct(self.mode), group=self.group)

    def _remove_stale(self) -> None:
        try:
            st = os.lstat(self.path)
        except FileNotFoundError:
            return
        if not stat.S_ISSOCK(st.st_mode):
            raise ControlError(f"control socket path {self.path} exists and is not a socket")
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            probe.connect(str(self.path))
        except (ConnectionRefusedError, FileNotFoundError):
            self.path.unlink(missing_ok=True)
            log.warning("control_stale_socket_removed", path=str(self.path))
            return
        finally:
            probe.close()
        raise SocketInUse(f"another daemon is listening on {self.path}")

    async def close(self) -> None:
        for noise in (self._refused_log, self._dropped_log, self._sent_data_log):
            noise.flush()
        if self._server is not None:
            self._server.close()
            tasks = self._connections | self._subscribers
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            await self._server.wait_closed()
            self._server = None
            with contextlib.suppress(FileNotFoundError):
                self.path.unlink()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        try:
            if len(self._connections) >= self.MAX_CONNECTIONS:
                await self._serve_overflow(task, reader, writer)
            else:
                self._connections.add(task)
                await self._serve_requests(task, reader, writer)
        except (ConnectionError, asyncio.IncompleteReadError, TimeoutError):
            pass  # gone, or not reading its replies: hung up on below
        finally:
            writer.transport.abort()  # a no-op after a hang-up; else nobody may keep the descriptor
            self._connections.discard(task)
            self._subscribers.discard(task)

    async def _serve_requests(self, task: asyncio.Task[None], reader: asyncio.StreamReader,
                              writer: asyncio.StreamWriter) -> None:
        while True:
            try:
                async with asyncio.timeout(self.IDLE_TIMEOUT_S):
                    raw = await reader.readline()
            except TimeoutError:
                break  # an idle connection holds a descriptor and a connection slot
            except ValueError:  # longer than MAX_LINE
                await self._send(writer, _error(None, "ProtocolError", f"line longer than {self.MAX_LINE} bytes"))
                break
            if not raw:
                break
            request = self._parse(raw)
            if "error" in request:
                await self._send(writer, request)
                continue
            if request["cmd"] == "subscribe":
                self._connections.discard(task)
                await self._subscribe(task, request, reader, writer)
                return
            await self._send(writer, await self._call(request))
        await hang_up(writer, self.HANG_UP_GRACE_S, reader)

    async def _send(self, writer: asyncio.StreamWriter, reply: dict[str, Any]) -> None:
        """Write one reply; a client that does not read it within IDLE_TIMEOUT_S is hung up on."""
        writer.write(_line(reply))
        async with asyncio.timeout(self.IDLE_TIMEOUT_S):
            await writer.drain()

    async def _serve_overflow(self, task: asyncio.Task[None], reader: asyncio.StreamReader,
                              writer: asyncio.StreamWriter) -> None:
        """A connection beyond MAX_CONNECTIONS: its one request is read and an urgent one served.

        The wait for the request line (REFUSE_WAIT_S) also lets a refused client read why: a reply
        sent before the client has written makes its write fail and it never reads the answer. At
        most RESERVED connections wait like that; beyond them only a request already received is
        read, so a flood never holds more descriptors than that."""
        waiting = self._overflow < self.RESERVED
        self._overflow += waiting
        try:
            request: dict[str, Any] | None = None
            with contextlib.suppress(TimeoutError, ValueError):
                async with asyncio.timeout(self.REFUSE_WAIT_S if waiting else 0.0):
                    raw = await reader.readline()
                request = self._parse(raw) if raw else None
            if request is not None and request.get("cmd") == "subscribe":
                self._overflow -= waiting  # it leaves the overflow for the subscribers' pool
                waiting = False
                await self._subscribe(task, request, reader, writer)
                return
            if request is not None and request.get("cmd") in self.URGENT:
                await self._send(writer, await self._call(request))
            else:
                self._refused_log.report(limit=self.MAX_CONNECTIONS)
                await self._send(writer, _error(request.get("id") if request else None, "TooManyConnections",
                                                f"{self.MAX_CONNECTIONS} control connections are open; try "
                                                "again (status, abort and reset are always served)"))
            await hang_up(writer, self.REFUSE_WAIT_S if waiting else 0.0, reader)
        finally:
            self._overflow -= waiting

    def _parse(self, raw: bytes) -> dict[str, Any]:
        try:
            request = json.loads(raw)
        except ValueError as exc:
            return _error(None, "ProtocolError", f"not JSON: {exc}")
        except RecursionError:
            return _error(None, "ProtocolError", "JSON nested too deeply")
        if not isinstance(request, dict) or request.get("cmd") not in COMMANDS:
            cmd = request.get("cmd") if isinstance(request, dict) else None
            return _error(request.get("id") if isinstance(request, dict) else None, "ProtocolError",
                          f"unknown command {cmd!r}; commands: {', '.join(COMMANDS)}")
        args = request.get("args", {})
        if not isinstance(args, dict):
            return _error(request.get("id"), "ProtocolError", "args must be an object")
        return {"id": request.get("id"), "cmd": request["cmd"], "args": args}

    async def _call(self, request: dict[str, Any]) -> dict[str, Any]:
        cmd, args = request["cmd"], request["args"]
        try:
            method = getattr(self.handler, cmd)
            result = await _resolve(method(**args) if cmd in ("scan", "calibrate") else method())
        except Exception as exc:  # reported to the client with its type, and logged
            log.warning("control_command_failed", cmd=cmd, error_type=type(exc).__name__,
                        error=str(exc))
            return _error(request["id"], type(exc).__name__, str(exc))
        (log.debug if cmd == "status" else log.info)("control_command", cmd=cmd)
        return {"id": request["id"], "ok": True, "result": result}

    async def _subscribe(self, task: asyncio.Task[None], request: dict[str, Any],
                         reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if len(self._subscribers) >= self.MAX_SUBSCRIBERS:
            self._refused_log.report(limit=self.MAX_SUBSCRIBERS, subscribers=True, **peer_of(writer))
            await self._send(writer, _error(request["id"], "TooManySubscribers",
                                            f"{self.MAX_SUBSCRIBERS} subscriptions are open; try again"))
            await hang_up(writer, self.HANG_UP_GRACE_S, reader)
            return
        self._subscribers.add(task)
        events = aiter(self.handler.subscribe())
        # Start waiting for the first event before taking the snapshot, so an async generator
        # handler has subscribed by then and nothing between the two is missed.
        first: asyncio.Future[Any] = asyncio.ensure_future(anext(events))
        await asyncio.sleep(0)
        try:
            status = await _resolve(self.handler.status())
            subscriber = Subscriber(reader, writer, events, _line, max_pending=self.MAX_PENDING_EVENTS)
            ended = await subscriber.run(first, _line({"id": request["id"], "ok": True, "result": status}))
            if ended is Ended.TOO_SLOW:
                self._dropped_log.report(pending_events=subscriber.dropped_pending,
                                         unsent_bytes=writer.transport.get_write_buffer_size(), **peer_of(writer))
            elif ended is Ended.SENT_DATA:
                self._sent_data_log.report(**peer_of(writer))
        finally:
            first.cancel()
            with contextlib.suppress(asyncio.CancelledError, StopAsyncIteration):
                await first
            await close_events(events)
        await hang_up(writer, self.HANG_UP_GRACE_S, reader)


def _error(request_id: Any, error_type: str, message: str) -> dict[str, Any]:
    return {"id": request_id, "ok": False, "error": {"type": error_type, "message": message}}


class ControlClient:
    """Talks to a running daemon; one connection per request, one per subscription."""

    TIMEOUT_S = 10.0

    def __init__(self, path: Path | str | None = None) -> None:
        self.path = Path(path) if path is not None else default_socket()
        self._next_id = 0

    async def _open(self) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        try:
            async with asyncio.timeout(self.TIMEOUT_S):
                return await asyncio.open_unix_connection(str(self.path), limit=ControlServer.MAX_LINE)
        except FileNotFoundError:
            raise DaemonUnavailable(self.path, "no socket (is the daemon running?)") from None
        except (ConnectionRefusedError, PermissionError) as exc:
            raise DaemonUnavailable(self.path, exc.strerror or str(exc)) from None
        except TimeoutError:
            raise DaemonUnavailable(self.path, f"no connection within {self.TIMEOUT_S:g} s") from None

    @contextlib.asynccontextmanager
    async def _connection(self) -> AsyncIterator[tuple[asyncio.StreamReader, asyncio.StreamWriter]]:
        """A connection to the daemon for the block, closed when the block ends."""
        reader, writer = await self._open()
        try:
            yield reader, writer
        finally:
            writer.close()
            with contextlib.suppress(OSError):  # ENOTCONN after a hang-up is no news
                await writer.wait_closed()

    async def _exchange(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                        cmd: str, args: dict[str, Any]) -> Any:
        self._next_id += 1
        writer.write(_line({"id": self._next_id, "cmd": cmd, "args": args}))
        try:
            async with asyncio.timeout(self.TIMEOUT_S):
                await writer.drain()
                raw = await reader.readline()
        except TimeoutError:
            raise DaemonUnavailable(self.path, f"no reply to {cmd!r} within {self.TIMEOUT_S:g} s") from None
        except ConnectionError as exc:
            raise DaemonUnavailable(self.path, f"connection lost during {cmd!r}: {exc}") from None
        if not raw:
            raise DaemonUnavailable(self.path, f"the daemon hung up during {cmd!r}")
        reply = _parse_reply(raw)
        if not reply.get("ok"):
            raise _refusal(cmd, reply)
        return reply.get("result")

    async def request(self, cmd: str, **args: Any) -> Any:
        """Send one command and return its result; CommandFailed if the daemon refuses it."""
        async with self._connection() as (reader, writer):
            return await self._exchange(reader, writer, cmd, args)

    async def status(self) -> dict[str, Any]:
        reply: dict[str, Any] = await self.request("status")
        return reply

    async def scan(self, **args: Any) -> dict[str, Any]:
        reply: dict[str, Any] = await self.request("scan", **args)
        return reply

    async def calibrate(self, **args: Any) -> dict[str, Any]:
        reply: dict[str, Any] = await self.request("calibrate", **args)
        return reply

    async def report_of(self, key: str, id_key: str, job_id: str, timeout_s: float = 60.0) -> dict[str, Any]:
        """The daemon's report of a job once it has closed its folder: ``status()[key]`` once its
        ``id_key`` is ``job_id`` (``last_scan``/``scan_id``, ``last_calibration_rotation``/``rotation_id``).
        DaemonUnavailable when none comes within ``timeout_s``."""
        try:
            async with asyncio.timeout(timeout_s):
                while True:
                    last = (await self.status()).get(key) or {}
                    if last.get(id_key) == job_id:
                        return last
                    await asyncio.sleep(0.2)
        except TimeoutError:
            raise DaemonUnavailable(self.path, f"no report of {job_id} within {timeout_s:g} s") from None

    async def abort(self) -> dict[str, Any]:
        reply: dict[str, Any] = await self.request("abort")
        return reply

    async def reset(self) -> dict[str, Any]:
        reply: dict[str, Any] = await self.request("reset")
        return reply

    async def subscribe(self) -> AsyncIterator[dict[str, Any]]:
        """The current status first, then every status event as the daemon publishes it.

        CommandFailed when the daemon refuses the subscription (TooManySubscribers) or ends it
        (SubscriberTooSlow: the client fell MAX_PENDING_EVENTS behind)."""
        async with self._connection() as (reader, writer):
            yield await self._exchange(reader, writer, "subscribe", {})
            while True:
                try:
                    raw = await reader.readline()
                except ConnectionError as exc:
                    raise DaemonUnavailable(self.path, f"subscription lost: {exc}") from None
                if not raw:
                    raise DaemonUnavailable(self.path, "the daemon closed the subscription")
                message = _parse_reply(raw)
                if message.get("ok") is False:  # the daemon ends the subscription and says why
                    raise _refusal("subscribe", message)
                if "event" not in message:
                    raise ProtocolError(f"expected an event line, got {raw[:200]!r}")
                yield message["event"]


def _refusal(cmd: str, reply: dict[str, Any]) -> CommandFailed:
    """The daemon's refusal of ``cmd`` (a reply with ok false), typed."""
    err = reply.get("error") or {}
    return CommandFailed(cmd, str(err.get("type", "Error")), str(err.get("message", "")))


def _parse_reply(raw: bytes) -> dict[str, Any]:
    try:
        reply = json.loads(raw)
    except (ValueError, RecursionError) as exc:
        raise ProtocolError(f"daemon sent a line that is not JSON: {raw[:200]!r}") from exc
    if not isinstance(reply, dict):
        raise ProtocolError(f"daemon sent {raw[:200]!r}; expected an object")
    return reply
