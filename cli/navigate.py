"""``tbp navigate SCAN_DIR --point X,Y,Z | --vertex I``: the best image of a spot on the skin."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from cli import options


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "navigate",
        help="find the image that shows a spot on the body best, and the pixel where it lands",
        description="For a point on the scanned body (mm, world frame; snapped to the scan's mesh) "
        "or a mesh vertex: the captured image that images it best (lowest cost of the focus plan: "
        "sharp, close, head-on, near the image centre), the pixel (u, v) where it lands, and the "
        "runners-up.",
    )
    parser.add_argument("scan_dir", type=Path, help="a scan folder")
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--point", help="X,Y,Z in mm")
    where.add_argument("--vertex", type=int, help="vertex index of the scan's mesh.ply")
    parser.add_argument("--count", type=int, default=5, help="the best image and this many minus one runners-up")
    options.rig(parser, "the rig file the scan was taken with (default: calibration_data/rig.yaml)")
    parser.add_argument("--json", action="store_true", help="print JSON")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from analysis.navigate import NavigationError, navigate
    from daemon.logs import configure_logging
    from daemon.records.atomic import StoreError
    from planner.rig import RigConfigError

    configure_logging(level="warning", stream=sys.stderr)
    try:
        answer = navigate(args.scan_dir, point=args.point, vertex=args.vertex, count=args.count,
                          rig_path=args.rig)
    except (NavigationError, StoreError, RigConfigError) as exc:
        print(f"tbp navigate: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(answer, indent=1))
        return 0
    x, y, z = answer["point_mm"]
    print(f"skin point ({x:.1f}, {y:.1f}, {z:.1f}) mm")
    if answer["missing_files"]:
        print(f"{len(answer['missing_files'])} verified image(s) are no longer on disk and were left out "
              f"(tbp scans --check lists them)", file=sys.stderr)
    if not answer["views"]:
        print("no captured image shows this point")
        return 1
    for rank, view in enumerate(answer["views"]):
        label = "best" if rank == 0 else f"#{rank + 1}"
        print(f"{label:>5}  {view['file']}  camera {view['camera_id']} at {view['angle_deg']:.1f} deg  "
              f"pixel ({view['u_px']:.0f}, {view['v_px']:.0f})  {'sharp' if view['in_focus'] else 'blurred'}  "
              f"depth {view['depth_mm']:.0f} mm  focus {view['focus_mm']:.0f} mm  "
              f"{view['resolution_mm_px']:.3f} mm/px  cost {view['cost']:.3f}")
    return 0
