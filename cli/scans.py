"""`tbp scans [--store DIR] [--check]`: list the scan folders in the store, optionally re-verified.

One line a scan: its folder, how it ended (complete, partial: images missing, aborted, fault,
incomplete: interrupted, or in progress), images verified of those planned, the sharp skin
(the QA report's figure, analysis/skin_map.py; "-" without a report), and why it is not
complete: the reason and the images missing per phone and why. Reads the store directly (no
daemon needed). ``--check`` re-reads every scan against its manifest (``ScanFolder.check``: every
listed file is there, every verified image has its recorded size and SHA-256, no folder is still
marked in progress), says under each scan what it verified or what it found, and ends with the
totals. Exit code 1 when --check finds a problem or a manifest is unreadable, 2 when
the store folder does not exist or cannot be read.
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import Any

from cli import options


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "scans", help="list the scans in the store (state, image counts); --check re-verifies",
        description=__doc__,
    )
    options.store(parser)
    parser.add_argument("--check", action="store_true",
                        help="re-read every verified image and compare size and SHA-256")
    parser.add_argument("--json", action="store_true", help="one JSON object a scan")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import json

    from analysis.skin_map import read_skin_shares
    from daemon.records.manifest import ManifestError, ScanEnd
    from daemon.records.store import ScanStore

    root = options.store_root(args)
    problem = ("does not exist" if not root.exists() else "is not a folder" if not root.is_dir()
               else "cannot be read" if not os.access(root, os.R_OK | os.X_OK) else None)
    if problem is not None:
        print(f"tbp scans: scan store {root} {problem}", file=sys.stderr)
        return 2
    store = ScanStore(root)
    status = 0
    folders = store.folders()
    totals = {"scans": 0, "images": 0, "files": 0, "problems": 0}
    if folders and not args.json:
        print(f"{'FOLDER':<{max(len(p.name) for p in folders)}}  {'HOW IT ENDED':<24} {'VERIFIED':>8}  "
              f"{'SHARP SKIN':>10}  WHY")
    for path in folders:
        try:
            folder = store.open(path)
        except ManifestError as exc:
            print(json.dumps({"folder": path.name, "error": str(exc)}) if args.json
                  else f"{path.name}  UNREADABLE  {exc}")
            status = 1
            continue
        m = folder.manifest
        problems = folder.check() if args.check else []
        status = 1 if problems else status
        checked = {"images": _verified(m), "files": len(m.files)}
        if args.check:
            totals.update(scans=totals["scans"] + 1, images=totals["images"] + checked["images"],
                          files=totals["files"] + checked["files"], problems=totals["problems"] + len(problems))
        shares = read_skin_shares(path)
        if args.json:
            print(json.dumps({"folder": path.name, "scan_id": m.scan_id, "state": m.state.value,
                              "in_progress": m.in_progress, "reason": m.reason, "counts": m.counts(),
                              "missing_by_phone": m.missing_by_phone(),
                              "sharp_skin": None if shares is None else shares["sharp"],
                              **({"checked": checked, "problems": problems} if args.check else {})}))
            continue
        c = m.counts()
        ended = "in progress" if m.in_progress else _ENDED.get(m.state.value, m.state.value)
        why = [m.reason] if m.reason and m.state is not ScanEnd.PARTIAL else []
        why += [text] if (text := m.missing_summary()) else []
        sharp = "-" if shares is None else f"{100 * shares['sharp']:.1f} %"
        line = f"{path.name}  {ended:<24} {c['verified']:>4}/{len(m.images):<3}  {sharp:>10}  {' | '.join(why)}"
        print(line.rstrip())
        for problem in problems:
            print(f"    problem: {problem}")
        if args.check and not problems:
            print(f"    checked: {_checked(checked)}: all as the manifest records")
    if args.check and not args.json:
        print(f"--check: {totals['scans']} scans, {_checked(totals)}; "
              f"{totals['problems']} problem{'' if totals['problems'] == 1 else 's'}")
    return status


def _verified(manifest: Any) -> int:
    """The verified images ``--check`` re-reads in a scan."""
    from daemon.records.manifest import ImageStatus

    return sum(image.status is ImageStatus.VERIFIED for image in manifest.images)


def _checked(counts: dict[str, int]) -> str:
    return (f"{counts['images']} verified images re-read (size and SHA-256), "
            f"{counts['files']} listed files present")


_ENDED = {"complete": "complete", "partial": "partial: images missing", "aborted": "aborted", "fault": "fault",
          "incomplete": "incomplete: interrupted"}
