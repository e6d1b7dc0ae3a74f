"""The beam-angle file of a depth recording: which beam angle every recorded frame was taken at.

A RealSense recording holds depth frames and their device timestamps but nothing of the beam;
``NAME.beam.json`` beside ``NAME.db3`` adds it, so a recorded sweep replays as the sweep it was
(the daemon poses each frame at its recorded angle instead of the live encoder's)::

    {"format": "tbp-depth-beam/1", "camera_id": "depth0", "recording": "depth0.db3",
     "source": {...free-form provenance...},
     "frames": [[frame_number, device_time_ms, beam_angle_deg], ...]}

``device_time_ms`` is the frame's own timestamp in the recording: playback checks it, so a
beam file that belongs to another recording is refused rather than silently mis-posing frames.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from drivers.depth.errors import RecordingUnreadable
from drivers.depth.recording import atomic_write

FORMAT = "tbp-depth-beam/1"
SUFFIX = ".beam.json"
DEVICE_TIME_TOLERANCE_MS = 1e-3


def beam_angles_path(recording: Path | str) -> Path:
    """``dir/NAME.beam.json`` for the recording ``dir/NAME.db3`` (or ``NAME.bag``)."""
    recording = Path(recording)
    return recording.with_name(recording.stem + SUFFIX)


@dataclass(frozen=True)
class BeamAngles:
    """Per recorded frame number: (device time ms, beam angle deg)."""

    camera_id: str
    frames: dict[int, tuple[float, float]]
    source: dict[str, Any] = field(default_factory=dict)

    def angle_of(self, path: Path | str, frame_number: int, device_ms: float) -> float:
        """The recorded angle of a played-back frame; RecordingUnreadable when it is not in the file."""
        entry = self.frames.get(frame_number)
        if entry is None:
            raise RecordingUnreadable(self.camera_id, path, f"frame {frame_number} has no recorded beam angle")
        recorded_ms, angle = entry
        if abs(recorded_ms - device_ms) > DEVICE_TIME_TOLERANCE_MS:
            raise RecordingUnreadable(
                self.camera_id, path, f"frame {frame_number} is stamped {device_ms:.3f} ms in the recording but "
                f"{recorded_ms:.3f} ms in the beam-angle file: they belong to different recordings")
        return angle


def write_beam_angles(path: Path | str, camera_id: str, recording: Path | str,
                      frames: Iterable[tuple[int, float, float]], source: dict[str, Any]) -> Path:
    """Write the beam-angle file (atomically); frames: (frame_number, device_time_ms, beam_angle_deg)."""
    path = Path(path)
    rows = [[int(n), float(ms), float(a)] for n, ms, a in frames]
    index = {"format": FORMAT, "camera_id": camera_id, "recording": Path(recording).name,
             "source": source, "frames": rows}
    atomic_write(path, lambda fh: fh.write(json.dumps(index, indent=None).encode()))
    return path


def read_beam_angles(path: Path | str, camera_id: str) -> BeamAngles:
    """Read a beam-angle file; RecordingUnreadable (naming the file and the problem) if it is not one."""
    try:
        raw = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise RecordingUnreadable(camera_id, path, f"unreadable beam-angle file: {exc}") from exc
    if not isinstance(raw, dict) or raw.get("format") != FORMAT:
        found = raw.get("format") if isinstance(raw, dict) else type(raw).__name__
        raise RecordingUnreadable(camera_id, path, f"format {found!r}, expected {FORMAT!r}")
    frames: dict[int, tuple[float, float]] = {}
    try:
        for n, ms, angle in raw["frames"]:
            if not (math.isfinite(ms) and math.isfinite(angle)):
                raise ValueError(f"frame {n}: non-finite time or angle")
            frames[int(n)] = (float(ms), float(angle))
        source = dict(raw.get("source", {}))
    except (KeyError, TypeError, ValueError) as exc:
        raise RecordingUnreadable(camera_id, path, f"malformed beam-angle file: {exc!r}") from exc
    if not frames:
        raise RecordingUnreadable(camera_id, path, "the beam-angle file lists no frames")
    return BeamAngles(str(raw.get("camera_id", camera_id)), frames, source)
