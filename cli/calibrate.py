"""``tbp calibrate``: every camera's pose and lens from pictures of the ChArUco cuboid.

  tbp calibrate target --out DIR            printable boards of the cuboid (PNG + true-size PDF per face)
  tbp calibrate --sim --seed S --out DIR    the simulated rig (true poses off nominal by a seeded error)
                                            photographs the cuboid on a stop-and-go rotation, then calibrates;
                                            DIR gets calibration.yaml, truth.yaml (the simulated rig's true
                                            poses, same format), the pictures and report/index.html
  tbp calibrate --pictures FILE --out DIR   calibrate from a calibration rotation's captures.json
  tbp calibrate focus --sim --seed S --out DIR
                                            each simulated phone sweeps its focus over a board at known
                                            distances; DIR/<phone>.yaml is its focus table (name it in the
                                            rig file's phones[].focus_calibration)

Install the result as the rig's calibration by copying DIR/calibration.yaml next to the rig file
(``calibration_data/`` or ``/etc/tbp-rig/``; the rig file's ``calibration.file`` names it).
Not built yet: the calibration rotation through the daemon on the real rig, and the focus sweep
of real phones (board stand + sweep over ADB); both pipelines take their pictures as above. Pictures that cannot be used are listed with the
reason and the rest still calibrates; the exit status is 1 when no calibration could be made.
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
    parser.add_argument("--sim", action="store_true", help="simulated rig and pictures, in this process")
    options.seed(parser, "simulated rig errors and picture noise (--sim)")
    parser.add_argument("--pictures", type=Path, default=None, metavar="FILE",
                        help="captures.json of a calibration rotation to calibrate from")
    options.rig(parser)
    parser.add_argument("--target", type=Path, default=None,
                        help="target file (default calibration_data/target/cuboid.yaml)")
    parser.add_argument("--jobs", type=int, default=2, help="worker threads/processes (default 2)")
    parser.set_defaults(func=run)


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
    if args.action == "target":
        from analysis.target_prints import write_target_prints

        for path in write_target_prints(target, args.out):
            print(path)
        return 0
    if args.action == "focus":
        return _focus(args, rig, target)
    if args.sim == (args.pictures is not None):
        print("tbp calibrate: give either --sim or --pictures FILE (calibrating on the rig through the daemon "
              "is not built yet: run the calibration rotation's pictures through --pictures)", file=sys.stderr)
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
        from sim.calibration import render_calibration_captures, true_rig

        truth = true_rig(rig, target, args.seed).save(out / "truth.yaml")
        print(f"simulated rig, seed {args.seed}: true poses in {out / 'truth.yaml'}", flush=True)
        print("photographing the cuboid at every capture angle", flush=True)
        captures = render_calibration_captures(rig, target, truth, out / "pictures", seed=args.seed, jobs=args.jobs,
                                               progress=lambda d, n: _progress("pictures", d, n))
        source = f"simulated rig, seed {args.seed}"
    else:
        captures = args.pictures
        source = f"pictures {captures}"
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


def _focus(args: argparse.Namespace, rig: Any, target: Any) -> int:
    if not args.sim:
        print("tbp calibrate focus: only --sim is built (the real phones' sweep needs the board stand "
              "procedure over ADB, not built yet)", file=sys.stderr)
        return 2
    from sim.focus_calibration import CHECK_MM, calibrate_sim_focus

    print(f"focus sweeps of the simulated phones (seed {args.seed}) over a board at known distances", flush=True)
    results = calibrate_sim_focus(rig, target, args.seed, args.out)
    print(f"focus error against each phone's true lens at {', '.join(f'{d:g}' for d in CHECK_MM)} mm "
          "(worst, mm): measured table / shared default table")
    for r in results:
        print(f"  {r.phone}: {abs(r.error_mm).max():6.2f} / {abs(r.default_error_mm).max():6.2f}   "
              f"fit residual {r.rms_diopters:.4f} D  -> {args.out / (r.phone + '.yaml')}")
    return 0
