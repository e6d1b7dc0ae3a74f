"""Shared fixtures of the depth and TSDF tests: a low-resolution rig and analytic subjects."""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import numpy as np
import trimesh

from planner.rig import Rig, load_rig


def small_rig(scale: int = 4, **tsdf: float) -> Rig:
    """The default rig with the depth images scaled down by ``scale`` (fast ray casting)."""
    rig = load_rig()
    m = rig.depth_camera_model
    model = dataclasses.replace(
        m,
        width_px=m.width_px // scale,
        height_px=m.height_px // scale,
        fx_px=m.fx_px / scale,
        fy_px=m.fy_px / scale,
        cx_px=m.cx_px / scale,
        cy_px=m.cy_px / scale,
    )
    return dataclasses.replace(rig, depth_camera_model=model, tsdf=dataclasses.replace(rig.tsdf, **tsdf))


def sphere(radius: float = 200.0, centre: tuple[float, float, float] = (0.0, 0.0, 1000.0)) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=5, radius=radius).apply_translation(centre)


def cylinder(radius: float = 150.0, height: float = 1700.0, bottom: float = 0.0) -> trimesh.Trimesh:
    """A standing cylinder (vertical axis on the rotation axis)."""
    mesh = trimesh.creation.cylinder(radius=radius, height=height, sections=128)
    return mesh.apply_translation([0.0, 0.0, bottom + height / 2])


@functools.cache
def cylinder_sweep(scale: int = 2) -> tuple[Any, ...]:
    """The posed frames of the standing cylinder (radius 150 mm, 1.7 m) swept by
    ``small_rig(scale)`` about every 9 deg (seed 0, with noise), in rig order: ray cast once per
    process for the fusion tests. Their arrays are read-only, so no test changes another's."""
    from drivers.sim.depth import simulate_sweep

    frames = simulate_sweep(cylinder(150.0, 1700.0), small_rig(scale=scale), seed=0, noise=True,
                            frame_spacing_deg=9.0).frames
    for frame in frames:
        for array in (frame.depth, frame.intrinsics, frame.camera_to_world):
            array.setflags(write=False)
    return tuple(frames)


def wall(distance: float, size: float = 4000.0) -> trimesh.Trimesh:
    """A thin box whose face at x = -distance faces +x (towards a camera at the origin looking -x)."""
    box = trimesh.creation.box(extents=[10.0, size, size])
    return box.apply_translation([-distance - 5.0, 0.0, 0.0])


def look_minus_x(origin: tuple[float, float, float] = (0.0, 0.0, 0.0), yaw_deg: float = 0.0) -> np.ndarray:
    """(4, 4) camera-to-world: camera at origin looking along -x (turned by yaw about z), image down = -z."""
    yaw = np.radians(yaw_deg)
    forward = np.array([-np.cos(yaw), -np.sin(yaw), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    right = np.cross(down, forward)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, down, forward, origin
    return m
