"""``tbp scan``: one complete scan.

``tbp scan --sim`` runs the whole daemon in-process on simulated hardware, on the virtual-time
loop (as fast as possible, or ``--time-scale X`` times real time); progress lines go to stdout
and the scan folder's path is the LAST line. Without ``--sim`` it asks the running daemon over
the control socket to start a scan and follows its status until the scan ends.

Exit codes: 0 the scan completed; 1 it did not (aborted or faulted), or the daemon refused it
(busy, fault latched, the store cannot take it); 2 it could not be asked for (the daemon is
unreachable or went away, a rig file, subject mesh or scan store that cannot be used).
Each failure is one line on stderr.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import sys
from pathlib import Path
from typing import Any

from cli import options


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser("scan", help="run one complete scan (simulated with --sim)",
                                   description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    options.simulated_rig(parser)
    options.time_scale(parser, None)
    options.store(parser)
    options.rig(parser)
    options.plan_points(parser)
    options.socket(parser)
    options.log_level(parser, "warning")
    parser.add_argument("--verbose", action="store_const", dest="log_level", const="info",
                        help="the same as --log-level info")
    patient = parser.add_argument_group("patient", "who the scan is for (kept in the scan's manifest only)")
    patient.add_argument("--patient-id", default=None, metavar="ID", help="the clinic's patient id")
    patient.add_argument("--patient-name", default=None, metavar="NAME", help='"Family^Given" (DICOM person name)')
    patient.add_argument("--birth-date", default=None, metavar="YYYYMMDD")
    patient.add_argument("--sex", default=None, choices=("M", "F", "O"))
    patient.add_argument("--accession-number", default=None, metavar="N", help="the order's accession number")
    parser.set_defaults(func=run)


def patient_args(args: argparse.Namespace) -> dict[str, str]:
    """The control API's patient arguments from the command line (only those given)."""
    given = {"patient_id": args.patient_id, "patient_name": args.patient_name, "birth_date": args.birth_date,
             "sex": args.sex, "accession_number": args.accession_number}
    return {k: v for k, v in given.items() if v is not None}


def run(args: argparse.Namespace) -> int:
    from daemon.clinic.patient import PatientError, ScanSubject
    from daemon.logs import configure_logging

    configure_logging(level=args.log_level, stream=sys.stderr)
    try:
        subject = ScanSubject.from_args(patient_args(args))
    except PatientError as exc:
        print(f"tbp scan: {exc}", file=sys.stderr)
        return 2
    if args.sim:
        return _simulated(args, subject)
    from daemon.server.control import CommandFailed, ControlError, DaemonUnavailable

    try:
        return asyncio.run(_remote(args.socket, patient_args(args)))
    except CommandFailed as exc:
        print(f"tbp scan: refused: {exc}", file=sys.stderr)
        return 1
    except (DaemonUnavailable, ControlError) as exc:
        print(f"tbp scan: {exc}", file=sys.stderr)
        return 2


def _simulated(args: argparse.Namespace, patient: Any) -> int:
    from analysis.body_texture import report_and_body
    from daemon.errors import DaemonError
    from planner.focus_errors import FocusPlanError
    from planner.rig import RigConfigError
    from sim.body import load_subject
    from sim.body_errors import BodyError
    from sim.run import run_sim_scan

    try:
        report = run_sim_scan(
            config=args.rig, store=options.store_root(args), seed=args.seed, time_scale=args.time_scale,
            plan_points=args.plan_points, depth_decimation=args.depth_decimation, out=sys.stdout,
            subject=load_subject(args.subject) if args.subject else None,
            panel=not args.no_panel, qa_report=report_and_body, patient=patient,
            lesion_changes=args.lesion_changes,
        )
    except (RigConfigError, FocusPlanError, DaemonError, BodyError) as exc:  # DaemonError: ScanRefused (the store)
        print(f"tbp scan: {exc}", file=sys.stderr)
        return 2
    _summary(report)
    print(report.folder, flush=True)
    return 0 if report.outcome.value == "COMPLETED" else 1


def _summary(report: Any) -> None:
    """The scan's figures against the rig goals, one line each."""
    lines = [
        f"outcome {report.outcome.value}" + (f": {report.reason}" if report.reason else ""),
        (f"images {report.captured} captured, {report.verified} in the folder, {report.missing} missing, "
         f"{report.retaken} retaken"),
        *(f"phone {d['camera']} dropped after {d['failures']} failed captures in a row: {d['first_error']}"
          for d in report.dropped_phones if not d["rejoined"]),
        f"max |exposure angle - planned| {report.max_abs_angle_error_deg or 0.0:.3f} deg (goal <= 0.2)",
        f"lens late {report.lens_late}; min beam speed / profile {report.min_speed_ratio or 0.0:.4f}",
        f"sweep end -> capture start {report.sweep_to_capture_s:.2f} s (goal <= 2 s); "
        f"rig time {report.phase_s.get('total', 0.0):.1f} s (goal <= 100 s)",
    ]
    for line in lines:
        print(line, flush=True)


async def _remote(socket: Path | None, patient: dict[str, str]) -> int:
    """Ask the running daemon for a scan (for ``patient``, the control API's arguments) and follow
    its events until it ends."""
    from daemon.server.control import ControlClient, DaemonUnavailable

    client = ControlClient(socket)
    async with contextlib.aclosing(client.subscribe()) as events:
        await anext(events)  # subscribed (the current status) before the scan can emit anything
        started = await client.scan(**patient)
        scan_id = started["scan_id"]
        print(f"scan {scan_id} requested", flush=True)
        async for event in events:
            print(_describe(event), flush=True)
            if event.get("kind") == "transition" and event.get("state") in ("IDLE", "FAULT"):
                last = await client.report_of("last_scan", "scan_id", scan_id)
                if last.get("folder"):
                    print(last["folder"], flush=True)
                return 0 if last.get("outcome") == "COMPLETED" else 1
    raise DaemonUnavailable(client.path, "the daemon ended the subscription before the scan ended")


def _describe(event: dict[str, Any]) -> str:
    data = event.get("data") or {}
    extra = " ".join(f"{k}={v}" for k, v in data.items())
    return f"[{event.get('time_s', 0.0):9.2f} s] {event.get('state')}: {event.get('cause')} {extra}".rstrip()
