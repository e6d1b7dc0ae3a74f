"""``tbp motor``: commission the beam drive by hand (status, enable, zero, move, rotate, reset).

For installing and checking a drive, or a simulated one served by ``tbp sim motor``; never while
the daemon runs, because bring-up resets the drive's CANopen communication. Every action ends
with the drive disabled (BeamDrive.close), the beam standing where the action left it.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from cli import options


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "motor",
        help="commission the beam drive: status, enable, zero, move, rotate, stop, reset",
        description="Connect to the beam's CiA 402 drive, run one action and print the drive's state "
        "and beam angle. Not while the daemon runs: bring-up resets the drive's communication.",
    )
    parser.add_argument("--interface", default=None,
                        help="python-can interface (default: the hardware file's can.interface)")
    parser.add_argument("--channel", default=None, help="CAN channel (default: the hardware file's can.channel)")
    parser.add_argument("--host", default=None, help="socketcand host (default: the hardware file's, else 127.0.0.1)")
    parser.add_argument("--port", type=int, default=None,
                        help="socketcand TCP port (default: the hardware file's, else 29536)")
    options.rig(parser)
    options.hardware(parser)
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    actions.add_parser("status", help="connect and report")
    actions.add_parser("enable", help="check the drive reaches OPERATION ENABLED")
    actions.add_parser("disable", help="disable voltage")
    actions.add_parser("reset", help="reset a latched fault")
    zero = actions.add_parser("zero", help="make the current position read as ANGLE")
    zero.add_argument("angle", type=float, nargs="?", default=0.0, help="deg (default 0)")
    move = actions.add_parser("move", help="move to ANGLE and wait")
    move.add_argument("angle", type=float, help="deg")
    rotate = actions.add_parser("rotate", help="rotate at SPEED for --seconds, then stop")
    rotate.add_argument("speed", type=float, help="deg/s, signed")
    rotate.add_argument("--seconds", type=float, default=2.0, help="time at speed (default 2)")
    for sub in (move, rotate):
        sub.add_argument(
            "--speed",
            dest="limit_speed",
            type=float,
            default=None,
            help="deg/s (default: a quarter of the rig's maximum)",
        )
        sub.add_argument(
            "--acceleration",
            type=float,
            default=None,
            help="deg/s^2 (default: a quarter of the rig's maximum)",
        )
    parser.set_defaults(func=run)


def _open_port(args: argparse.Namespace, rig: Any) -> Any:
    """The drive's bus: the hardware file's ``can`` section (when there is a file), overridden by
    the command line; without either, SocketCAN ``can0``."""
    from daemon.rig.hardware_config import CanBus
    from drivers.motor import PythonCanPort

    path = options.hardware_path(args)
    bus = _configured_bus(path, rig) if path.is_file() else CanBus("socketcan", "can0")
    interface = args.interface or bus.interface
    channel = args.channel or bus.channel
    extra: dict[str, Any] = {}
    if interface == "socketcand":
        extra = {"host": args.host or bus.host or "127.0.0.1", "port": args.port or bus.port or 29536}
    elif interface == "slcan":
        extra = {"bitrate": bus.bitrate or rig.motor.bitrate}
    return PythonCanPort.open(interface, channel, **extra)


def _configured_bus(path: Any, rig: Any) -> Any:
    from daemon.rig.hardware_config import load_hardware

    return load_hardware(path, rig).can


async def _act(args: argparse.Namespace) -> str:
    from drivers.motor import BeamDrive
    from planner.rig import DEFAULT_RIG_PATH, load_rig

    rig = load_rig(args.rig or DEFAULT_RIG_PATH)
    motor = rig.motor
    drive = BeamDrive(_open_port(args, rig), motor)
    speed = getattr(args, "limit_speed", None) or motor.max_speed_deg_s / 4
    accel = getattr(args, "acceleration", None) or motor.max_acceleration_deg_s2 / 4
    try:
        await drive.connect()
        if args.action in ("enable", "zero", "move", "rotate"):
            await drive.enable()
        if args.action == "disable":
            await drive.disable()
        elif args.action == "reset":
            await drive.reset_fault()
        elif args.action == "zero":
            await drive.set_zero(args.angle)
        elif args.action == "move":
            await drive.move_to(args.angle, speed, accel)
        elif args.action == "rotate":
            import asyncio

            await drive.rotate(args.speed, accel)
            await drive.wait_speed(args.speed)
            await asyncio.sleep(args.seconds)
            await drive.stop(accel)
        sample = drive.latest
        angle = f"{sample.angle_deg:.3f} deg" if sample else "unknown"
        return f"{drive.name}: {drive.state.value}, angle {angle}, statusword 0x{drive.statusword:04X}"
    finally:
        await drive.close()


def run(args: argparse.Namespace) -> int:
    import asyncio

    from drivers.motor import DriveError
    from planner.rig import RigConfigError

    try:
        print(asyncio.run(_act(args)))
    except (DriveError, RigConfigError) as exc:
        print(f"tbp motor {args.action}: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    return 0
