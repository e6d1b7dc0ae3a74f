"""The probe of issue 14, end to end: `tbp daemon --sim` under `ulimit -n 256` while a client
holds 300 control connections. The daemon refuses what it cannot serve, never runs out of file
descriptors, and a scan started in the middle of it ends with a recorded outcome (before the
fix, EMFILE killed the scan task and left the rig stuck in STORING)."""

from __future__ import annotations

import asyncio
import json
import os
import resource
import socket
import subprocess
from pathlib import Path
from typing import Any

import pytest

from daemon.server.control import CommandFailed, ControlClient, DaemonUnavailable
from tests.daemon_rigs import BODY_TEXEL_MM, capsule_subject, sparse_rig_file
from tests.test_daemon_restart import TBP, _ready

pytestmark = [pytest.mark.slow, pytest.mark.realtime]

LIMIT = 256
HELD = 300


def _hold_connections(sock: Path, count: int) -> list[socket.socket]:
    held = []
    for _ in range(count):
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            s.connect(str(sock))
        except OSError:  # the daemon's backlog is full: that connection is refused, which is fine
            s.close()
            continue
        held.append(s)
    return held


async def _retrying(call: Any) -> Any:
    """The daemon serves 16 connections and closes idle ones; an operator's command is retried
    until it gets a slot, as `tbp` users would."""
    async with asyncio.timeout(300):
        while True:
            try:
                return await call()
            except CommandFailed as exc:
                assert exc.error_type == "TooManyConnections", exc
                await asyncio.sleep(0.2)
            except DaemonUnavailable:  # a flood beyond the refusal queue is hung up on at once
                await asyncio.sleep(0.2)


async def _scan_to_the_end(sock: Path) -> dict:
    client = ControlClient(sock)

    async def subscribed() -> Any:
        events = client.subscribe()
        await anext(events)
        return events

    events = await _retrying(subscribed)
    scan_id = (await _retrying(lambda: client.scan(scan_id="crowded")))["scan_id"]
    async with asyncio.timeout(600):
        async for event in events:
            if event["kind"] == "transition" and event["state"] in ("IDLE", "FAULT") and event["previous"] != "IDLE":
                return {"scan_id": scan_id, **event}
    raise AssertionError("the scan never ended")


def test_three_hundred_connections_under_a_256_descriptor_limit(tmp_path: Path) -> None:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and hard < HELD + 64:
        pytest.skip(f"this test process may open only {hard} files; it needs {HELD + 64}")
    resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, min(hard, 4096)), hard))
    sock, store, subject, log = tmp_path / "c.sock", tmp_path / "scans", tmp_path / "subject.ply", tmp_path / "log"
    capsule_subject().export(subject)
    cmd = [TBP, "daemon", "--sim", "--rig", str(sparse_rig_file(tmp_path)), "--no-panel", "--subject", str(subject),
           "--socket", str(sock),
           "--store", str(store), "--time-scale", "10", "--plan-points", "1500", "--depth-decimation", "4", "--body-texel-mm", BODY_TEXEL_MM,
           "--log-level", "warning", "--http", "off"]
    limited = ["sh", "-c", f'ulimit -n {LIMIT} && exec "$@"', "sh", *cmd]  # as the probe did; no preexec_fn
    proc = subprocess.Popen(limited, stdout=log.open("ab"), stderr=subprocess.STDOUT,
                            env={**os.environ, "NOTIFY_SOCKET": ""})
    held: list[socket.socket] = []
    try:
        asyncio.run(_ready(sock, proc))
        held = _hold_connections(sock, HELD)
        ended = asyncio.run(_scan_to_the_end(sock))
        assert proc.poll() is None, "the daemon died"
        status = asyncio.run(_retrying(ControlClient(sock).status))
    finally:
        for s in held:
            s.close()
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
    assert ended["state"] in ("IDLE", "FAULT")
    folder = next(p for p in store.iterdir() if p.name.endswith("crowded"))
    manifest = json.loads((folder / "manifest.json").read_text())
    assert manifest["in_progress"] is False, "the scan folder was left open"
    assert manifest["state"] in ("complete", "fault", "incomplete")
    if ended["state"] == "IDLE":
        assert manifest["state"] == "complete"
    assert status["state"] == ended["state"]
    text = log.read_text(errors="replace")
    assert "Too many open files" not in text, text[-3000:]
