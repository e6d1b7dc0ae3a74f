"""``tbp daemon``: the long-running rig daemon (systemd ``Type=notify`` service).

With ``--sim`` the whole simulated rig runs inside the daemon on the virtual-time loop, paced
at real time (``--time-scale``), so the control API, the panel logic and scans behave as on
the real rig.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser("daemon", help="run the rig daemon", description=__doc__,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sim", action="store_true", help="simulated hardware, in this process")
    parser.add_argument("--config", type=Path, default=None, help="rig file (default calibration_data/rig.yaml)")
    parser.add_argument("--store", type=Path, default=Path("/var/lib/tbp-rig/scans"), help="scan store folder")
    parser.add_argument("--socket", type=Path, default=None,
                        help="control socket (default $TBP_CONTROL_SOCKET or /run/tbp-rig/control.sock)")
    parser.add_argument("--group", default=None, help="group of the control socket (default $TBP_CONTROL_GROUP)")
    parser.add_argument("--seed", type=int, default=0, help="simulated subject and noise seed (--sim)")
    parser.add_argument("--time-scale", type=float, default=1.0, metavar="X",
                        help="with --sim: virtual time runs at X times real time (default 1)")
    parser.add_argument("--plan-points", type=int, default=None, metavar="N",
                        help="surface samples for planning (default: the rig file's planner.points)")
    parser.add_argument("--depth-decimation", type=int, default=2, metavar="N",
                        help="with --sim: depth cameras render at 1/N resolution")
    parser.add_argument("--subject", type=Path, default=None, metavar="MESH",
                        help="with --sim: the subject's mesh file (default: a body for --seed)")
    parser.add_argument("--no-panel", action="store_true", help="with --sim: a rig without a panel")
    parser.add_argument("--log-level", default="info", help="debug, info, warning or error")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from daemon.control import default_group, default_socket
    from daemon.logs import configure_logging

    configure_logging(level=args.log_level, stream=sys.stdout)
    socket_path = args.socket or default_socket()
    group = args.group or default_group()
    if not args.sim:
        print("tbp daemon: real hardware wiring is not configured on this machine; use --sim",
              file=sys.stderr)
        return 2
    import asyncio

    from analysis.qa_report import generate_report
    from sim.clock import VirtualTimeLoop
    from sim.run import sim_service

    with asyncio.Runner(loop_factory=lambda: VirtualTimeLoop(time_scale=args.time_scale)) as runner:
        return runner.run(sim_service(
            config=args.config, store=args.store, socket_path=socket_path, seed=args.seed,
            plan_points=args.plan_points, depth_decimation=args.depth_decimation, group=group,
            subject_path=args.subject, panel=not args.no_panel, qa_report=generate_report,
        ))
