"""``tbp check`` against simulators on loopback: the drive behind socketcand, phones' adbds over
TCP, the panel on a pty; each probed through the real driver, as on a rig PC."""

from __future__ import annotations

import asyncio
import json
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from cli import main
from planner.rig import DEFAULT_RIG_PATH, load_rig
from sim.loopback import free_port

RIG = load_rig(DEFAULT_RIG_PATH)


class Simulators:
    """The rig's devices simulated in a background event loop; ``hardware(path)`` wires them."""

    def __init__(self, tmp: Path, *, missing_phones: tuple[str, ...] = (), drive_class: Any = None) -> None:
        self.tmp = tmp
        self.missing_phones = missing_phones
        self.drive_class = drive_class
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.tasks: list[asyncio.Task[Any]] = []
        self.closers: list[Any] = []
        self.phone_ports: dict[str, int] = {}
        self.call(self._start())

    def call(self, coro: Any) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(30)

    async def _start(self) -> None:
        from drivers.motor.port import LoopbackCanBus
        from drivers.sim.drive import SimulatedDrive
        from drivers.sim.panel import SimulatedPanel
        from drivers.sim.phone import SimulatedPhone
        from drivers.sim.socketcand import SocketcandServer

        bus = LoopbackCanBus("sim")
        drive = (self.drive_class or SimulatedDrive)(bus.port("drive"), RIG.motor)
        self.tasks.append(asyncio.create_task(drive.run()))
        self.bridge = SocketcandServer(bus, channel="can0", host="127.0.0.1", port=0)
        await self.bridge.start()
        self.closers.append(self.bridge.close)
        for phone in RIG.phones:
            if phone.id in self.missing_phones:
                self.phone_ports[phone.id] = free_port()
                continue
            sim = SimulatedPhone(phone.serial, optics=RIG.optics)
            server = await asyncio.start_server(sim.accept, "127.0.0.1", 0)
            self.phone_ports[phone.id] = server.sockets[0].getsockname()[1]
            self.closers.append(_closer(server))
        self.panel, self.panel_tty = await SimulatedPanel.on_pty()
        self.tasks.append(asyncio.create_task(self.panel.run()))

    def hardware(self, *, missing_recording: str | None = None) -> Path:
        recordings = {}
        for camera in RIG.depth_cameras:
            path = self.tmp / f"{camera.id}.db3"
            if camera.id != missing_recording:
                path.write_bytes(b"\0" * 64)
            recordings[camera.id] = {"recording": str(path)}
        config = {
            "can": {"interface": "socketcand", "channel": "can0", "host": "127.0.0.1", "port": self.bridge.port},
            "phones": {p.id: {"tcp": f"127.0.0.1:{self.phone_ports[p.id]}"} for p in RIG.phones},
            "depth_cameras": recordings,
            "panel": {"device": self.panel_tty, "baud": 115200},
            "timeouts": {"open_s": 5.0},
        }
        path = self.tmp / "hardware.yaml"
        path.write_text(yaml.safe_dump(config))
        return path

    def close(self) -> None:
        async def stop() -> None:
            self.panel.close()
            for task in self.tasks:
                task.cancel()
            await asyncio.gather(*self.tasks, return_exceptions=True)
            for close in self.closers:
                await close()

        self.call(stop())
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5)


def _closer(server: asyncio.Server) -> Any:
    async def close() -> None:
        server.close()

    return close


@pytest.fixture
def simulators(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[Simulators]:
    sims = Simulators(tmp_path, missing_phones=getattr(request, "param", ()))
    try:
        yield sims
    finally:
        sims.close()


def _check(tmp_path: Path, hardware: Path, *extra: str) -> list[str]:
    return ["check", "--rig", str(DEFAULT_RIG_PATH), "--hardware", str(hardware), "--socket",
            str(tmp_path / "no-daemon.sock"), "--state-dir", str(tmp_path / "state"), *extra]


def test_every_device_answering_is_reported_with_identity_and_latency(
        simulators: Simulators, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(_check(tmp_path, simulators.hardware(), "--json")) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["ok"] and report["source"] == "probe"
    devices = {d["device"]: d for d in report["devices"]}
    assert set(devices) == {"drive", "panel"} | {p.id for p in RIG.phones} | {c.id for c in RIG.depth_cameras}
    assert all(d["found"] and d["verdict"] == "ok" and d["latency_ms"] >= 0 for d in devices.values())
    assert devices["drive"]["identity"].startswith("CiA 402 vendor 0x00000544")
    stop = {row["address"]: row for row in devices["drive"]["stop_configuration"]}
    assert all(row["ok"] for row in stop.values()) and devices["drive"]["problems"] == []
    assert stop["0x6007:0"]["value"] == 1 and stop["0x6007:0"]["shown"] == "1 (fault)"
    assert stop["0x1029:1"]["value"] == 1 and stop["0x1600:0"]["value"] == [0x6040_0010]
    assert devices["drive"]["address"] == f"socketcand://127.0.0.1:{simulators.bridge.port}/can0"
    assert "TBP Simulated Phone" in devices[RIG.phones[0].id]["identity"]
    assert RIG.phones[0].serial in devices[RIG.phones[0].id]["identity"]


@pytest.mark.parametrize("simulators", [("cam3",)], indirect=True)
def test_a_missing_phone_and_recording_fail_the_check_naming_each(
        simulators: Simulators, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(_check(tmp_path, simulators.hardware(missing_recording="depth1"))) == 1
    table = capsys.readouterr().out.split("\n\n")[0].splitlines()
    assert table[0].split()[:6] == ["DEVICE", "ADDRESS", "FOUND", "IDENTITY", "LATENCY", "VERDICT"]
    rows = {line.split()[0]: line for line in table[1:]}
    assert f"tcp:127.0.0.1:{simulators.phone_ports['cam3']}" in rows["cam3"]
    assert "MISSING" in rows["cam3"] and "USB cable" in rows["cam3"]
    assert "MISSING" in rows["depth1"] and "no recording" in rows["depth1"]
    others = [name for name in rows if name not in ("cam3", "depth1")]
    assert others and all(rows[name].rstrip().endswith("ok") for name in others)


def _drive_stuck_at_no_action() -> Any:
    from drivers.motor import sdo_aborts
    from drivers.sim.canopen_node import SdoAbortRequest
    from drivers.sim.drive import SimulatedDrive

    class StuckDrive(SimulatedDrive):
        """A drive whose abort connection option stays 0 (no action)."""

        def write_object(self, index: int, subindex: int, value: int) -> None:
            if index == 0x6007 and value != 0:
                raise SdoAbortRequest(sdo_aborts.ABORT_VALUE_RANGE)
            super().write_object(index, subindex, value)

    return StuckDrive


def test_a_drive_that_would_not_stop_by_itself_is_a_problem_naming_the_object(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    sims = Simulators(tmp_path, drive_class=_drive_stuck_at_no_action())
    capsys.readouterr()  # the simulators' start-up lines
    try:
        assert main(_check(tmp_path, sims.hardware(), "--json")) == 1
        report = json.loads(capsys.readouterr().out)
        drive = next(d for d in report["devices"] if d["device"] == "drive")
        assert not report["ok"] and drive["found"] and drive["verdict"] == "PROBLEM"
        assert "0x6007:0" in drive["problems"][0] and "refused with SDO abort 0x06090030" in drive["problems"][0]
        assert "0x6007:0 abort connection option code is 0 (no action), the rig requires 1 (fault)" in drive["problems"]
        assert "vendor's tool" in drive["check"]
        assert main(_check(tmp_path, sims.hardware())) == 1
        table, stop = capsys.readouterr().out.split("\n\n")[:2]
        assert "PROBLEM: beam [" in next(line for line in table.splitlines() if line.startswith("drive "))
        assert next(line for line in stop.splitlines() if line.startswith("0x6007:0")).endswith("REQUIRED: 1 (fault)")
        assert next(line for line in stop.splitlines() if line.startswith("0x6085:0")).endswith("ok")
    finally:
        sims.close()


def test_a_bad_hardware_file_is_one_line_and_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    hardware = tmp_path / "hardware.yaml"
    hardware.write_text("can: {interface: carrier-pigeon, channel: can0}\nphones: {}\ndepth_cameras: {}\npanel: null\n")
    assert main(_check(tmp_path, hardware)) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "can.interface" in err and "carrier-pigeon" in err


def test_while_the_daemon_runs_the_check_shows_its_view_without_touching_the_devices(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from tests.daemon_mocks import answering_daemon

    devices = [{"device": "drive", "kind": "drive", "address": "socketcan:can0", "ok": True, "error": None,
                "check": None},
               {"device": "cam0", "kind": "phone", "address": "usb:X", "ok": False, "error": "gone", "check": "cable"}]
    sock = tmp_path / "control.sock"
    with answering_daemon(sock, {"state": "IDLE", "devices": devices}):
        hardware = tmp_path / "hw.yaml"
        hardware.write_text(yaml.safe_dump({
            "can": {"interface": "socketcan", "channel": "can0"},
            "phones": {p.id: "usb" for p in RIG.phones},
            "depth_cameras": {c.id: "realsense" for c in RIG.depth_cameras}, "panel": None}))
        argv = ["check", "--rig", str(DEFAULT_RIG_PATH), "--hardware", str(hardware), "--socket", str(sock), "--json"]
        assert main(argv) == 1
        out = capsys.readouterr().out
        report = json.loads(out[out.index("{\n"):])  # after the stand-in daemon's own log line
        assert report["source"] == "daemon"
        assert [(d["device"], d["found"]) for d in report["devices"]] == [("drive", True), ("cam0", False)]


def test_a_daemon_that_refuses_its_status_is_not_probed_under(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A refusal is an answer: a daemon runs and owns the devices (probing the drive would reset
    its CANopen communication mid-scan), so the check stops instead of probing."""
    from tests.daemon_mocks import answering_daemon

    sock = tmp_path / "control.sock"
    with answering_daemon(sock, RuntimeError("status is broken")):
        hardware = tmp_path / "hw.yaml"
        hardware.write_text(yaml.safe_dump({
            "can": {"interface": "socketcan", "channel": "can0"},
            "phones": {p.id: "usb" for p in RIG.phones},
            "depth_cameras": {c.id: "realsense" for c in RIG.depth_cameras}, "panel": None}))
        argv = ["check", "--rig", str(DEFAULT_RIG_PATH), "--hardware", str(hardware), "--socket", str(sock),
                "--state-dir", str(tmp_path / "state")]
        assert main(argv) == 2
    err = capsys.readouterr().err
    assert "refused its status" in err and "RuntimeError: status is broken" in err
