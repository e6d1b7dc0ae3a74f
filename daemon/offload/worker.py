"""The compute worker: one process for the scan's compute steps (TSDF fusion, planning, QA report).

On the real rig these steps never run in the daemon's process, so they never hold its
interpreter lock: the drive's heartbeat (100 ms, lost after 300 ms) and the panel's keep running
while a body is fused and planned. The worker starts from a fresh interpreter (``forkserver``:
nothing of the daemon's threads or sockets is inherited), as a batch job (SCHED_BATCH: it never
preempts the daemon when it wakes, yet keeps its fair share of a core), imports the heavy
libraries once and logs as the daemon does (JSON lines on the daemon's stdout, each with
``process: compute``). Its jobs get their depth images through shared memory
(daemon/offload/compute.py). It ends with the daemon's process, however that ends: a daemon
killed with SIGKILL cannot stop its pool, and the worker would otherwise wait on its job queue
for ever (the queue's pipe never reports the end: the worker holds both of its ends).
"""

from __future__ import annotations

import multiprocessing
import os
import select
import threading
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from typing import Any, TypeVar

import structlog
from threadpoolctl import threadpool_limits

from daemon.logs import configure_logging, log_settings
from planner.cores import every_core

Result = TypeVar("Result")

WORKER_POLICY = os.SCHED_BATCH
"""The worker's scheduling policy: a batch job keeps its fair share of a core but never preempts
the daemon (at a nice level the scheduler leaves the worker sharing the busy core, and planning
takes about twice as long; bench numbers in the commit history)."""

THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
"""How OpenMP (Open3D's ray casting) and the BLAS libraries learn their thread count at start."""


def compute_threads() -> int:
    """Threads for the worker's parallel loops: every core this process may use but one, which
    stays the daemon's and the simulators'. On two cores with one busy, an OpenMP loop split over
    both waits at every barrier for the half that shares the busy core."""
    return max(1, len(os.sched_getaffinity(0)) - 1)


def one_numeric_thread() -> None:
    """Run this process's numeric libraries (the BLAS copies, OpenMP) on one thread each: the
    ones loaded already, and through :data:`THREAD_VARIABLES` the ones loaded later and the
    processes this one starts. The daemon's own numeric work is small and runs on its loop's
    thread (the viewer's query for the best images of a spot: about 4 ms, with one thread or
    two); a product large enough for a BLAS to split over every core would wait at each barrier
    for the core the compute worker holds (a (786k, 3) x (3, 3) product of a phone's rays:
    130-175 ms instead of 2 ms with the other core busy), so none is split."""
    os.environ.update({name: "1" for name in THREAD_VARIABLES})
    threadpool_limits(limits=1)


def compute_pool() -> ProcessPoolExecutor:
    """One worker process for the scan's compute steps (the steps of a scan run one at a time),
    started now: the first scan does not wait for its interpreter and imports (about 3 s).

    The worker (and the forkserver it comes from) is started with :data:`THREAD_VARIABLES` set
    to :func:`compute_threads`; this process's own environment is left as it was."""
    saved = {name: os.environ.get(name) for name in THREAD_VARIABLES}
    os.environ.update({name: str(compute_threads()) for name in THREAD_VARIABLES})
    try:
        pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("forkserver"),
                                   initializer=_warm_up, initargs=(log_settings(), os.getpid()))
        pool.submit(_started)  # starts the worker now, with the environment above
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
    return pool


def on_every_core(work: Callable[..., Result], /, *args: Any, **kwargs: Any) -> Result:
    """``work(*args, **kwargs)`` with the worker's loops split over every core it may use
    (planner/cores.py :func:`~planner.cores.every_core`), not the one it is given: for the step
    after a scan (its QA report and textured body), which runs in STORING with the beam still
    and no other job started until it ends. The worker stays a batch job, so the daemon's loop
    takes a core from either of its threads whenever it wakes (the loopback rig's scan checks
    the loop's lag and the drive's heartbeat in STORING)."""
    with every_core():
        return work(*args, **kwargs)


def _started() -> None:
    """The first job: makes the pool start its worker (and run :func:`_warm_up`) at once."""


def exit_with(pid: int) -> None:
    """End this process at once when process ``pid`` ends (at once if it already has): a thread
    waits on the process's pidfd, which becomes readable when it exits."""
    try:
        process = os.pidfd_open(pid)
    except ProcessLookupError:
        os._exit(0)

    def watch() -> None:
        select.select([process], [], [])
        os._exit(0)

    threading.Thread(target=watch, name=f"exit-with-{pid}", daemon=True).start()


def _warm_up(log_setup: dict[str, Any], daemon_pid: int) -> None:
    """In the worker: end with the daemon's process (``daemon_pid``), log as the daemon does
    (``log_setup``: :func:`daemon.logs.log_settings`), run as a batch job and import what every
    scan's jobs need, so the first scan's do not (their modules, not the daemon's), and compile
    the planner's descent loop, the TSDF's carving, the stored surface's fit to the frames and the
    texture's view costs (seconds the first time, from numba's cache after)."""
    exit_with(daemon_pid)
    configure_logging(json=log_setup["json"], level=log_setup["level"])
    structlog.contextvars.bind_contextvars(process="compute")
    os.sched_setscheduler(0, WORKER_POLICY, os.sched_param(0))
    # Imported here, in the worker only: Open3D, the fusion and the planner (numba) cost the
    # daemon's process seconds and memory it never uses.
    import open3d  # noqa: F401

    import daemon.offload.fusion
    import daemon.offload.planning  # noqa: F401
    from planner import candidate_costs, carve, refine, surface_fit
    from planner.rig import load_rig

    rig = load_rig()
    refine.warm_up(rig)
    carve.warm_up(rig.depth_camera_model)
    surface_fit.warm_up()
    candidate_costs.warm_up()
