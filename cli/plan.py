"""``tbp plan``: plan the focus of every pose for a subject mesh and compare the methods."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from cli import options

if TYPE_CHECKING:
    import trimesh

    from planner.plan import PlanResult
    from planner.rig import Rig


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "plan",
        help="plan per-pose focus distances for a mesh and compare focus methods",
        description="Sample the mesh surface, find what every camera pose sees, and plan one focus "
        "distance per pose (closest, average, fixed, autofocus, EM, shape-aware). Prints a table "
        "and optionally writes the plan as JSON (pose order: angle-major).",
    )
    parser.add_argument("--mesh", required=True, type=Path, help="subject mesh in mm (PLY, OBJ, STL...)")
    options.rig(parser)
    options.plan_points(parser)
    options.seed(parser, "surface sampling seed")
    parser.add_argument("--json", dest="json_out", type=Path, default=None, help="write the plan here")
    parser.add_argument(
        "--fresh", type=int, default=0, metavar="N",
        help="also score the plan to capture with (robust) on N fresh, independent surface samples",
    )
    parser.add_argument(
        "--backend", choices=("open3d", "embree"), default="open3d",
        help="ray casting backend for the occlusion tests (default: open3d)",
    )
    parser.add_argument(
        "--view", action="append", default=[], metavar="X,Y,Z",
        help="print the best captures (camera, angle, pixel) of the skin point nearest X,Y,Z mm "
        "under the shape-aware plan; repeatable",
    )
    parser.set_defaults(func=run)


def _parse_point(text: str) -> tuple[float, float, float] | None:
    try:
        x, y, z = (float(v) for v in text.split(","))
    except ValueError:
        return None
    return x, y, z


def _table(result: dict) -> str:
    lines = [f"{'method':<12} {'total cost':>11} {'in focus %':>10} {'seconds':>8}"]
    for name, m in result["methods"].items():
        lines.append(
            f"{name:<12} {m['total_cost']:>11.1f} {100 * m['in_focus_fraction']:>10.1f} {m['seconds']:>8.3f}"
        )
    res = result["resolution_mm_per_px"]
    lines.append(
        f"visible {100 * result['visible_fraction']:.1f} % of {result['points']} samples from "
        f"{result['poses']} poses; resolution {res['mean']:.4f} +- {res['std']:.4f} mm/px, "
        f"{100 * res['share_at_most_0.075']:.1f} % of the surface at <= 0.075 mm/px"
    )
    t = result["timing_s"]
    lines.append(
        f"time: visibility {t['visibility']:.3f} s, plan (visibility + EM + refinement) "
        f"{t['plan']:.3f} s, total {t['total']:.3f} s"
    )
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from planner.focus_errors import FocusPlanError
    from planner.plan import evaluate, load_subject_mesh, plan_focus
    from planner.rig import DEFAULT_RIG_PATH, RigConfigError, load_rig

    if args.plan_points is not None and args.plan_points <= 0:
        print(f"tbp plan: --plan-points must be positive, got {args.plan_points}", file=sys.stderr)
        return 2
    from cli.outputs import output_problem

    problem = output_problem("--json", args.json_out)
    if problem is not None:  # found now, not after planning
        print(f"tbp plan: {problem}", file=sys.stderr)
        return 2
    queries = [_parse_point(v) for v in args.view]
    if None in queries:
        bad = args.view[queries.index(None)]
        print(f"tbp plan: --view expects X,Y,Z in mm, got {bad!r}", file=sys.stderr)
        return 2
    try:
        rig = load_rig(args.rig or DEFAULT_RIG_PATH)
        mesh = load_subject_mesh(args.mesh)
        result = plan_focus(
            mesh, rig, points=args.plan_points, seed=args.seed, backend=args.backend, mesh_name=str(args.mesh)
        )
    except (RigConfigError, FocusPlanError) as exc:
        print(f"tbp plan: {exc}", file=sys.stderr)
        return 1
    from planner.bound import in_focus_bound
    from planner.poses import rgb_poses

    out = result.to_json()
    bound = in_focus_bound(result.table)
    out["in_focus_bound"] = round(bound.fraction, 6)
    if args.fresh > 0:
        fresh = evaluate(
            result.focus_mm, mesh, rig, points=args.fresh, seed=args.seed + 1_000_003, backend=args.backend,
            poses=rgb_poses(rig, result.capture_angles_deg)
        )
        out["fresh_sample"] = {
            "points": fresh.n_points,
            "total_cost": round(fresh.total_cost, 4),
            "in_focus_fraction": round(fresh.in_focus_fraction, 6),
            "visible_fraction": round(fresh.visible_fraction, 6),
        }
    print(_table(out))
    if "robust" in result.methods:
        reach = result.methods["robust"].in_focus_fraction / max(bound.fraction, 1e-12)
        print(f"bound: no focus plan of the rig's poses holds more than {100 * bound.fraction:.2f} % of these "
              f"samples sharp (certified); the robust plan reaches {100 * reach:.2f} % of it")
    if args.fresh > 0:
        f = out["fresh_sample"]
        print(
            f"fresh sample ({f['points']} points): {result.capture_method} in focus "
            f"{100 * f['in_focus_fraction']:.1f} %, visible {100 * f['visible_fraction']:.1f} %"
        )
    if queries:
        _print_views(mesh, rig, result, queries, args.backend)
    if args.json_out is not None:
        args.json_out.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.json_out.with_name(args.json_out.name + ".tmp")
        tmp.write_text(json.dumps(out, indent=1) + "\n")
        tmp.replace(args.json_out)
        print(f"plan written to {args.json_out}")
    return 0


def _print_views(
    mesh: trimesh.Trimesh,
    rig: Rig,
    result: PlanResult,
    queries: list[tuple[float, float, float]],
    backend: str,
) -> None:
    import numpy as np

    from planner.navigation import find_views
    from planner.poses import rgb_poses
    from planner.visibility import RayScene

    scene = RayScene(mesh, backend)
    on_skin, _ = scene.closest_faces(np.array(queries))
    angles = result.capture_angles_deg
    views = find_views(scene, rig, rgb_poses(rig, angles), result.focus_mm, on_skin, limit=3, angles_deg=angles)
    for query, point, found in zip(queries, on_skin, views):
        where = ", ".join(f"{v:.1f}" for v in point)
        if not found:
            print(f"point ({where}) near {query}: seen by no capture")
            continue
        print(f"point ({where}) mm near {query}:")
        for v in found:
            print(
                f"  {rig.phones[v.camera_index].id} at {v.angle_deg:g} deg (pose {v.pose}): pixel "
                f"({v.u_px:.0f}, {v.v_px:.0f}), depth {v.depth_mm:.0f} mm, cost {v.cost:.3f}, "
                f"{'sharp' if v.in_focus else 'out of focus'}"
            )
