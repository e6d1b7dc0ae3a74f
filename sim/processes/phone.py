"""``tbp sim phone``: one simulated phone's adbd with the capture agent on 127.0.0.1:PORT.

The agent is the Python twin, or with ``--agent-runtime jvm`` the real agent's JVM build
(agent/, ``./dev agent``) that the host pushes and the phone runs with ``java``; ``--agent-jar``
installs that jar beforehand (without it the host must push one: ``tbp phone check --agent-jar``).

With ``--body-seed N`` the phone photographs simulated adult N from one rig camera's pose: at a
fixed beam angle (``--angle``), or, with ``--follow-beam HOST:PORT``, at the angle the drive of
``tbp sim motor`` reports on its socketcand bridge at the moment of each exposure
(``sim.processes.beam_follower``), so its images match the angle they were taken at.
"""

from __future__ import annotations

import argparse
import asyncio
from pathlib import Path

import numpy as np

from drivers.sim.phone import AGENT_RUNTIMES, SimulatedPhone
from planner.rig import DEFAULT_RIG_PATH, Rig, load_rig
from sim.processes.keys import stop_signals


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
    parser.add_argument("--angle", type=float, default=0.0,
                        help="beam angle of that pose (deg); with --follow-beam, until the drive reports one")
    parser.add_argument("--follow-beam", type=_bridge_address, default=None, metavar="HOST:PORT",
                        help="pose the camera at the beam angle the drive reports on this socketcand bridge "
                        "(tbp sim motor's; needs --body-seed)")
    parser.add_argument("--agent-runtime", choices=AGENT_RUNTIMES, default="python",
                        help="the capture agent: the Python twin, or the agent's JVM build run with java")
    parser.add_argument("--agent-jar", type=Path, default=None, metavar="JAR",
                        help="with --agent-runtime jvm: install this JVM jar (agent/build/tbp-capture-agent-jvm.jar) "
                        "on the phone beforehand")
    parser.add_argument("--rig", type=Path, default=None,
                        help="rig file: camera poses, drive node id and gearing (default: calibration_data/rig.yaml)")


def _bridge_address(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise argparse.ArgumentTypeError(f"{text!r}: expected HOST:PORT, e.g. 127.0.0.1:29536")
    return host, int(port)


def _camera_index(rig: Rig, args: argparse.Namespace) -> int:
    ids = [p.id for p in rig.phones]
    camera = args.camera or next((p.id for p in rig.phones if p.serial == args.serial), ids[0])
    if camera not in ids:
        raise SystemExit(f"--camera {camera!r}: the rig's cameras are {', '.join(ids)}")
    return ids.index(camera)


async def serve(args: argparse.Namespace) -> int:
    """Run one simulated phone as a TCP adbd on 127.0.0.1:PORT until SIGINT/SIGTERM."""
    from sim.processes.beam_follower import BeamFollower
    from sim.rig import phone_pose_source

    if args.follow_beam is not None and args.body_seed is None:
        raise SystemExit("--follow-beam needs --body-seed: an empty rig looks the same at every angle")
    if args.agent_jar is not None and args.agent_runtime != "jvm":
        raise SystemExit("--agent-jar is the JVM build's jar: it needs --agent-runtime jvm")
    rig = load_rig(args.rig or DEFAULT_RIG_PATH)
    subject, pose, follower = None, None, None
    if args.body_seed is not None:
        from sim.body import make_body

        index = _camera_index(rig, args)
        subject = make_body(seed=args.body_seed)
        if args.follow_beam is not None:
            follower = BeamFollower(rig.motor, *args.follow_beam, fallback_deg=args.angle)
            pose = phone_pose_source(rig, index, follower.angle_at)
        else:
            pose = phone_pose_source(rig, index, lambda _time_s: args.angle)
    phone = SimulatedPhone(args.serial, seed=args.seed, accept_new_keys=not args.refuse_keys, subject=subject,
                           pose=pose, optics=rig.optics, agent_runtime=args.agent_runtime, agent_jar=args.agent_jar,
                           agent_installed=args.agent_runtime == "python" or args.agent_jar is not None)
    if pose is not None:  # build the ray-casting scene now: in real time a first capture must not wait for it
        phone._picture(pose(0.0), 0.0, 0)
    rng = np.random.default_rng(args.seed)
    for spec in args.file:
        path, _, size = spec.partition("=")
        phone.fs.write(path, rng.integers(0, 256, int(size), dtype=np.uint8).tobytes())
    server = await asyncio.start_server(phone.accept, "127.0.0.1", args.port)
    port = server.sockets[0].getsockname()[1]
    print(f"simulated phone {args.serial} (adbd) on 127.0.0.1:{port}", flush=True)
    if follower is not None:
        follower.start()
        host, bridge_port = args.follow_beam
        print(f"following the beam's position on socketcand {host}:{bridge_port}", flush=True)
    with stop_signals() as stop:
        async with server:
            await stop.wait()
        await phone.shut_down()  # the host links and the agent end before the process does
    if follower is not None:
        await asyncio.to_thread(follower.stop)  # the join may wait out a reconnection attempt
    return 0
