"""The kinds of depth camera a hardware file may name, one registry line each.

A kind is the hardware file's word for it (``depth0: realsense``, ``depth1: {recording: f.db3}``),
what its value names (``serial``: the rig file's serial, which the file may repeat; ``path``: a
file, relative to the hardware file), the driver that streams the camera, the finder that tells
whether it is there without streaming (the bring-up's re-probes, ``tbp check``) and the SDK the
daemon loads before its devices' heartbeats run. Adding a kind of depth camera is a driver module
implementing :class:`~drivers.depth.base.DepthCamera` and a finder, its twin in drivers/sim/, and
one line here (docs/architecture.md, "Adding a depth camera kind").
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

from drivers.depth.bag import BagPlayback, RecordingFinder
from drivers.depth.base import DepthCamera, DepthFinder, DepthSource
from drivers.depth.realsense import RealSenseCamera, load_pyrealsense2
from drivers.depth.realsense_probe import RealSenseProbe
from planner.rig import DepthCamera as DepthCameraConfig
from planner.rig import DepthCameraModel


@dataclass(frozen=True)
class DepthKind:
    """One kind of depth camera.

    name: the hardware file's word; takes: what its value names ("serial" or "path");
    open: the camera's driver for a rig camera, its source and the rig's camera model (not started);
    finder: makes the finder the daemon keeps for every camera of the kind;
    load: loads the kind's SDK (its import holds the interpreter lock);
    doc: what the hardware file's entry means (docs/configuration.md lists it).
    """

    name: str
    takes: Literal["serial", "path"]
    open: Callable[[DepthCameraConfig, DepthSource, DepthCameraModel], DepthCamera]
    finder: Callable[[], DepthFinder]
    load: Callable[[], None]
    doc: str


DEPTH_KINDS: dict[str, DepthKind] = {kind.name: kind for kind in (
    DepthKind("realsense", "serial", RealSenseCamera.for_source, RealSenseProbe, load_pyrealsense2,
              "the RealSense with the rig file's serial; {realsense: SERIAL} only with that serial"),
    DepthKind("recording", "path", BagPlayback.for_source, RecordingFinder, load_pyrealsense2,
              "play a recorded sweep: FILE.db3 with FILE.beam.json beside it"),
)}
"""Kind name -> kind, in the order the hardware file's errors list them."""
