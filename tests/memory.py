"""Memory bounds for hostile-input tests: this process's RSS, watched from a thread.

A hostile device or file must not make the host allocate without bound. :func:`within_rss` runs a
coroutine while a thread samples the resident set every millisecond; past ``limit_bytes`` of
growth it cancels the coroutine's task and the test fails naming the growth, so a regression fails
fast instead of taking the machine down. The thread works whatever the event loop's clock does
(a flood of ready I/O keeps a virtual-time loop from ever reaching a timer).
"""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import threading
from collections.abc import Coroutine
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")

HOSTILE_RSS_LIMIT = 200 * 1024 * 1024  # the goal of issue 14: each hostile-device test stays below
_PAGE = os.sysconf("SC_PAGE_SIZE")


def rss_bytes() -> int:
    """Resident set size of this process now, bytes (Linux /proc)."""
    with open("/proc/self/statm", "rb") as f:
        return int(f.read().split()[1]) * _PAGE


class RssExceeded(AssertionError):
    """The watched coroutine made the process grow past the limit."""


async def within_rss(coro: Coroutine[Any, Any, T], limit_bytes: int = HOSTILE_RSS_LIMIT) -> tuple[T, int]:
    """(coro's result, peak RSS growth in bytes); RssExceeded once growth passes limit_bytes."""
    loop = asyncio.get_running_loop()
    task = asyncio.ensure_future(coro)
    start = rss_bytes()
    peak = 0
    stop = threading.Event()
    tripped = threading.Event()

    def watch() -> None:
        nonlocal peak
        while not stop.wait(0.001):
            peak = max(peak, rss_bytes() - start)
            if peak > limit_bytes and not tripped.is_set():
                tripped.set()
                loop.call_soon_threadsafe(task.cancel)

    thread = threading.Thread(target=watch, name="rss-watch", daemon=True)
    thread.start()
    try:
        result = await task
    except asyncio.CancelledError:
        if not tripped.is_set():
            raise
        raise RssExceeded(f"RSS grew by {peak / 2**20:.0f} MiB, limit {limit_bytes / 2**20:.0f} MiB") from None
    finally:
        stop.set()
        thread.join()
    peak = max(peak, rss_bytes() - start)
    if peak > limit_bytes:
        raise RssExceeded(f"RSS grew by {peak / 2**20:.0f} MiB, limit {limit_bytes / 2**20:.0f} MiB")
    return result, peak


def run_bounded(setup: str, hostile: str, *, growth_bytes: int = HOSTILE_RSS_LIMIT,
                timeout_s: float = 120.0) -> subprocess.CompletedProcess[str]:
    """Run Python ``setup`` then ``hostile`` in a fresh interpreter whose address space may grow by
    at most growth_bytes after setup (RLIMIT_AS), for hostile input a thread cannot interrupt
    (a repr() or a parser in C). The child's rc, stdout and stderr come back; MemoryError means the
    bound was hit."""
    code = "\n".join([
        "import resource",
        setup,
        "def _vm():",
        "    for line in open('/proc/self/status'):",
        "        if line.startswith('VmSize:'):",
        "            return int(line.split()[1]) * 1024",
        f"_limit = _vm() + {int(growth_bytes)}",
        "resource.setrlimit(resource.RLIMIT_AS, (_limit, _limit))",
        hostile,
    ])
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout_s,
                          env=env, cwd=str(Path(__file__).resolve().parent.parent))
