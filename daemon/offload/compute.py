"""Compute steps off the event loop: their compute time measured where they run, and the depth
sweep handed to them in shared memory.

The steps run in the compute worker (daemon/offload/worker.py). A sweep is hundreds of megabytes of depth
images; pickling it to the worker would hold the lock for as long as the copy takes.
:func:`share_frames` copies the images into one shared memory block instead (NumPy copies without
the lock, in a thread) and the worker gets only their names, shapes and poses.
"""

from __future__ import annotations

import dataclasses
import mmap
import time
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.shared_memory import SharedMemory
from pathlib import Path
from typing import Any

import numpy as np

SHM_DIR = Path("/dev/shm")


def timed(func: Callable[..., Any], *args: Any) -> tuple[Any, float]:
    """Run ``func`` (in the executor) and measure its duration there: compute time, not rig time."""
    started = time.perf_counter()
    result = func(*args)
    return result, time.perf_counter() - started


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
