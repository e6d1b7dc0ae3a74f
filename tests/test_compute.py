"""The compute worker process and the depth sweep handed to it through shared memory (daemon/compute.py)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from daemon.compute import SHM_DIR, compute_pool, release, share_frames, unshare_frames
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


def test_the_worker_process_reads_the_sweep_from_shared_memory() -> None:
    import os

    frames = _frames([(360, 640)] * 4 + [(180, 320)], seed=7)
    block, shared = share_frames(frames)
    try:
        with compute_pool() as pool:
            got = pool.submit(_digest, shared).result(timeout=120)
            niceness = pool.submit(os.nice, 0).result(timeout=30)
    finally:
        release(block)
    assert [(c, s) for c, s, _ in got] == [(f.camera_id, int(f.depth.astype(np.int64).sum())) for f in frames]
    assert {pid for _, _, pid in got} != {os.getpid()}  # another process
    assert niceness >= os.nice(0) + 10  # below the daemon's priority
