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
        parser.add_argument("--json", action="store_true", help="print raw JSON lines")
        if name == "status":
            parser.add_argument("--follow", "-f", action="store_true",
                                help="keep printing status events until interrupted")
        parser.set_defaults(func=run, control_cmd=name)


def _format(message: dict[str, Any]) -> str:
    """A status event as one readable line; a status reply as one "key: value" line per key."""
    if "kind" in message:
        head = f"{message.get('state')}"
        if message.get("kind") == "transition":
            head = f"{message.get('previous')} -> {head}"
        data = " ".join(f"{k}={v}" for k, v in (message.get("data") or {}).items())
        scan = f" scan={message['scan_id']}" if message.get("scan_id") else ""
        return f"[{message.get('time_s', 0.0):10.3f}] {head}{scan}: {message.get('cause', '')} {data}".rstrip()
    lines = []
    for key, value in message.items():
        if key == "fault_causes":
            text = "; ".join(cause["text"] for cause in value) or "none"
        elif key == "last_scan" and isinstance(value, dict):
            text = _last_scan(value)
        else:
            text = json.dumps(value) if isinstance(value, (dict, list)) else str(value)
        lines.append(f"{key}: {text}")
    return "\n".join(lines)


def _last_scan(report: dict[str, Any]) -> str:
    """The last scan's outcome on one line: "sim-seed1 PARTIAL, 260 of 336 images in the folder:
    76 of 336 images missing: cam2 28 (...); cam4 48 (48 pull failed) (/scans/...)"."""
    planned = (report.get("verified") or 0) + (report.get("missing") or 0)
    text = (f"{report.get('scan_id')} {report.get('outcome')}, {report.get('verified')} of {planned} "
            "images in the folder")
    if report.get("reason"):
        text += f": {report['reason']}"
    return f"{text} ({report.get('folder')})"


def run(args: argparse.Namespace) -> int:
    import asyncio

    from daemon.control import CommandFailed, ControlClient, ControlError, DaemonUnavailable

    client = ControlClient(args.socket)

    def show(message: Any) -> None:
        if args.json or not isinstance(message, dict):
            print(json.dumps(message), flush=True)
        else:
            print(_format(message), flush=True)

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
    except DaemonUnavailable as exc:
        print(f"tbp {args.control_cmd}: {exc}", file=sys.stderr)
        return 2
    except ControlError as exc:
        print(f"tbp {args.control_cmd}: {exc}", file=sys.stderr)
        return 2
    return 0
