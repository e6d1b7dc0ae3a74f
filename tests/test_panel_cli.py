"""``tbp sim panel`` as its own process: it prints its pty path and a real OperatorPanel talks to it."""

from __future__ import annotations

import asyncio
import os
import signal
import sys
from pathlib import Path

import pytest

from cli import build_parser
from drivers.panel import OperatorPanel, PanelEvent, StatusLed, open_serial

TBP = Path(sys.executable).with_name("tbp")


@pytest.mark.realtime
async def test_tbp_sim_panel_serves_a_pty_that_the_driver_can_use() -> None:
    proc = await asyncio.create_subprocess_exec(
        str(TBP), "sim", "panel", "--estop",
        stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE,
    )
    panel: OperatorPanel | None = None
    try:
        assert proc.stdout is not None and proc.stdin is not None
        async with asyncio.timeout(60):
            line = (await proc.stdout.readline()).decode()
        assert line.startswith("simulated panel on /dev/"), line
        path = line.split(" on ", 1)[1].strip()
        assert os.path.exists(path)
        panel = OperatorPanel(*await open_serial(path), name="cli-panel")
        await panel.connect()
        events = panel.events()
        async with asyncio.timeout(5):
            assert await anext(events) is PanelEvent.ESTOP_PRESSED  # --estop: held at power-on
        await panel.set_status(StatusLed.IDLE)
        async with asyncio.timeout(5):  # the simulator shows what the host commanded
            assert (await proc.stdout.readline()).decode().strip() == "LED IDLE, light off"
        proc.stdin.write(b"r")  # the operator releases the e-stop and presses START
        proc.stdin.write(b"s")
        await proc.stdin.drain()
        async with asyncio.timeout(5):
            assert await anext(events) is PanelEvent.ESTOP_RELEASED
            assert await anext(events) is PanelEvent.START_PRESSED
    finally:
        if panel is not None:
            await panel.close()
        if proc.returncode is None:
            proc.send_signal(signal.SIGTERM)
        async with asyncio.timeout(30):
            code = await proc.wait()
    assert code == 0


def test_sim_subcommands_take_their_simulators_options() -> None:
    args = build_parser().parse_args(["sim", "panel", "--noise", "0.1", "--seed", "3"])
    assert (args.sim_module, args.noise, args.seed) == ("sim.processes.panel", 0.1, 3)
    args = build_parser().parse_args(["sim", "phone", "--port", "5999", "--seed", "2"])
    assert (args.sim_module, args.port, args.seed) == ("sim.processes.phone", 5999, 2)
    args = build_parser().parse_args(["sim", "motor", "--port", "29999"])
    assert (args.sim_module, args.port) == ("sim.processes.motor", 29999)


def test_unknown_simulator_option_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        build_parser().parse_args(["sim", "panel", "--port", "5"])
    assert info.value.code == 2
    assert "unrecognized arguments: --port" in capsys.readouterr().err


def test_missing_simulator_module_is_a_clear_error(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import cli.sim as sim_cli

    monkeypatch.setitem(sim_cli.SIMULATORS, "lidar", ("drivers.sim.no_such_lidar", "not here"))
    with pytest.raises(SystemExit):
        build_parser().parse_args(["sim", "lidar"])
    assert "drivers.sim.no_such_lidar cannot be imported" in capsys.readouterr().err
    assert build_parser().parse_args(["sim", "panel"]).sim_module == "sim.processes.panel"


async def _tbp(*argv: str) -> asyncio.subprocess.Process:
    return await asyncio.create_subprocess_exec(
        str(TBP), *argv, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE
    )


@pytest.mark.realtime
async def test_tbp_panel_commissions_a_panel_on_a_serial_port() -> None:
    from drivers.sim.panel import SimulatedPanel

    sim, path = await SimulatedPanel.on_pty(estop=True)
    task = asyncio.create_task(sim.run())
    try:
        proc = await _tbp("panel", "--port", path, "status")
        out, err = await asyncio.wait_for(proc.communicate(), 60)
        assert proc.returncode == 0, err.decode()
        assert f"panel {path}: connected, e-stop PRESSED, LED OFF, light off" in out.decode()

        # The CLI holds the LED for --seconds after its line: long enough for a test process a
        # loaded machine delays to see it lit before BYE puts it out.
        proc = await _tbp("panel", "--port", path, "led", "SCANNING", "--seconds", "5")
        assert proc.stdout is not None
        assert (await asyncio.wait_for(proc.stdout.readline(), 60)).startswith(b"LED SCANNING")
        assert sim.led is StatusLed.SCANNING
        await asyncio.wait_for(proc.wait(), 30)
        assert proc.returncode == 0 and sim.led is StatusLed.OFF  # BYE at the end

        sim.release_estop()
        proc = await _tbp("panel", "--port", path, "watch", "--seconds", "6")  # START comes within it
        assert proc.stdout is not None
        assert b"e-stop released" in await asyncio.wait_for(proc.stdout.readline(), 60)
        sim.press_start()
        out, err = await asyncio.wait_for(proc.communicate(), 30)
        assert proc.returncode == 0, err.decode()
        assert out.decode().split() == ["START_PRESSED"]
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        sim.close()


async def test_tbp_panel_reports_a_missing_port() -> None:
    proc = await _tbp("panel", "--port", "/dev/tbp-no-such-panel", "status")
    _, err = await asyncio.wait_for(proc.communicate(), 60)
    assert proc.returncode == 1
    assert "tbp panel: operator panel /dev/tbp-no-such-panel: link lost: cannot open" in err.decode()


@pytest.mark.parametrize(
    ("device", "banner"),
    [("motor", "simulated drive node "), ("phone", "simulated phone TBPSIM00 (adbd) on 127.0.0.1:")],
)
@pytest.mark.realtime
async def test_tbp_sim_serves_the_other_simulators_until_sigterm(device: str, banner: str) -> None:
    proc = await asyncio.create_subprocess_exec(
        str(TBP), "sim", device, "--port", "0",
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
    )
    try:
        assert proc.stdout is not None
        async with asyncio.timeout(60):
            line = (await proc.stdout.readline()).decode()
        assert line.startswith(banner), line
    finally:
        if proc.returncode is None:
            proc.send_signal(signal.SIGTERM)
        async with asyncio.timeout(30):
            _, err = await proc.communicate()
    assert proc.returncode == 0, err.decode()[-2000:]
