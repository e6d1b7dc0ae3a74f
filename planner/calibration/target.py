"""The ChArUco calibration cuboid (``calibration_data/target/cuboid.yaml``): load, validate, geometry.

Cuboid frame: origin at the centre of the bottom face, z up the long axis, mm. Each long face
carries one ChArUco board covering it from outside; a board's own frame is OpenCV's (origin at
the top-left corner of the printed board, x right, y down, z into the cuboid). Chessboard
corners get one id across the whole target: ``face_index * corners_per_face + local id``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from planner.rig import CALIBRATION_DIR
from planner.schema import ConfigError, show
from planner.schema.tables import TARGET_FILE

MAX_FILE_BYTES = TARGET_FILE.max_bytes  # the cuboid's file is 2 KB

DEFAULT_TARGET_PATH = CALIBRATION_DIR / "target" / "cuboid.yaml"
_NORMALS = {"+x": (1.0, 0.0, 0.0), "-x": (-1.0, 0.0, 0.0), "+y": (0.0, 1.0, 0.0), "-y": (0.0, -1.0, 0.0)}


class TargetError(ConfigError):
    """A target file is unreadable or a key is missing, unknown or out of range."""


@dataclass(frozen=True)
class Face:
    """One board on the cuboid: its outward normal and the rigid map board frame -> cuboid frame.

    cuboid_from_board: (4, 4) float, mm.
    """

    index: int
    name: str
    first_marker_id: int
    normal: np.ndarray
    cuboid_from_board: np.ndarray


@dataclass(frozen=True)
class CuboidTarget:
    """The validated target: board layout shared by the faces, one :class:`Face` per board."""

    path: str
    digest: str
    name: str
    size_mm: tuple[float, float, float]
    dictionary: str
    legacy_pattern: bool
    squares: tuple[int, int]
    square_mm: float
    marker_mm: float
    print_dpi: int
    faces: tuple[Face, ...]
    _boards: dict[int, Any] = field(default_factory=dict, repr=False, compare=False)

    def __getstate__(self) -> dict[str, Any]:
        """Pickle without the OpenCV boards (rebuilt on use): the target goes to worker processes."""
        state = dict(self.__dict__)
        state["_boards"] = {}
        return state

    @property
    def markers_per_face(self) -> int:
        return self.squares[0] * self.squares[1] // 2

    @property
    def corners_per_face(self) -> int:
        return (self.squares[0] - 1) * (self.squares[1] - 1)

    @property
    def n_corners(self) -> int:
        return self.corners_per_face * len(self.faces)

    def aruco_dictionary(self) -> Any:
        import cv2

        return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))

    def board(self, face: int) -> Any:
        """The OpenCV ``CharucoBoard`` of one face (its own marker ids, legacy flag set explicitly)."""
        if face not in self._boards:
            import cv2

            first = self.faces[face].first_marker_id
            ids = np.arange(first, first + self.markers_per_face, dtype=np.int32)
            board = cv2.aruco.CharucoBoard(self.squares, self.square_mm, self.marker_mm,
                                           self.aruco_dictionary(), ids)
            board.setLegacyPattern(self.legacy_pattern)
            self._boards[face] = board
        return self._boards[face]

    @cached_property
    def board_corners(self) -> np.ndarray:
        """(corners_per_face, 3) float chessboard corners in the board frame (z = 0), mm."""
        return np.asarray(self.board(0).getChessboardCorners(), dtype=float)

    @cached_property
    def corners(self) -> np.ndarray:
        """(n_corners, 3) float every chessboard corner in the cuboid frame, by global corner id."""
        local = np.c_[self.board_corners, np.ones(len(self.board_corners))]
        return np.concatenate([(local @ f.cuboid_from_board.T)[:, :3] for f in self.faces])

    def face_of_marker(self, marker_ids: np.ndarray) -> np.ndarray:
        """(M,) int face index of each marker id, -1 for ids that are not on this target."""
        marker_ids = np.asarray(marker_ids, dtype=int)
        out = np.full(marker_ids.shape, -1)
        for f in self.faces:
            out[(marker_ids >= f.first_marker_id) & (marker_ids < f.first_marker_id + self.markers_per_face)] = f.index
        return out

    def board_image(self, face: int, px_per_mm: float, border_bits: int = 1) -> np.ndarray:
        """(H, W) uint8 picture of one face's board, px_per_mm pixels per millimetre, no margin."""
        width = int(round(self.squares[0] * self.square_mm * px_per_mm))
        height = int(round(self.squares[1] * self.square_mm * px_per_mm))
        result: np.ndarray = self.board(face).generateImage((width, height), marginSize=0, borderBits=border_bits)
        return result


def _face(index: int, name: str, first_id: int, size: tuple[float, float, float],
          board_w: float, board_h: float) -> Face:
    n = np.array(_NORMALS[name])
    up = np.array([0.0, 0.0, 1.0])
    right = np.cross(up, n)  # a viewer outside, looking along -n with z up, has this on the right
    half_depth = abs(n @ np.array([size[0], size[1], 0.0])) / 2
    # The board is centred on the face and its top edge meets the top of the cuboid.
    origin = half_depth * n - board_w / 2 * right + size[2] * up
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, -up, -n, origin
    return Face(index, name, first_id, n, m)


def load_target(path: Path | str = DEFAULT_TARGET_PATH) -> CuboidTarget:
    """Load and validate a target file (its table: planner/schema/tables.py); TargetError names the
    file, the key and the allowed values."""
    import cv2

    v, digest = TARGET_FILE.load(path, TargetError)
    path = str(path)
    size, squares, square, marker = tuple(v["size_mm"]), tuple(v["squares"]), v["square_mm"], v["marker_mm"]
    if marker >= square:
        raise TargetError(path, "marker_mm", f"got {marker:g}; must be smaller than square_mm {square:g}")
    dictionary = v["dictionary"]
    if not hasattr(cv2.aruco, dictionary):
        raise TargetError(path, "dictionary", f"got {show(dictionary)}; expected "
                          f"{TARGET_FILE.table.fields['dictionary'].form()}")
    board_w, board_h = squares[0] * square, squares[1] * square
    n_markers = squares[0] * squares[1] // 2
    dictionary_size = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)).bytesList.shape[0]
    faces: list[Face] = []
    used: list[tuple[int, int, str]] = []
    for i, f in enumerate(v["faces"]):
        key = f"faces[{i}]"
        first, name = f["first_marker_id"], f["name"]
        if first > dictionary_size - n_markers:
            raise TargetError(path, f"{key}.first_marker_id", f"got {first}; expected an integer in "
                              f"[0, {dictionary_size - n_markers}] ({n_markers} markers of {dictionary})")
        for lo, hi, other in used:
            if first < hi and lo < first + n_markers:
                raise TargetError(path, f"{key}.first_marker_id", f"ids {first}..{first + n_markers - 1} "
                                  f"overlap face {other}'s {lo}..{hi - 1}; ids must be unique across faces")
            if other == name:
                raise TargetError(path, f"{key}.name", f"face {other} appears twice")
        used.append((first, first + n_markers, name))
        width = abs(np.cross([0.0, 0.0, 1.0], _NORMALS[name]) @ np.array([size[0], size[1], 0.0]))
        if board_w > width + 1e-6 or board_h > size[2] + 1e-6:
            raise TargetError(path, "squares", f"board {board_w:g} x {board_h:g} mm does not fit face "
                              f"{name} ({width:g} x {size[2]:g} mm)")
        faces.append(_face(i, name, first, size, board_w, board_h))
    return CuboidTarget(
        path=path, digest=digest, name=v["name"], size_mm=size, dictionary=dictionary,
        legacy_pattern=v["legacy_pattern"], squares=squares, square_mm=square, marker_mm=marker,
        print_dpi=v["print_dpi"], faces=tuple(faces))
