"""``tbp sim panel``: the simulated operator panel on a new pty."""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import stat
import sys
from typing import Any

from drivers.panel import protocol
from drivers.sim.panel import SimulatedPanel


def _is_stream(file: Any) -> bool:
    """True for a pipe or terminal the event loop can watch (not /dev/null or a regular file)."""
    if file is None or file.closed:
        return False
    mode = os.fstat(file.fileno()).st_mode
    return stat.S_ISFIFO(mode) or file.isatty()


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

    Keys on stdin press buttons: ``s`` start, ``x`` stop, ``e`` e-stop, ``r`` release it.
    """
    panel, path = await SimulatedPanel.on_pty(
        estop=args.estop, protocol_version=args.protocol_version, noise=args.noise, seed=args.seed
    )
    if args.no_heartbeat:
        panel.stop_heartbeats()
    print(f"simulated panel on {path}", flush=True)
    panel.on_change = lambda p: print(
        f"LED {p.led.value}, light {'on' if p.light else 'off'}"
        + (", host lost" if p.host_lost else ""), flush=True)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    keys = {"s": panel.press_start, "x": panel.press_stop, "e": panel.press_estop,
            "r": panel.release_estop}

    def on_stdin() -> None:
        data = os.read(sys.stdin.fileno(), 64).decode(errors="replace")
        if not data:
            loop.remove_reader(sys.stdin.fileno())
        for key in data:
            if key in keys:
                keys[key]()

    watching_stdin = _is_stream(sys.stdin)
    if watching_stdin:
        loop.add_reader(sys.stdin.fileno(), on_stdin)
    runner = asyncio.create_task(panel.run(), name="sim-panel")
    try:
        await stop.wait()
    finally:
        if watching_stdin:
            loop.remove_reader(sys.stdin.fileno())
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
        runner.cancel()
        await asyncio.gather(runner, return_exceptions=True)
        panel.close()
    return 0
