"""``tbp body``: write a simulated subject (an Anny adult) as a mesh file for the simulators."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from cli import options


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "body",
        help="write a simulated subject mesh (Anny adult, mm, feet on z=0, facing +x)",
        description="Generate a realistic adult body from the Anny model in a standing anatomical "
        "pose (arms lowered, feet slightly apart) and write its closed outer skin in millimetres, "
        "feet on z = 0, centred on the rotation axis, facing +x. Without --phenotype the seed draws "
        "a random adult.",
    )
    parser.add_argument("--out", required=True, type=Path, help="output mesh (.ply: binary PLY; .stl, .obj...)")
    options.seed(parser, "random adult and sway axes")
    parser.add_argument(
        "--phenotype", default=None, metavar="G,A,M,W,H,P",
        help="Anny gender (0 male..1 female), age (2/3 young adult..1 old), muscle, weight, height, "
        "proportions, each in [0, 1], e.g. 0.5,0.75,0.5,0.5,0.38,0.5",
    )
    parser.add_argument("--sway", type=float, default=0.0, metavar="DEG",
                        help="postural sway: turn ankles, knees, hips, lumbar, neck and head by DEG")
    parser.add_argument("--sway-seed", type=int, default=None, metavar="K",
                        help="draw the sway axes from K instead of --seed (several poses of one adult)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from cli.outputs import output_problem
    from sim.body import Phenotype, generate_body, save_body
    from sim.body_errors import BodyError

    if problem := output_problem("--out", args.out):  # before the body model's seconds of loading
        print(f"tbp body: {problem}", file=sys.stderr)
        return 2
    try:
        phenotype = Phenotype.parse(args.phenotype) if args.phenotype is not None else None
        body = generate_body(seed=args.seed, phenotype=phenotype, sway_deg=args.sway, sway_seed=args.sway_seed)
        mesh = body.mesh.copy()
        save_body(mesh, args.out)
    except BodyError as exc:
        print(f"tbp body: {exc}", file=sys.stderr)
        return 2 if isinstance(exc, ValueError) else 1
    print(f"phenotype (g,a,m,w,h,p): {body.phenotype}; sway {body.sway_deg:g} deg")
    print(f"height {body.height_mm:.1f} mm; {len(mesh.vertices)} vertices, {len(mesh.faces)} faces; "
          f"watertight {mesh.is_watertight}")
    print(f"written to {args.out}")
    return 0
