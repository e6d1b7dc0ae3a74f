"""Part of ``./dev bench safety``: the daemon's control socket and web server under hostile clients.

Goal (issue 28): with 20 subscribers that never read and one that sends as fast as it can after
``subscribe``, ``tbp status`` and ``tbp abort`` answer in <= 1 s and the daemon grows by <= 50 MB;
a normal web request is answered while 200 clients hold slow request headers.

``tbp daemon --sim`` runs as its own process at time scale 1: its control socket and web server
are served in real time (the simulated world's virtual clock is paced at the wall clock whenever
the loop is idle). The scans are started and aborted over and over while the hostile clients
stay, each run long enough to be aborted in another state; silent subscribers the daemon drops
are replaced, and the flooding one subscribes again each time it is hung up on. The simulated
world's clock moves only while no input is waiting (sim/clock.py), so under the flood its scans
advance slowly: they are aborted in earlier states than the quiet ones. Answer times are
ControlClient round trips (what ``tbp status`` and ``tbp abort`` do once the interpreter has
started); a few ``tbp status`` processes are timed whole.
"""

from __future__ import annotations

import asyncio
import json
import os
import select
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from daemon.logs import configure_logging
from daemon.server.control import CommandFailed, ControlClient, DaemonUnavailable
from tests.daemon_rigs import PLAN_POINTS, capsule_subject

SILENT = 20
SLOW_HEADERS = 200
CYCLES = 20
IDLE_S = 30.0
RUN_S = (3.0, 8.0, 15.0)  # a scan runs this long before it is aborted (wall s), each in a later state
TBP = [sys.executable, "-m", "cli"]


def _rss(pid: int) -> int:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError(f"no VmRSS for {pid}")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class Hostiles:
    """The silent subscribers and the flooding one, each in its own thread."""

    path: Path
    stop: threading.Event = field(default_factory=threading.Event)
    subscribed: int = 0
    refused: int = 0
    dropped: int = 0
    flood_subscriptions: int = 0
    flood_refused: int = 0
    threads: list[threading.Thread] = field(default_factory=list)

    def _subscribe(self) -> tuple[socket.socket, dict]:
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.connect(str(self.path))
        s.sendall(b'{"id": 1, "cmd": "subscribe"}\n')
        reply = b""
        while not reply.endswith(b"\n"):
            chunk = s.recv(1)
            if not chunk:
                break
            reply += chunk
        return s, json.loads(reply) if reply else {"ok": False}

    def silent(self) -> None:
        """SILENT subscribers that read their reply and nothing more; a dropped one is replaced."""
        held: list[socket.socket] = []
        poller = select.poll()
        try:
            while not self.stop.is_set():
                while len(held) < SILENT and not self.stop.is_set():
                    s, reply = self._subscribe()
                    if not reply.get("ok"):
                        self.refused += 1
                        s.close()
                        time.sleep(0.2)
                        continue
                    self.subscribed += 1
                    held.append(s)
                    poller.register(s, select.POLLRDHUP)
                for fd, _ in poller.poll(200):
                    gone = next(s for s in held if s.fileno() == fd)
                    poller.unregister(gone)
                    held.remove(gone)
                    gone.close()
                    self.dropped += 1
        finally:
            for s in held:
                s.close()

    def flood(self) -> None:
        chunk = b"x" * (1 << 20)
        while not self.stop.is_set():
            s, reply = self._subscribe()
            try:
                if not reply.get("ok"):
                    self.flood_refused += 1
                    continue
                self.flood_subscriptions += 1
                while not self.stop.is_set():
                    s.sendall(chunk)
            except OSError:
                pass
            finally:
                s.close()

    def start(self) -> None:
        self.threads = [threading.Thread(target=self.silent, daemon=True),
                        threading.Thread(target=self.flood, daemon=True)]
        for thread in self.threads:
            thread.start()

    def close(self) -> None:
        self.stop.set()
        for thread in self.threads:
            thread.join(10)


class RssPeak:
    """The daemon's peak resident set, sampled every 20 ms from a thread."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.peak = _rss(pid)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        while not self._stop.wait(0.02):
            self.peak = max(self.peak, _rss(self.pid))

    def close(self) -> int:
        self._stop.set()
        self._thread.join()
        return self.peak


async def _until_idle(client: ControlClient, status_times: list[float]) -> None:
    while True:
        started = time.perf_counter()
        state = (await client.status())["state"]
        status_times.append(time.perf_counter() - started)
        if state == "IDLE":
            return
        await asyncio.sleep(0.25)


async def _cycles(sock: Path, count: int) -> tuple[list[float], list[float], list[str]]:
    """Start a scan, let it run RUN_S, abort it, wait for IDLE; status timed throughout."""
    client = ControlClient(sock)
    status_times: list[float] = []
    abort_times: list[float] = []
    aborted_in: list[str] = []
    for i in range(count):
        await client.scan(scan_id=f"bench{i:02d}")
        deadline = time.perf_counter() + RUN_S[i % len(RUN_S)]
        state = "PREPARING"
        while time.perf_counter() < deadline:
            started = time.perf_counter()
            state = (await client.status())["state"]
            status_times.append(time.perf_counter() - started)
            await asyncio.sleep(0.25)
        started = time.perf_counter()
        await client.abort()
        abort_times.append(time.perf_counter() - started)
        aborted_in.append(state)
        await _until_idle(client, status_times)
    return status_times, abort_times, aborted_in


def _tbp_status(sock: Path, times: int) -> list[float]:
    out = []
    for _ in range(times):
        started = time.perf_counter()
        subprocess.run([*TBP, "status", "--socket", str(sock)], capture_output=True, check=True)
        out.append(time.perf_counter() - started)
    return out


async def _web(port: int) -> dict[str, float]:
    """200 slow-header clients, then 20 normal requests timed, then the slow ones' fate."""
    slow = []
    for _ in range(SLOW_HEADERS):
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.write(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
        slow.append((reader, writer))
    await asyncio.sleep(0.5)
    times = []
    for _ in range(20):
        started = time.perf_counter()
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.write(b"GET /api/rig/status HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
        answer = await reader.read()
        times.append(time.perf_counter() - started)
        writer.close()
        if not answer.startswith(b"HTTP/1.1 200 "):
            raise RuntimeError(f"the web server answered {answer[:60]!r}")
    started = time.perf_counter()

    async def closed(reader: asyncio.StreamReader) -> float:
        try:
            await reader.read()
        except ConnectionError:
            pass
        return time.perf_counter() - started

    async with asyncio.timeout(60):
        freed = await asyncio.gather(*(closed(reader) for reader, _ in slow))
    for _, writer in slow:
        writer.close()
    return {"median": statistics.median(times), "worst": max(times), "freed_s": max(freed)}


def _daemon(tmp: Path, sock: Path, port: int) -> subprocess.Popen[bytes]:
    subject = tmp / "subject.ply"
    capsule_subject().export(subject)
    cmd = [*TBP, "daemon", "--sim", "--no-panel", "--subject", str(subject), "--socket", str(sock),
           "--store", str(tmp / "scans"), "--time-scale", "1", "--plan-points", str(PLAN_POINTS),
           "--depth-decimation", "4", "--log-level", "warning", "--http", f"127.0.0.1:{port}"]
    return subprocess.Popen(cmd, stdout=(tmp / "daemon.log").open("ab"), stderr=subprocess.STDOUT,
                            env={**os.environ, "NOTIFY_SOCKET": ""})


async def _ready(sock: Path, proc: subprocess.Popen[bytes]) -> None:
    async with asyncio.timeout(180):
        while True:
            if proc.poll() is not None:
                raise RuntimeError(f"the daemon exited with {proc.returncode}")
            try:
                await ControlClient(sock).status()
                return
            except (DaemonUnavailable, CommandFailed):
                await asyncio.sleep(0.2)


def _states(states: list[str]) -> str:
    return ", ".join(f"{s} x{states.count(s)}" for s in sorted(set(states)))


def _ms(values: list[float]) -> str:
    return f"median {statistics.median(values) * 1000:7.1f} ms, worst {max(values) * 1000:7.1f} ms (n={len(values)})"


async def _idle(sock: Path, seconds: float) -> tuple[list[float], list[float]]:
    """status and abort (a no-op: no scan) timed in turn while the daemon idles."""
    client = ControlClient(sock)
    status_times: list[float] = []
    abort_times: list[float] = []
    deadline = time.perf_counter() + seconds
    while time.perf_counter() < deadline:
        for call, times in ((client.status, status_times), (client.abort, abort_times)):
            started = time.perf_counter()
            await call()
            times.append(time.perf_counter() - started)
        await asyncio.sleep(0.25)
    return status_times, abort_times


def _growth(pid: int, baseline: int, phase: object) -> tuple[object, int]:
    """(phase's result, the daemon's peak RSS above baseline during it)."""
    peak = RssPeak(pid)
    try:
        result = phase()  # type: ignore[operator]
    finally:
        top = peak.close()
    return result, top - baseline


def run() -> None:
    configure_logging(level="error", stream=sys.stderr)
    with tempfile.TemporaryDirectory() as folder:
        tmp = Path(folder)
        sock, port = tmp / "control.sock", _free_port()
        proc = _daemon(tmp, sock, port)
        try:
            asyncio.run(_ready(sock, proc))
            asyncio.run(_cycles(sock, len(RUN_S)))  # warms the scan's code paths and the allocator
            baseline = _rss(proc.pid)
            (quiet_status, quiet_abort, quiet_in), quiet_grown = _growth(
                proc.pid, baseline, lambda: asyncio.run(_cycles(sock, len(RUN_S))))
            quiet_cli = _tbp_status(sock, 5)
            hostiles = Hostiles(sock)
            hostiles.start()
            try:
                time.sleep(2.0)
                (idle_status, idle_abort), idle_grown = _growth(
                    proc.pid, baseline, lambda: asyncio.run(_idle(sock, IDLE_S)))
                (status_times, abort_times, aborted_in), grown = _growth(
                    proc.pid, baseline, lambda: asyncio.run(_cycles(sock, CYCLES)))
                cli_times = _tbp_status(sock, 5)
            finally:
                hostiles.close()
            web = asyncio.run(_web(port))
            after = _rss(proc.pid) - baseline
        finally:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
    mib = 2**20
    print(f"tbp daemon --sim at time scale 1: control socket and web served in real time; scans started, "
          f"run {'/'.join(f'{s:g}' for s in RUN_S)} s and aborted")
    print(f"quiet, {len(RUN_S)} scans        status {_ms(quiet_status)}; abort {_ms(quiet_abort)} "
          f"(aborted in {_states(quiet_in)})")
    print(f"hostile ({SILENT} silent subscribers, 1 flooding):")
    print(f"  idle {IDLE_S:g} s         status {_ms(idle_status)}; abort (no scan) {_ms(idle_abort)}")
    print(f"  {CYCLES} scans            status {_ms(status_times)}   goal <= 1 s")
    print(f"                       abort  {_ms(abort_times)}   goal <= 1 s  (aborted in "
          f"{_states(aborted_in)})")
    print(f"tbp status process     quiet {_ms(quiet_cli)}; hostile {_ms(cli_times)} (interpreter start included)")
    print(f"daemon RSS, peak above the warmed-up idle daemon ({baseline / mib:.0f} MiB): quiet scans "
          f"{quiet_grown / mib:.1f} MiB; hostile idle {idle_grown / mib:.1f} MiB; hostile scans {grown / mib:.1f} MiB; "
          f"after {after / mib:.1f} MiB   goal <= 50 MB")
    print(f"silent subscribers     {hostiles.subscribed} subscribed, {hostiles.dropped} dropped by the daemon "
          f"(too slow), {hostiles.refused} refused")
    print(f"flooding subscriber    {hostiles.flood_subscriptions} subscriptions (each hung up on after its "
          f"first bytes), {hostiles.flood_refused} refused")
    print(f"web, {SLOW_HEADERS} slow headers   normal request median {web['median'] * 1000:.1f} ms, worst "
          f"{web['worst'] * 1000:.1f} ms (n=20); every slow client closed within {web['freed_s']:.1f} s")
