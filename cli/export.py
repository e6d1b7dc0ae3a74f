"""``tbp export SCAN_DIR``: send one scan to the clinic's archive as one DICOM study.

``--pacs HOST:PORT --called-aet AET`` sends over C-STORE (``--calling-aet``: this rig's AE title),
``--dicomweb URL`` over STOW-RS; ``--out DIR`` writes the instances as DICOM files instead.
Every image is a VL Photographic Image carrying the phone's JPEG unchanged, the mesh an
Encapsulated STL, each mark a Key Object Selection pointing at its best image, the QA report a
Basic Text SR (docs/archive.md). The instance UIDs come from the scan, so a second export adds
nothing. ``--deidentify``: DICOM PS3.15's basic profile (archive/deidentify.py).

Exit codes: 0 sent; 1 the archive refused or the transfer failed (the message names the peer and
the reason); 2 the scan or the options cannot be used.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from cli import options


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser("export", help="send a scan to the archive (DICOM C-STORE or STOW-RS)",
                                   description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scan_dir", type=Path, metavar="SCAN_DIR")
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--pacs", metavar="HOST:PORT", help="the archive's DICOM address (C-STORE)")
    where.add_argument("--dicomweb", metavar="URL", help="the archive's DICOMweb root (STOW-RS)")
    where.add_argument("--out", type=Path, metavar="DIR", help="write the instances as DICOM files into DIR")
    parser.add_argument("--called-aet", metavar="AET", help="the archive's AE title (with --pacs)")
    parser.add_argument("--calling-aet", default="TBPRIG", metavar="AET", help="this rig's AE title (default TBPRIG)")
    parser.add_argument("--deidentify", action="store_true", help="DICOM PS3.15 basic profile (research, sharing)")
    options.rig(parser, "the rig file the scan was taken with (default: calibration_data/rig.yaml)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from archive.deidentify import deidentified, new_uid
    from archive.instances import ExportError, StudyBuilder, study_file
    from archive.send import send_dimse, send_stow
    from daemon.clinic.dimse import DicomPeerError
    from daemon.clinic.site import Peer, SiteConfigError, ae_title
    from daemon.records.atomic import StoreError
    from planner.rig import RigConfigError
    from planner.schema.tables import HOST_PORT

    started = time.perf_counter()
    try:
        peer = None
        if args.pacs is not None:
            match = HOST_PORT.fullmatch(args.pacs)
            if match is None or not 0 < int(match["port"]) < 65536:
                raise SiteConfigError("--pacs", "HOST:PORT", f"got {args.pacs[:80]!r}")
            if args.called_aet is None:
                raise SiteConfigError("--called-aet", "AET", "required with --pacs: the archive's AE title")
            peer = Peer(match["host"].strip("[]"), int(match["port"]), ae_title(args.called_aet, "--called-aet"))
            calling = ae_title(args.calling_aet, "--calling-aet")
        if problem := options.url_problem("--dicomweb", args.dicomweb):
            raise SiteConfigError("--dicomweb", "URL", problem.removeprefix("--dicomweb "))
        builder = StudyBuilder(args.scan_dir, args.rig)
        instances = deidentified(builder) if args.deidentify else builder.instances()
    except (ExportError, StoreError, SiteConfigError, RigConfigError) as exc:
        print(f"tbp export: {exc}", file=sys.stderr)
        return 2
    kinds = {k: sum(i.kind == k for i in instances) for k in ("image", "mesh", "mark", "report")}
    try:
        if args.out is not None:
            args.out.mkdir(parents=True, exist_ok=True)
            for n, instance in enumerate(instances):
                study_file(instance).save_as(args.out / f"{n:04d}-{instance.kind}.dcm", enforce_file_format=True)
            target = str(args.out)
        elif peer is not None:
            send_dimse(instances, calling, peer)
            target = str(peer)
        else:
            study = builder.study.study_instance_uid
            study = new_uid(study) if args.deidentify else study
            send_stow(instances, args.dicomweb.rstrip("/"), study)
            target = args.dicomweb
    except DicomPeerError as exc:
        print(f"tbp export: {exc}", file=sys.stderr)
        return 1
    except ExportError as exc:
        print(f"tbp export: {exc}", file=sys.stderr)
        return 2
    print(f"{len(instances)} instances ({', '.join(f'{k} {v}' for k, v in kinds.items())}) to {target} "
          f"in {time.perf_counter() - started:.1f} s")
    return 0
