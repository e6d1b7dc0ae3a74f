"""sd_notify datagrams and the health-gated watchdog (daemon/server/notify.py)."""

from __future__ import annotations

import asyncio
import os
import socket
import uuid

import pytest

from daemon.server.notify import SystemdNotifier, run_watchdog, watchdog_period_s
from sim.clock import run_virtual


def _receiver(address: str) -> socket.socket:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + address[1:] if address.startswith("@") else address)
    sock.setblocking(False)
    return sock


def _drain(sock: socket.socket) -> list[str]:
    out = []
    while True:
        try:
            out.append(sock.recv(4096).decode())
        except BlockingIOError:
            return out


@pytest.fixture(params=["path", "abstract"])
def listener(request, tmp_path):
    address = str(tmp_path / "notify.sock") if request.param == "path" else f"@tbp-test-{uuid.uuid4().hex}"
    sock = _receiver(address)
    yield address, sock
    sock.close()


def test_datagrams_reach_the_notify_socket(listener):
    address, sock = listener
    n = SystemdNotifier.from_env({"NOTIFY_SOCKET": address})
    assert n.enabled
    assert n.ready("idle, 7 phones")
    assert n.status("CAPTURING angle 12/48\nsecond line dropped")
    assert n.watchdog()
    assert n.stopping()
    assert _drain(sock) == [
        "READY=1\nSTATUS=idle, 7 phones",
        "STATUS=CAPTURING angle 12/48",
        "WATCHDOG=1",
        "STOPPING=1",
    ]
    n.close()


def test_no_op_outside_systemd(monkeypatch):
    n = SystemdNotifier.from_env({})
    assert not n.enabled and n.ready() is False and n.watchdog() is False
    assert asyncio.run(run_watchdog(n, lambda: True, period_s=0.1)) is None
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    assert not SystemdNotifier().enabled


def test_default_reads_the_environment(listener, monkeypatch):
    address, sock = listener
    monkeypatch.setenv("NOTIFY_SOCKET", address)
    assert SystemdNotifier().ready()
    assert _drain(sock) == ["READY=1"]
    assert not SystemdNotifier("").enabled


def test_unreachable_notify_socket_reports_failure(tmp_path):
    n = SystemdNotifier(str(tmp_path / "gone.sock"))
    assert n.ready() is False


def test_watchdog_period_from_environment():
    pid = os.getpid()
    assert watchdog_period_s({"WATCHDOG_USEC": "30000000"}) == 10.0
    assert watchdog_period_s({"WATCHDOG_USEC": "30000000", "WATCHDOG_PID": str(pid)}) == 10.0
    assert watchdog_period_s({"WATCHDOG_USEC": "20000000", "WATCHDOG_PID": str(pid + 1)}) is None
    assert watchdog_period_s({}) is None
    assert watchdog_period_s({"WATCHDOG_USEC": "soon"}) is None


def test_watchdog_pings_only_while_healthy(listener):
    address, sock = listener
    notifier = SystemdNotifier(address)

    async def scenario() -> list[int]:
        loop = asyncio.get_running_loop()
        start = loop.time()
        health = {"ok": True}
        task = asyncio.create_task(
            run_watchdog(notifier, lambda: health["ok"],
                         period_s=watchdog_period_s({"WATCHDOG_USEC": "3000000"}))
        )
        counts = []
        for t_s, ok in ((0.05, True), (3.05, False), (6.05, True), (9.05, True)):
            await asyncio.sleep(start + t_s - loop.time())
            counts.append(len(_drain(sock)))
            health["ok"] = ok
        task.cancel()
        return counts

    # 1 s pings on virtual time: 1 at t=0; 3 more by 3 s; none while unhealthy; 3 after.
    assert run_virtual(scenario()) == [1, 3, 0, 3]


@pytest.mark.slow
@pytest.mark.realtime
def test_sim_daemon_speaks_the_type_notify_protocol(tmp_path):
    """`tbp daemon --sim` as systemd runs it: READY=1 once up, watchdog pings, STOPPING=1."""
    import subprocess
    import sys
    from pathlib import Path

    tbp = Path(sys.executable).parent / "tbp"
    if not tbp.exists():
        pytest.skip("the tbp command is not installed in this environment")
    sock = _receiver(str(tmp_path / "notify.sock"))
    sock.setblocking(True)
    sock.settimeout(120.0)  # a generous wait for a loaded machine, not a timing assertion
    env = dict(os.environ, NOTIFY_SOCKET=str(tmp_path / "notify.sock"), WATCHDOG_USEC="1000000")
    proc = subprocess.Popen(
        [str(tbp), "daemon", "--sim", "--socket", str(tmp_path / "control.sock"),
         "--store", str(tmp_path / "store"), "--http", "off"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
    )
    try:
        messages = [sock.recv(4096).decode()]
        while sum(m == "WATCHDOG=1" for m in messages) < 2:
            messages.append(sock.recv(4096).decode())
        proc.terminate()
        while not messages[-1].startswith("STOPPING=1"):
            messages.append(sock.recv(4096).decode())
        assert proc.wait(60) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        sock.close()
    ready = [i for i, m in enumerate(messages) if m.startswith("READY=1\nSTATUS=")]
    assert len(ready) == 1, messages
    assert messages[ready[0] + 1:].count("WATCHDOG=1") >= 1  # pings once ready
    assert messages[-1].startswith("STOPPING=1")
    assert not (tmp_path / "control.sock").exists()  # removed on the way out
