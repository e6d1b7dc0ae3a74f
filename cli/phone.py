"""``tbp phone``: commission the rig phones - list them on USB, and check one end to end.

``tbp phone check`` runs what a scan needs from one phone: ADB connect with the rig's host key
(the phone asks to allow it on first use), push the capture agent when ``--agent-jar`` differs
from the phone's copy, start it, clock round trips, focus moves across its calibrated range, one
capture and a verified pull. It works the same against ``tbp sim phone`` (``--tcp
127.0.0.1:PORT``; with ``--agent-runtime jvm`` the pushed jar is the agent's JVM build).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from cli import options


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "phone",
        help="list the ADB phones on USB, or check one phone end to end",
        description="Commissioning of the rig phones over ADB (USB or wireless debugging).",
    )
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    actions.add_parser("list", help="serials of the USB devices with an ADB interface")
    check = actions.add_parser("check", help="connect, start the agent, focus, capture and pull once")
    link = check.add_mutually_exclusive_group(required=True)
    link.add_argument("--usb", metavar="SERIAL", help="the phone with this serial on USB")
    link.add_argument("--tcp", metavar="HOST[:PORT]", help="a phone in wireless debugging (port 5555)")
    check.add_argument("--camera", help="rig camera id (default: the rig phone with the --usb serial)")
    options.rig(check)
    check.add_argument("--state-dir", type=Path, default=Path("/var/lib/tbp-rig"),
                       help="folder of the host's ADB key (adbkey, adbkey.pub); created if missing")
    check.add_argument("--agent-jar", type=Path, default=None,
                       help="capture agent jar to push when the phone's copy differs (docs/phones.md: the dex jar "
                       "for a phone, the JVM jar for tbp sim phone --agent-runtime jvm)")
    check.add_argument("--out", type=Path, default=Path("."), help="folder for the test image")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import asyncio
    import sys

    if args.action == "list":
        from drivers.adb.usb import adb_devices

        for serial, device in adb_devices():
            print(f"{serial}\tbus {device.bus} address {device.address}")
        return 0
    try:
        return asyncio.run(_check(args))
    except Exception as exc:  # a commissioning tool reports the typed error and fails
        print(f"FAILED: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1


async def _check(args: argparse.Namespace) -> int:
    import asyncio

    from drivers.adb.auth import AdbKey
    from drivers.phone.camera import PhoneCamera
    from drivers.phone.focus import load_focus_calibration
    from drivers.phone.links import tcp_link, usb_link
    from planner.rig import DEFAULT_RIG_PATH, load_rig

    rig = load_rig(args.rig or DEFAULT_RIG_PATH)
    phones = [p for p in rig.phones if p.id == args.camera or (args.camera is None and p.serial == args.usb)]
    if not phones:
        raise SystemExit(f"no rig phone with camera id {args.camera!r} / serial {args.usb!r} in the rig file")
    phone = phones[0]
    if args.usb:
        link = usb_link(args.usb)
    else:
        host, _, port = args.tcp.partition(":")
        link = tcp_link(host, int(port or 5555))
    table = load_focus_calibration(rig.resolve(phone.focus_calibration))
    camera = PhoneCamera(link, phone, table, key=AdbKey.load_or_create(args.state_dir), agent_jar=args.agent_jar)
    loop = asyncio.get_running_loop()
    began = loop.time()
    try:
        info = await camera.connect()
        agent = (f"agent pushed ({camera.agent_pushed_bytes} bytes)" if camera.agent_pushed_bytes
                 else "the phone's agent")
        print(f"{phone.id} {info.serial} {info.model}: min focus {info.min_focus_diopters:g} D, "
              f"focus calibration {info.focus_calibration_quality}, timestamps {info.timestamp_source}; "
              f"{agent}, started in {loop.time() - began:.2f} s")
        samples = [await camera.clock_sample() for _ in range(8)]
        best = min(samples, key=lambda s: s.host_recv_s - s.host_send_s)
        print(f"clock: best round trip {1000 * (best.host_recv_s - best.host_send_s):.2f} ms of {len(samples)}")
        reach = min(info.min_focus_diopters, table.max_diopters)  # the lens' and the table's nearest
        near = table.focus_mm(reach) if reach >= table.diopters[0] else table.far_mm
        for focus_mm in (near * 1.05, (near + table.far_mm) / 2, table.far_mm * 0.95, 450.0):
            start = loop.time()
            done = await camera.set_focus_mm(focus_mm)
            print(f"focus {focus_mm:7.1f} mm -> {done.diopters:.3f} D, lens still after "
                  f"{1000 * (loop.time() - start):.0f} ms")
        start = loop.time()
        shot = await camera.capture()
        print(f"capture: {shot.path} {shot.size_bytes} bytes, exposure {shot.exposure_s:g} s, "
              f"answered after {1000 * (loop.time() - start):.0f} ms")
        args.out.mkdir(parents=True, exist_ok=True)
        dest = args.out / f"{phone.id}-check.jpg"
        size, sha = await camera.pull(shot.path, dest)
        if size != shot.size_bytes:
            raise SystemExit(f"pulled {size} bytes, the phone reported {shot.size_bytes}")
        print(f"pulled {dest} sha256 {sha}")
        await camera.delete(shot.path)
        print(f"connect, agent start, clock, focus, capture and pull: {loop.time() - began:.2f} s")
    finally:
        await camera.close()
    print("OK")
    return 0
