"""`tbp scans [--store DIR] [--check]`: list the scan folders in the store, optionally re-verified.

Reads the store directly (no daemon needed). Exit code 1 when --check finds a problem or a
manifest is unreadable, 2 when the store folder does not exist or cannot be read.
"""

from __future__ import annotations

import argparse
import os
import sys

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

    from daemon.manifest import ManifestError
    from daemon.store import ScanStore

    root = options.store_root(args)
    problem = ("does not exist" if not root.exists() else "is not a folder" if not root.is_dir()
               else "cannot be read" if not os.access(root, os.R_OK | os.X_OK) else None)
    if problem is not None:
        print(f"tbp scans: scan store {root} {problem}", file=sys.stderr)
        return 2
    store = ScanStore(root)
    status = 0
    for path in store.folders():
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
        if args.json:
            print(json.dumps({"folder": path.name, "scan_id": m.scan_id, "state": m.state.value,
                              "in_progress": m.in_progress, "reason": m.reason,
                              "counts": m.counts(), **({"problems": problems} if args.check else {})}))
            continue
        c = m.counts()
        state = m.state.value + (" (in progress)" if m.in_progress else "")
        print(f"{path.name}  {state:<24} verified {c['verified']:>3}  captured {c['captured']:>3}  "
              f"failed {c['failed']:>3}  missing {c['missing']:>3}"
              + (f"  reason: {m.reason}" if m.reason else ""))
        for problem in problems:
            print(f"    problem: {problem}")
    return status
