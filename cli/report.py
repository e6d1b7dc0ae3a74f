"""``tbp report SCAN_DIR``: (re)generate a scan folder's QA report."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from cli import options


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "report",
        help="write a scan's QA report (HTML with figures) into its folder",
        description="Regenerate <SCAN_DIR>/report/index.html: sharp, blurred and unseen skin from "
        "four sides, focus against angle per camera, the speed profile with capture marks, planned "
        "vs actual angles, the resolution histogram, and every missing or failed image.",
    )
    parser.add_argument("scan_dir", type=Path, help="a scan folder")
    options.rig(parser, "the rig file the scan was taken with (default: calibration_data/rig.yaml)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from analysis.qa_report import generate_report
    from daemon.logs import configure_logging
    from daemon.records.atomic import StoreError
    from planner.rig import RigConfigError

    configure_logging(level="warning", stream=sys.stderr)
    try:
        print(generate_report(args.scan_dir, rig_path=args.rig))
    except (StoreError, RigConfigError) as exc:  # not a scan folder, a file missing or unreadable, another rig
        print(f"tbp report: {exc}", file=sys.stderr)
        return 2
    return 0
