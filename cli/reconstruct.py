"""``tbp reconstruct``: TSDF shape estimate from a recorded depth sweep or a simulated one."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from cli import options

if TYPE_CHECKING:
    from planner.rig import Rig
    from planner.sweep import Sweep


MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off", ".glb")  # what trimesh writes for a triangle mesh


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "reconstruct",
        help="estimate the subject's surface mesh from depth frames (TSDF)",
        description="Fuse a depth sweep into the subject's surface mesh. The sweep is a recorded "
        "folder (sweep.json + one .npz per frame) or a simulated sweep of a body mesh. The mesh is the "
        "surface a scan stores as mesh.ply (fused at the rig's tsdf.surface_voxel_mm), or with "
        "--planner-mesh the one its plan is made on (tsdf.voxel_mm). With a known true body, reports "
        "Chamfer distances both ways and coverage.",
    )
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--frames", type=Path, help="recorded sweep folder (sweep.json + .npz frames)")
    source.add_argument("--sim-body", type=Path, help="simulate the sweep of this body mesh (mm)")
    source.add_argument(
        "--bag", action="append", metavar="CAMERA=FILE.db3",
        help="RealSense recording of one rig depth camera (repeat per camera; needs pyrealsense2); posed at "
        "its recorded beam angles (FILE.beam.json beside it, as tbp depth record writes) or with --trace",
    )
    parser.add_argument(
        "--trace", type=Path,
        help="beam trace JSON for --bag recordings without beam angles: time_s (seconds from each "
        "recording's first frame), angle_deg",
    )
    options.seed(parser, "depth noise seed of the simulated sweep")
    parser.add_argument("--no-noise", action="store_true", help="simulate without depth noise")
    parser.add_argument("--true-body", type=Path, help="true body mesh for metrics (default: --sim-body)")
    options.rig(parser)
    parser.add_argument("--save-frames", type=Path, help="also write the simulated sweep to this folder")
    parser.add_argument("--planner-mesh", action="store_true",
                        help="the planner's mesh (tsdf.voxel_mm) rather than the stored surface")
    parser.add_argument("--out", type=Path, help="write the mesh here (.ply, .obj, .stl, .off, .glb)")
    parser.add_argument("--json", dest="json_out", type=Path, help="write timings and metrics as JSON here")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from drivers.depth.errors import DepthCameraError
    from drivers.depth.recording import load_sweep, save_sweep
    from planner.mesh_metrics import shape_metrics
    from planner.plan import load_subject_mesh
    from planner.rig import DEFAULT_RIG_PATH, RigConfigError, load_rig
    from planner.shape_errors import ShapeEstimateError
    from planner.tsdf import FRAME_SPACING_DEG, fuse

    report: dict = {"timings_s": {}}
    problem = _output_problem(args)
    if problem is not None:  # found now, not after the whole fusion
        print(f"tbp reconstruct: {problem}", file=sys.stderr)
        return 2
    try:
        rig = load_rig(args.rig or DEFAULT_RIG_PATH)
        truth_path = args.true_body or args.sim_body
        truth = load_subject_mesh(truth_path) if truth_path else None
        t0 = time.perf_counter()
        if args.sim_body:
            from drivers.sim.depth import simulate_sweep

            sweep = simulate_sweep(truth, rig, args.seed, not args.no_noise, frame_spacing_deg=FRAME_SPACING_DEG)
            report["timings_s"]["simulate"] = time.perf_counter() - t0
            if args.save_frames:
                save_sweep(sweep, args.save_frames)
        elif args.bag:
            sweep = _read_bags(args, rig)
            report["timings_s"]["load"] = time.perf_counter() - t0
        else:
            model = rig.depth_camera_model
            sweep = load_sweep(args.frames, max_frame_px=model.width_px * model.height_px)
            report["timings_s"]["load"] = time.perf_counter() - t0
        result = fuse(sweep.frames, rig, surface=not args.planner_mesh)
    except (RigConfigError, ShapeEstimateError, DepthCameraError, OSError, ValueError) as exc:
        print(f"tbp reconstruct: {exc}", file=sys.stderr)
        return 1
    report["timings_s"].update({f"tsdf_{k}": v for k, v in result.timings_s.items()})
    report["surface"] = "planner's mesh" if args.planner_mesh else "stored surface"
    report["voxel_mm"] = rig.tsdf.voxel_mm if args.planner_mesh else rig.tsdf.surface_voxel_mm
    report["frames_used"] = result.frames_used
    report["per_camera"] = result.per_camera
    report["vertices"] = len(result.mesh.vertices)
    report["triangles"] = len(result.mesh.faces)
    if truth is not None:
        report["metrics"] = shape_metrics(truth, result.mesh).as_dict()
    if args.out:
        result.mesh.export(args.out)
        report["mesh"] = str(args.out)
    text = json.dumps(report, indent=2, sort_keys=True)
    if args.json_out:
        args.json_out.write_text(text + "\n")
    print(text)
    return 0


def _output_problem(args: argparse.Namespace) -> str | None:
    """Why --out, --json or --save-frames cannot be written, or None: checked before any work."""
    from cli.outputs import output_problem

    return (output_problem("--out", args.out, suffixes=MESH_SUFFIXES)
            or output_problem("--json", args.json_out)
            or output_problem("--save-frames", args.save_frames, folder=True))


def _read_bags(args: argparse.Namespace, rig: Rig) -> Sweep:
    """The sweep from ``--bag CAMERA=FILE`` recordings at their recorded angles or tagged with ``--trace``."""
    import asyncio

    from drivers.depth.bag import BagPlayback
    from drivers.depth.recording import load_trace, read_recordings
    from planner.tsdf import FRAME_SPACING_DEG

    cameras = []
    for item in args.bag:
        camera_id, sep, path = item.partition("=")
        if not sep or not camera_id or not path:
            raise ValueError(f"--bag {item!r}: expected CAMERA=FILE.db3, e.g. depth0=sweep/depth0.db3")
        cameras.append(BagPlayback(path, camera_id=camera_id, realtime=False))
    trace = load_trace(args.trace) if args.trace is not None else None
    return asyncio.run(read_recordings(cameras, trace, rig, FRAME_SPACING_DEG))
