"""``tbp calibrate``: every camera's pose and lens from pictures of the ChArUco cuboid.

  tbp calibrate --out DIR                   on the rig: the running daemon turns the beam stop by stop
                                            with the cuboid in place, every phone and depth camera
                                            (infrared) photographs it at each stop; then this command
                                            calibrates from the rotation's pictures
  tbp calibrate --sim --seed S --out DIR    the same through the daemon's code on the simulated rig (true
                                            poses off nominal by a seeded error, in this process);
                                            DIR gets calibration.yaml, truth.yaml (the simulated rig's true
                                            poses, same format), the rotation's folder and report/index.html
  tbp calibrate --pictures FILE --out DIR   calibrate from a calibration rotation's captures.json
  tbp calibrate target --out DIR            printable boards of the cuboid (PNG + true-size PDF per face)
  tbp calibrate focus [--phone ID] --out DIR each phone of the hardware file (daemon stopped) sweeps its lens
                                            over a board the operator stands at known distances (Enter at
                                            each); DIR/<phone>.yaml is its focus table (name it in the rig
                                            file's phones[].focus_calibration), DIR/<phone>.png the sweeps
  tbp calibrate focus --sim --seed S --out DIR
                                            the same procedure, through the phone driver, on the simulated
                                            phones (a simulated board stand; each lens off by a seeded error)

Install the result as the rig's calibration by copying DIR/calibration.yaml next to the rig file
(``calibration_data/`` or ``/etc/tbp-rig/``; the rig file's ``calibration.file`` names it).
Pictures that cannot be used are listed with the reason and the rest still calibrates; the exit
status is 1 when no calibration could be made.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from cli import options


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser("calibrate", help="calibrate every camera's pose and lens from the ChArUco cuboid",
                                   description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("action", nargs="?", choices=["target", "focus"], default=None,
                        help="'target': write the printable boards; 'focus': the phones' focus tables")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--sim", action="store_true", help="the simulated rig, in this process")
    options.seed(parser, "simulated rig errors and picture noise (--sim)")
    parser.add_argument("--pictures", type=Path, default=None, metavar="FILE",
                        help="captures.json of a calibration rotation to calibrate from")
    options.rig(parser)
    parser.add_argument("--target", type=Path, default=None,
                        help="target file (default calibration_data/target/cuboid.yaml)")
    parser.add_argument("--jobs", type=int, default=2, help="worker threads/processes (default 2)")
    options.hardware(parser)
    options.socket(parser)
    parser.add_argument("--state-dir", type=Path, default=None, metavar="DIR",
                        help="focus: where the ADB key the phones authorised is kept (as tbp check)")
    parser.add_argument("--phone", action="append", default=[], metavar="ID",
                        help="focus on the rig: only this phone (repeatable; default every phone)")
    parser.add_argument("--distances", type=_distances, default=None,
                        metavar="MM,MM,...", help="focus: board distances, mm (default 180,220,...,1100)")
    parser.add_argument("--yes", action="store_true",
                        help="focus on the rig: do not wait for Enter at each distance (a motorised stand)")
    parser.set_defaults(func=run)


def _distances(text: str) -> list[float]:
    """--distances: comma-separated millimetres."""
    try:
        return [float(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a comma-separated list of millimetres") from None


def _progress(stage: str, done: int, total: int) -> None:
    step = max(1, total // 10)
    if done == total or done % step == 0:
        print(f"  {stage}: {done}/{total}", flush=True)


def run(args: argparse.Namespace) -> int:
    from planner.calibration.target import TargetError, load_target
    from planner.rig import DEFAULT_RIG_PATH, RigConfigError, load_rig

    try:
        target = load_target(args.target) if args.target else load_target()
        rig = load_rig(args.rig or DEFAULT_RIG_PATH)
    except (TargetError, RigConfigError) as exc:
        print(f"tbp calibrate: {exc}", file=sys.stderr)
        return 2
    from cli.outputs import output_problem

    # before a rotation or a focus sweep; nothing made yet (a running daemon may still refuse it)
    if problem := output_problem("--out", args.out, folder=True, create=False):
        print(f"tbp calibrate: {problem}", file=sys.stderr)
        return 2
    if args.action == "target":
        from analysis.target_prints import write_target_prints

        for path in write_target_prints(target, args.out):
            print(path)
        return 0
    if args.action == "focus":
        return _focus(args, rig, target)
    if args.sim and args.pictures is not None:
        print("tbp calibrate: give --sim or --pictures FILE, not both", file=sys.stderr)
        return 2
    return _calibrate(args, rig, target)


def _calibrate(args: argparse.Namespace, rig: Any, target: Any) -> int:
    from analysis.calibration_report import write_report
    from daemon.utc import utc_stamp
    from planner.calibration.calibrate import CalibrationFailed, calibrate, read_captures

    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    truth = None
    if args.sim:
        from sim.calibration import true_rig

        truth = true_rig(rig, target, args.seed).save(out / "truth.yaml")
        print(f"simulated rig, seed {args.seed}: true poses in {out / 'truth.yaml'}", flush=True)
        captures = _rotate_sim(args, rig, target, truth, out)
        source = f"simulated rig, seed {args.seed}"
    elif args.pictures is not None:
        captures = args.pictures
        source = f"pictures {captures}"
    else:
        captures = _rotate_rig(args)
        if captures is None:
            return 1
        source = f"calibration rotation {captures.parent.name}"
    try:
        pictures = read_captures(captures)
        print(f"calibrating from {len(pictures)} pictures", flush=True)
        run = calibrate(rig, target, pictures, created_utc=utc_stamp(), source=source, jobs=args.jobs,
                        progress=_progress)
    except CalibrationFailed as exc:
        print(f"tbp calibrate: {exc}", file=sys.stderr)
        return 1
    for problem in run.problems:
        print(f"  not used: {problem}", flush=True)
    calibration = run.calibration.save(out / "calibration.yaml")
    page = write_report(run, pictures, rig, out, truth=truth)
    r = calibration.residuals
    assert r is not None
    print(f"reprojection error: mean {r.mean_px:.3f} px over {r.count} corners ({r.discarded} over 4 px dropped)")
    print("time: " + ", ".join(f"{k.replace('_', ' ')} {v:.1f} s" for k, v in run.timings_s.items()))
    if truth is not None:
        from planner.calibration.compare import compare

        for kind in ("phone", "depth"):
            ids = [c.id for c in calibration.cameras if c.kind == kind]
            s = compare(calibration, truth, rig.capture.angles_deg, ids).summary()
            print(f"{kind} poses against the truth: median {s['median_mm']:.3f} mm / {s['median_deg']:.4f} deg, "
                  f"worst {s['max_mm']:.3f} mm / {s['max_deg']:.4f} deg")
    print(f"report: {page}")
    print(out / "calibration.yaml", flush=True)
    return 0


def _rotate_sim(args: argparse.Namespace, rig: Any, target: Any, truth: Any, out: Path) -> Path:
    """The daemon's calibration rotation on the simulated rig (virtual time); its captures.json."""
    from sim.clock import run_virtual
    from sim.cuboid_stage import CuboidStage
    from sim.run import sim_calibration_rotation

    print("calibration rotation through the daemon on the simulated rig, the cuboid in place", flush=True)
    stage = CuboidStage(rig, target, truth, seed=args.seed)
    report = run_virtual(sim_calibration_rotation(rig, stage, store=out, target=args.target, seed=args.seed,
                                                  out=sys.stdout))
    for problem in report.problems:
        print(f"  rotation: {problem}", flush=True)
    return report.folder / "captures.json"


def _rotate_rig(args: argparse.Namespace) -> Path | None:
    """Ask the running daemon for a calibration rotation, follow it to its end; its captures.json,
    or None (printed why) when it did not complete."""
    import asyncio

    from daemon.server.control import ControlError

    try:
        return asyncio.run(_follow_rotation(args.socket))
    except ControlError as exc:
        print(f"tbp calibrate: {exc}", file=sys.stderr)
        return None


async def _follow_rotation(socket: Path | None) -> Path | None:
    import contextlib

    from daemon.server.control import ControlClient, DaemonUnavailable

    client = ControlClient(socket)
    async with contextlib.aclosing(client.subscribe()) as events:
        await anext(events)  # subscribed before the rotation can emit anything
        started = await client.calibrate()
        print(f"calibration rotation {started['rotation_id']} started: {started['folder']}", flush=True)
        async for event in events:
            data = event.get("data") or {}
            if event.get("cause") == "calibration stop":
                print(f"  stop {data.get('angle_index')}: encoder {data.get('encoder_deg')} deg, "
                      f"{data.get('pictures')} pictures", flush=True)
            elif event.get("cause") == "calibration problem":
                print(f"  {data.get('problem')}", flush=True)
            elif event.get("kind") == "transition":
                print(f"  {event.get('state')}: {event.get('cause')}", flush=True)
                if event.get("state") in ("IDLE", "FAULT"):
                    last = await client.report_of("last_calibration_rotation", "rotation_id", started["rotation_id"])
                    if last.get("outcome") != "COMPLETED":
                        print(f"tbp calibrate: the rotation did not complete ({last.get('outcome', event.get('state'))}"
                              f"{': ' + '; '.join(last.get('causes', [])) if last.get('causes') else ''}); "
                              f"its pictures so far: {started['folder']}", file=sys.stderr)
                        return None
                    return Path(started["folder"]) / "captures.json"
    raise DaemonUnavailable(client.path, "the daemon ended the subscription before the rotation ended")


def _focus(args: argparse.Namespace, rig: Any, target: Any) -> int:
    from analysis.focus_report import write_focus_figure
    from daemon.jobs.focus_sweep import SweepSettings
    from planner.calibration.focus_fit import FocusFitError

    try:
        board_mm = min(target.squares) * target.square_mm  # the board of face 0: the sweeps' board
        distances = tuple(args.distances) if args.distances else SweepSettings.distances_mm
        settings = SweepSettings(distances_mm=distances, board_width_mm=board_mm)
    except ValueError as exc:
        print(f"tbp calibrate focus: {exc}", file=sys.stderr)
        return 2
    try:
        if args.sim:
            return _focus_sim(args, rig, target, settings, write_focus_figure)
        return _focus_rig(args, rig, settings, write_focus_figure)
    except FocusFitError as exc:
        print(f"tbp calibrate focus: {exc}", file=sys.stderr)
        return 1


def _focus_sim(args: argparse.Namespace, rig: Any, target: Any, settings: Any, figure: Any) -> int:
    from planner.calibration.focus_fit import CHECK_MM
    from sim.focus_calibration import calibrate_sim_focus

    print(f"focus sweeps of the simulated phones (seed {args.seed}) over a board at known distances, "
          "through the phone driver", flush=True)
    results = calibrate_sim_focus(rig, target, args.seed, args.out, settings=settings,
                                  progress=lambda phone, done, total: _progress(f"{phone} pictures", done, total))
    print(f"focus error against each phone's true lens at {', '.join(f'{d:g}' for d in CHECK_MM)} mm "
          "(worst, mm): measured table / shared default table")
    for r in results:
        figure(r.table, r.previous, args.out / f"{r.phone}.png")
        print(f"  {r.phone}: {abs(r.error_mm).max():6.2f} / {abs(r.default_error_mm).max():6.2f}   "
              f"fit residual {r.table.rms_diopters:.4f} D, {r.pictures} pictures  -> {r.table.path}")
    return 0


def _focus_rig(args: argparse.Namespace, rig: Any, settings: Any, figure: Any) -> int:
    import asyncio

    from daemon.jobs.focus_sweep import SweepPictureError
    from daemon.rig.hardware_config import HardwareConfigError, load_hardware
    from drivers.phone.errors import PhoneError
    from planner.calibration.focus_fit import FocusFitError

    try:
        config = load_hardware(options.hardware_path(args), rig)
    except HardwareConfigError as exc:
        print(f"tbp calibrate focus: {exc}", file=sys.stderr)
        return 2
    known = [p.id for p in rig.phones]
    unknown = [p for p in args.phone if p not in known]
    if unknown:
        print(f"tbp calibrate focus: no phone {unknown[0]!r} in the rig file; phones: {', '.join(known)}",
              file=sys.stderr)
        return 2
    if _daemon_running(args):
        print("tbp calibrate focus: the daemon is running and owns the phones; stop it first "
              "(sudo systemctl stop tbp-rig)", file=sys.stderr)
        return 2
    phones = [p for p in rig.phones if not args.phone or p.id in args.phone]
    failed = 0
    for phone in phones:
        try:
            asyncio.run(_focus_one_phone(args, rig, config, phone, settings, figure))
        except (PhoneError, OSError, FocusFitError, SweepPictureError) as exc:  # the next phone still goes
            print(f"  {phone.id}: {exc}", file=sys.stderr, flush=True)
            failed += 1
    return 1 if failed else 0


def _daemon_running(args: argparse.Namespace) -> bool:
    import asyncio

    from daemon.server.control import ControlClient, ControlError, default_socket

    try:
        asyncio.run(ControlClient(args.socket or default_socket()).status())
    except (ControlError, OSError):
        return False
    return True


async def _focus_one_phone(args: argparse.Namespace, rig: Any, config: Any, phone: Any, settings: Any,
                           figure: Any) -> None:
    import asyncio

    from daemon.jobs.focus_sweep import calibrate_focus
    from daemon.server.real_rig import make_phone
    from daemon.utc import utc_stamp
    from drivers.adb.auth import AdbKey
    from drivers.phone.focus import FocusCalibration
    from planner.calibration.focus_fit import CHECK_MM

    link = config.phones[phone.id]
    camera = make_phone(rig, phone, link, AdbKey.load_or_create(options.state_dir(args.state_dir)),
                        config.capture_agent)
    loop = asyncio.get_running_loop()

    async def place_board(distance_mm: float) -> None:
        place = (f"{phone.id} ({link.address}): stand the board square-on, its centre on the phone's "
                 f"optical axis, {distance_mm:g} mm from the lens")
        if args.yes:
            print(place, flush=True)
        else:
            await loop.run_in_executor(None, input, place + "; press Enter ")

    print(f"{phone.id}: connecting ({link.address})", flush=True)
    await camera.connect(timeout_s=config.timeouts.open_s)
    try:
        table = await calibrate_focus(camera, rig.optics, settings, place_board, args.out,
                                      measured=f"{utc_stamp()} by tbp calibrate focus",
                                      progress=lambda done, total: _progress(f"{phone.id} pictures", done, total))
    finally:
        await camera.close()
    previous = camera.focus_table
    figure(table, previous, args.out / f"{phone.id}.png")
    measured = FocusCalibration(table.diopters, table.distance_mm, source=phone.id)
    moved = max(abs(previous.focus_mm(measured.diopters_for(x)) - x) for x in CHECK_MM)
    print(f"  {phone.id}: fit residual {table.rms_diopters:.4f} D; the table it used was off by up to "
          f"{moved:.1f} mm at {CHECK_MM[0]:g}-{CHECK_MM[-1]:g} mm  -> {table.path}", flush=True)
