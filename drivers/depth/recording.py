"""A recorded depth sweep on disk: one compressed ``.npz`` per frame plus ``sweep.json``.

``sweep.json`` holds the format tag, the beam trace (time_s, angle_deg) and per frame its file,
camera id, frame number, timestamp, beam angle, depth unit, intrinsics (3x3) and camera-to-world
pose (4x4, mm). Each ``.npz`` holds ``depth``: (H, W) uint16 in depth units. Files are written
to a temporary name and renamed, so a folder never holds a half-written frame.

Recordings from the cameras themselves (RealSense ``.db3``/``.bag`` files) are read through the
DepthCamera interface, posed at their recorded beam angles or tagged with a beam trace JSON
(:func:`read_recordings`, :func:`load_trace`).
"""

from __future__ import annotations

import dataclasses
import json
import os
import zipfile
import zlib
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import BinaryIO

import numpy as np

from drivers.depth.base import DepthCamera
from planner.files import read_at_most
from planner.rig import Rig
from planner.shape_errors import ShapeEstimateError
from planner.sweep import AngleSpacing, BeamTrace, PosedDepth, Sweep, pose_frame

FORMAT = "tbp-depth-sweep/1"
INDEX = "sweep.json"
MAX_INDEX_BYTES = 16 * 1024 * 1024  # ~1 KB a frame
MAX_FRAME_PX = 4096 * 4096  # default bound of one frame; callers pass their depth camera's size


class RecordingError(ShapeEstimateError):
    """A recorded sweep folder is missing, of another format, or inconsistent."""

    def __init__(self, path: Path | str, problem: str) -> None:
        self.path, self.problem = str(path), problem
        super().__init__(f"{path}: {problem}")


def atomic_write(path: Path, write: Callable[[BinaryIO], object]) -> None:
    """Write path through ``NAME.tmp``, fsync and rename: the path never holds a half-written file."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        write(fh)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def save_sweep(sweep: Sweep, folder: Path | str) -> Path:
    """Write the sweep into folder (created); returns the index file's path."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    entries = []
    for i, f in enumerate(sweep.frames):
        name = f"{i:05d}_{f.camera_id}_{f.frame_number:06d}.npz"
        atomic_write(folder / name, lambda fh: np.savez_compressed(fh, depth=f.depth))  # called here, with this f
        entries.append(
            {
                "file": name,
                "camera_id": f.camera_id,
                "frame_number": f.frame_number,
                "timestamp_s": f.timestamp_s,
                "beam_angle_deg": f.beam_angle_deg,
                "depth_unit_mm": f.depth_unit_mm,
                "intrinsics": np.asarray(f.intrinsics).tolist(),
                "camera_to_world": np.asarray(f.camera_to_world).tolist(),
            }
        )
    index = {
        "format": FORMAT,
        "trace": {"time_s": sweep.trace.time_s.tolist(), "angle_deg": sweep.trace.angle_deg.tolist()},
        "frames": entries,
    }
    path = folder / INDEX
    atomic_write(path, lambda fh: fh.write(json.dumps(index, indent=1).encode()))
    return path


def _read_depth(path: Path, max_px: int) -> np.ndarray:
    """The (H, W) uint16 ``depth`` array of one frame file, at most max_px pixels.

    The size the zip declares is checked before anything is decompressed (a small file may
    inflate to gigabytes); a truncated or corrupt file is a RecordingError naming it.
    """
    limit = max_px * 2 + 4096  # uint16 pixels plus the .npy header
    try:
        with zipfile.ZipFile(path) as archive:
            info = archive.getinfo("depth.npy")
            if info.file_size > limit:
                raise RecordingError(path, f"depth frame of {info.file_size} bytes, more than the "
                                           f"{max_px} pixels allowed")
        with np.load(path) as data:
            depth: np.ndarray = data["depth"]
    except RecordingError:
        raise
    except KeyError:
        raise RecordingError(path, "no 'depth' array in the frame file") from None
    except OSError as exc:
        raise RecordingError(path, f"unreadable frame file: {exc.strerror or exc}") from exc
    except (EOFError, ValueError, zipfile.BadZipFile, zlib.error) as exc:
        raise RecordingError(path, f"unreadable frame file (truncated or corrupt): {exc}") from exc
    if depth.dtype != np.uint16 or depth.ndim != 2:
        raise RecordingError(path, f"depth is {depth.dtype} {depth.shape}, expected (H, W) uint16")
    return depth


def load_sweep(folder: Path | str, *, max_frame_px: int = MAX_FRAME_PX) -> Sweep:
    """Read a folder written by :func:`save_sweep`; raises RecordingError naming what is wrong.

    Sizes are bounded before reading: the index by MAX_INDEX_BYTES, each frame by max_frame_px.
    """
    folder = Path(folder)
    path = folder / INDEX
    try:
        text = read_at_most(path, MAX_INDEX_BYTES, "sweep index", lambda problem: RecordingError(path, problem))
        index = json.loads(text)
    except FileNotFoundError:
        raise RecordingError(folder, f"no {INDEX}: not a recorded depth sweep") from None
    except (OSError, ValueError, RecursionError) as exc:
        raise RecordingError(path, f"unreadable: {exc}") from exc
    if not isinstance(index, dict) or index.get("format") != FORMAT:
        found = index.get("format") if isinstance(index, dict) else type(index).__name__
        raise RecordingError(path, f"format {found!r}, expected {FORMAT!r}")
    try:
        trace = BeamTrace(np.array(index["trace"]["time_s"]), np.array(index["trace"]["angle_deg"]))
        frames = []
        for e in index["frames"]:
            name = str(e["file"])
            if Path(name).name != name or name in ("", ".", ".."):
                raise RecordingError(path, f"frame file {name[:100]!r} is not a file name in the sweep folder")
            frame = PosedDepth(
                camera_id=str(e["camera_id"]),
                frame_number=int(e["frame_number"]),
                timestamp_s=float(e["timestamp_s"]),
                beam_angle_deg=float(e["beam_angle_deg"]),
                depth=np.zeros((0, 0), np.uint16),
                depth_unit_mm=float(e["depth_unit_mm"]),
                intrinsics=np.array(e["intrinsics"], dtype=float).reshape(3, 3),
                camera_to_world=np.array(e["camera_to_world"], dtype=float).reshape(4, 4),
            )  # the entry is checked whole before its frame file is read
            frames.append(dataclasses.replace(frame, depth=_read_depth(folder / name, max_frame_px)))
    except (KeyError, TypeError, ValueError, OSError) as exc:
        raise RecordingError(path, f"inconsistent entry: {exc!r}") from exc
    return Sweep(tuple(frames), trace)


async def read_recordings(cameras: Sequence[DepthCamera], trace: BeamTrace | None, rig: Rig,
                          spacing_deg: float) -> Sweep:
    """A sweep from finite recordings (e.g. ``BagPlayback``), read one camera after the other.

    A frame with a recorded beam angle (a sweep recording) is posed there; any other frame is
    tagged in ``trace``, whose time_s counts seconds from each recording's first frame, so every
    camera's frames are tagged on the same axis (frames outside the trace are skipped). Frames are
    thinned to one per spacing_deg of beam angle per camera as they are read (a whole 30 fps
    recording would not fit in memory comfortably). RecordingError when a frame has no angle and
    there is no trace. The returned sweep's trace is ``trace``, or the recorded angles over time.
    """
    frames = []
    spacing = AngleSpacing(spacing_deg)
    recorded: list[tuple[float, float]] = []
    for camera in cameras:
        await camera.start()
        try:
            first: float | None = None
            async for frame in camera.frames():
                first = frame.timestamp_s if first is None else first
                t = frame.timestamp_s - first
                if frame.beam_angle_deg is not None:
                    angle = frame.beam_angle_deg
                    recorded.append((t, angle))
                elif trace is None:
                    raise RecordingError(camera.id, f"frame {frame.frame_number} has no recorded beam angle "
                                                    "and no beam trace was given")
                elif trace.covers(t):
                    angle = float(trace.angle_at(t))
                else:
                    continue
                if spacing.keep(camera.id, angle):
                    frames.append(pose_frame(dataclasses.replace(frame, timestamp_s=t), angle, rig))
        finally:
            await camera.stop()
    if trace is None:
        trace = BeamTrace.from_columns([r[0] for r in recorded], [r[1] for r in recorded])
    return Sweep(tuple(frames), trace)


def load_trace(path: Path | str) -> BeamTrace:
    """A beam trace JSON file: {"time_s": [...], "angle_deg": [...]} (RecordingError if malformed)."""
    try:
        raw = json.loads(Path(path).read_text())
        return BeamTrace(np.asarray(raw["time_s"], dtype=float), np.asarray(raw["angle_deg"], dtype=float))
    except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise RecordingError(path, f"not a beam trace ({{'time_s': [...], 'angle_deg': [...]}}): {exc!r}") from exc
