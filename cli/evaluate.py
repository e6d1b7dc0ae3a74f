"""``tbp evaluate``: the paper's table and robustness studies over a corpus of simulated adults."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from cli import options


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "evaluate",
        help="evaluate every focus method and the robustness studies on simulated bodies",
        description="Plan every focus method (and per-subject capture angles) on N simulated adults "
        "of varied phenotype, then judge every plan side by side on its planning samples, on fresh "
        "samples, under calibration noise, under postural sway and after planning on the TSDF "
        "estimate, with the certified in-focus bound per body and the motion blur of the default "
        "profile. Writes report.md, results.json and PNG figures into --out. The same seed gives "
        "the same numbers whatever --jobs is.",
    )
    parser.add_argument("--bodies", type=int, required=True, help="number of simulated adults")
    options.seed(parser, "corpus seed (bodies, samples, noise)")
    parser.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    options.plan_points(parser, 10_000)
    parser.add_argument("--calibration-trials", type=int, default=10, help="calibration-noise trials per body")
    parser.add_argument("--sway-poses", type=int, default=5, help="swayed poses per body")
    parser.add_argument("--no-shape", action="store_true", help="skip the TSDF shape-error study")
    parser.add_argument("--no-angles", action="store_true", help="skip the per-subject capture angles")
    parser.add_argument("--extremes", action="store_true",
                        help="add a tall (2.1 m) and a short (1.5 m) adult to the corpus")
    options.rig(parser)
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from analysis.evaluation import StudyOptions, run_corpus
    from analysis.evaluation_report import write
    from daemon.logs import configure_logging

    configure_logging(level="warning", stream=sys.stderr)
    if args.bodies < 1 or args.jobs < 1 or args.plan_points < 100:
        print(f"tbp evaluate: --bodies and --jobs must be >= 1 and --points >= 100 "
              f"(got {args.bodies}, {args.jobs}, {args.plan_points})", file=sys.stderr)
        return 2
    if args.calibration_trials < 0 or args.sway_poses < 0:
        print(f"tbp evaluate: --calibration-trials and --sway-poses must be >= 0 (0 skips the study; "
              f"got {args.calibration_trials}, {args.sway_poses})", file=sys.stderr)
        return 2
    from cli.outputs import output_problem

    problem = output_problem("--out", args.out, folder=True)
    if problem is not None:  # found now, not after the whole corpus
        print(f"tbp evaluate: {problem}", file=sys.stderr)
        return 2
    options = StudyOptions(
        points=args.plan_points,
        calibration_trials=args.calibration_trials,
        sway_poses=args.sway_poses,
        shape=not args.no_shape,
        angles=not args.no_angles,
        extremes=args.extremes,
    )

    def progress(done: int, total: int) -> None:
        bar = "#" * (30 * done // total)
        print(f"\r[{bar:<30}] {done}/{total} bodies", end="" if done < total else "\n",
              file=sys.stderr, flush=True)

    results = run_corpus(args.bodies, seed=args.seed, jobs=args.jobs, options=options,
                         rig_path=str(args.rig) if args.rig else None, progress=progress)
    for path in write(results, args.out):
        print(path)
    return 0
