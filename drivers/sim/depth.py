"""Simulated depth camera: ray-cast depth frames of the simulated subject with a RealSense-like error model.

The subject (a trimesh in mm) and the floor are put once into an Open3D ``RaycastingScene``;
each frame casts one ray per pixel from the depth camera's pose at the current beam angle. Ray
directions are pinhole directions with z = 1 in the camera frame, so ``t_hit`` is z-depth.

Error model (active stereo, D415 class):
- depth noise with RMS ``z^2 * subpixel / (fx * baseline)`` (grows with depth squared);
- quantisation to the depth unit;
- holes where the incidence angle exceeds ``grazing_limit_deg`` and at silhouette edges
  (depth discontinuities), as stereo matching fails there;
- no depth outside ``[min_range_mm, max_range_mm]``.
"""

from __future__ import annotations

import asyncio
import dataclasses
import math
from collections.abc import AsyncIterator, Callable, Generator, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, TypeVar

import numpy as np
import structlog
import trimesh

from drivers.depth.base import DepthCamera, DepthFrame
from drivers.depth.beam_angles import beam_angles_path, write_beam_angles
from drivers.depth.errors import InfraredUnavailable
from drivers.depth.recorder import DepthRecorder
from drivers.sim.trapezoid import Trajectory, position_move
from planner.poses import depth_camera_pose
from planner.rig import DepthCamera as DepthCameraConfig
from planner.rig import DepthCameraModel, Rig
from planner.sweep import BeamTrace, PosedDepth, Sweep

log = structlog.get_logger(__name__)

#: A depth jump larger than this between neighbouring pixels (relative to depth) is a silhouette edge.
EDGE_JUMP_RELATIVE = 0.03
#: Pixels within this many pixels of a silhouette edge get no depth.
EDGE_WIDTH_PX = 2
#: Half the side of the square floor put under the subject (mm).
FLOOR_HALF_SIDE_MM = 2500.0
#: Rays cast between two turns of the event loop when a frame is rendered in steps (~10 ms here).
RAYS_PER_STEP = 1 << 15

T = TypeVar("T")


class DepthScene:
    """A subject mesh standing on a floor, ready for ray casting (build once per subject).

    mesh: the subject in mm, world frame (z up, feet on z = 0). floor: add the z = 0 floor square.
    """

    def __init__(self, mesh: trimesh.Trimesh, *, floor: bool = True) -> None:
        import open3d as o3d  # seconds to import: only where a scene is ray cast

        self._o3d = o3d
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(
            o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
            o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)),
        )
        if floor:
            s = FLOOR_HALF_SIDE_MM
            verts = np.array([[-s, -s, 0], [s, -s, 0], [s, s, 0], [-s, s, 0]], dtype=np.float32)
            faces = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32)
            self.scene.add_triangles(o3d.core.Tensor(verts), o3d.core.Tensor(faces))

    def cast(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cast (N, 6) float32 rays [origin, direction] (world). Returns t_hit (N,) and normals (N, 3)."""
        ans = self.scene.cast_rays(self._o3d.core.Tensor.from_numpy(rays))
        return ans["t_hit"].numpy(), ans["primitive_normals"].numpy()


@dataclass(frozen=True)
class SampledDepthModel(DepthCameraModel):
    """A depth camera's model sampled at every ``every_px``-th pixel (the simulator's cheaper
    frames, sim.rig.sim_depth_model): the intrinsics and noise are given in the coarser pixels,
    and a silhouette edge leaves as much skin without depth as the full camera's does."""

    every_px: int = 1

    @property
    def edge_width_px(self) -> int:
        """EDGE_WIDTH_PX of the full camera, in these pixels (at least one)."""
        return max(1, round(EDGE_WIDTH_PX / self.every_px))


class DepthRenderer:
    """Renders depth images (uint16, depth units) of a :class:`DepthScene` for one camera model."""

    def __init__(self, scene: DepthScene, model: DepthCameraModel) -> None:
        self.scene = scene
        self.model = model
        self.edge_width_px = model.edge_width_px if isinstance(model, SampledDepthModel) else EDGE_WIDTH_PX
        u, v = np.meshgrid(
            np.arange(model.width_px, dtype=np.float32), np.arange(model.height_px, dtype=np.float32)
        )
        self._rays_camera = np.stack(
            [(u - model.cx_px) / model.fx_px, (v - model.cy_px) / model.fy_px, np.ones_like(u)], axis=-1
        ).reshape(-1, 3)
        # a rotation keeps ray lengths: 1 / |ray| once per camera model
        self._inverse_length = 1.0 / np.linalg.norm(self._rays_camera, axis=1)
        self._rays = np.empty((len(self._rays_camera), 6), dtype=np.float32)

    def true_depth_steps(self, camera_to_world: np.ndarray) -> Generator[None, None, tuple[np.ndarray, np.ndarray]]:
        """(H, W) float z-depth in mm (inf where nothing is hit) and (H, W) cos of incidence, cast
        in steps of at most :data:`RAYS_PER_STEP` rays with a yield between steps, so an event
        loop rendering frames keeps answering in between."""
        m = self.model
        rays = self._rays
        rays[:, :3] = camera_to_world[:3, 3]
        np.matmul(self._rays_camera, camera_to_world[:3, :3].T.astype(np.float32), out=rays[:, 3:])
        t_hit = np.empty(len(rays), dtype=np.float32)
        normals = np.empty((len(rays), 3), dtype=np.float32)
        for start in range(0, len(rays), RAYS_PER_STEP):
            if start:
                yield
            stop = start + RAYS_PER_STEP
            t_hit[start:stop], normals[start:stop] = self.scene.cast(rays[start:stop])
        cos_incidence = np.abs(np.einsum("ij,ij->i", normals, rays[:, 3:])) * self._inverse_length
        return t_hit.reshape(m.height_px, m.width_px), cos_incidence.reshape(m.height_px, m.width_px)

    def render(self, camera_to_world: np.ndarray, rng: np.random.Generator | None) -> np.ndarray:
        """(H, W) uint16 depth in depth units, 0 = hole. rng None renders without noise (still quantised)."""
        return _finish(self.render_steps(camera_to_world, rng))

    def render_steps(
        self, camera_to_world: np.ndarray, rng: np.random.Generator | None
    ) -> Generator[None, None, np.ndarray]:
        """:meth:`render` in steps (see :meth:`true_depth_steps`); the generator returns the image."""
        m = self.model
        z, cos_incidence = yield from self.true_depth_steps(camera_to_world)
        yield
        valid = np.isfinite(z) & (z >= m.min_range_mm) & (z <= m.max_range_mm)
        valid &= cos_incidence >= math.cos(math.radians(m.grazing_limit_deg))
        valid &= ~silhouette_edges(z, self.edge_width_px)
        if rng is not None:
            sigma = np.where(valid, z, 0.0) ** 2 * (m.subpixel_px / (m.fx_px * m.baseline_mm))
            z = z + rng.standard_normal(z.shape) * sigma
        units = np.where(valid, np.rint(z / m.depth_unit_mm), 0.0)
        return np.clip(units, 0, np.iinfo(np.uint16).max).astype(np.uint16)


def _finish(steps: Generator[None, None, T]) -> T:
    """Run a stepwise computation to its end; its result."""
    while True:
        try:
            next(steps)
        except StopIteration as done:
            result: T = done.value
            return result


def silhouette_edges(z: np.ndarray, width_px: int = EDGE_WIDTH_PX) -> np.ndarray:
    """(H, W) bool: pixels within ``width_px`` (at least 1) of a depth discontinuity (inf counts as far)."""
    finite = np.where(np.isfinite(z), z, 1e9)
    jump = np.zeros(z.shape, dtype=bool)
    for axis in (0, 1):
        d = np.abs(np.diff(finite, axis=axis))
        near = np.minimum(np.delete(finite, 0, axis=axis), np.delete(finite, -1, axis=axis))
        step = d > EDGE_JUMP_RELATIVE * near
        if axis == 0:
            jump[1:] |= step
            jump[:-1] |= step
        else:
            jump[:, 1:] |= step
            jump[:, :-1] |= step
    grown = jump.copy()
    for _ in range(width_px - 1):
        g = grown.copy()
        g[1:] |= grown[:-1]
        g[:-1] |= grown[1:]
        g[:, 1:] |= grown[:, :-1]
        g[:, :-1] |= grown[:, 1:]
        grown = g
    return grown


@dataclass
class DepthFaults:
    """Injected faults: frame numbers to drop or deliver empty, and a frame after which streaming stops."""

    drop_frames: set[int] = field(default_factory=set)
    empty_frames: set[int] = field(default_factory=set)
    stop_after_frame: int | None = None


class SimulatedDepthCamera:
    """A depth camera on the beam that streams ray-cast frames on the shared event-loop clock.

    beam_angle_deg: callable event-loop time (s) -> beam angle (deg), supplied by the sim wiring
    (e.g. the simulated drive's true angle). Frames come at ``model.fps`` from ``start()``.
    infrared_source: callable (frame number, beam angle in deg at the frame's time) -> (H, W) uint8
    infrared picture at the model's resolution, supplied by the sim wiring (the camera does not know
    what it looks at). With ``infrared`` on at ``start()`` every frame carries it; without a source
    ``start()`` raises InfraredUnavailable.
    """

    def __init__(
        self,
        camera: DepthCameraConfig,
        model: DepthCameraModel,
        subject: trimesh.Trimesh | DepthScene,
        beam_angle_deg: Callable[[float], float],
        *,
        seed: int = 0,
        noise: bool = True,
        faults: DepthFaults | None = None,
        infrared_source: Callable[[int, float], np.ndarray] | None = None,
    ) -> None:
        self.id = camera.id
        self.infrared = False
        self.infrared_source = infrared_source
        self._streaming_infrared: Callable[[int, float], np.ndarray] | None = None  # set by start()
        self.camera = camera
        self.model = model
        scene = subject if isinstance(subject, DepthScene) else DepthScene(subject)
        self.renderer = DepthRenderer(scene, model)
        self.beam_angle_deg = beam_angle_deg
        self.faults = faults or DepthFaults()
        self._rng = np.random.default_rng(seed) if noise else None
        self._t0: float | None = None
        self._frame_number = 0

    async def start(self) -> None:
        """Start streaming: frame k is exposed at start time + k / fps. InfraredUnavailable when
        ``infrared`` is on and there is no infrared source."""
        if self.infrared and self.infrared_source is None:
            raise InfraredUnavailable(self.id, "the simulated camera was given no infrared source")
        self._streaming_infrared = self.infrared_source if self.infrared else None
        self._t0 = asyncio.get_running_loop().time()
        self._frame_number = 0
        log.info("depth_sim.start", camera=self.id, fps=self.model.fps)

    async def stop(self) -> None:
        """Stop streaming (idempotent)."""
        if self._t0 is not None:
            log.info("depth_sim.stop", camera=self.id, frames=self._frame_number)
        self._t0 = None

    def drop_next(self, n: int) -> None:
        """Fault: the next n frames are lost."""
        self.faults.drop_frames.update(range(self._frame_number, self._frame_number + n))

    def stop_streaming(self) -> None:
        """Fault: the camera silently stops delivering frames (the USB link stalls)."""
        self.faults.stop_after_frame = self._frame_number - 1

    async def frames(self) -> AsyncIterator[DepthFrame]:
        """Frames in order; a stopped camera stalls (the consumer's timeout decides)."""
        loop = asyncio.get_running_loop()
        period = 1.0 / self.model.fps
        while self._t0 is not None:
            k = self._frame_number
            await asyncio.sleep(max(0.0, self._t0 + k * period - loop.time()))
            if self._t0 is None:
                return
            stop_after = self.faults.stop_after_frame
            if stop_after is not None and k > stop_after:
                await asyncio.Event().wait()
            self._frame_number += 1
            if k in self.faults.drop_frames:
                continue
            t = loop.time()
            yield await self.render_frame_async(k, t)

    def render_frame(self, frame_number: int, time_s: float) -> DepthFrame:
        """The frame exposed at event-loop time time_s (beam angle from the angle source)."""
        angle = self.beam_angle_deg(time_s)
        depth = _finish(self._depth_steps(frame_number, angle))
        source = self._streaming_infrared
        picture = None if source is None else self._checked_infrared(source(frame_number, angle))
        return self._frame(frame_number, time_s, depth, picture)

    async def render_frame_async(self, frame_number: int, time_s: float) -> DepthFrame:
        """:meth:`render_frame`, giving the event loop a turn between steps of the ray casting (a
        whole frame held a loop that also serves the console for 30-90 ms) and rendering the
        infrared picture (one call) in the executor. The angle is taken before the first step;
        the frame is the same."""
        angle = self.beam_angle_deg(time_s)
        steps = self._depth_steps(frame_number, angle)
        while True:
            try:
                next(steps)
            except StopIteration as done:
                depth = done.value
                break
            await asyncio.sleep(0)
        picture = None
        source = self._streaming_infrared
        if source is not None:
            raw = await asyncio.get_running_loop().run_in_executor(None, source, frame_number, angle)
            picture = self._checked_infrared(raw)
        return self._frame(frame_number, time_s, depth, picture)

    def _depth_steps(self, frame_number: int, angle_deg: float) -> Generator[None, None, np.ndarray]:
        m = self.model
        if frame_number in self.faults.empty_frames:
            return np.zeros((m.height_px, m.width_px), dtype=np.uint16)
        pose = depth_camera_pose(self.camera, math.radians(angle_deg))
        return (yield from self.renderer.render_steps(pose, self._rng))

    def _frame(self, frame_number: int, time_s: float, depth: np.ndarray, infrared: np.ndarray | None) -> DepthFrame:
        m = self.model
        return DepthFrame(
            camera_id=self.id,
            frame_number=frame_number,
            timestamp_s=time_s,
            device_timestamp_ms=frame_number * 1000.0 / m.fps,
            depth=depth,
            depth_unit_mm=m.depth_unit_mm,
            intrinsics=m.intrinsic_matrix,
            infrared=infrared,
        )

    def _checked_infrared(self, picture: np.ndarray) -> np.ndarray:
        """The infrared source's picture if it is (H, W) uint8 at the model's resolution, else ValueError."""
        image = np.asarray(picture)
        wanted = (self.model.height_px, self.model.width_px)
        if image.shape != wanted or image.dtype != np.uint8:
            raise ValueError(f"depth camera {self.id}: the infrared source gave a {image.shape} {image.dtype} "
                             f"image, not {wanted} uint8")
        return image


class DepthTwin(Protocol):
    """How the simulated rig makes a depth camera kind's twin: the rig camera, its model, the scene
    it sees, the beam's angle over time, a seed and (for calibration) its infrared pictures."""

    def __call__(self, camera: DepthCameraConfig, model: DepthCameraModel, subject: DepthScene,
                 beam_angle_deg: Callable[[float], float], *, seed: int,
                 infrared_source: Callable[[int, float], np.ndarray] | None) -> DepthCamera: ...


DEPTH_TWINS: dict[str, DepthTwin] = {"realsense": SimulatedDepthCamera}
"""Depth camera kind (drivers/depth/kinds.py) -> its twin, which the simulated rig streams from
(``SimOptions.depth_kind``). The ``recording`` kind plays a file: its twin is the recording
:func:`record_sweep` writes of a simulated sweep (the loopback rig plays those)."""


def sweep_frame_times(rig: Rig) -> np.ndarray:
    """(F,) float seconds from the sweep start: 30 fps-style frame times of a constant-speed sweep."""
    s, m = rig.depth_sweep, rig.depth_camera_model
    duration = (s.end_deg - s.start_deg) / s.speed_deg_s
    return np.arange(int(math.floor(duration * m.fps + 1e-9)) + 1) / m.fps


def simulate_sweep(
    body: trimesh.Trimesh | DepthScene,
    rig: Rig,
    seed: int = 0,
    noise: bool = True,
    *,
    frame_spacing_deg: float | None = None,
) -> Sweep:
    """A depth sweep at ``depth_sweep.speed_deg_s`` without an event loop (tools and tests).

    Every depth camera renders the frames a constant-speed sweep from start_deg to end_deg would
    produce at the model's fps; with frame_spacing_deg only frames about that many degrees apart are
    rendered (the ones the TSDF would keep), which saves ray casting time.
    """
    s, m = rig.depth_sweep, rig.depth_camera_model
    scene = body if isinstance(body, DepthScene) else DepthScene(body)
    renderer = DepthRenderer(scene, m)
    times = sweep_frame_times(rig)
    trace = BeamTrace(np.array([0.0, times[-1]]), s.start_deg + s.speed_deg_s * np.array([0.0, times[-1]]))
    stride = 1
    if frame_spacing_deg is not None:
        stride = max(1, int(round(frame_spacing_deg * m.fps / s.speed_deg_s)))
    keep = np.unique(np.r_[np.arange(0, len(times), stride), len(times) - 1])
    frames = []
    for i, camera in enumerate(rig.depth_cameras):
        rng = np.random.default_rng([seed, i]) if noise else None
        for k in keep:
            angle = float(trace.angle_at(times[k]))
            pose = depth_camera_pose(camera, math.radians(angle))
            frames.append(
                PosedDepth(
                    camera_id=camera.id,
                    frame_number=int(k),
                    timestamp_s=float(times[k]),
                    beam_angle_deg=angle,
                    depth=renderer.render(pose, rng),
                    depth_unit_mm=m.depth_unit_mm,
                    intrinsics=m.intrinsic_matrix,
                    camera_to_world=pose,
                )
            )
    return Sweep(tuple(frames), trace)


@dataclass(frozen=True)
class RecordedFrame:
    """One frame of a simulated sweep recording: depth (H, W) uint16 in depth units, taken at
    ``device_ms`` on the camera's clock with the beam at ``beam_angle_deg``."""

    frame_number: int
    device_ms: float
    beam_angle_deg: float
    depth: np.ndarray


def sweep_trajectory(rig: Rig) -> Trajectory:
    """The beam during the daemon's depth sweep (deg, s from the move's start): at rest at start_deg,
    then a trapezoid at ``depth_sweep.speed_deg_s`` and the motor's maximum acceleration to end_deg."""
    s, a = rig.depth_sweep, rig.motor.max_acceleration_deg_s2
    return position_move(0.0, s.start_deg, 0.0, s.end_deg, s.speed_deg_s, a, a)


def record_sweep_frames(
    scene: DepthScene,
    rig: Rig,
    camera: DepthCameraConfig,
    model: DepthCameraModel,
    *,
    seed: int = 0,
    noise: bool = True,
) -> Iterator[RecordedFrame]:
    """The frames one depth camera streams at ``model.fps`` through the sweep (:func:`sweep_trajectory`),
    from the move's start to the end at rest; frame k is taken k / fps after the start."""
    trajectory = sweep_trajectory(rig)
    renderer = DepthRenderer(scene, model)
    rng = np.random.default_rng(seed) if noise else None
    count = int(math.floor(trajectory.end_time * model.fps + 1e-9)) + 1
    for k in range(count):
        t = k / model.fps
        angle, _speed = trajectory.at(t)
        depth = renderer.render(depth_camera_pose(camera, math.radians(angle)), rng)
        yield RecordedFrame(k, 1000.0 * t, float(angle), depth)


def record_sweep(
    scene: DepthScene,
    rig: Rig,
    model: DepthCameraModel,
    folder: Path,
    *,
    seed: int = 0,
    noise: bool = True,
    camera_ids: Sequence[str] | None = None,
    source: dict[str, Any] | None = None,
) -> list[Path]:
    """Record the sweep of every rig depth camera (or those in camera_ids) into ``folder``:
    ``CAMERA.db3`` (RealSense recording, pyrealsense2's recorder) and ``CAMERA.beam.json`` (the
    beam angle of each frame). Camera i's noise seed is ``seed * 100 + i``; source: provenance
    stored in each beam-angle file. Returns the recordings' paths in rig order."""
    paths = []
    for i, camera in enumerate(rig.depth_cameras):
        if camera_ids is not None and camera.id not in camera_ids:
            continue
        path = Path(folder) / f"{camera.id}.db3"
        rows = []
        with DepthRecorder(path, camera_id=camera.id, width=model.width_px, height=model.height_px,
                           intrinsics=model.intrinsic_matrix, depth_unit_mm=model.depth_unit_mm,
                           fps=model.fps, serial=camera.serial) as recorder:
            for frame in record_sweep_frames(scene, rig, camera, model, seed=seed * 100 + i, noise=noise):
                recorder.write(frame.frame_number, frame.device_ms, frame.depth)
                rows.append((frame.frame_number, frame.device_ms, frame.beam_angle_deg))
        provenance = {**(source or {}), "simulated": True, "noise_seed": seed * 100 + i if noise else None,
                      "rig_digest": rig.digest, "fps": model.fps, "width_px": model.width_px,
                      "height_px": model.height_px, "depth_sweep": dataclasses.asdict(rig.depth_sweep)}
        write_beam_angles(beam_angles_path(path), camera.id, path, rows, provenance)
        paths.append(path)
        log.info("depth_sim.recorded", camera=camera.id, path=str(path), frames=len(rows))
    return paths
