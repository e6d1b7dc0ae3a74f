"""``tbp sim panel``: the simulated operator panel on a new pty."""

from __future__ import annotations

import argparse
import asyncio

from drivers.panel import protocol
from drivers.sim.panel import SimulatedPanel
from sim.processes.keys import say, stop_signals


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``tbp sim panel``."""
    parser.add_argument("--estop", action="store_true", help="the e-stop is pressed at power-on")
    parser.add_argument("--protocol-version", type=int, default=protocol.PROTOCOL_VERSION,
                        help="protocol version to answer HELLO with (test a mismatch)")
    parser.add_argument("--no-heartbeat", action="store_true",
                        help="never send heartbeats (the host must report the panel lost)")
    parser.add_argument("--noise", type=float, default=0.0,
                        help="fraction of sent lines whose checksum is broken (line noise)")
    parser.add_argument("--seed", type=int, default=0, help="seeds which lines the noise hits")


async def serve(args: argparse.Namespace) -> int:
    """Run a simulated panel on a new pty until SIGINT/SIGTERM; prints the pty path.

    Keys on stdin (sim/processes/keys.py) press buttons: ``s`` start, ``x`` stop, ``e`` e-stop, ``r``
    release it; ``h`` stops the panel's heartbeats, ``H`` resumes them.
    """
    panel, path = await SimulatedPanel.on_pty(
        estop=args.estop, protocol_version=args.protocol_version, noise=args.noise, seed=args.seed
    )
    if args.no_heartbeat:
        panel.stop_heartbeats()
    print(f"simulated panel on {path}", flush=True)
    panel.on_change = lambda p: say(
        f"LED {p.led.value}, light {'on' if p.light else 'off'}" + (", host lost" if p.host_lost else ""))
    keys = {"s": ("start pressed", panel.press_start), "x": ("stop pressed", panel.press_stop),
            "e": ("e-stop pressed", panel.press_estop), "r": ("e-stop released", panel.release_estop),
            "h": ("heartbeats stopped", panel.stop_heartbeats), "H": ("heartbeats resumed", panel.resume_heartbeats)}
    runner = asyncio.create_task(panel.run(), name="sim-panel")
    try:
        with stop_signals(keys) as stop:
            await stop.wait()
    finally:
        runner.cancel()
        await asyncio.gather(runner, return_exceptions=True)
        panel.close()
    return 0
