"""`tbp status [--follow]`, `tbp abort`, `tbp reset`: talk to the running daemon's control socket.

Exit codes: 0 done, 1 the daemon refused or failed the command, 2 the daemon is unreachable.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from cli import options


def register(subparsers: argparse._SubParsersAction) -> None:
    for name, help_text in (
        ("status", "show the rig daemon's state (--follow streams status events)"),
        ("abort", "abort the running scan: the beam decelerates, captured images are kept"),
        ("reset", "clear a latched FAULT (after the cause is fixed)"),
    ):
        parser = subparsers.add_parser(name, help=help_text, description=help_text)
        options.socket(parser)
        parser.add_argument("--json", action="store_true",
                            help="print the daemon's JSON, one object a line (for scripts; default: a table)")
        if name == "status":
            parser.add_argument("--follow", "-f", action="store_true",
                                help="keep printing status events until interrupted")
        parser.set_defaults(func=run, control_cmd=name)


def run(args: argparse.Namespace) -> int:
    import asyncio

    from cli.status_table import event_line, status_table
    from daemon.server.control import CommandFailed, ControlClient, ControlError

    client = ControlClient(args.socket)

    def show(message: Any) -> None:
        if args.json or not isinstance(message, dict):
            print(json.dumps(message), flush=True)
        else:
            print(event_line(message) if "kind" in message else status_table(message), flush=True)

    async def go() -> None:
        if args.control_cmd == "status" and args.follow:
            async for message in client.subscribe():
                show(message)
        else:
            show(await client.request(args.control_cmd))

    try:
        asyncio.run(go())
    except CommandFailed as exc:
        print(f"tbp {args.control_cmd}: refused: {exc}", file=sys.stderr)
        return 1
    except ControlError as exc:  # DaemonUnavailable among them
        print(f"tbp {args.control_cmd}: {exc}", file=sys.stderr)
        return 2
    return 0
