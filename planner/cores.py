"""The cores a computation may use: whether a second thread runs beside this one, and a map
that uses it.

The daemon's compute worker is given one core of a two-core rig PC (``OMP_NUM_THREADS``: the
other stays the daemon's) and every core for a step run while the beam is still
(:func:`every_core`); a command run by hand has every core. Work split over two threads helps
where most of each item's time is spent in NumPy, Pillow or Open3D calls that let the other
thread run meanwhile."""

from __future__ import annotations

import ctypes
import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from contextvars import ContextVar
from typing import TypeVar

from threadpoolctl import threadpool_limits

Item = TypeVar("Item")
Result = TypeVar("Result")

#: glibc's mallopt parameters (malloc.h).
M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD = -1, -2, -3

_EVERY_CORE: ContextVar[bool] = ContextVar("every_core", default=False)


@contextmanager
def every_core() -> Iterator[None]:
    """Within: :func:`spare_core` counts every core in this process' affinity, whatever
    ``OMP_NUM_THREADS`` says (the daemon's compute worker, held to one core while the beam
    moves, runs the step after a scan this way: daemon/offload/worker.py on_every_core)."""
    token = _EVERY_CORE.set(True)
    try:
        yield
    finally:
        _EVERY_CORE.reset(token)


def spare_core() -> bool:
    """True when this process may run two threads at once: more than one core in its affinity,
    and ``OMP_NUM_THREADS`` (the daemon's compute worker is given the cores it may use there,
    one on a two-core rig PC) unset or above one, or the caller inside :func:`every_core`."""
    cores = len(os.sched_getaffinity(0))
    if _EVERY_CORE.get():
        return cores > 1
    try:
        cores = min(cores, int(os.environ.get("OMP_NUM_THREADS", "").split(",")[0]))
    except ValueError:
        pass  # unset or not a number: OpenMP's own default, every core
    return cores > 1


def each(work: Callable[[Item], Result], items: Iterable[Item], *, name: str = "each") -> list[Result]:
    """``work(item)`` of every item, in the items' order: on two threads where a core is spare
    (:func:`spare_core`), else one after another on this one. Two at most, whatever the cores:
    each item's temporary arrays are in memory at once, and a texture's are hundreds of MB.

    Meanwhile the BLAS runs each product on the thread that calls it: the products here are thin
    ((n, 3) by (3, 3)), gain nothing from more threads, and the BLAS' own threads, spinning
    between products, would take the core the second thread runs on."""
    if not spare_core():
        return [work(item) for item in items]
    try:
        with threadpool_limits(limits=1, user_api="blas"), ThreadPoolExecutor(2, thread_name_prefix=name) as pool:
            return list(pool.map(work, items))
    finally:
        _trim_heaps()


def heap_for_large_arrays() -> None:
    """Set this process's malloc (glibc's; elsewhere nothing) for steps that allocate arrays of
    megabytes in every block: arrays up to 32 MiB come from the heap, not each from a fresh
    mapping whose pages the kernel zeroes on first touch and unmaps when freed (from under every
    thread), and up to 256 MiB freed at a heap's top stay for the next block's arrays. Each
    :func:`each` gives the heaps back when it ends. Settings, not memory: calling it again changes
    nothing."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return
    for option, value in ((M_TRIM_THRESHOLD, 256 << 20), (M_TOP_PAD, 64 << 20), (M_MMAP_THRESHOLD, 32 << 20)):
        mallopt(option, value)


def _trim_heaps() -> None:
    """Give the memory the threads freed back to the system. glibc's malloc keeps a heap per
    thread that allocates, and the pages freed in the worker thread's heap stay the process'
    (half a GiB at a texture's peak) until trimmed. Elsewhere than glibc: nothing."""
    try:
        libc = ctypes.CDLL(None)
        trim = libc.malloc_trim
    except (OSError, AttributeError):
        return
    trim(0)
