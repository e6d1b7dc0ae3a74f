"""``tbp depth``: commission the RealSense depth cameras (list, check streaming, record, play).

``check`` streams each rig camera for a few seconds through the same driver the daemon uses
and prints what matters for the sweep: frame rate, depth unit, intrinsics, timestamp domain,
dropped frames and the share of pixels without depth. Not while the daemon runs (it holds the
cameras). ``record --sim`` writes a sweep recording of the simulated depth cameras (one ``.db3``
and one ``.beam.json`` per camera) that the daemon can play back in place of the cameras;
``play`` replays a recording through the playback driver.
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
        help="commission the RealSense depth cameras: list, check, record, play",
        description="List connected RealSense devices, stream the rig's depth cameras for a few "
        "seconds, record a simulated sweep, or replay a recording, through the drivers the daemon uses.",
    )
    options.rig(parser)
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    actions.add_parser("list", help="connected RealSense devices")
    check = actions.add_parser("check", help="stream each rig camera and report")
    check.add_argument("--camera", action="append", default=None, metavar="ID",
                       help="only this camera id (repeatable; default: all in the rig file)")
    check.add_argument("--seconds", type=float, default=3.0, help="how long each (default 3)")
    record = actions.add_parser(
        "record", help="record a depth sweep of the simulated cameras (.db3 + .beam.json per camera)",
        description="Render the depth sweep the daemon runs (the beam from depth_sweep.start_deg to "
        "end_deg on its trapezoid) with the simulated depth cameras and write one RealSense recording "
        "per camera, OUT/CAMERA.db3, with its beam angles in OUT/CAMERA.beam.json. Prints the folder last.")
    record.add_argument("--sim", action="store_true", required=True,
                        help="record the simulated cameras (recording the rig's own cameras is not built)")
    record.add_argument("--out", type=Path, required=True, help="folder for the recordings (created)")
    body = record.add_mutually_exclusive_group(required=True)
    body.add_argument("--body-seed", type=int, metavar="N", help="simulated adult N (sim/body.py), as "
                      "tbp sim phone --body-seed N")
    body.add_argument("--body", type=Path, metavar="FILE", help="subject mesh (mm, feet on z = 0)")
    record.add_argument("--camera", action="append", default=None, metavar="ID",
                        help="only this camera id (repeatable; default: all in the rig file)")
    record.add_argument("--fps", type=float, default=None, help="frame rate (default: the rig's camera model)")
    record.add_argument("--decimation", type=int, default=1,
                        help="record at 1/N of the rig's resolution, intrinsics scaled alike (default 1)")
    record.add_argument("--seed", type=int, default=0, help="depth noise seed (default 0)")
    record.add_argument("--no-noise", action="store_true", help="record without depth noise")
    play = actions.add_parser("play", help="replay a recording (.db3, or .bag) as fast as it can be read")
    play.add_argument("path", type=Path)
    play.add_argument("--camera-id", default="bag", help="id the frames carry")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import asyncio

    from daemon.logs import configure_logging
    from drivers.depth.errors import DepthCameraError
    from planner.rig import RigConfigError

    configure_logging(level="warning", stream=sys.stderr)
    try:
        if args.action == "record":
            return _record(args)
        return asyncio.run(_ACTIONS[args.action](args))
    except (DepthCameraError, RigConfigError) as exc:
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


def _cameras_known(wanted: list[str] | None, rig_cameras: list[str]) -> bool:
    """Whether every --camera names a depth camera of the rig file; says which one does not."""
    unknown = sorted(set(wanted or ()) - set(rig_cameras))
    if unknown:
        print(f"tbp depth: no depth camera {unknown[0]!r} in the rig file", file=sys.stderr)
    return not unknown


async def _check(args: argparse.Namespace) -> int:
    from drivers.depth.errors import DepthCameraError
    from drivers.depth.realsense import RealSenseCamera
    from planner.rig import DEFAULT_RIG_PATH, load_rig

    rig = load_rig(args.rig or DEFAULT_RIG_PATH)
    cameras = [c for c in rig.depth_cameras if args.camera is None or c.id in args.camera]
    if not _cameras_known(args.camera, [c.id for c in rig.depth_cameras]):
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


def _record(args: argparse.Namespace) -> int:
    """Render and write one sweep recording per rig depth camera; prints the folder last."""
    import trimesh

    from drivers.depth.beam_angles import beam_angles_path, read_beam_angles
    from drivers.sim.depth import DepthScene, record_sweep
    from planner.rig import DEFAULT_RIG_PATH, load_rig
    from sim.rig import sim_depth_model

    rig = load_rig(args.rig or DEFAULT_RIG_PATH)
    if not _cameras_known(args.camera, [c.id for c in rig.depth_cameras]):
        return 2
    if args.decimation < 1 or (args.fps is not None and not 0 < args.fps <= 90):
        print(f"tbp depth: --decimation {args.decimation} must be >= 1 and --fps {args.fps} in (0, 90]",
              file=sys.stderr)
        return 2
    model = sim_depth_model(rig.depth_camera_model, args.decimation, args.fps or rig.depth_camera_model.fps)
    if args.body is not None:
        subject, body = trimesh.load(args.body, force="mesh"), {"body": str(args.body)}
    else:
        from sim.body import make_body

        subject, body = make_body(seed=args.body_seed), {"body_seed": args.body_seed}
    paths = record_sweep(DepthScene(subject), rig, model, args.out, seed=args.seed, noise=not args.no_noise,
                         camera_ids=args.camera, source={**body, "decimation": args.decimation})
    for path in paths:
        angles = read_beam_angles(beam_angles_path(path), path.stem)
        first, last = min(angles.frames), max(angles.frames)
        print(f"{path.stem}: {path}, {len(angles.frames)} frames {model.width_px}x{model.height_px} at "
              f"{model.fps:g} fps, beam {angles.frames[first][1]:.1f} .. {angles.frames[last][1]:.1f} deg",
              flush=True)
    print(args.out, flush=True)
    return 0


async def _play(args: argparse.Namespace) -> int:
    from drivers.depth.bag import BagPlayback

    bag = BagPlayback(args.path, camera_id=args.camera_id)
    frames = await _stream(bag, None)
    print(_report(args.camera_id, str(args.path), frames, bag), flush=True)
    angles = [f.beam_angle_deg for f in frames if f.beam_angle_deg is not None]
    if angles:
        print(f"{args.camera_id}: recorded beam angles {angles[0]:.1f} .. {angles[-1]:.1f} deg", flush=True)
    else:
        print(f"{args.camera_id}: no beam-angle file: the daemon tags its frames with the live encoder", flush=True)
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
