"""``tbp daemon``: the long-running rig daemon (systemd ``Type=notify`` service).

Without ``--sim`` it runs the real rig: the rig file says what the rig is, the hardware file
(``--hardware``, default hardware.yaml beside the rig file) how this PC reaches every device.
A device that is missing keeps the daemon up and NOT READY, naming it, until it answers.
The ADB key the phones authorise is kept in $STATE_DIRECTORY (systemd's StateDirectory=),
else ~/.local/state/tbp-rig.

With ``--sim`` the whole simulated rig runs inside the daemon on the virtual-time loop, paced
at real time (``--time-scale``), so the control API, the panel logic and scans behave as on
the real rig.
"""

from __future__ import annotations

import argparse
import functools
import sys
from pathlib import Path
from typing import Any

from cli import options

DEFAULT_HTTP = "127.0.0.1:8470"


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser("daemon", help="run the rig daemon", description=__doc__,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    options.simulated_rig(parser)
    options.rig(parser)
    options.hardware(parser)
    options.store(parser)
    options.socket(parser)
    parser.add_argument("--group", default=None, help="group of the control socket (default $TBP_CONTROL_GROUP)")
    options.time_scale(parser, 1.0)
    options.plan_points(parser)
    options.body_texel(parser)
    parser.add_argument("--http", default=DEFAULT_HTTP, metavar="HOST:PORT",
                        help=f"web viewer and console address (default {DEFAULT_HTTP}: this machine only); "
                             "'off' serves none")
    parser.add_argument("--http-token-file", type=Path, default=None, metavar="FILE",
                        help="operator token for START/ABORT/RESET and marks over the web; needed to allow "
                             "them when --http listens beyond loopback; beyond loopback readers log in with it too")
    parser.add_argument("--http-open-reads", action="store_true",
                        help="beyond loopback, show scans to anyone who reaches --http without a login "
                             "(patients' images on the network: a deliberate choice)")
    parser.add_argument("--site", type=Path, default=None, metavar="FILE",
                        help="site file: the clinic's worklist and archive (default: site.yaml beside the rig file, "
                             "if there is one)")
    options.log_level(parser, "info")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """The daemon; its log lines leave through a queue (daemon/log_sink.py), written out before it exits."""
    from daemon.logs import close_logging, configure_logging

    configure_logging(level=args.log_level, stream=sys.stdout, queued=True)
    try:
        return _serve(args)
    finally:
        close_logging()


def _serve(args: argparse.Namespace) -> int:
    from daemon.server.control import default_group, default_socket
    from planner.rig import RigConfigError

    if problem := options.texel_problem("--body-texel-mm", args.body_texel_mm):
        print(f"tbp daemon: {problem}", file=sys.stderr)
        return 2
    socket_path = args.socket or default_socket()
    group = args.group or default_group()
    try:
        site = _site(args)
    except (RigConfigError, OSError) as exc:
        print(f"tbp daemon: {exc}", file=sys.stderr)
        return 2
    attach = _clinic(site, args.rig)
    if args.http != "off":
        from web.access import Access, AccessError, parse_listen, read_token

        try:
            host, port = parse_listen(args.http)
            token = read_token(args.http_token_file) if args.http_token_file else None
            access = Access(host, port, token, open_reads=args.http_open_reads)
        except AccessError as exc:
            print(f"tbp daemon: {exc}", file=sys.stderr)
            return 2
        attach = _web(args, access, attach)
    from analysis.body_texture import report_and_body

    after_scan = functools.partial(report_and_body, texel_mm=args.body_texel_mm)
    if not args.sim:
        return _real(args, socket_path, group, after_scan, attach)
    import asyncio

    from planner.focus_errors import FocusPlanError
    from sim.body_errors import BodyError
    from sim.clock import VirtualTimeLoop
    from sim.run import sim_service

    with asyncio.Runner(loop_factory=lambda: VirtualTimeLoop(time_scale=args.time_scale)) as runner:
        try:
            return runner.run(sim_service(
                config=args.rig, store=options.store_root(args), socket_path=socket_path, seed=args.seed,
                plan_points=args.plan_points, depth_decimation=args.depth_decimation, group=group,
                subject_path=args.subject, panel=not args.no_panel, qa_report=after_scan, attach=attach,
                lesion_changes=args.lesion_changes,
            ))
        except (RigConfigError, FocusPlanError, BodyError) as exc:  # the rig file, --subject: before serving
            print(f"tbp daemon: {exc}", file=sys.stderr)
            return 2


def _real(args: argparse.Namespace, socket_path: Path, group: str | None, qa_report: Any, attach: Any) -> int:
    """The daemon on the real rig the rig and hardware files describe; a bad file exits 2
    (systemd's RestartPreventExitStatus: restarting would not fix it)."""
    import asyncio

    from daemon.server.control import ControlError
    from daemon.server.real_rig import real_service

    loaded = options.rig_and_hardware(args, "daemon")
    if loaded is None:
        return 2
    rig, config = loaded
    state_dir = options.state_dir()
    try:
        return asyncio.run(real_service(
            rig=rig, config=config, store=options.store_root(args), socket_path=socket_path,
            state_dir=state_dir, group=group, plan_points=args.plan_points, qa_report=qa_report,
            attach=attach))
    except ControlError as exc:  # the control socket cannot be served: a setup problem
        print(f"tbp daemon: {exc}", file=sys.stderr)
        return 2


def _site(args: argparse.Namespace) -> Any:
    """The site file (--site, else site.yaml beside the rig file when it exists), None without."""
    from daemon.clinic.site import default_site_path, load_site
    from planner.rig import DEFAULT_RIG_PATH

    path = args.site or default_site_path(args.rig or DEFAULT_RIG_PATH)
    if args.site is None and not path.is_file():
        return None
    return load_site(path)


def _clinic(site: Any, rig_path: Path | None) -> Any:
    """attach(service): the site file's worklist for the console and, with an archive, the export
    queue that sends every completed scan (its state in the status as ``archive``)."""

    def attach(service: Any) -> None:
        service.site = site
        if site is not None and site.archive is not None:
            from archive.queue import ExportQueue

            queue = ExportQueue(service.controller.store, site, rig_path=rig_path)
            service.attach(queue)
            service.status_parts["archive"] = queue.status

    return attach


def _web(args: argparse.Namespace, access: Any, before: Any) -> Any:
    """attach(service): ``before``, then the web server on the daemon's store, control through the
    service."""

    def attach(service: Any) -> None:
        from web.app import make_app
        from web.server import WebServer

        before(service)
        app = make_app(service.controller.store, access, service=service, rig_path=args.rig)
        service.attach(WebServer(app, access.host, access.port))

    return attach
