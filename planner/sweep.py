"""Depth sweep geometry: tag depth frames with the beam angle and the camera pose at that angle.

The beam angle of a live frame is interpolated in the motor's position trace (event-loop time,
beam angle) at the frame's host timestamp; a frame played back from a sweep recording brings the
angle it was recorded at. The frame's camera-to-world pose is the beam rotation applied to the
depth camera's extrinsics from the rig file. Pure computation: frames are any objects with the
``DepthFrame`` attributes (camera_id, frame_number, timestamp_s, depth, depth_unit_mm, intrinsics).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

from planner.poses import rig_depth_pose
from planner.rig import Rig
from planner.shape_errors import BadTrace, FrameOutsideTrace, UnknownDepthCamera

if TYPE_CHECKING:
    from planner.calibration.model import Calibration


class FrameLike(Protocol):
    @property
    def camera_id(self) -> str: ...
    @property
    def frame_number(self) -> int: ...
    @property
    def timestamp_s(self) -> float: ...
    @property
    def depth(self) -> np.ndarray: ...
    @property
    def depth_unit_mm(self) -> float: ...
    @property
    def intrinsics(self) -> np.ndarray: ...


@dataclass(frozen=True)
class BeamTrace:
    """The beam's recorded position: time_s (N,) increasing event-loop seconds, angle_deg (N,) unwrapped."""

    time_s: np.ndarray
    angle_deg: np.ndarray

    def __post_init__(self) -> None:
        t, a = np.asarray(self.time_s, dtype=float), np.asarray(self.angle_deg, dtype=float)
        if t.ndim != 1 or t.shape != a.shape:
            raise BadTrace(f"beam trace times {t.shape} and angles {a.shape} must be equal-length 1-D")
        if len(t) < 2:
            raise BadTrace(f"beam trace has {len(t)} samples, need at least 2 to interpolate")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(a))):
            raise BadTrace("beam trace holds non-finite times or angles")
        steps = np.diff(t)
        if np.any(steps <= 0):
            i = int(np.argmin(steps))
            raise BadTrace(f"beam trace times must increase; sample {i + 1} at {t[i + 1]:.6f} s follows {t[i]:.6f} s")
        object.__setattr__(self, "time_s", t)
        object.__setattr__(self, "angle_deg", a)

    @classmethod
    def from_samples(cls, samples: Iterable[object]) -> BeamTrace:
        """From motor samples with ``time_s`` and ``angle_deg`` (e.g. BeamSample), duplicates in time dropped."""
        rows = [(float(s.time_s), float(s.angle_deg)) for s in samples]  # type: ignore[attr-defined]
        return cls.from_columns([r[0] for r in rows], [r[1] for r in rows])

    @classmethod
    def from_columns(cls, time_s: Iterable[float], angle_deg: Iterable[float]) -> BeamTrace:
        """From (N,) times and (N,) angles in any order; a repeated time keeps its last angle."""
        pairs = sorted(dict(zip(map(float, time_s), map(float, angle_deg), strict=True)).items())
        return cls(np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs]))

    @property
    def start_s(self) -> float:
        return float(self.time_s[0])

    @property
    def end_s(self) -> float:
        return float(self.time_s[-1])

    def covers(self, time_s: float) -> bool:
        return self.start_s <= time_s <= self.end_s

    def angle_at(self, time_s: float | np.ndarray) -> np.ndarray:
        """Beam angle (deg) at event-loop time(s), linear between samples; no extrapolation."""
        t = np.asarray(time_s, dtype=float)
        if np.any((t < self.start_s) | (t > self.end_s)):
            raise BadTrace(
                f"time(s) {t.min():.4f}..{t.max():.4f} s outside the trace [{self.start_s:.4f}, {self.end_s:.4f}] s"
            )
        result: np.ndarray = np.interp(t, self.time_s, self.angle_deg)
        return result


@dataclass(frozen=True)
class PosedDepth:
    """A depth frame with its beam angle and pose.

    depth: (H, W) uint16 in depth units (0 = hole); intrinsics (3, 3); camera_to_world (4, 4) mm,
    OpenCV camera axes.
    """

    camera_id: str
    frame_number: int
    timestamp_s: float
    beam_angle_deg: float
    depth: np.ndarray
    depth_unit_mm: float
    intrinsics: np.ndarray
    camera_to_world: np.ndarray

    @property
    def valid_pixels(self) -> int:
        return int(np.count_nonzero(self.depth))


@dataclass(frozen=True)
class Sweep:
    """Posed frames of a depth sweep and the beam trace they were tagged with."""

    frames: tuple[PosedDepth, ...]
    trace: BeamTrace

    def per_camera(self) -> dict[str, int]:
        counts: dict[str, int] = {}
        for f in self.frames:
            counts[f.camera_id] = counts.get(f.camera_id, 0) + 1
        return counts


def tag_frame(frame: FrameLike, trace: BeamTrace, rig: Rig, calibration: Calibration | None = None) -> PosedDepth:
    """The frame with its interpolated beam angle and camera-to-world pose.

    Raises FrameOutsideTrace when the frame's timestamp is not covered by the trace, and
    UnknownDepthCamera when the rig has no camera of that id.
    """
    if frame.camera_id not in {c.id for c in rig.depth_cameras}:
        raise UnknownDepthCamera(frame.camera_id, sorted(c.id for c in rig.depth_cameras))
    if not trace.covers(frame.timestamp_s):
        raise FrameOutsideTrace(frame.camera_id, frame.frame_number, frame.timestamp_s, trace.start_s, trace.end_s)
    return pose_frame(frame, float(trace.angle_at(frame.timestamp_s)), rig, calibration)


def pose_frame(frame: FrameLike, angle_deg: float, rig: Rig, calibration: Calibration | None = None) -> PosedDepth:
    """The frame posed at beam angle ``angle_deg`` (a recorded angle, or one read off the trace);
    the calibrated depth camera pose when a calibration is given, else the rig file's.

    Raises UnknownDepthCamera when the rig has no camera of that id.
    """
    cameras = {c.id: c for c in rig.depth_cameras}
    if frame.camera_id not in cameras:
        raise UnknownDepthCamera(frame.camera_id, sorted(cameras))
    angle = float(angle_deg)
    return PosedDepth(
        camera_id=frame.camera_id,
        frame_number=frame.frame_number,
        timestamp_s=frame.timestamp_s,
        beam_angle_deg=angle,
        depth=frame.depth,
        depth_unit_mm=frame.depth_unit_mm,
        intrinsics=np.asarray(frame.intrinsics, dtype=float),
        camera_to_world=rig_depth_pose(cameras[frame.camera_id], math.radians(angle), calibration),
    )


def tag_frames(frames: Sequence[FrameLike], trace: BeamTrace, rig: Rig, calibration: Calibration | None = None) -> Sweep:
    """Tag every frame (all must lie inside the trace; see :func:`tag_frame`); calibrated poses with a calibration."""
    return Sweep(tuple(tag_frame(f, trace, rig, calibration) for f in frames), trace)


class AngleSpacing:
    """Per camera, keeps a frame only when the beam turned at least ``spacing_deg`` since the camera's
    last kept frame (the first is kept; 0 keeps every frame).

    Consecutive 30 fps frames a fraction of a degree apart add little to the fusion but cost
    integration time and memory (a whole sweep of three cameras would hold about 1 GB).
    """

    def __init__(self, spacing_deg: float) -> None:
        self.spacing_deg = spacing_deg
        self._last: dict[str, float] = {}

    def keep(self, camera_id: str, angle_deg: float) -> bool:
        """Whether to keep this camera's frame at this beam angle (and remember it if kept)."""
        last = self._last.get(camera_id)
        if last is not None and abs(angle_deg - last) < self.spacing_deg - 1e-9:
            return False
        self._last[camera_id] = angle_deg
        return True


def observed(points: np.ndarray, frames: Sequence[PosedDepth], tolerance_mm: float = 10.0) -> np.ndarray:
    """(N,) bool: which of (N, 3) world points some frame measured (valid depth within tolerance_mm).

    The sweep's coverage of a known surface: a point counts as seen when it projects inside a
    frame and that pixel's depth agrees with the point's depth (so occluded points do not count).
    """
    seen = np.zeros(len(points), dtype=bool)
    for f in frames:
        world_to_camera = np.linalg.inv(f.camera_to_world)
        p = points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
        z = p[:, 2]
        front = z > 1e-6
        k = f.intrinsics
        u = np.full(len(points), -1, dtype=np.int64)
        v = np.full(len(points), -1, dtype=np.int64)
        u[front] = np.floor(k[0, 0] * p[front, 0] / z[front] + k[0, 2]).astype(np.int64)
        v[front] = np.floor(k[1, 1] * p[front, 1] / z[front] + k[1, 2]).astype(np.int64)
        h, w = f.depth.shape
        inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        idx = np.flatnonzero(inside)
        measured = f.depth[v[idx], u[idx]].astype(float) * f.depth_unit_mm
        seen[idx[(measured > 0) & (np.abs(measured - z[idx]) <= tolerance_mm)]] = True
    return seen
