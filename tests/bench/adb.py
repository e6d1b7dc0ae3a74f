"""ADB pull benchmark: a 20 MB file from the simulated phone over TCP loopback.

The simulated phone runs in its own process (``sim.processes.phone.serve``, as ``tbp sim phone``
does) so the client under test has this process to itself. Measured, median of RUNS pulls each:

* the project's client (AdbConnection + SyncClient.pull: sha256 and fsync'd atomic file
  included), on a standard asyncio loop in real time;
* the standard adb client (Debian's ``adb``, with a private server port and a throwaway HOME),
  when installed, pulling the same file; its time includes starting the ``adb pull`` process
  (its server and connection are up beforehand), ours includes sha256 and fsync.

Runs alternate between the two clients so both see the same load on a shared machine.

Goal: >= 100 MB/s, and at least as fast as the standard adb client.

    python -m tests.bench adb
"""

from __future__ import annotations

import asyncio
import os
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

GOAL_MB_S = 100.0
SIZE = 20_000_000
RUNS = 7
REMOTE = "/sdcard/DCIM/bench.bin"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start_phone(port: int) -> subprocess.Popen:
    code = ("import asyncio, argparse, sys; from sim.processes.phone import add_arguments, serve; "
            "p = argparse.ArgumentParser(); add_arguments(p); "
            "sys.exit(asyncio.run(serve(p.parse_args(sys.argv[1:]))))")
    proc = subprocess.Popen([sys.executable, "-c", code, "--port", str(port), "--serial", "BENCH001",
                             "--file", f"{REMOTE}={SIZE}"], stdout=subprocess.PIPE, text=True)
    proc.stdout.readline()  # the "listening" line
    return proc


async def _our_client(port: int) -> object:
    import structlog

    from drivers.adb.auth import AdbKey
    from drivers.adb.connection import AdbConnection
    from drivers.adb.transport import open_tcp

    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(30))
    conn = AdbConnection(await open_tcp("127.0.0.1", port), AdbKey.generate("bench@host"))
    await conn.connect()
    return conn


async def _our_pull(conn, dest: Path, cpu_ms: list[float]) -> float:
    start, cpu = time.perf_counter(), time.process_time()
    async with await conn.sync() as sync:
        size, _ = await sync.pull(REMOTE, dest)
    rate = size / (time.perf_counter() - start) / 1e6
    cpu_ms.append((time.process_time() - cpu) * 1000)
    dest.unlink()
    return rate


class _StandardAdb:
    """Debian's adb with a private server port and a throwaway HOME (so a throwaway key)."""

    def __init__(self, adb: str, port: int, folder: Path) -> None:
        self.adb = adb
        self.serial = f"127.0.0.1:{port}"
        self.env = {**os.environ, "HOME": str(folder), "ANDROID_SDK_HOME": str(folder),
                    "ANDROID_ADB_SERVER_PORT": str(_free_port())}

    def _run(self, *args: str, check: bool = False) -> None:
        subprocess.run([self.adb, *args], env=self.env, capture_output=True, timeout=60, check=check)

    def connect(self) -> None:
        self._run("connect", self.serial)
        self._run("-s", self.serial, "wait-for-device", check=True)

    def pull(self, dest: Path) -> float:
        start = time.perf_counter()
        self._run("-s", self.serial, "pull", REMOTE, str(dest), check=True)
        rate = dest.stat().st_size / (time.perf_counter() - start) / 1e6
        dest.unlink()
        return rate

    def kill_server(self) -> None:
        self._run("kill-server")


async def _our_transfer(conn) -> float:
    """The same pull into memory: the wire protocol alone, without sha256, disk write and fsync."""
    start = time.perf_counter()
    async with await conn.sync() as sync:
        size = len(await sync.pull_bytes(REMOTE))
    return size / (time.perf_counter() - start) / 1e6


async def _measure(port: int, folder: Path) -> tuple[list[float], list[float], list[float], list[float] | None]:
    """Alternate our pulls with adb's so both see the same machine load."""
    conn = await _our_client(port)
    adb_path = shutil.which("adb")
    standard = _StandardAdb(adb_path, port, folder) if adb_path else None
    ours: list[float] = []
    transfer: list[float] = []
    cpu_ms: list[float] = []
    theirs: list[float] = []
    try:
        if standard is not None:
            standard.connect()
        for i in range(RUNS):
            ours.append(await _our_pull(conn, folder / f"ours{i}.bin", cpu_ms))
            transfer.append(await _our_transfer(conn))
            if standard is not None:
                theirs.append(standard.pull(folder / f"adb{i}.bin"))
    finally:
        await conn.close()
        if standard is not None:
            standard.kill_server()
    return ours, transfer, cpu_ms, theirs if standard is not None else None


def run() -> None:
    port = _free_port()
    phone = _start_phone(port)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            ours, transfer, cpu_ms, standard = asyncio.run(_measure(port, Path(tmp)))
    finally:
        phone.terminate()
        phone.wait(timeout=10)
    median = statistics.median(ours)
    print(f"project client pull 20 MB over TCP loopback (sha256 + fsync included): {median:.0f} MB/s "
          f"median of {RUNS} (min {min(ours):.0f}, max {max(ours):.0f})   goal >= {GOAL_MB_S:.0f} MB/s "
          f"{'OK' if median >= GOAL_MB_S else 'MISSED'}")
    print(f"  same client, transfer only (into memory, no sha256/disk): {statistics.median(transfer):.0f} MB/s "
          f"median of {RUNS}")
    print(f"  client CPU per 20 MB pull: {statistics.median(cpu_ms):.0f} ms median "
          f"(= {SIZE / 1e3 / statistics.median(cpu_ms):.0f} MB/s of CPU); load average {os.getloadavg()[0]:.1f}")
    if standard is None:
        print("standard adb client: not installed (apt-get install adb) - comparison skipped")
        return
    theirs = statistics.median(standard)
    print(f"standard adb client pull, same file and phone: {theirs:.0f} MB/s median of {RUNS} "
          f"(min {min(standard):.0f}, max {max(standard):.0f})   goal: project >= adb "
          f"{'OK' if median >= theirs else 'MISSED'} (ratio {median / theirs:.2f})")
