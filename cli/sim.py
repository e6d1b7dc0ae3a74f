"""``tbp sim motor|phone|panel``: run one simulated device as a standalone process.

Each simulator process module (sim.processes.motor, .phone, .panel) owns its options
(``add_arguments``) and its server (``serve``); this command only dispatches. A simulator module
is imported when its sub-command is parsed, so ``tbp --help`` stays fast and one simulator that
cannot be imported never breaks the others.
"""

from __future__ import annotations

import argparse
import importlib
from types import ModuleType
from typing import Any

from cli import options

SIMULATORS = {
    "motor": ("sim.processes.motor",
              "CiA 402 beam drive on a socketcand bridge at 127.0.0.1:--port"),
    "phone": ("sim.processes.phone", "one phone's adbd with the capture agent at 127.0.0.1:--port"),
    "panel": ("sim.processes.panel", "the operator panel on a new pty (prints its path)"),
}


class _SimulatorParser(argparse.ArgumentParser):
    """A sub-command parser that imports its simulator and adds its options on first use."""

    def __init__(self, *args: Any, module: str = "", **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.module_name = module
        self.module: ModuleType | None = None

    def load(self) -> ModuleType:
        if self.module is None:
            try:
                module = importlib.import_module(self.module_name)
            except ImportError as exc:
                self.error(f"simulator module {self.module_name} cannot be imported: {exc}")
            if not callable(getattr(module, "add_arguments", None)) or not callable(
                getattr(module, "serve", None)
            ):
                self.error(f"simulator module {self.module_name} lacks add_arguments/serve")
            module.add_arguments(self)
            self.set_defaults(sim_module=self.module_name)
            self.module = module
        return self.module

    def parse_known_args(self, args: Any = None, namespace: Any = None) -> Any:
        self.load()
        return super().parse_known_args(args, namespace)


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "sim",
        help="run a simulated motor drive, phone or operator panel as its own process",
        description="Serve one simulated device at the protocol level (socketcand, ADB, serial "
        "pty) until SIGINT/SIGTERM, for driver commissioning and protocol tests.",
    )
    devices = parser.add_subparsers(
        dest="device", metavar="DEVICE", required=True, parser_class=_SimulatorParser
    )
    for name, (module, help_text) in SIMULATORS.items():
        devices.add_parser(name, help=help_text, description=help_text, module=module)
    options.log_level(parser, "warning")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import asyncio
    import signal
    import sys

    from daemon.logs import close_logging, configure_logging
    from daemon.offload.worker import one_numeric_thread

    # A simulator holds its device's heartbeats on its event loop, as the daemon does its own: its
    # log lines go out from a writer thread, never from the loop (a write to a log file can wait
    # hundreds of ms for a disk busy with a scan's images).
    configure_logging(level=args.log_level, stream=sys.stderr, queued=True)
    # A simulator stands in for a device with its own processor, yet shares the cores of the
    # machine the daemon runs on: its renders run on one thread and never wait at a barrier for
    # a core the daemon or its compute worker holds.
    one_numeric_thread()
    module = importlib.import_module(args.sim_module)
    for sig in (signal.SIGINT, signal.SIGTERM):  # until the simulator installs its own handlers
        signal.signal(sig, _stop_before_ready)
    try:
        return int(asyncio.run(module.serve(args)) or 0)
    finally:
        close_logging()


def _stop_before_ready(signum: int, frame: object) -> None:
    """SIGINT/SIGTERM before the simulator's own handlers exist: the same orderly exit (0)."""
    raise SystemExit(0)
