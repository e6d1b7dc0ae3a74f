"""The compute worker process (daemon/offload/worker.py) and the depth sweep handed to it through shared memory
(daemon/offload/compute.py)."""

from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from daemon.offload.compute import SHM_DIR, release, share_frames, unshare_frames
from daemon.offload.worker import compute_pool, compute_threads, on_every_core
from planner.cores import spare_core
from planner.sweep import PosedDepth


def _frames(shapes: list[tuple[int, int]], seed: int = 0) -> list[PosedDepth]:
    rng = np.random.default_rng(seed)
    return [PosedDepth(camera_id=f"depth{i % 3}", frame_number=i, timestamp_s=0.1 * i, beam_angle_deg=3.0 * i,
                       depth=rng.integers(0, 65535, shape, dtype=np.uint16), depth_unit_mm=1.0,
                       intrinsics=np.eye(3) * (i + 1), camera_to_world=np.eye(4) + i)
            for i, shape in enumerate(shapes)]


def _same(a: PosedDepth, b: PosedDepth) -> bool:
    return (a.camera_id, a.frame_number, a.timestamp_s, a.beam_angle_deg, a.depth_unit_mm) == \
        (b.camera_id, b.frame_number, b.timestamp_s, b.beam_angle_deg, b.depth_unit_mm) and \
        np.array_equal(a.depth, b.depth) and a.depth.dtype == b.depth.dtype and \
        np.array_equal(a.intrinsics, b.intrinsics) and np.array_equal(a.camera_to_world, b.camera_to_world)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.tuples(st.integers(1, 37), st.integers(1, 53)), min_size=1, max_size=6), st.integers(0, 99))
def test_frames_come_out_of_shared_memory_as_they_went_in(shapes: list[tuple[int, int]], seed: int) -> None:
    frames = _frames(shapes, seed)
    block, shared = share_frames(frames)
    try:
        assert all(f.depth.size == 0 for f in shared.frames)  # what is pickled carries no image
        back = unshare_frames(shared)
    finally:
        release(block)
    assert len(back) == len(frames) and all(_same(a, b) for a, b in zip(frames, back, strict=True))
    assert not (SHM_DIR / block.name.lstrip("/")).exists()


def _digest(shared: object) -> list[tuple[str, int, int]]:
    """Runs in the worker process."""
    import os

    return [(f.camera_id, int(f.depth.astype(np.int64).sum()), os.getpid()) for f in unshare_frames(shared)]


def _omp_threads() -> str | None:
    """Runs in the worker process."""
    import os

    return os.environ.get("OMP_NUM_THREADS")


@pytest.mark.slow  # a worker process
def test_the_worker_process_reads_the_sweep_from_shared_memory() -> None:
    import os

    frames = _frames([(360, 640)] * 4 + [(180, 320)], seed=7)
    ours = os.environ.get("OMP_NUM_THREADS")
    block, shared = share_frames(frames)
    try:
        with compute_pool() as pool:
            got = pool.submit(_digest, shared).result(timeout=120)
            policy = pool.submit(os.sched_getscheduler, 0).result(timeout=30)
            threads = pool.submit(_omp_threads).result(timeout=30)
            imported = pool.submit(_imported, "daemon.offload.fusion", "daemon.offload.planning",
                                   "daemon.jobs.scan").result(timeout=30)
            spare = pool.submit(spare_core).result(timeout=30)
            spare_storing = pool.submit(on_every_core, spare_core).result(timeout=30)
    finally:
        release(block)
    assert [(c, s) for c, s, _ in got] == [(f.camera_id, int(f.depth.astype(np.int64).sum())) for f in frames]
    assert {pid for _, _, pid in got} != {os.getpid()}  # another process
    assert policy == os.SCHED_BATCH  # never preempts the daemon on wake-up
    assert threads == str(compute_threads()) and int(threads) < max(2, len(os.sched_getaffinity(0)))
    assert os.environ.get("OMP_NUM_THREADS") == ours  # this process's environment is left as it was
    # one core for its loops while the beam moves, every core for the step after a scan
    assert not spare and spare_storing is (len(os.sched_getaffinity(0)) > 1)
    # the jobs' modules are loaded before the first scan, and not the daemon's
    assert imported == {"daemon.offload.fusion": True, "daemon.offload.planning": True, "daemon.jobs.scan": False}


def _imported(*names: str) -> dict[str, bool]:
    """Runs in the worker process."""
    import sys

    return {name: name in sys.modules for name in names}


def _mesh_digest(mesh: object, tag: str) -> tuple[str, int, float, int]:
    """Runs in the worker process, on the fusion's own mesh."""
    import os

    return tag, len(mesh.faces), float(mesh.vertices.sum()), os.getpid()  # type: ignore[attr-defined]


def _worker_pid(pool: object) -> int:
    """The worker process's id (asked of the worker)."""
    import os

    return int(pool.submit(os.getpid).result(timeout=30))  # type: ignore[attr-defined]


def _open_sessions() -> int:
    """Runs in the worker process."""
    from daemon.offload.fusion import _OPEN

    return len(_OPEN)


@pytest.mark.slow  # a worker process
@pytest.mark.xdist_group("tsdf-cylinder")  # one worker ray casts the shared sweep
def test_a_sweep_fused_batch_by_batch_in_the_worker_gives_the_whole_sweep_s_mesh(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """daemon/offload/fusion.py: the TSDF lives in the worker between jobs; images go through shared memory."""
    import asyncio

    import daemon.offload.fusion
    from daemon.offload.fusion import _OPEN, FusionSession
    from planner.mesh_metrics import shape_metrics
    from planner.tsdf import fuse
    from tests.depth_helpers import cylinder_sweep, small_rig

    rig = small_rig(scale=2)
    frames = sorted(cylinder_sweep(), key=lambda f: f.timestamp_s)
    blocks: list[str] = []  # this session's shared-memory blocks (other processes may have their own)

    def sharing(batch: list[object]) -> object:
        block, shared = share_frames(batch)
        blocks.append(block.name)
        return block, shared

    monkeypatch.setattr(daemon.offload.fusion, "share_frames", sharing)

    async def fused(pool: object) -> object:
        async with FusionSession(pool, rig, "scan-1") as fusion:
            for start in range(0, len(frames), 7):
                await fusion.add(frames[start:start + 7])
            result, then = await fusion.result_then(_mesh_digest, "plan")
            digest, seconds = await then
        assert digest == ("plan", len(result.mesh.faces), float(result.mesh.vertices.sum()), _worker_pid(pool))
        assert seconds >= 0 and fusion.closed is not None
        await fusion.closed  # asked for at the end of the session, not waited for there
        return result, fusion.seconds

    with compute_pool() as pool:
        live, seconds = asyncio.run(fused(pool))
        left = pool.submit(_open_sessions).result(timeout=30)  # the worker keeps nothing once it ends
    whole = fuse(frames, rig)
    assert live.per_camera == whole.per_camera and seconds > 0 and left == 0
    assert "scan-1" not in _OPEN  # it lived in the worker, never here
    metrics = shape_metrics(whole.mesh, live.mesh, samples=20_000)
    assert metrics.true_to_estimate_mean_mm < 0.05 and metrics.estimate_to_true_mean_mm < 0.05
    assert blocks and not [b for b in blocks if (SHM_DIR / b.lstrip("/")).exists()]  # every batch's block released


def test_the_daemon_process_does_not_load_numba() -> None:
    """Only the process that plans compiles or loads the planner's loops (0.8 s of numba's import
    alone): importing the daemon's scan, which reaches the planner, leaves numba out."""
    import subprocess
    import sys

    probe = "import sys, daemon.jobs.scan, daemon.offload.planning, planner.em; print('numba' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "False"


_THREADS_PROBE = """
import json, os
import numpy, scipy.linalg  # their BLAS loaded with every core
from threadpoolctl import threadpool_info
before = [p["num_threads"] for p in threadpool_info()]
from daemon.offload.worker import one_numeric_thread
one_numeric_thread()
import cv2, open3d  # loaded after: the variables reach them
print(json.dumps({"before": before, "after": [p["num_threads"] for p in threadpool_info()],
                  "environ": [os.environ.get(n) for n in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS")]}))
"""


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="one core: every library has one thread already")
def test_one_numeric_thread_reaches_the_libraries_loaded_before_and_after() -> None:
    """The daemon's process (daemon/server/serve.py) and the tests run their numeric libraries on
    one thread each, whatever the machine's cores: the ones loaded before the call and after it."""
    import json
    import subprocess
    import sys

    from daemon.offload.worker import THREAD_VARIABLES

    env = {k: v for k, v in os.environ.items() if k not in THREAD_VARIABLES}
    out = subprocess.run([sys.executable, "-c", _THREADS_PROBE], env=env, capture_output=True, text=True,
                         timeout=120, check=True).stdout
    got = json.loads(out.splitlines()[-1])
    assert max(got["before"]) > 1  # the libraries' default: every core
    assert got["after"] and set(got["after"]) == {1}
    assert got["environ"] == ["1", "1"]
