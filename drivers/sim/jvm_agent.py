"""The capture agent's JVM build (agent/) run by a simulated phone in place of the Python twin.

When the host runs ``CLASSPATH=<jar> app_process / com.tbp.CaptureAgent ARGS`` on a shell
stream, the phone copies the jar the host pushed to a host folder and runs ``java -cp JAR
com.tbp.CaptureAgent ARGS`` with stdin, stdout and stderr on that stream, as adbd runs a shell
command. The agent's core is then the real one: framing, ids, error answers, the camera queue,
the image folder, the READY line, the exit when the shell stream closes. Two things are the
simulator's (agent/src/jvm): the agent's abstract socket and its camera are carried on one
UNIX socket to this phone, the bus (frames of kind, channel, length, payload; ``SimBus.java``).
Each host stream to ``localabstract:NAME`` is a bus channel, and each camera call (info,
focus, capture, clock) is answered by this phone's camera (drivers/sim/phone.py) on the event
loop's clock. /sdcard/DCIM/tbp is a host folder mounted into the phone's file system: the agent
writes the images, adbd's sync service serves them.

Virtual time: the agent computes in real time while the phone's clock may be virtual. Every
frame the phone sends is followed by a SYNC, which the agent acknowledges once its dispatcher
has handled everything before it. While a SYNC is unanswered, from the start until READY, and
from the end of the shell stream until the process has exited and is cleaned up, the phone
holds the loop's clock with a job in an executor (a VirtualTimeLoop stands still while one
runs, sim/clock.py). The agent's work so takes no simulated time and a run is as deterministic
as with the twin. An agent that holds the clock for HOLD_LIMIT_S real seconds is killed.
"""

from __future__ import annotations

import asyncio
import functools
import itertools
import json
import os
import shutil
import socket
import struct
import tempfile
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

import structlog

from drivers.adb.errors import AdbError
from drivers.adb.streams import AdbStream
from drivers.phone import protocol
from drivers.sim.phone_agent import CaptureFailure

if TYPE_CHECKING:
    from drivers.sim.phone import SimulatedPhone

log = structlog.get_logger("drivers.sim.jvm_agent")

# Frame kinds (agent/src/jvm/com/tbp/agent/sim/SimBus.java): from the phone, then from the agent.
OPEN, DATA, CLOSE, REPLY, SYNC = 1, 2, 3, 4, 5
LISTEN, SENT, CLOSED, CALL, SYNCED = 11, 12, 13, 14, 15
_HEADER = struct.Struct(">BII")
MAX_FRAME = 1 << 20  # the agent sends answer lines (<= 64 KiB) and small camera calls
# A short-lived, small JVM: start-up time matters more than peak speed.
JAVA_OPTIONS = ("-XX:TieredStopAtLevel=1", "-XX:+UseSerialGC", "-Xshare:auto", "-Xmx96m")


def _frame(kind: int, channel: int, payload: bytes = b"") -> bytes:
    return _HEADER.pack(kind, channel, len(payload)) + payload


def app_process_args(argv: list[str]) -> tuple[str, list[str]] | str:
    """(class, its arguments) of ``app_process [vm-options] cmd-dir [--options] class [args]``,
    or the error app_process prints."""
    i = 1
    while i < len(argv) and argv[i].startswith("-"):
        i += 1
    i += 1  # the command directory ("/")
    while i < len(argv) and argv[i].startswith("--"):
        i += 1
    if i >= len(argv):
        return "Error: no class name or --zygote supplied.\n"
    return argv[i], argv[i + 1:]


class JvmRuntime:
    """Runs the jar the host pushed with ``java`` whenever the host starts the agent.

    Attributes:
        exits: each agent process's exit status, in order (0: it ended because its shell stream
            closed; negative: killed by that signal).
        killed: processes killed for holding the clock HOLD_LIMIT_S.
    """

    HOLD_LIMIT_S = 30.0  # real seconds

    def __init__(self, phone: SimulatedPhone, jar: Path | None, java: str = "java") -> None:
        self.phone = phone
        self.jar = jar
        self.java = java
        self._folder = tempfile.TemporaryDirectory(prefix=f"tbp-sim-{phone.serial}-")
        self.root = Path(self._folder.name)
        self.storage = self.root / "DCIM-tbp"
        self.storage.mkdir()
        phone.fs.mount(phone.IMAGE_DIR, self.storage)
        self.exits: list[int] = []
        self.killed = 0
        self._process: _JvmProcess | None = None
        self._runs = itertools.count()

    @property
    def running(self) -> bool:
        return self._process is not None

    @property
    def process(self) -> asyncio.subprocess.Process | None:
        """The agent's JVM while it runs."""
        return None if self._process is None else self._process.proc

    def installed_jar(self) -> bytes:
        if self.jar is None:
            raise ValueError("a simulated phone with the jvm agent runtime and agent_installed=True needs agent_jar")
        return self.jar.read_bytes()

    def crash(self) -> None:
        if self._process is not None:
            self._process.kill("crash_agent fault")

    async def app_process(self, argv: list[str], env: dict[str, str], stream: AdbStream) -> None:
        self._process = process = _JvmProcess(self, next(self._runs))
        try:
            await process.run(argv, env, stream)
        finally:
            self._process = None


class _ClockHold:
    """Holds a virtual-time loop's clock while acquired (counted): one job waits in an executor.

    After ``limit_s`` real seconds held, ``on_timeout`` runs and the hold lets go.
    """

    def __init__(self, limit_s: float, on_timeout: Callable[[], None]) -> None:
        self.limit_s = limit_s
        self.on_timeout = on_timeout
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="agent-jvm-hold")
        self._count = 0
        self._event: threading.Event | None = None
        self._closed = False

    def acquire(self) -> None:
        if self._closed:
            return
        self._count += 1
        if self._count == 1:
            event = self._event = threading.Event()
            job = asyncio.get_running_loop().run_in_executor(self._executor, event.wait, self.limit_s)
            job.add_done_callback(functools.partial(self._ended, event))

    def release(self) -> None:
        if self._count > 0:
            self._count -= 1
            if self._count == 0 and self._event is not None:
                self._event.set()

    def _ended(self, event: threading.Event, job: asyncio.Future[bool]) -> None:
        if not job.cancelled() and job.result() is False and self._event is event:
            self._count, self._event = 0, None
            self.on_timeout()

    def close(self) -> None:
        self._closed = True
        self._count = 0
        if self._event is not None:
            self._event.set()
        self._executor.shutdown(wait=False)


class _JvmProcess:
    """One run of the agent's JVM, from app_process to its exit."""

    def __init__(self, runtime: JvmRuntime, run: int) -> None:
        self.runtime = runtime
        self.phone = runtime.phone
        self.hold = _ClockHold(runtime.HOLD_LIMIT_S, self._stuck)
        self.proc: asyncio.subprocess.Process | None = None
        self.jar_path = runtime.root / f"agent-{run}.jar"
        self.bus_path = runtime.root / f"bus-{run}.sock"
        self._writer: asyncio.StreamWriter | None = None
        self._seq = itertools.count(1)
        self._syncs: dict[int, asyncio.Future[None]] = {}
        self._channels: dict[int, asyncio.Queue[bytes | None]] = {}
        self._channel_ids = itertools.count(1)
        self._sessions: set[AdbStream] = set()
        self._calls: set[asyncio.Task[None]] = set()
        self._socket_name: str | None = None
        self._starting = False

    # ---------------------------------------------------------------- life
    async def run(self, argv: list[str], env: dict[str, str], shell: AdbStream) -> None:
        command = app_process_args(argv)
        java = shutil.which(self.runtime.java)
        if isinstance(command, str) or java is None:
            await shell.write(command.encode() if isinstance(command, str) else
                              f"/system/bin/sh: {self.runtime.java}: inaccessible or not found "
                              "(the jvm agent runtime needs a JDK: apt-get install default-jdk-headless)\n".encode())
            return
        main_class, args = command
        jar = self.phone.fs.read(env.get("CLASSPATH", ""))
        if jar is not None:
            self.jar_path.write_bytes(jar)
        listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        listener.bind(str(self.bus_path))
        listener.listen(1)
        listener.setblocking(False)
        self._starting = True
        self.hold.acquire()  # the start: until READY reaches the host or the process ends
        tasks: list[asyncio.Task[Any]] = []
        cancelled = False
        try:
            self.proc = await asyncio.create_subprocess_exec(
                java, *JAVA_OPTIONS, "-cp", str(self.jar_path), main_class, *args,
                stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT,
                env={"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "LANG": "C.UTF-8",
                     "TBP_SIM_BUS": str(self.bus_path), "TBP_SIM_STORAGE": str(self.runtime.storage)})
            log.info("sim_phone_agent_started", serial=self.phone.serial, runtime="jvm", pid=self.proc.pid)
            tasks = [asyncio.create_task(self._serve_bus(listener)), asyncio.create_task(self._pump_out(shell)),
                     asyncio.create_task(self._pump_in(shell))]
            exited = asyncio.create_task(self.proc.wait())
            try:
                await asyncio.wait({tasks[2], exited}, return_when=asyncio.FIRST_COMPLETED)
            except asyncio.CancelledError:  # adbd dropped the shell stream (the link is gone)
                cancelled = True
            cancelled |= await self._end(exited)
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            await self._clean_up(listener)
        if cancelled:
            raise asyncio.CancelledError

    async def _end(self, exited: asyncio.Task[int]) -> bool:
        """The shell stream ended or the process did: close stdin, wait for the exit with the clock
        held (the agent exits by itself; a hold over HOLD_LIMIT_S kills it). True if cancelled
        meanwhile: the cancellation is passed on once the agent has gone."""
        self.hold.acquire()
        cancelled = False
        assert self.proc is not None
        if self.proc.stdin is not None and not self.proc.stdin.is_closing():
            self.proc.stdin.close()
        while not exited.done():  # adbd cancels its services again as it closes the link: keep waiting
            try:
                await asyncio.wait({exited})
            except asyncio.CancelledError:
                cancelled = True
        self.runtime.exits.append(exited.result())
        log.info("sim_phone_agent_stopped", serial=self.phone.serial, runtime="jvm", status=exited.result())
        return cancelled

    async def _clean_up(self, listener: socket.socket) -> None:
        listener.close()
        self.bus_path.unlink(missing_ok=True)
        if self._socket_name is not None:
            self.phone.listeners.pop(self._socket_name, None)
        for task in self._calls:
            task.cancel()
        await asyncio.gather(*self._calls, return_exceptions=True)
        for session in list(self._sessions):  # its sockets close with the process
            await session.close()
        for seq in list(self._syncs):
            self._synced(seq)
        self.hold.close()

    def kill(self, reason: str) -> None:
        if self.proc is not None and self.proc.returncode is None:
            log.warning("sim_phone_agent_killed", serial=self.phone.serial, reason=reason)
            self.hold.acquire()  # until its end is cleaned up
            self.proc.kill()

    def _stuck(self) -> None:
        log.error("sim_phone_agent_stuck", serial=self.phone.serial, limit_s=self.runtime.HOLD_LIMIT_S)
        self.runtime.killed += 1
        self.kill(f"held the clock {self.runtime.HOLD_LIMIT_S:g} s")

    def _started(self) -> None:
        if self._starting:
            self._starting = False
            self.hold.release()

    # ---------------------------------------------------------------- shell stream
    async def _pump_in(self, shell: AdbStream) -> None:
        """The shell stream's input to the agent's stdin; returns when the host closes it."""
        assert self.proc is not None and self.proc.stdin is not None
        while data := await shell.read():
            if not self.proc.stdin.is_closing():
                self.proc.stdin.write(data)

    async def _pump_out(self, shell: AdbStream) -> None:
        """The agent's stdout and stderr to the shell stream; the READY line goes out once the
        phone has taken in everything the agent sent before it (its socket is bound)."""
        assert self.proc is not None and self.proc.stdout is not None
        pending = bytearray()
        forwarding = True
        while chunk := await self.proc.stdout.read(1 << 16):
            if not self._starting:
                forwarding = await _forward(shell, chunk, forwarding)
                continue
            pending += chunk
            while self._starting and (end := pending.find(b"\n")) >= 0:
                line = bytes(pending[:end + 1])
                del pending[:end + 1]
                if line.startswith(protocol.READY_PREFIX.encode()):
                    await self._send(None)
                    self._started()
                forwarding = await _forward(shell, line, forwarding)
            if pending and (not self._starting or len(pending) > protocol.MAX_LINE):
                forwarding = await _forward(shell, bytes(pending), forwarding)
                pending.clear()
        if pending:
            await _forward(shell, bytes(pending), forwarding)
        self._started()

    # ---------------------------------------------------------------- the bus
    def _send(self, kind: int | None, channel: int = 0, payload: bytes = b"") -> asyncio.Future[None]:
        """Sends a frame (none for kind None) and a SYNC; the future is done once the agent acknowledged."""
        done: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        writer = self._writer
        if writer is None or writer.is_closing():
            done.set_result(None)
            return done
        seq = next(self._seq)
        writer.write((b"" if kind is None else _frame(kind, channel, payload)) + _frame(SYNC, seq))
        self._syncs[seq] = done
        self.hold.acquire()
        return done

    def _synced(self, seq: int) -> None:
        done = self._syncs.pop(seq, None)
        if done is not None:
            done.set_result(None)
            self.hold.release()

    async def _serve_bus(self, listener: socket.socket) -> None:
        connection, _ = await asyncio.get_running_loop().sock_accept(listener)
        reader, self._writer = await asyncio.open_unix_connection(sock=connection)
        try:
            while True:
                try:
                    kind, channel, length = _HEADER.unpack(await reader.readexactly(_HEADER.size))
                except asyncio.IncompleteReadError:
                    return
                if length > MAX_FRAME:
                    self.kill(f"bus frame of {length} bytes")
                    return
                self._on_frame(kind, channel, await reader.readexactly(length))
        finally:
            self._writer.close()
            self._writer = None
            for seq in list(self._syncs):
                self._synced(seq)
            for queue in self._channels.values():
                queue.put_nowait(None)

    def _on_frame(self, kind: int, channel: int, payload: bytes) -> None:
        if kind == SYNCED:
            self._synced(channel)
        elif kind == SENT or kind == CLOSED:
            queue = self._channels.get(channel)
            if queue is not None:
                queue.put_nowait(payload if kind == SENT else None)
        elif kind == CALL:
            try:
                request = json.loads(payload)
            except ValueError:
                self.kill(f"malformed camera call {payload[:80]!r}")
                return
            task = asyncio.create_task(self._call(channel, request))
            self._calls.add(task)
            task.add_done_callback(self._calls.discard)
        elif kind == LISTEN:
            self._socket_name = payload.decode()
            self.phone.listeners[self._socket_name] = self._session
        else:
            self.kill(f"unknown bus frame kind {kind}")

    async def _call(self, call_id: int, request: dict[str, Any]) -> None:
        reply, tail = await camera_call(self.phone, request)
        self._send(REPLY, call_id, json.dumps(reply).encode() + b"\n" + tail)

    # ---------------------------------------------------------------- the agent's socket
    async def _session(self, stream: AdbStream) -> None:
        """One host stream to ``localabstract:NAME``: a bus channel to the agent."""
        if self._writer is None:  # the agent has gone; its listener is being removed
            return
        channel = next(self._channel_ids)
        answers: asyncio.Queue[bytes | None] = asyncio.Queue()
        self._channels[channel] = answers
        self._sessions.add(stream)
        self._send(OPEN, channel)
        forward = asyncio.create_task(self._forward_answers(stream, answers))
        try:
            while data := await stream.read():
                self._send(DATA, channel, data)
            self._send(CLOSE, channel)
        finally:
            forward.cancel()
            await asyncio.gather(forward, return_exceptions=True)
            self._channels.pop(channel, None)
            self._sessions.discard(stream)

    async def _forward_answers(self, stream: AdbStream, answers: asyncio.Queue[bytes | None]) -> None:
        while (data := await answers.get()) is not None:
            if self.phone.answer_delay_s > 0:
                await asyncio.sleep(self.phone.answer_delay_s)
            await stream.write(data)
        await stream.close()  # the agent closed this connection


async def camera_call(phone: SimulatedPhone, request: dict[str, Any]) -> tuple[dict[str, Any], bytes]:
    """One camera call of the agent's simulator platform: (its JSON answer, the JPEG after it)."""
    op = request.get("op")
    try:
        if op == "info":
            return {"ok": True, **phone.camera_info()}, b""
        if op == "focus":
            diopters, stationary_ns = await phone.move_lens(float(request["diopters"]))
            return {"ok": True, "diopters": diopters, "stationary_at_ns": stationary_ns}, b""
        if op == "capture":
            still = await phone.expose(float(request["exposure_s"]))
            return {"ok": True, "sensor_timestamp_ns": still.sensor_timestamp_ns, "exposure_s": still.exposure_s,
                    "focus_diopters": still.focus_diopters}, still.jpeg
        if op == "clock":
            return {"ok": True, "device_ns": await phone.read_clock()}, b""
        return {"ok": False, "code": "CAMERA_ERROR", "message": f"unknown camera call {op!r}"}, b""
    except CaptureFailure as exc:
        return {"ok": False, "code": "CAPTURE_FAILED", "message": str(exc)}, b""
    except (ValueError, TypeError, KeyError, RuntimeError, OSError) as exc:  # as the twin answers them
        log.error("sim_phone_agent_error", serial=phone.serial, op=op, error=repr(exc))
        return {"ok": False, "code": "CAMERA_ERROR", "message": f"{op}: {exc!r}"}, b""


async def _forward(shell: AdbStream, data: bytes, forwarding: bool) -> bool:
    """Writes to the shell stream while it takes data; False once it failed (the rest is dropped)."""
    if forwarding:
        try:
            await shell.write(data)
        except AdbError:
            return False
    return forwarding
