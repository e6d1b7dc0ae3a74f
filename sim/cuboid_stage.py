"""The simulated rig as built, with the calibration cuboid in place of a subject: what each simulated
camera sees during the daemon's calibration rotation.

The phones photograph the cuboid (drivers/sim/cuboid_render.py) through their true lenses from their
true poses at the drive's physical angle (the truth: sim/calibration.py), focused where their lens
really is sharp; the depth cameras' infrared imagers do the same through the lens they report, and
their depth frames ray-cast the cuboid. The daemon knows none of this: it drives the simulators over
CAN and ADB exactly as it drives a rig.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import trimesh

from planner.calibration.model import Calibration
from planner.calibration.target import CuboidTarget
from planner.rig import DepthCameraModel, Rig


class CuboidStage:
    """The cuboid where the truth puts it, and each camera's view of it (cameras built on first use)."""

    def __init__(self, rig: Rig, target: CuboidTarget, truth: Calibration, *, seed: int = 0,
                 texture_px_per_mm: float = 4.0) -> None:
        from drivers.sim.cuboid_render import CuboidScene

        self.rig, self.target, self.truth, self.seed = rig, target, truth, seed
        self.scene = CuboidScene(target, truth.world_from_cuboid, truth.cuboid_from_boards,
                                 texture_px_per_mm=texture_px_per_mm)

    def mesh(self) -> trimesh.Trimesh:
        """The cuboid as a mesh in the world (mm), for the depth cameras' ray casting."""
        sx, sy, sz = self.target.size_mm
        box = trimesh.creation.box(extents=(sx, sy, sz))
        box.apply_translation((0.0, 0.0, sz / 2))
        box.apply_transform(self.truth.world_from_cuboid)
        return box

    def pose(self, camera_id: str, beam_angle_deg: Callable[..., float]) -> Callable[[float], np.ndarray]:
        """time -> the camera's true (4, 4) camera-to-world pose at the beam's physical angle."""
        return lambda _t=0.0: self.truth.world_from_camera(camera_id, beam_angle_deg())

    def phone_picture(self, camera_id: str) -> Callable[[np.ndarray | None, float, np.random.Generator], np.ndarray]:
        """A simulated phone's picture source: the cuboid through its true lens, sharp where it focuses."""
        from drivers.sim.cuboid_render import CuboidCamera

        camera: list[CuboidCamera] = []

        def picture(pose: np.ndarray | None, sharp_mm: float, rng: np.random.Generator) -> np.ndarray:
            if pose is None:
                raise ValueError(f"phone {camera_id}: the cuboid stage needs the phone's pose")
            if not camera:
                camera.append(CuboidCamera(self.scene, self.truth.camera(camera_id).intrinsics,
                                           optics=self.rig.optics, psf_sigma_px=0.6, noise_sigma=2.0))
            return camera[0].render(pose, rng, focus_mm=sharp_mm)

        return picture

    def infrared(self, camera_id: str, model: DepthCameraModel) -> Callable[[int, float], np.ndarray]:
        """A simulated depth camera's infrared source at ``model``'s resolution: frame number and
        beam angle (deg) -> (H, W) uint8, the cuboid through the lens the camera reports (a depth
        camera's infrared imager is rectified and calibrated in the factory: its frames carry it)."""
        from drivers.sim.cuboid_render import CuboidCamera
        from planner.calibration.model import Intrinsics

        lens = Intrinsics(model.width_px, model.height_px, model.fx_px, model.fy_px, model.cx_px, model.cy_px)
        index = [c.id for c in self.truth.cameras].index(camera_id)
        camera: list[CuboidCamera] = []

        def picture(frame_number: int, beam_angle_deg: float) -> np.ndarray:
            if not camera:
                camera.append(CuboidCamera(self.scene, lens, psf_sigma_px=0.8, noise_sigma=3.0))
            rng = np.random.default_rng([self.seed, index, frame_number, 0x1F2A])
            return camera[0].render(self.truth.world_from_camera(camera_id, beam_angle_deg), rng)

        return picture
