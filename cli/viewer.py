"""``tbp viewer --dicomweb URL``: the scan viewer on a dermatologist's workstation, reading the
clinic's archive by DICOMweb (QIDO-RS to list the studies, WADO-RS to retrieve one), no rig PC
needed. Retrieved studies are kept in ``--cache DIR`` and opened by the same viewer as on the rig
(``/archive`` lists the archive's studies). Serves 127.0.0.1:8471 unless told otherwise; beyond
loopback readers log in with ``--http-token-file`` (docs/web.md)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from cli import options

DEFAULT_HTTP = "127.0.0.1:8471"


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser("viewer", help="the scan viewer reading the clinic's archive (DICOMweb)",
                                   description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dicomweb", required=True, metavar="URL", help="the archive's DICOMweb root")
    parser.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "tbp-rig" / "archive", metavar="DIR",
                        help="where retrieved studies are kept (default ~/.cache/tbp-rig/archive)")
    parser.add_argument("--http", default=DEFAULT_HTTP, metavar="HOST:PORT", help=f"(default {DEFAULT_HTTP})")
    parser.add_argument("--http-token-file", type=Path, default=None, metavar="FILE")
    options.rig(parser, "the rig file the scans were taken with (default: calibration_data/rig.yaml)")
    options.log_level(parser, "info")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import asyncio
    import signal

    from daemon.logs import configure_logging
    from web.access import Access, AccessError, parse_listen, read_token
    from web.app import make_app
    from web.server import WebServer

    configure_logging(level=args.log_level, stream=sys.stderr)
    if problem := options.url_problem("--dicomweb", args.dicomweb):
        print(f"tbp viewer: {problem}", file=sys.stderr)
        return 2
    try:
        host, port = parse_listen(args.http)
        access = Access(host, port, read_token(args.http_token_file) if args.http_token_file else None)
    except AccessError as exc:
        print(f"tbp viewer: {exc}", file=sys.stderr)
        return 2
    args.cache.mkdir(parents=True, exist_ok=True, mode=0o700)

    async def serve() -> int:
        server = WebServer(make_app(args.cache, access, rig_path=args.rig, archive_url=args.dicomweb), host, port)
        await server.start()
        print(f"viewer on {server.url}/archive, reading {args.dicomweb}", flush=True)
        stop = asyncio.Event()
        for sig in (signal.SIGINT, signal.SIGTERM):
            asyncio.get_running_loop().add_signal_handler(sig, stop.set)
        await stop.wait()
        await server.close()
        return 0

    return asyncio.run(serve())
