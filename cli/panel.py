"""``tbp panel``: commission the operator panel by hand (status, LED, lights, watch the buttons).

For wiring up and checking a panel, or the simulated one served by ``tbp sim panel``; never
while the daemon runs (the port is opened exclusively). Every action ends with BYE, so the panel
is left dark and without a FAULT indication.
"""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from drivers.panel import OperatorPanel

DEFAULT_PORT = "/dev/tbp-panel"  # the udev rule's name for the panel's serial port


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "panel",
        help="commission the operator panel: status, led, light, watch",
        description="Connect to the operator panel over its serial port, run one action and say "
        "BYE. Not while the daemon runs: the port is opened exclusively.",
    )
    parser.add_argument("--port", default=DEFAULT_PORT, help=f"serial port (default {DEFAULT_PORT})")
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    actions.add_parser("status", help="connect and print what the panel reports")
    led = actions.add_parser("led", help="show a status on the LED for --seconds")
    led.add_argument("status", choices=["OFF", "IDLE", "BUSY", "SCANNING", "FAULT"])
    light = actions.add_parser("light", help="switch the subject lights for --seconds")
    light.add_argument("state", choices=["on", "off"])
    watch = actions.add_parser("watch", help="print button and e-stop events for --seconds")
    for sub in (led, light, watch):
        sub.add_argument("--seconds", type=float, default=5.0, help="how long (default 5)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import asyncio

    from daemon.logs import configure_logging
    from drivers.panel import PanelError

    configure_logging(level="warning", stream=sys.stderr)
    try:
        asyncio.run(_action(args))
    except PanelError as exc:
        print(f"tbp panel: {exc}", file=sys.stderr)
        return 1
    return 0


async def _action(args: argparse.Namespace) -> None:
    import asyncio
    import contextlib

    from drivers.panel import OperatorPanel, StatusLed, open_serial

    panel = OperatorPanel(*await open_serial(args.port, name=args.port), name=args.port)
    try:
        await panel.connect()
        await asyncio.sleep(2 * panel.HEARTBEAT_PERIOD_S)  # one heartbeat tells LED and light
        if args.action == "status":
            _print_status(panel)
        elif args.action == "led":
            await panel.set_status(StatusLed(args.status))
            print(f"LED {args.status} for {args.seconds:g} s", flush=True)
            await asyncio.sleep(args.seconds)
        elif args.action == "light":
            await panel.set_light(args.state == "on")
            print(f"light {args.state} for {args.seconds:g} s", flush=True)
            await asyncio.sleep(args.seconds)
        else:
            _print_status(panel)
            with contextlib.suppress(TimeoutError):  # the watch simply ends after --seconds
                async with asyncio.timeout(args.seconds):
                    async for event in panel.events():
                        print(f"{event.name}", flush=True)
        if panel.fault is not None:
            raise panel.fault
    finally:
        await panel.close()


def _print_status(panel: OperatorPanel) -> None:
    led, light = panel.reported_led, panel.reported_light
    print(
        f"panel {panel.name}: {panel.state.value}, "
        f"e-stop {'PRESSED' if panel.estop_active else 'released'}, "
        f"LED {led.value if led is not None else 'unknown'}, "
        f"light {'unknown' if light is None else ('on' if light else 'off')}, "
        f"bad lines {panel.bad_lines}",
        flush=True,
    )
