"""`tbp daemon --sim`'s own stdout through a scan: JSON lines only, each naming the scan, the
state and (in a driver's lines) the device, as README and docs/install.md promise."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from daemon.server.control import ControlClient, DaemonUnavailable
from tests.daemon_rigs import BODY_TEXEL_MM, PLAN_POINTS, capsule_subject, sparse_rig_file

pytestmark = [pytest.mark.slow, pytest.mark.realtime]

TBP = str(Path(sys.executable).with_name("tbp"))


async def _scan(sock: Path, proc: subprocess.Popen) -> str:
    async with asyncio.timeout(300):
        while True:
            assert proc.poll() is None, f"daemon exited with {proc.returncode}"
            try:
                await ControlClient(sock).status()
                break
            except DaemonUnavailable:
                await asyncio.sleep(0.2)
        client = ControlClient(sock)
        events = client.subscribe()
        await anext(events)
        scan_id = (await client.scan(scan_id="logged-scan"))["scan_id"]
        async for event in events:
            if event["kind"] == "transition" and event["state"] == "IDLE":
                return scan_id
    raise AssertionError("the scan never ended")


def test_the_daemons_stdout_is_json_lines_naming_scan_state_and_device(tmp_path: Path) -> None:
    sock, subject = tmp_path / "c.sock", tmp_path / "subject.ply"
    capsule_subject().export(subject)
    out, err = tmp_path / "stdout", tmp_path / "stderr"
    cmd = [TBP, "daemon", "--sim", "--rig", str(sparse_rig_file(tmp_path)), "--subject", str(subject),
           "--socket", str(sock), "--store", str(tmp_path / "scans"), "--time-scale", "20", "--plan-points", str(PLAN_POINTS),
           "--depth-decimation", "4", "--body-texel-mm", BODY_TEXEL_MM, "--log-level", "info", "--http", "off"]
    proc = subprocess.Popen(cmd, stdout=out.open("wb"), stderr=err.open("wb"),
                            env={**os.environ, "NOTIFY_SOCKET": ""})
    try:
        scan_id = asyncio.run(_scan(sock, proc))
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=60) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
    text = out.read_text()
    lines = []
    for number, raw in enumerate(text.splitlines(), 1):
        try:
            lines.append(json.loads(raw))
        except ValueError:
            pytest.fail(f"stdout line {number} is not JSON: {raw[:200]!r}")
    assert lines[-1]["event"] == "daemon_stopped"
    for line in lines:
        assert {"timestamp", "level", "event", "scan_id", "state", "device"} <= set(line), line
    during = [x for x in lines if x["scan_id"] == scan_id]
    assert {"PREPARING", "DEPTH_SWEEP", "CAPTURING", "STORING"} <= {x["state"] for x in during}
    assert all(x["state"] == "IDLE" for x in lines if x["event"] == "daemon_ready")
    devices = {x["device"] for x in lines if x.get("device")}
    assert {"drive", "panel"} <= devices and any(d.startswith("cam") for d in devices)
    compute = [x for x in lines if x.get("process") == "compute"]  # the worker process logs JSON too
    assert compute and all(x["level"] != "debug" for x in compute)  # at the daemon's level
    assert not err.read_text()
