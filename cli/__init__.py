"""The ``tbp`` command.

Every module in this package that defines ``register(subparsers)`` adds its sub-commands;
the sub-command's ``func(args) -> int`` runs it. Heavy imports happen inside ``func`` so
``tbp --help`` stays fast.

Results go to stdout, logs to stderr: every command's log lines (structlog and the standard
library's logging, info and above) are written on stderr unless the command configures its own
(``tbp daemon`` writes its log on stdout, which journald collects), so ``tbp plan > plan.txt``
holds the results alone.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tbp", description="Shape-aware total body photography rig controller."
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        module = importlib.import_module(f"{__name__}.{info.name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    from cli.pages import numpy_page_advice
    from daemon.logs import configure_logging

    numpy_page_advice()
    args = build_parser().parse_args(argv)
    configure_logging(level="info", stream=sys.stderr)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
