"""``tbp texture SCAN_DIR``: (re)write a scan's textured body, ``SCAN_DIR/body.glb``."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from cli import options


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "texture",
        help="texture a scan's mesh from its images (body.glb in the scan folder)",
        description="Unwrap the scan's mesh into a texture atlas and fill every texel from the images "
        "that hold its skin best (the focus plan's cost under the focus actually captured: sharp first), "
        "exposure-matched and blended across seams; stored as a glTF binary, SCAN_DIR/body.glb, listed in "
        "the scan's manifest. Progress on stderr, the file's path on stdout.",
    )
    parser.add_argument("scan_dir", type=Path, help="a scan folder")
    parser.add_argument("--texel-mm", type=float, default=None, metavar="MM",
                        help="texel side on the skin (default: 0.7 of the best images' mm per pixel there); coarser "
                        "where the mesh's area would need more than 15 M texels")
    options.rig(parser, "the rig file the scan was taken with (default: calibration_data/rig.yaml)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from analysis.atlas import AtlasError
    from analysis.body_texture import TextureError, write_body
    from daemon.logs import configure_logging
    from daemon.records.atomic import StoreError
    from planner.rig import RigConfigError

    configure_logging(level="warning")
    started = time.perf_counter()

    def progress(text: str) -> None:
        print(f"[{time.perf_counter() - started:6.1f} s] {text}", file=sys.stderr, flush=True)

    if problem := options.texel_problem("--texel-mm", args.texel_mm):
        print(f"tbp texture: {problem}", file=sys.stderr)
        return 2
    try:
        path = write_body(args.scan_dir, rig_path=args.rig, texel_mm=args.texel_mm, progress=progress)
    except (StoreError, TextureError, AtlasError, RigConfigError) as exc:  # not a scan folder, no mesh or images, a rig file
        print(f"tbp texture: {exc}", file=sys.stderr)
        return 2
    progress(f"done, {path.stat().st_size / 1e6:.1f} MB")
    print(path)
    return 0
