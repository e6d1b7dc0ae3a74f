"""The TSDF fused while the depth sweep runs, in the compute executor.

The sweep delivers posed frames in batches (daemon/jobs/depth_sweep.py); each batch is fused at once
in the compute worker (daemon/offload/compute.py: images through shared memory, never pickled on the
loop), so when the beam stops only the last frames, the mesh extraction and the cleaning are
left before planning. The fusion lives in the process that fuses: the worker keeps it in
:data:`_OPEN` under the scan's key between jobs (the pool has one worker; a thread executor keeps
it in this process). Jobs of one session are awaited one after the other, never concurrently;
the exceptions, :meth:`FusionSession.result_then`, :meth:`FusionSession.on_mesh` and
:meth:`FusionSession.surface`, only read the extracted mesh or the kept frames, which the fusion
keeps (and extracts once) until the session closes; the session closes once they are done. Work
on the mesh is asked for this way so the mesh never crosses back to the worker: pickling it holds
this process's interpreter lock, which the event loop needs, for tens of milliseconds.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Sequence
from concurrent.futures import Executor, ProcessPoolExecutor
from typing import Any

from daemon.offload.compute import SharedFrames, release, share_frames, timed, unshare_frames
from planner.rig import Rig
from planner.sweep import PosedDepth
from planner.tsdf import TsdfFusion, TsdfResult

_OPEN: dict[str, TsdfFusion] = {}


def _open(key: str, rig: Rig) -> None:
    _OPEN[key] = TsdfFusion(rig)


def _add(key: str, frames: Sequence[PosedDepth] | SharedFrames) -> int:
    batch = unshare_frames(frames) if isinstance(frames, SharedFrames) else frames
    return _OPEN[key].add(batch)


def fused_mesh(key: str) -> TsdfResult:
    """In the executor: the subject mesh of the session ``key`` (vertices and faces in the TSDF's
    canonical order, so a seeded scan plans the same)."""
    return _OPEN[key].result()


def surface_mesh(key: str) -> TsdfResult:
    """In the executor: the session's stored surface (the frames fused again at the rig's
    ``tsdf.surface_voxel_mm``, :meth:`planner.tsdf.TsdfFusion.surface`)."""
    return _OPEN[key].surface()


def on_fused_mesh(key: str, func: Callable[..., Any], *args: Any) -> Any:
    """In the executor: ``func(mesh, *args)`` on the session's subject mesh, extracted once."""
    return func(_OPEN[key].result().mesh, *args)


def _ignore(future: asyncio.Future[Any]) -> None:
    if not future.cancelled():
        future.exception()


def _close(key: str) -> None:
    _OPEN.pop(key, None)


class FusionSession:
    """One scan's TSDF in ``executor`` (None: the loop's default thread pool).

    ``async with`` opens it and, at the end, whatever happened, asks the worker to drop its
    copy without waiting: freeing the voxel blocks takes 50-75 ms, and the capture's plan, asked
    for before the end, need not wait for it. :meth:`add` fuses a batch, :meth:`result` extracts
    the subject. ``seconds`` sums the compute time of every job, measured where it ran.
    """

    def __init__(self, executor: Executor | None, rig: Rig, key: str) -> None:
        self.executor = executor
        self.rig = rig
        self.key = key
        self.seconds = 0.0
        self._lock = asyncio.Lock()
        self.closed: asyncio.Future[Any] | None = None
        """The worker's drop of this fusion, once asked for (awaitable; nothing waits for it)."""
        self._on_mesh: list[asyncio.Future[Any]] = []

    async def __aenter__(self) -> FusionSession:
        await self._run(_open, self.key, self.rig)
        return self

    async def __aexit__(self, *_exc: object) -> None:
        self.closed = asyncio.ensure_future(self._close())

    async def _close(self) -> None:
        """Drop the fusion in the worker once the jobs on its mesh are done (or cancelled)."""
        if self._on_mesh:
            await asyncio.wait(self._on_mesh)
        await asyncio.get_running_loop().run_in_executor(self.executor, _close, self.key)

    async def add(self, frames: Sequence[PosedDepth]) -> None:
        """Fuse ``frames`` (each camera's in time order, after the ones already added)."""
        if not frames:
            return
        if not isinstance(self.executor, ProcessPoolExecutor):
            await self._run(_add, self.key, list(frames))
            return
        block, shared = await asyncio.to_thread(share_frames, list(frames))
        try:
            await self._run(_add, self.key, shared)
        finally:
            release(block)

    async def result(self) -> TsdfResult:
        """The subject's mesh from every frame added (raises the TSDF's typed refusals)."""
        result: TsdfResult = await self._run(fused_mesh, self.key)
        return result

    async def result_then(self, func: Callable[..., Any], *args: Any) -> tuple[TsdfResult, asyncio.Future[Any]]:
        """:meth:`result`, and ``func(mesh, *args)`` on the mesh where it was made, both asked for
        at once: the worker goes from the extraction to ``func`` without sending the mesh back and
        forth (megabytes pickled twice, and a wait for this loop in between). Returns the mesh
        and the future of (``func``'s result, its compute seconds); when the extraction fails, that
        future is dropped and the extraction's error raised."""
        loop = asyncio.get_running_loop()
        async with self._lock:
            extraction = loop.run_in_executor(self.executor, timed, fused_mesh, self.key)
            then = loop.run_in_executor(self.executor, timed, on_fused_mesh, self.key, func, *args)
            try:
                result, seconds = await extraction
            except BaseException:
                then.cancel()
                then.add_done_callback(_ignore)  # the same refusal again, or cancelled: not news
                raise
            self.seconds += seconds
            return result, then

    def on_mesh(self, func: Callable[..., Any], *args: Any) -> asyncio.Future[Any]:
        """``func(mesh, *args)`` on the extracted mesh where it was made, asked for now; the
        future of (its result, its compute seconds). Closing the session waits for it; cancel the
        future if nothing will await it."""
        return self._asked(on_fused_mesh, self.key, func, *args)

    def surface(self) -> asyncio.Future[Any]:
        """The stored surface (a :class:`TsdfResult`, from every frame added), asked for now; the
        future of (it, its compute seconds). Closing the session waits for it, as for
        :meth:`on_mesh`."""
        return self._asked(surface_mesh, self.key)

    def _asked(self, func: Callable[..., Any], *args: Any) -> asyncio.Future[Any]:
        job = asyncio.get_running_loop().run_in_executor(self.executor, timed, func, *args)
        job.add_done_callback(_ignore)  # its awaiter gets the error; a job nobody awaits is not news
        self._on_mesh.append(job)
        return job

    async def _run(self, func: Any, *args: Any) -> Any:
        async with self._lock:  # one job of this session at a time, in the order asked
            result, seconds = await asyncio.get_running_loop().run_in_executor(self.executor, timed, func, *args)
            self.seconds += seconds
            return result

