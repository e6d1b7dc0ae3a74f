"""``tbp sim motor``: the simulated CiA 402 beam drive behind a socketcand bridge on loopback."""

from __future__ import annotations

import argparse
import asyncio
from collections.abc import Callable
from typing import Any

from drivers.motor.port import LoopbackCanBus
from drivers.sim.drive import SimulatedDrive
from sim.processes.keys import stop_signals


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``tbp sim motor`` (an option the caller already defined, such as a common
    ``--port``, is left as it is)."""

    def option(*flags: str, **kwargs: Any) -> None:
        if not any(flag in parser._option_string_actions for flag in flags):
            parser.add_argument(*flags, **kwargs)

    option("--port", type=int, default=29536, help="TCP port of the socketcand bridge on 127.0.0.1")
    option("--channel", default="can0", help="CAN channel name the bridge serves")
    option("--rig", default=None, help="rig file (default: calibration_data/rig.yaml)")
    option("--initial-angle", type=float, default=0.0, help="beam angle at power-on, deg")
    option("--init-s", type=float, default=0.0, help="power-on self-test time (NOT READY), s")
    option("--sdo-delay", type=float, default=0.0, help="fault: answer every SDO request this late, s")
    option("--estop-after", type=float, default=None, help="fault: press the e-stop after this many s")
    option("--fault-after", type=float, default=None, help="fault: raise --fault-code after this many s")
    option("--fault-code", type=lambda text: int(text, 0), default=0x2310, help="EMCY code (default 0x2310)")


async def _inject_later(delay_s: float | None, action: Callable[[], None]) -> None:
    if delay_s is not None:
        await asyncio.sleep(delay_s)
        action()


async def serve(args: argparse.Namespace) -> None:
    """Serve the simulated drive on a socketcand bridge at 127.0.0.1:args.port until SIGINT/SIGTERM.

    Keys on stdin (sim/processes/keys.py) inject faults: ``f`` raises --fault-code, ``h`` stops the
    drive's heartbeat and ``H`` resumes it, ``e`` opens the e-stop input and ``r`` closes it."""
    from drivers.sim.socketcand import SocketcandServer
    from planner.rig import DEFAULT_RIG_PATH, load_rig

    rig = load_rig(args.rig or DEFAULT_RIG_PATH)
    bus = LoopbackCanBus("sim")
    drive = SimulatedDrive(
        bus.port("drive"), rig.motor, initial_angle_deg=args.initial_angle, init_s=args.init_s
    )
    drive.sdo_delay_s = args.sdo_delay
    server = SocketcandServer(bus, channel=args.channel, host="127.0.0.1", port=args.port)
    await server.start()
    tasks = [
        asyncio.create_task(drive.run(), name="sim-drive"),
        asyncio.create_task(_inject_later(args.estop_after, drive.press_estop)),
        asyncio.create_task(_inject_later(args.fault_after, lambda: drive.inject_fault(args.fault_code))),
    ]
    keys = {
        "f": (f"fault 0x{args.fault_code:04X} raised", lambda: drive.inject_fault(args.fault_code)),
        "h": ("heartbeat stopped", drive.stop_heartbeat), "H": ("heartbeat resumed", drive.resume_heartbeat),
        "e": ("e-stop input opened", drive.press_estop), "r": ("e-stop input closed", drive.release_estop),
    }
    try:
        with stop_signals(keys) as stop:
            print(
                f"simulated drive node {rig.motor.node_id} on socketcand "
                f"127.0.0.1:{server.port} channel {args.channel}",
                flush=True,
            )
            await stop.wait()
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        await server.close()
