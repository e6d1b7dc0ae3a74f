"""Compute steps off the event loop: a worker process, and the depth sweep handed over in shared memory.

On the real rig the TSDF fusion, the planning and the QA report run in a separate process, so
they never hold the daemon's interpreter lock: the drive's heartbeat (100 ms, lost after
300 ms) and the panel's keep running while a body is fused and planned. The worker starts
from a fresh interpreter (``forkserver``: nothing of the daemon's threads or sockets is
inherited), as a batch job (SCHED_BATCH: it never preempts the daemon when it wakes, yet keeps its
fair share of a core), imports the heavy libraries once and logs as the daemon does (JSON lines
on the daemon's stdout, each with ``process: compute``).

A sweep is hundreds of megabytes of depth images; pickling it to the worker would hold the
lock for as long as the copy takes. :func:`share_frames` copies the images into one shared
memory block instead (NumPy copies without the lock, in a thread) and the worker gets only
their names, shapes and poses.
"""

from __future__ import annotations

import dataclasses
import mmap
import multiprocessing
import os
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing.shared_memory import SharedMemory
from pathlib import Path
from typing import Any

import numpy as np

from daemon.logs import configure_logging, log_settings

WORKER_POLICY = os.SCHED_BATCH
"""The worker's scheduling policy. It was nice 10 before: with the other core busy, the scheduler
then left the worker sharing that core, and the plan between the sweep and the capture took
1.0-1.4 s instead of 0.56-0.73 s (this machine, a `while True` on the other core)."""
SHM_DIR = Path("/dev/shm")


THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
"""How OpenMP (Open3D's ray casting) and the BLAS libraries learn their thread count at start."""


def compute_threads() -> int:
    """Threads for the worker's parallel loops: every core this process may use but one, which
    stays the daemon's and the simulators'. On two cores with one busy, an OpenMP loop split over
    both waits at every barrier for the half that shares the busy core: planning took 1.05 s
    instead of 0.66 s on one thread."""
    return max(1, len(os.sched_getaffinity(0)) - 1)


def compute_pool() -> ProcessPoolExecutor:
    """One worker process for the scan's compute steps (the steps of a scan run one at a time),
    started now: the first scan does not wait for its interpreter and imports (about 3 s).

    The worker (and the forkserver it comes from) is started with :data:`THREAD_VARIABLES` set
    to :func:`compute_threads`; this process's own environment is left as it was."""
    saved = {name: os.environ.get(name) for name in THREAD_VARIABLES}
    os.environ.update({name: str(compute_threads()) for name in THREAD_VARIABLES})
    try:
        pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("forkserver"),
                                   initializer=_warm_up, initargs=(log_settings(),))
        pool.submit(_started)  # starts the worker now, with the environment above
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
    return pool


def timed(func: Callable[..., Any], *args: Any) -> tuple[Any, float]:
    """Run ``func`` (in the executor) and measure its duration there: compute time, not rig time."""
    started = time.perf_counter()
    result = func(*args)
    return result, time.perf_counter() - started


def _started() -> None:
    """The first job: makes the pool start its worker (and run :func:`_warm_up`) at once."""


def _warm_up(log_setup: dict[str, Any]) -> None:
    """In the worker: log as the daemon does (``log_setup``: :func:`daemon.logs.log_settings`), run
    as a batch job and import what every scan's jobs need, so the first scan's do not (their
    modules, not the daemon's: importing ``daemon.scan`` here took 0.3 s of the first scan's gap
    between the sweep and the capture), and compile the planner's descent loop (seconds the first
    time, from numba's cache after)."""
    import structlog

    configure_logging(json=log_setup["json"], level=log_setup["level"])
    structlog.contextvars.bind_contextvars(process="compute")
    os.sched_setscheduler(0, WORKER_POLICY, os.sched_param(0))
    import open3d  # noqa: F401

    import daemon.fusion
    import daemon.planning  # noqa: F401
    from planner.refine import warm_up
    from planner.rig import load_rig

    warm_up(load_rig())


@dataclass(frozen=True)
class SharedFrames:
    """Posed depth frames whose images live in the shared memory block ``name`` (image ``i`` at
    ``offsets[i]``, shaped ``shapes[i]``, dtype ``dtypes[i]``); ``frames`` hold everything else."""

    name: str
    frames: tuple[Any, ...]
    offsets: tuple[int, ...]
    shapes: tuple[tuple[int, ...], ...]
    dtypes: tuple[str, ...]


def share_frames(frames: list[Any]) -> tuple[SharedMemory, SharedFrames]:
    """Copy the frames' depth images into a new shared memory block; the caller closes and unlinks it
    (:func:`release`) once the worker is done."""
    offsets, total = [], 0
    for frame in frames:
        offsets.append(total)
        total += (frame.depth.nbytes + 63) // 64 * 64
    block = SharedMemory(create=True, size=max(total, 1))
    try:
        for frame, offset in zip(frames, offsets, strict=True):
            target = np.ndarray(frame.depth.shape, frame.depth.dtype, buffer=block.buf, offset=offset)
            np.copyto(target, frame.depth)
            del target
    except BaseException:
        release(block)
        raise
    empty = np.zeros((0, 0), np.uint16)
    shared = SharedFrames(block.name, tuple(dataclasses.replace(f, depth=empty) for f in frames), tuple(offsets),
                          tuple(f.depth.shape for f in frames), tuple(f.depth.dtype.str for f in frames))
    return block, shared


def unshare_frames(shared: SharedFrames) -> list[Any]:
    """In the worker: the frames with their images copied out of the shared block."""
    # Mapped by its path, not attached as a SharedMemory: before Python 3.13 attaching registers
    # the block with the resource tracker a second time, which then complains when it is unlinked.
    with open(SHM_DIR / shared.name.lstrip("/"), "rb") as file, \
            mmap.mmap(file.fileno(), 0, access=mmap.ACCESS_READ) as buffer:
        return [
            dataclasses.replace(frame, depth=np.frombuffer(buffer, np.dtype(dtype), int(np.prod(shape)),
                                                           offset).reshape(shape).copy())
            for frame, offset, shape, dtype in zip(shared.frames, shared.offsets, shared.shapes, shared.dtypes,
                                                    strict=True)
        ]


def release(block: SharedMemory) -> None:
    block.close()
    block.unlink()
