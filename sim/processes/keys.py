"""Fault keys on a simulator's standard input, each acknowledged with when it acted, and the
signals that stop a simulator process.

A harness (the loopback rig, ``./dev bench safety``) writes one character to a simulator's stdin
to press a button or inject a fault; the simulator acts on it and prints ``<action> mono_s=<t>``
(``time.monotonic()``, the machine-wide clock every process on it shares), so the harness can time
how long the daemon took to react. Those lines, and every other line a simulator prints while its
device runs, go out through :func:`say`.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import stat
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

from daemon.log_sink import LineSink

Keys = dict[str, tuple[str, Callable[[], None]]]
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


_out: LineSink | None = None


def say(line: str) -> None:
    """Print ``line`` on stdout from a writer thread (daemon/log_sink.py), never from the event
    loop: the loop holds the device's heartbeats, as a device with its own processor would, and a
    write can wait hundreds of ms for a reader or a disk busy with a scan. Lines queued when the
    process ends are written out at exit."""
    global _out
    if _out is None:
        _out = LineSink(sys.stdout, lambda n: f"({n} simulator lines dropped)")
    _out.put(line)


def is_stream(file: Any) -> bool:
    """True for a pipe or terminal the event loop can watch (not /dev/null or a regular file)."""
    if file is None or file.closed:
        return False
    mode = os.fstat(file.fileno()).st_mode
    return stat.S_ISFIFO(mode) or file.isatty()


def watch_keys(keys: Keys) -> Callable[[], None]:
    """Act on ``keys`` (character -> (action name, action)) read from stdin, if stdin is a pipe or
    terminal; returns the function that stops watching."""
    loop = asyncio.get_running_loop()
    if not is_stream(sys.stdin):
        return lambda: None
    fd = sys.stdin.fileno()

    def on_stdin() -> None:
        data = os.read(fd, 64).decode(errors="replace")
        if not data:
            loop.remove_reader(fd)
        for key in data:
            if key in keys:
                name, action = keys[key]
                # Stamped before acting: the daemon may react (and, with its larger CPU share,
                # run first) between the action's write and a stamp taken after it.
                at = time.monotonic()
                action()
                say(f"{name} mono_s={at:.6f}")

    loop.add_reader(fd, on_stdin)
    return lambda: loop.remove_reader(fd)


@contextlib.contextmanager
def stop_signals(keys: Keys | None = None) -> Iterator[asyncio.Event]:
    """An event SIGINT or SIGTERM sets, with ``keys`` watched on stdin (:func:`watch_keys`) while
    the block runs; leaving it stops the watch and removes the signal handlers."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in STOP_SIGNALS:
        loop.add_signal_handler(sig, stop.set)
    unwatch = watch_keys(keys) if keys is not None else (lambda: None)
    try:
        yield stop
    finally:
        unwatch()
        for sig in STOP_SIGNALS:
            loop.remove_signal_handler(sig)
