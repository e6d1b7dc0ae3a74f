"""Control API over a real Unix socket (daemon/server/control.py, cli/control.py)."""

from __future__ import annotations

import asyncio
import json
import os
import socket
import stat
from pathlib import Path

import pytest

from cli import main as tbp_main
from daemon.faults import FaultCause, FaultSource
from daemon.rig.states import ScanState, ScanStateMachine
from daemon.server.control import CommandFailed, ControlClient, ControlServer, DaemonUnavailable, SocketInUse


class Refused(RuntimeError):
    pass


class FakeDaemon:
    """The handler the daemon core provides, backed by the real state machine."""

    def __init__(self) -> None:
        self.machine = ScanStateMachine()
        self.scans: list[dict] = []

    def status(self) -> dict:
        return {"state": self.machine.state.value, "faults": [c.as_dict() for c in self.machine.fault_causes]}

    async def scan(self, **args) -> dict:
        if self.machine.state is not ScanState.IDLE:
            raise Refused(f"rig is {self.machine.state.value}; a scan needs IDLE")
        self.scans.append(args)
        self.machine.transition(ScanState.PREPARING, "scan requested over the control socket")
        return {"scan_id": "abc123"}

    def abort(self) -> dict:
        self.machine.transition(ScanState.ABORTING, "abort requested")
        return {"state": self.machine.state.value}

    def reset(self) -> dict:
        self.machine.reset("operator")
        return {"state": self.machine.state.value}

    def subscribe(self):
        return self.machine.subscribe()


@pytest.fixture
def sock(tmp_path) -> Path:
    return tmp_path / "run" / "control.sock"


async def test_round_trips_and_socket_mode(sock):
    daemon = FakeDaemon()
    async with ControlServer(sock, daemon):
        assert stat.S_IMODE(os.stat(sock).st_mode) == 0o660
        client = ControlClient(sock)
        assert await client.status() == {"state": "IDLE", "faults": []}
        assert await client.scan(seed=3) == {"scan_id": "abc123"}
        assert daemon.scans == [{"seed": 3}]
        with pytest.raises(CommandFailed) as info:
            await client.scan()
        assert info.value.error_type == "Refused" and "PREPARING" in info.value.message
        assert (await client.abort())["state"] == "ABORTING"
        with pytest.raises(CommandFailed, match="IllegalTransition"):
            await client.reset()
    assert not sock.exists()


async def test_subscription_streams_events_as_they_happen(sock):
    daemon = FakeDaemon()
    async with ControlServer(sock, daemon):
        stream = ControlClient(sock).subscribe()
        first = await anext(stream)
        assert first["state"] == "IDLE"
        daemon.machine.transition(ScanState.PREPARING, "start pressed")
        daemon.machine.progress("captured", images=12)
        daemon.machine.transition(ScanState.FAULT, FaultCause(FaultSource.ESTOP, "panel", "e-stop pressed"))
        events = [await asyncio.wait_for(anext(stream), 5.0) for _ in range(3)]
        assert [e["state"] for e in events] == ["PREPARING", "PREPARING", "FAULT"]
        assert events[1]["kind"] == "progress" and events[1]["data"] == {"images": 12}
        assert events[2]["cause"] == "panel: e-stop pressed"
        assert (events[2]["source"], events[2]["device"]) == ("estop", "panel")
        await stream.aclose()
        for _ in range(100):  # the server notices the hang-up and unsubscribes
            if not daemon.machine._subscribers:
                break
            await asyncio.sleep(0.01)
        assert not daemon.machine._subscribers


async def test_a_subscription_the_daemon_ends_is_a_typed_refusal(sock):
    """The daemon drops a subscriber that falls behind with a SubscriberTooSlow line: the client
    raises it as the daemon's refusal, not as a malformed line."""
    sock.parent.mkdir(parents=True)

    async def serve(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await reader.readline()
        writer.write(b'{"id": 1, "ok": true, "result": {"state": "IDLE"}}\n'
                     b'{"id": null, "ok": false, "error": {"type": "SubscriberTooSlow", "message": "256 events"}}\n')
        await writer.drain()
        writer.close()

    server = await asyncio.start_unix_server(serve, path=str(sock))
    try:
        stream = ControlClient(sock).subscribe()
        assert (await anext(stream))["state"] == "IDLE"
        with pytest.raises(CommandFailed) as dropped:
            await anext(stream)
        assert (dropped.value.error_type, dropped.value.message) == ("SubscriberTooSlow", "256 events")
    finally:
        server.close()
        await server.wait_closed()


class GeneratorDaemon(FakeDaemon):
    """A handler whose subscribe() is an async generator (subscribes on first iteration)."""

    async def subscribe(self):
        async for event in self.machine.subscribe():
            yield event.as_dict()


async def test_async_generator_subscription_misses_nothing(sock):
    daemon = GeneratorDaemon()
    async with ControlServer(sock, daemon):
        reader, writer = await asyncio.open_unix_connection(str(sock))
        writer.write(b'{"id": 1, "cmd": "subscribe"}\n')
        await writer.drain()
        # the snapshot is taken after the handler has subscribed: an event published right
        # after the reply is on the wire still arrives
        assert json.loads(await reader.readline())["result"]["state"] == "IDLE"
        daemon.machine.transition(ScanState.PREPARING, "start pressed")
        event = json.loads(await asyncio.wait_for(reader.readline(), 5.0))["event"]
        assert event["state"] == "PREPARING" and event["previous"] == "IDLE"
        writer.close()
        await writer.wait_closed()
        for _ in range(100):
            if not daemon.machine._subscribers:
                break
            await asyncio.sleep(0.01)
        assert not daemon.machine._subscribers


async def test_bad_requests_get_typed_errors(sock):
    async with ControlServer(sock, FakeDaemon()):
        reader, writer = await asyncio.open_unix_connection(str(sock))
        for raw in (b"not json\n", b'{"id": 7, "cmd": "launch"}\n', b'{"cmd": "scan", "args": 3}\n'):
            writer.write(raw)
            reply = json.loads(await reader.readline())
            assert reply["ok"] is False and reply["error"]["type"] == "ProtocolError"
        assert "launch" in reply["error"]["message"] or reply["id"] is None
        writer.write(b'{"id": 8, "cmd": "status"}\n')
        assert json.loads(await reader.readline()) == {"id": 8, "ok": True,
                                                        "result": {"state": "IDLE", "faults": []}}
        writer.close()
        await writer.wait_closed()


async def test_stale_socket_is_removed_and_live_one_refused(sock):
    sock.parent.mkdir(parents=True)
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(sock))
    stale.close()  # a killed daemon's socket file: nobody listens
    async with ControlServer(sock, FakeDaemon()):
        assert await ControlClient(sock).status()
        with pytest.raises(SocketInUse):
            await ControlServer(sock, FakeDaemon()).start()


async def test_client_without_daemon(sock):
    with pytest.raises(DaemonUnavailable, match="no socket"):
        await ControlClient(sock).status()


async def test_socket_is_given_to_the_operators_group(sock):
    import grp

    others = [g for g in grp.getgrall() if g.gr_gid != os.getgid()]
    if os.geteuid() != 0 or not others:
        pytest.skip("needs root and a second group to chown the socket to")
    group = others[0]
    async with ControlServer(sock, FakeDaemon(), group=group.gr_name):
        st = os.stat(sock)
        assert st.st_gid == group.gr_gid and stat.S_IMODE(st.st_mode) == 0o660


async def test_unknown_group_is_refused(sock):
    from daemon.server.control import ControlError

    with pytest.raises(ControlError, match="no group"):
        await ControlServer(sock, FakeDaemon(), group="no-such-group-tbp").start()
    assert not sock.exists()


def test_cli_status_abort_reset(sock, capsys):
    """`tbp status/abort/reset --socket` against a server in another thread's loop."""
    import threading

    daemon = FakeDaemon()
    ready = threading.Event()
    stop: list[asyncio.Event] = []

    async def serve() -> None:
        stop.append(asyncio.Event())
        async with ControlServer(sock, daemon):
            ready.set()
            await stop[0].wait()

    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_until_complete, args=(serve(),))
    thread.start()
    try:
        assert ready.wait(10)
        assert tbp_main(["status", "--socket", str(sock)]) == 0
        out = capsys.readouterr().out.splitlines()
        assert out[-2:] == ["State        IDLE", "faults       []"]
        assert tbp_main(["status", "--json", "--socket", str(sock)]) == 0
        # the server's log lines share this process's stdout; the reply is the last line
        assert json.loads(capsys.readouterr().out.splitlines()[-1])["state"] == "IDLE"
        assert tbp_main(["reset", "--socket", str(sock)]) == 1
        assert "IllegalTransition" in capsys.readouterr().err
    finally:
        loop.call_soon_threadsafe(stop[0].set)
        thread.join(10)
        loop.close()
    assert tbp_main(["abort", "--socket", str(sock)]) == 2
    assert "not reachable" in capsys.readouterr().err


def test_cli_formats_status_events_on_one_line_at_their_clock_time():
    from datetime import datetime

    from cli.status_table import event_line

    utc = "2025-03-04T13:02:07.250000+00:00"
    local = datetime.fromisoformat(utc).astimezone().strftime("%H:%M:%S")
    line = event_line({"kind": "transition", "state": "FAULT", "previous": "CAPTURING",
                       "cause": "e-stop pressed", "time_s": 41.25, "scan_id": "abc123", "utc": utc,
                       "data": {"angle_index": 17}})
    assert line == f"[{local}] CAPTURING -> FAULT scan=abc123: e-stop pressed angle_index=17"
    progress = event_line({"kind": "progress", "state": "CAPTURING", "previous": "CAPTURING",
                           "cause": "captured", "time_s": 3.0, "scan_id": None, "data": {}, "utc": utc})
    assert progress == f"[{local}] CAPTURING: captured"


def test_cli_status_is_a_table_a_person_reads():
    from cli.status_table import status_table

    status = {"state": "CAPTURING", "scan_id": "abc123",
              "job_time": {"elapsed_s": 65.2, "state_s": 10.0, "remaining_s": 130.4},
              "counts": {"captured": 120, "verified": 98},
              "states": {"active": [], "job": []}, "healthy": True, "health_problems": [], "ready": True,
              "beam_angle_deg": 123.44, "beam_speed_deg_s": 12.0,
              "fault_causes": [FaultCause(FaultSource.ESTOP, "panel", "e-stop pressed").as_dict(),
                               FaultCause(FaultSource.DRIVE_FAULT, "beam", "EMCY 0x5441").as_dict()],
              "devices": [{"device": "drive", "ok": True, "address": "can0"},
                          {"device": "cam0", "ok": False, "address": "usb:1", "error": "no reply",
                           "check": "check the cable"}],
              "last_scan": {"scan_id": "abc123", "outcome": "PARTIAL", "verified": 290, "missing": 46,
                            "reason": "46 of 336 images missing: cam2 46 (43 phone dropped, 3 capture missed)",
                            "folder": "/scans/x"},
              "recovered_scans": [], "loop_lag": {"IDLE": {"samples": 9, "p50_ms": 0.1, "p99_ms": 1.5, "max_ms": 2.0}},
              "something_new": {"a": 1}}
    assert status_table(status).splitlines() == [
        "State        CAPTURING (scan abc123; elapsed 1 min 05 s, about 2 min 10 s of the beam's schedule left; "
        "120 images captured, 98 images verified)",
        "Daemon       healthy",
        "Rig          ready",
        "Beam         123.4 deg at 12.0 deg/s",
        "Faults       panel: e-stop pressed; beam: EMCY 0x5441",
        "Devices      drive  answers  can0",
        "             cam0   MISSING  usb:1: no reply; check the cable",
        "Last scan    abc123 PARTIAL, 290 of 336 images in the folder: 46 of 336 images missing: "
        "cam2 46 (43 phone dropped, 3 capture missed) (/scans/x)",
        "Loop lag     IDLE: p50 0.1 / p99 1.5 / max 2.0 ms",
        'something_new {"a": 1}',
    ]


def test_cli_status_follow_streams_until_the_daemon_goes(sock, capsys):
    import threading
    import time

    daemon = FakeDaemon()
    loop = asyncio.new_event_loop()
    ready = threading.Event()
    stop = asyncio.Event()

    async def serve() -> None:
        async with ControlServer(sock, daemon):
            ready.set()
            await stop.wait()

    server = threading.Thread(target=loop.run_until_complete, args=(serve(),))
    server.start()
    assert ready.wait(10)
    result: list[int] = []
    follower = threading.Thread(target=lambda: result.append(
        tbp_main(["status", "--follow", "--json", "--socket", str(sock)])))
    follower.start()
    try:
        for _ in range(1000):  # wait (polling, no timing assertion) until it has subscribed
            if daemon.machine._subscribers:
                break
            time.sleep(0.01)
        loop.call_soon_threadsafe(daemon.machine.transition, ScanState.PREPARING, "start pressed")
        loop.call_soon_threadsafe(daemon.machine.transition, ScanState.FAULT,
                                  FaultCause(FaultSource.DRIVE_FAULT, "beam", "drive fault 0x2310"))
        out = ""
        for _ in range(1000):
            out += capsys.readouterr().out
            if '"state": "FAULT"' in out:
                break
            time.sleep(0.01)
    finally:
        loop.call_soon_threadsafe(stop.set)
        server.join(10)
        follower.join(10)
        loop.close()
    events = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    assert [e["state"] for e in events] == ["IDLE", "PREPARING", "FAULT"]
    assert events[2]["cause"] == "beam: drive fault 0x2310" and events[2]["source"] == "drive_fault"
    assert result == [2]  # then the daemon went away: unreachable
    assert "closed the subscription" in capsys.readouterr().err
