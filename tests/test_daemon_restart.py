"""`tbp daemon --sim` killed with SIGKILL mid-scan, then restarted: the folder is consistent, the
interrupted scan is reported, the beam stands still, and SIGTERM stops the daemon cleanly."""

from __future__ import annotations

import asyncio
import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from daemon.server.control import ControlClient, DaemonUnavailable
from tests.daemon_rigs import PLAN_POINTS, capsule_subject

pytestmark = [pytest.mark.slow, pytest.mark.realtime]

TBP = str(Path(sys.executable).with_name("tbp"))


def _start(sock: Path, store: Path, subject: Path, log: Path) -> subprocess.Popen:
    cmd = [TBP, "daemon", "--sim", "--no-panel", "--subject", str(subject), "--socket", str(sock),
           "--store", str(store), "--time-scale", "10", "--plan-points", str(PLAN_POINTS),
           "--depth-decimation", "4", "--log-level", "warning", "--http", "off"]
    return subprocess.Popen(cmd, stdout=log.open("ab"), stderr=subprocess.STDOUT,
                            env={**os.environ, "NOTIFY_SOCKET": ""})


async def _ready(sock: Path, proc: subprocess.Popen, timeout_s: float = 120.0) -> dict:
    async with asyncio.timeout(timeout_s):
        while True:
            assert proc.poll() is None, f"daemon exited with {proc.returncode}"
            try:
                return await ControlClient(sock).status()
            except DaemonUnavailable:
                await asyncio.sleep(0.2)


async def _scan_until_captured(sock: Path, count: int) -> str:
    client = ControlClient(sock)
    events = client.subscribe()
    await anext(events)
    scan_id = (await client.scan(scan_id="killed-scan"))["scan_id"]
    async with asyncio.timeout(180):
        async for event in events:
            if event["cause"] == "captured" and event["data"]["captured"] >= count:
                return scan_id
    raise AssertionError("the scan never reached the capture")


def _stat(pid: int) -> list[str] | None:
    """The fields of /proc/PID/stat after the command's name (state, parent, ...); None once ended."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None


def _descendants(pid: int) -> set[int]:
    """The processes below ``pid`` (children, theirs, ...), from /proc."""
    parents = {}
    for entry in Path("/proc").glob("[0-9]*"):
        if (fields := _stat(int(entry.name))) is not None:
            parents[int(entry.name)] = int(fields[1])
    below, grew = set(), True
    while grew:
        more = {child for child, parent in parents.items() if parent == pid or parent in below}
        grew = bool(more - below)
        below |= more
    return below


def _still_running(pids: set[int], within_s: float) -> set[int]:
    """Those of ``pids`` still running after ``within_s`` seconds at most (zombies count as ended)."""
    deadline = time.monotonic() + within_s
    while True:
        left = {pid for pid in pids if (fields := _stat(pid)) is not None and fields[0] != "Z"}
        if not left or time.monotonic() > deadline:
            return left
        time.sleep(0.1)


def test_sigkill_mid_scan_then_restart(tmp_path: Path) -> None:
    sock, store, subject, log = tmp_path / "c.sock", tmp_path / "scans", tmp_path / "subject.ply", tmp_path / "log"
    capsule_subject().export(subject)
    first = _start(sock, store, subject, log)
    try:
        asyncio.run(_ready(sock, first))
        scan_id = asyncio.run(_scan_until_captured(sock, 30))
        helpers = _descendants(first.pid)  # the compute worker and the forkserver it comes from
        first.send_signal(signal.SIGKILL)
        first.wait(timeout=10)
    finally:
        if first.poll() is None:
            first.kill()
    assert helpers, "the daemon had no compute worker"
    left = _still_running(helpers, within_s=20.0)
    assert not left, f"processes of the killed daemon still running: {sorted(left)}"
    folder = next(store.iterdir())
    assert folder.name.endswith(scan_id)
    interrupted = json.loads((folder / "manifest.json").read_text())  # a whole manifest, never torn
    assert interrupted["in_progress"] is True and interrupted["state"] == "incomplete"

    second = _start(sock, store, subject, log)
    try:
        status = asyncio.run(_ready(sock, second))
        assert [r["scan_id"] for r in status["recovered_scans"]] == [scan_id]
        assert status["state"] == "IDLE"
        assert status["beam_speed_deg_s"] == 0.0
        second.send_signal(signal.SIGTERM)
        assert second.wait(timeout=30) == 0
    finally:
        if second.poll() is None:
            second.kill()
    manifest = json.loads((folder / "manifest.json").read_text())
    assert manifest["in_progress"] is False and manifest["state"] == "incomplete"
    assert "stopped while the scan was in progress" in manifest["reason"]
    with np.load(folder / manifest["files"]["trace"]) as trace:  # saved while the scan ran
        assert len(trace["time_s"]) > 100 and np.all(np.diff(trace["time_s"]) > 0)
    events = [json.loads(line)["event"] for line in (folder / "events.jsonl").read_text().splitlines()]
    assert events[0] == "scan_started" and events[-1] == "scan_recovered"
    verified = [i for i in manifest["images"] if i["status"] == "verified"]
    assert verified, log.read_text()[-2000:]
    for image in verified:
        assert hashlib.sha256((folder / image["file"]).read_bytes()).hexdigest() == image["sha256"]
    assert not [p for p in folder.rglob(".*.tmp")]
