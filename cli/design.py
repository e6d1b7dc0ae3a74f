"""``tbp design``: search phone heights and tilts, depth camera placement and the angular pattern
for a body corpus under a rig builder's constraints; write the rig file and a report."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from cli import options


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "design",
        help="design a rig (phone heights/tilts, depth cameras, capture pattern) for a body corpus",
        description="Search the rig that sees the most skin on simulated adults (random adults plus a "
        "2.1 m and a 1.5 m adult) under the given constraints, then judge it against the default rig "
        "on other bodies. Writes OUT/rig.yaml (a valid rig file), OUT/design.json and OUT/report.html "
        "with figures. Takes several minutes; progress goes to stderr.",
    )
    parser.add_argument("--phones", type=int, default=None, help="number of phones (default: the base rig's)")
    parser.add_argument("--radius", type=float, default=None, help="ring (beam) radius, mm (default: the base rig's)")
    parser.add_argument("--column-height", type=float, default=2300.0, help="highest camera position, mm")
    parser.add_argument("--spacing", type=float, default=170.0, help="least distance between two phones, mm")
    parser.add_argument("--bodies", type=int, default=6, help="random design adults (tall and short are added)")
    parser.add_argument("--seed", type=int, default=1, metavar="S", help="seed of the design adults (default 1)")
    options.plan_points(parser, 3000)
    parser.add_argument("--verify-bodies", type=int, default=20, help="evaluation-corpus adults to judge on")
    parser.add_argument("--verify-points", type=int, default=10_000, help="samples per judged body")
    options.rig(parser, "base rig file (default: calibration_data/rig.yaml)")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from analysis.design import DesignOptions, design
    from cli.outputs import output_problem
    from daemon.logs import configure_logging
    from planner.design import Constraints, ConstraintValueError, DesignError
    from planner.rig import DEFAULT_RIG_PATH, RigConfigError, load_rig

    configure_logging(level="warning", stream=sys.stderr)
    if min(args.bodies, args.verify_bodies) < 0 or min(args.plan_points, args.verify_points) < 100:
        print("tbp design: --bodies and --verify-bodies must be >= 0, --plan-points and --verify-points >= 100",
              file=sys.stderr)
        return 2
    if problem := output_problem("--out", args.out, folder=True):
        print(f"tbp design: {problem}", file=sys.stderr)
        return 2
    base_path = args.rig or DEFAULT_RIG_PATH
    try:
        base = load_rig(base_path)
        constraints = Constraints(
            phones=base.n_cameras if args.phones is None else args.phones,
            ring_radius_mm=base.ring_radius_mm if args.radius is None else args.radius,
            column_height_mm=args.column_height,
            phone_spacing_mm=args.spacing,
        )
        constraints.heights()
    except ConstraintValueError as exc:
        flag = {"phones": "--phones", "ring_radius_mm": "--radius", "column_height_mm": "--column-height",
                "phone_spacing_mm": "--spacing"}.get(exc.name, exc.name)
        print(f"tbp design: {flag} {exc.value:g}: expected {exc.expected}", file=sys.stderr)
        return 2
    except (RigConfigError, DesignError) as exc:
        print(f"tbp design: {exc}", file=sys.stderr)
        return 2 if isinstance(exc, RigConfigError) else 1

    def progress(what: str, done: int, total: int) -> None:
        bar = "#" * (20 * done // max(total, 1))
        print(f"\r{what:<26} [{bar:<20}] {done}/{total}", end="\n" if done >= total else "", file=sys.stderr, flush=True)

    settings = DesignOptions(bodies=args.bodies, seed=args.seed, points=args.plan_points,
                            verify_bodies=args.verify_bodies, verify_points=args.verify_points)
    try:
        summary = design(constraints, settings, args.out, base_path=base_path, progress=progress)
    except DesignError as exc:
        print(f"tbp design: {exc}", file=sys.stderr)
        return 1
    for side in ("default", "designed"):
        rows = summary["verification"][side]
        vis = [100 * r["fresh_visible"] for r in rows]
        foc = [100 * r["fresh_in_focus"] for r in rows]
        print(f"{side:>8} rig: visible {sum(vis) / len(vis):.2f} % (worst {min(vis):.2f}), "
              f"in focus {sum(foc) / len(foc):.2f} % (worst {min(foc):.2f}) on fresh samples")
    print(summary["rig_path"])
    print(args.out / "report.html")
    return 0
