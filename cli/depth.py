"""``tbp depth``: commission the RealSense depth cameras (list, check streaming, play a recording).

``check`` streams each rig camera for a few seconds through the same driver the daemon uses
and prints what matters for the sweep: frame rate, depth unit, intrinsics, timestamp domain,
dropped frames and the share of pixels without depth. Not while the daemon runs (it holds the
cameras).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from cli import options


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "depth",
        help="commission the RealSense depth cameras: list, check, play",
        description="List connected RealSense devices, stream the rig's depth cameras for a few "
        "seconds, or replay a .bag recording, through the drivers the daemon uses.",
    )
    options.rig(parser)
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    actions.add_parser("list", help="connected RealSense devices")
    check = actions.add_parser("check", help="stream each rig camera and report")
    check.add_argument("--camera", action="append", default=None, metavar="ID",
                       help="only this camera id (repeatable; default: all in the rig file)")
    check.add_argument("--seconds", type=float, default=3.0, help="how long each (default 3)")
    play = actions.add_parser("play", help="replay a .bag recording as fast as it can be read")
    play.add_argument("path", type=Path)
    play.add_argument("--camera-id", default="bag", help="id the frames carry")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import asyncio

    from daemon.logs import configure_logging
    from drivers.depth.errors import DepthCameraError

    configure_logging(level="warning", stream=sys.stderr)
    try:
        return asyncio.run(_ACTIONS[args.action](args))
    except DepthCameraError as exc:
        print(f"tbp depth: {exc}", file=sys.stderr)
        return 1


async def _list(args: argparse.Namespace) -> int:
    from drivers.depth.realsense import import_pyrealsense2

    rs = import_pyrealsense2("-")
    devices = list(rs.context().query_devices())
    for device in devices:
        info = rs.camera_info
        print(f"serial {device.get_info(info.serial_number)}  "
              f"{device.get_info(info.product_line)}  firmware {device.get_info(info.firmware_version)}")
    if not devices:
        print("no RealSense device connected")
    return 0


async def _check(args: argparse.Namespace) -> int:
    from drivers.depth.errors import DepthCameraError
    from drivers.depth.realsense import RealSenseCamera
    from planner.rig import DEFAULT_RIG_PATH, load_rig

    rig = load_rig(args.rig or DEFAULT_RIG_PATH)
    cameras = [c for c in rig.depth_cameras if args.camera is None or c.id in args.camera]
    unknown = sorted(set(args.camera or ()) - {c.id for c in rig.depth_cameras})
    if unknown:
        print(f"tbp depth: no depth camera {unknown[0]!r} in the rig file", file=sys.stderr)
        return 2
    failures = 0
    for config in cameras:
        camera = RealSenseCamera(config, fps=rig.depth_camera_model.fps)
        try:
            print(_report(config.id, f"serial {config.serial}", await _stream(camera, args.seconds),
                          camera), flush=True)
        except DepthCameraError as exc:
            failures += 1
            print(f"{config.id}: FAILED: {exc}", flush=True)
    return 1 if failures else 0


async def _play(args: argparse.Namespace) -> int:
    from drivers.depth.bag import BagPlayback

    bag = BagPlayback(args.path, camera_id=args.camera_id)
    print(_report(args.camera_id, str(args.path), await _stream(bag, None), bag), flush=True)
    return 0


async def _stream(camera: Any, seconds: float | None) -> list[Any]:
    """Frames from ``camera`` for ``seconds`` (None: until its stream ends)."""
    import asyncio
    import contextlib

    frames: list[Any] = []
    await camera.start()
    try:
        with contextlib.suppress(TimeoutError):  # the check simply ends after --seconds
            async with asyncio.timeout(seconds):
                async for frame in camera.frames():
                    frames.append(frame)
    finally:
        await camera.stop()
    return frames


def _report(camera_id: str, source: str, frames: list[Any], camera: Any) -> str:
    if not frames:
        return f"{camera_id} ({source}): no frames"
    first, last = frames[0], frames[-1]
    span_s = last.timestamp_s - first.timestamp_s
    rate = (len(frames) - 1) / span_s if span_s > 0 else float("nan")
    holes = sum(float((f.depth == 0).mean()) for f in frames) / len(frames)
    k = first.intrinsics
    return (f"{camera_id} ({source}): {len(frames)} frames, {rate:.1f} fps, "
            f"{first.depth.shape[1]}x{first.depth.shape[0]}, depth unit {first.depth_unit_mm:.4f} mm, "
            f"fx {k[0, 0]:.1f} fy {k[1, 1]:.1f} cx {k[0, 2]:.1f} cy {k[1, 2]:.1f}, "
            f"timestamps {camera.timestamp_domain}, dropped {camera.dropped_frames}, "
            f"no depth {100 * holes:.1f} %")


_ACTIONS = {"list": _list, "check": _check, "play": _play}
