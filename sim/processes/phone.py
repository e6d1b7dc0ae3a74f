"""``tbp sim phone``: one simulated phone's adbd with the capture agent on 127.0.0.1:PORT."""

from __future__ import annotations

import argparse
import asyncio
import signal
from typing import Any

import numpy as np

from drivers.sim.phone import PoseSource, SimulatedPhone
from planner.rig import load_rig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``tbp sim phone``."""
    parser.add_argument("--port", type=int, default=5555, help="TCP port on 127.0.0.1 (adbd's is 5555)")
    parser.add_argument("--serial", default="TBPSIM00", help="ro.serialno of the simulated phone")
    parser.add_argument("--seed", type=int, default=0, help="seeds clock offset/drift and capture jitter")
    parser.add_argument("--refuse-keys", action="store_true",
                        help="refuse new host keys (the phone user says no)")
    parser.add_argument("--file", action="append", default=[], metavar="PHONE_PATH=SIZE",
                        help="preload a file of SIZE random bytes (e.g. /sdcard/big.bin=20000000)")
    parser.add_argument("--body-seed", type=int, default=None, metavar="N",
                        help="photograph simulated adult N (sim/body.py) instead of an empty rig")
    parser.add_argument("--camera", default=None,
                        help="rig camera id whose pose the phone takes (default: the one with --serial)")
    parser.add_argument("--angle", type=float, default=0.0, help="beam angle of that pose (deg)")


def _standing_subject(args: argparse.Namespace) -> tuple[Any, PoseSource]:
    """A simulated adult and the fixed pose of one rig camera at one beam angle (no motor here)."""
    from planner.poses import rgb_poses
    from sim.body import make_body

    rig = load_rig()
    ids = [p.id for p in rig.phones]
    camera = args.camera or next((p.id for p in rig.phones if p.serial == args.serial), ids[0])
    if camera not in ids:
        raise SystemExit(f"--camera {camera!r}: the rig's cameras are {', '.join(ids)}")
    camera_to_world = rgb_poses(rig, np.array([args.angle])).camera_to_world(ids.index(camera))
    return make_body(seed=args.body_seed), lambda _time_s: camera_to_world


async def serve(args: argparse.Namespace) -> int:
    """Run one simulated phone as a TCP adbd on 127.0.0.1:PORT until SIGINT/SIGTERM."""
    subject, pose = None, None
    if args.body_seed is not None:
        subject, pose = _standing_subject(args)
    phone = SimulatedPhone(args.serial, seed=args.seed, accept_new_keys=not args.refuse_keys, subject=subject,
                           pose=pose)
    if pose is not None:  # build the ray-casting scene now: in real time a first capture must not wait for it
        phone._picture(pose(0.0), 0.0, 0)
    rng = np.random.default_rng(args.seed)
    for spec in args.file:
        path, _, size = spec.partition("=")
        phone.fs.write(path, rng.integers(0, 256, int(size), dtype=np.uint8).tobytes())
    server = await asyncio.start_server(phone.accept, "127.0.0.1", args.port)
    port = server.sockets[0].getsockname()[1]
    print(f"simulated phone {args.serial} (adbd) on 127.0.0.1:{port}", flush=True)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    async with server:
        await stop.wait()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.remove_signal_handler(sig)
    return 0
