"""The socketcand bridge: python-can's own ``socketcand`` interface reaches the simulated drive.

The server runs in the test's event loop on 127.0.0.1; the python-can client connects from a
worker thread (its handshake blocks). Real time; nothing asserts on durations.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import AsyncIterator, Iterator

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.motor import BeamDrive, CanBusError, Cia402State, LoopbackCanBus, PythonCanPort
from drivers.sim.drive import SimulatedDrive
from drivers.sim.socketcand import SocketcandProtocolError, SocketcandServer, _bus_to_tcp, format_frame, parse_send
from planner.rig import load_rig
from sim.processes.beam_follower import BeamFollower

MOTOR = load_rig().motor


def test_frame_text_transcripts() -> None:
    msg = can.Message(
        arbitration_id=0x185, data=bytes.fromhex("39160000E8030000"), is_extended_id=False, timestamp=12.5
    )
    assert format_frame(msg) == "< frame 185 12.500000 39160000E8030000 >"
    empty = can.Message(arbitration_id=0x080, data=b"", is_extended_id=False, timestamp=1.0)
    assert format_frame(empty) == "< frame 080 1.000000  >"
    ext = can.Message(arbitration_id=0x18FF0005, data=b"\x01", is_extended_id=True, timestamp=0.0)
    assert format_frame(ext) == "< frame 18FF0005 0.000000 01 >"
    sent = parse_send("< send 605 8 40 41 60 0 0 0 0 0 >")
    assert (sent.arbitration_id, bytes(sent.data), sent.is_extended_id) == (
        0x605,
        bytes.fromhex("4041600000000000"),
        False,
    )
    assert parse_send("< send 0000007F 1 5 >").is_extended_id


frames = st.builds(
    lambda ext, cob, data, ts: can.Message(
        arbitration_id=cob & (0x1FFFFFFF if ext else 0x7FF), data=data, is_extended_id=ext, timestamp=ts
    ),
    st.booleans(),
    st.integers(0, 0x1FFFFFFF),
    st.binary(max_size=8),
    st.floats(0, 1e6, allow_nan=False).map(lambda t: round(t, 6)),
)


@given(frames)
def test_bridge_and_python_can_read_each_others_text(msg: can.Message) -> None:
    """Our parser reads python-can's ``< send >`` text and python-can reads our ``< frame >`` text."""
    from can.interfaces.socketcand import socketcand as client

    sent = parse_send(client.convert_can_message_to_ascii_message(msg))
    assert (sent.arbitration_id, bytes(sent.data), sent.is_extended_id) == (
        msg.arbitration_id,
        bytes(msg.data),
        msg.is_extended_id,
    )
    received = client.convert_ascii_message_to_can_message(format_frame(msg))
    assert (received.arbitration_id, bytes(received.data), received.is_extended_id) == (
        msg.arbitration_id,
        bytes(msg.data),
        msg.is_extended_id,
    )
    assert received.timestamp == pytest.approx(msg.timestamp, abs=1e-6)


@pytest.mark.parametrize(
    ("command", "problem"),
    [
        ("< sned 605 1 0 >", "not a send command"),
        ("< send 605 2 0 >", "dlc 2 but 1 data bytes"),
        ("< send 6G5 1 0 >", "bad number"),
        ("< send 805 1 0 >", "out of range"),
        ("< send 605 9 0 0 0 0 0 0 0 0 0 >", "dlc 9"),
    ],
)
def test_bad_send_commands_are_refused(command: str, problem: str) -> None:
    with pytest.raises(SocketcandProtocolError, match=problem):
        parse_send(command)


def test_server_refuses_non_loopback_addresses() -> None:
    with pytest.raises(ValueError, match="loopback"):
        SocketcandServer(LoopbackCanBus(), host="0.0.0.0")


@pytest.fixture
async def bridge() -> AsyncIterator[tuple[SocketcandServer, SimulatedDrive]]:
    bus = LoopbackCanBus("sim")
    sim = SimulatedDrive(bus.port("drive"), MOTOR)
    server = SocketcandServer(bus, channel="can0", port=0)
    await server.start()
    task = asyncio.create_task(sim.run())
    try:
        yield server, sim
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        await server.close()


async def _client_port(server: SocketcandServer, channel: str = "can0") -> PythonCanPort:
    bus = await asyncio.to_thread(
        can.Bus, interface="socketcand", host="127.0.0.1", port=server.port, channel=channel
    )
    return PythonCanPort(bus, name="socketcand")


class _RecordingWriter:
    """A StreamWriter's write/drain, keeping each write."""

    def __init__(self) -> None:
        self.writes: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.writes.append(data)

    async def drain(self) -> None:
        await asyncio.sleep(0)


async def test_frames_put_on_the_bus_together_go_out_in_one_write() -> None:
    bus = LoopbackCanBus("sim")
    drive, client = bus.port("drive"), bus.port("client")
    writer = _RecordingWriter()
    pump = asyncio.create_task(_bus_to_tcp(client, writer))  # type: ignore[arg-type]
    frames = [can.Message(arbitration_id=0x181 + k, data=bytes([k]), is_extended_id=False) for k in range(3)]
    try:
        for frame in frames[:2]:  # one drive cycle: TPDO1 and TPDO2 back to back
            await drive.send(frame)
        while not writer.writes:
            await asyncio.sleep(0)
        await drive.send(frames[2])  # the next cycle
        while len(writer.writes) < 2:
            await asyncio.sleep(0)
        first, second = (w.decode("ascii") for w in writer.writes)
        assert re.findall(r"< frame (\w+) ", first) == ["181", "182"]
        assert re.findall(r"< frame (\w+) ", second) == ["183"]
        client.close()
        await asyncio.wait_for(pump, 1.0)  # a closed port ends the pump
    finally:
        pump.cancel()
        await asyncio.gather(pump, return_exceptions=True)


# python-can's client raises from its constructor without closing the socket it connected.
@pytest.mark.filterwarnings("ignore::ResourceWarning")
async def test_handshake_refuses_unknown_channel(bridge: tuple[SocketcandServer, SimulatedDrive]) -> None:
    server, _ = bridge
    with pytest.raises(can.CanError, match="could not open bus"):
        await _client_port(server, channel="vcan9")


@pytest.mark.realtime
async def test_beam_drive_over_socketcand_bridge(bridge: tuple[SocketcandServer, SimulatedDrive]) -> None:
    server, sim = bridge
    drive = BeamDrive(await _client_port(server), MOTOR)
    try:
        await drive.connect()
        await drive.enable()
        assert sim.state is Cia402State.OPERATION_ENABLED
        stream = drive.samples()
        await drive.move_to(3.0, 30.0, 60.0)
        assert sim.true_angle_deg == pytest.approx(3.0, abs=1 / MOTOR.counts_per_degree)
        samples = [await anext(stream)]
        while abs(samples[-1].angle_deg - 3.0) > 0.01 and len(samples) < 5000:
            samples.append(await anext(stream))
        times = [s.time_s for s in samples]
        assert all(b > a for a, b in zip(times, times[1:]))
        angles = [s.angle_deg for s in samples]
        assert angles == sorted(angles) and angles[-1] == pytest.approx(3.0, abs=0.01)
        assert len(samples) > 10  # the move was streamed, not just its end
        await drive.disable()
    finally:
        await drive.close()


@pytest.mark.realtime
async def test_handshake_survives_a_busy_bus(bridge: tuple[SocketcandServer, SimulatedDrive]) -> None:
    server, _ = bridge
    chatter_port = server.bus.port("chatter")

    async def chatter() -> None:
        while True:
            await chatter_port.send(can.Message(arbitration_id=0x77F, data=b"\x05", is_extended_id=False))
            await asyncio.sleep(0.0005)

    task = asyncio.create_task(chatter())
    try:
        for _ in range(3):
            port = await _client_port(server)
            msg = await asyncio.wait_for(port.recv(), 30.0)  # a frame every 0.5 ms: a deadline for a loaded machine
            assert msg.arbitration_id == 0x77F
            port.close()
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)


@pytest.mark.realtime
async def test_client_going_away_leaves_the_bridge_serving(
    bridge: tuple[SocketcandServer, SimulatedDrive],
) -> None:
    server, sim = bridge
    first = await _client_port(server)
    first.close()
    drive = BeamDrive(await _client_port(server), MOTOR)
    try:
        await drive.connect()
        assert drive.latest is not None
    finally:
        await drive.close()


def test_sim_motor_options_leave_callers_common_options_alone() -> None:
    import argparse

    from sim.processes.motor import add_arguments

    parser = argparse.ArgumentParser()
    parser.add_argument("--port", type=int, default=7)  # `tbp sim` may define it for every simulator
    add_arguments(parser)
    args = parser.parse_args(["--estop-after", "2.5", "--fault-code", "0x4310"])
    assert (args.port, args.estop_after, args.fault_code, args.channel) == (7, 2.5, 0x4310, "can0")


@contextlib.contextmanager
def _served_drive(*options: str) -> Iterator[tuple[subprocess.Popen[str], int]]:
    """``sim.processes.motor.serve`` (what ``tbp sim motor`` runs) in its own process; yields the
    process and the bridge's TCP port; SIGTERM (then kill) on the way out."""
    code = (
        "import argparse, asyncio, logging, structlog\n"
        "structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))\n"
        "from sim.processes.motor import add_arguments, serve\n"
        "p = argparse.ArgumentParser(); add_arguments(p)\n"
        f"asyncio.run(serve(p.parse_args(['--port', '0', *{list(options)!r}])))\n"
    )
    with subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
    ) as proc:
        try:
            line = proc.stdout.readline() if proc.stdout else ""
            match = re.search(r"socketcand 127\.0\.0\.1:(\d+) channel can0", line)
            assert match, line
            yield proc, int(match.group(1))
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()


@pytest.mark.realtime
def test_serve_runs_the_drive_behind_the_bridge_until_sigterm() -> None:
    """``tbp sim motor``'s entry point in its own process: serves, answers SDO, exits on SIGTERM."""
    with _served_drive() as (proc, tcp_port):
        bus = can.Bus(interface="socketcand", host="127.0.0.1", port=tcp_port, channel="can0")
        try:
            request = bytes.fromhex("4041600000000000")
            bus.send(can.Message(arbitration_id=0x600 + MOTOR.node_id, data=request, is_extended_id=False))
            reply = None
            deadline = time.monotonic() + 30.0  # the reply, or a generous deadline for a loaded machine
            while reply is None and time.monotonic() < deadline:
                msg = bus.recv(timeout=0.1)
                if msg is not None and msg.arbitration_id == 0x580 + MOTOR.node_id:
                    reply = bytes(msg.data)
            assert reply is not None and reply[:4] == bytes.fromhex("4B416000")
        finally:
            bus.shutdown()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0


@pytest.mark.realtime
def test_tbp_motor_commissions_a_drive_served_by_another_process(capsys: pytest.CaptureFixture[str]) -> None:
    """``tbp motor`` against the simulated drive in its own process, through socketcand."""
    from cli import main

    with _served_drive() as (_, tcp_port):
        bus = ["motor", "--interface", "socketcand", "--port", str(tcp_port)]
        assert main([*bus, "move", "4", "--speed", "20", "--acceleration", "40"]) == 0
        assert "beam: operation enabled, angle 4.00" in capsys.readouterr().out
        assert main([*bus, "zero", "90"]) == 0
        assert main([*bus, "status"]) == 0
        assert "angle 90.00" in capsys.readouterr().out.splitlines()[-1]
        assert main([*bus, "rotate", "100"]) == 1
        assert "MotionLimitError" in capsys.readouterr().err


@pytest.mark.realtime
def test_served_drive_injects_the_e_stop_it_was_told_to(capsys: pytest.CaptureFixture[str]) -> None:
    from cli import main

    with _served_drive("--estop-after", "0") as (_, tcp_port):
        bus = ["motor", "--interface", "socketcand", "--port", str(tcp_port)]
        assert main([*bus, "enable"]) == 1
        assert "0x5441 (emergency stop input" in capsys.readouterr().err


@pytest.mark.realtime
async def test_a_simulated_phone_follows_the_angle_the_daemon_drives(
    bridge: tuple[SocketcandServer, SimulatedDrive],
) -> None:
    """``tbp sim phone --follow-beam``: its listening thread decodes the drive's position TPDOs."""
    server, _ = bridge
    follower = BeamFollower(MOTOR, "127.0.0.1", server.port, fallback_deg=-90.0)
    loop = asyncio.get_running_loop()
    assert follower.angle_at(loop.time()) == -90.0  # nothing streamed yet
    follower.start()
    drive = BeamDrive(await _client_port(server), MOTOR)
    try:
        await drive.connect()
        await drive.enable()
        await drive.move_to(3.0, 30.0, 60.0)
        deadline = loop.time() + 30.0  # until the follower has read a sample at the end of the move
        while abs(follower.angle_at(loop.time()) - 3.0) >= 0.01 and loop.time() < deadline:
            await asyncio.sleep(0.01)
        assert follower.angle_at(loop.time()) == pytest.approx(3.0, abs=0.01)
        await drive.disable()
    finally:
        await drive.close()
        await asyncio.to_thread(follower.stop)


class _DeafBridge:
    """A socketcand bridge that shakes hands, then never reads again (a hung bridge process),
    with a small receive buffer so the client's writes stall after a few kilobytes."""

    def __init__(self) -> None:
        self.listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 2048)
        self.listener.bind(("127.0.0.1", 0))
        self.listener.listen()
        self.port = self.listener.getsockname()[1]
        self.connections: list[socket.socket] = []
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        with contextlib.suppress(OSError):  # the listener closed
            while True:
                conn, _ = self.listener.accept()
                self.connections.append(conn)
                threading.Thread(target=self._handshake, args=(conn,), daemon=True).start()

    def _handshake(self, conn: socket.socket) -> None:
        with contextlib.suppress(OSError):  # the connection probe hangs up at once
            conn.sendall(b"< hi >")
            if not conn.recv(64):
                return
            conn.sendall(b"< ok >")
            conn.recv(64)
            conn.sendall(b"< ok >")

    def close(self) -> None:
        self.listener.close()
        for conn in self.connections:
            conn.close()


async def test_a_bridge_that_stops_reading_fails_the_port_without_blocking_the_loop() -> None:
    bridge = _DeafBridge()
    port = await PythonCanPort.connect("socketcand", "can0", host="127.0.0.1", port=bridge.port, name="deaf")
    port.bus._SocketCanDaemonBus__socket.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
    frame = can.Message(arbitration_id=0x77F, data=b"\x05", is_extended_id=False)
    sent = 0
    try:
        with pytest.raises(CanBusError) as info:
            async with asyncio.timeout(30.0):
                while True:  # a host heartbeat every loop-millisecond, as long as the port takes it
                    await port.send(frame)
                    sent += 1
                    await asyncio.sleep(0.001)
        assert info.value.device == "deaf" and sent > 10
        assert "link does not drain" in str(info.value) or "timed out" in str(info.value)
        # The transmit thread's write gives up after SEND_TIMEOUT_S: the port has failed.
        with pytest.raises(CanBusError, match="send 0x77F failed: timed out"):
            await asyncio.wait_for(port.recv(), 5.0)
    finally:
        port.close()
        bridge.close()
