"""The ChArUco calibration cuboid (``calibration_data/target/cuboid.yaml``): load, validate, geometry.

Cuboid frame: origin at the centre of the bottom face, z up the long axis, mm. Each long face
carries one ChArUco board covering it from outside; a board's own frame is OpenCV's (origin at
the top-left corner of the printed board, x right, y down, z into the cuboid). Chessboard
corners get one id across the whole target: ``face_index * corners_per_face + local id``.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from planner.calibration.model import CalibrationFileError
from planner.rig import CALIBRATION_DIR
from planner.yaml_files import read_yaml

MAX_FILE_BYTES = 1024 * 1024  # the cuboid's file is 2 KB

DEFAULT_TARGET_PATH = CALIBRATION_DIR / "target" / "cuboid.yaml"
_NORMALS = {"+x": (1.0, 0.0, 0.0), "-x": (-1.0, 0.0, 0.0), "+y": (0.0, 1.0, 0.0), "-y": (0.0, -1.0, 0.0)}
_KEYS = {"name", "size_mm", "dictionary", "legacy_pattern", "squares", "square_mm", "marker_mm",
         "print_dpi", "faces"}


class TargetError(CalibrationFileError):
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
        return self.board(face).generateImage((width, height), marginSize=0, borderBits=border_bits)


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
    """Load and validate a target file; TargetError names the file, the key and the allowed values."""
    import cv2

    path = Path(path)
    raw, text = read_yaml(path, max_bytes=MAX_FILE_BYTES, what="target file",
                          error=lambda problem: TargetError(path, "<file>", problem))
    if not isinstance(raw, dict):
        raise TargetError(path, "<top>", f"expected a mapping, got {type(raw).__name__}")
    unknown = sorted(set(raw) - _KEYS)
    if unknown:
        raise TargetError(path, unknown[0], f"unknown key; allowed: {', '.join(sorted(_KEYS))}")
    missing = sorted(_KEYS - set(raw))
    if missing:
        raise TargetError(path, missing[0], "missing")

    def number(key: str, value: Any, low: float, high: float) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
                math.isfinite(value) and low <= value <= high):
            raise TargetError(path, key, f"got {value!r}; expected a number in [{low:g}, {high:g}]")
        return float(value)

    def pair(key: str, value: Any, n: int) -> list[Any]:
        if not isinstance(value, list) or len(value) != n:
            raise TargetError(path, key, f"got {value!r}; expected a list of {n} numbers")
        return value

    size = tuple(number(f"size_mm[{i}]", v, 10.0, 5000.0) for i, v in enumerate(pair("size_mm", raw["size_mm"], 3)))
    squares = tuple(int(number(f"squares[{i}]", v, 3, 200)) for i, v in enumerate(pair("squares", raw["squares"], 2)))
    if any(not float(v).is_integer() for v in raw["squares"]):
        raise TargetError(path, "squares", f"got {raw['squares']!r}; expected whole numbers")
    square = number("square_mm", raw["square_mm"], 1.0, 1000.0)
    marker = number("marker_mm", raw["marker_mm"], 0.5, 1000.0)
    if marker >= square:
        raise TargetError(path, "marker_mm", f"got {marker:g}; must be smaller than square_mm {square:g}")
    dpi = int(number("print_dpi", raw["print_dpi"], 50, 1200))
    dictionary = raw["dictionary"]
    if not (isinstance(dictionary, str) and dictionary.startswith("DICT_") and hasattr(cv2.aruco, dictionary)):
        raise TargetError(path, "dictionary", f"got {dictionary!r}; expected an OpenCV predefined "
                          "ArUco dictionary such as DICT_5X5_1000")
    if not isinstance(raw["legacy_pattern"], bool):
        raise TargetError(path, "legacy_pattern", f"got {raw['legacy_pattern']!r}; expected true or false")
    if not isinstance(raw["name"], str) or not raw["name"]:
        raise TargetError(path, "name", f"got {raw['name']!r}; expected a non-empty string")
    board_w, board_h = squares[0] * square, squares[1] * square
    faces_raw = raw["faces"]
    if not isinstance(faces_raw, list) or not 1 <= len(faces_raw) <= 4:
        raise TargetError(path, "faces", f"got {faces_raw!r}; expected a list of 1 to 4 faces")
    n_markers = squares[0] * squares[1] // 2
    dictionary_size = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)).bytesList.shape[0]
    faces: list[Face] = []
    used: list[tuple[int, int, str]] = []
    for i, f in enumerate(faces_raw):
        key = f"faces[{i}]"
        if not isinstance(f, dict) or set(f) != {"name", "first_marker_id"}:
            raise TargetError(path, key, f"got {f!r}; expected {{name, first_marker_id}}")
        if f["name"] not in _NORMALS:
            raise TargetError(path, f"{key}.name", f"got {f['name']!r}; expected one of {sorted(_NORMALS)}")
        first = int(number(f"{key}.first_marker_id", f["first_marker_id"], 0, dictionary_size - n_markers))
        for lo, hi, other in used:
            if first < hi and lo < first + n_markers:
                raise TargetError(path, f"{key}.first_marker_id", f"ids {first}..{first + n_markers - 1} "
                                  f"overlap face {other}'s {lo}..{hi - 1}; ids must be unique across faces")
            if other == f["name"]:
                raise TargetError(path, f"{key}.name", f"face {other} appears twice")
        used.append((first, first + n_markers, f["name"]))
        width = abs(np.cross([0.0, 0.0, 1.0], _NORMALS[f["name"]]) @ np.array([size[0], size[1], 0.0]))
        if board_w > width + 1e-6 or board_h > size[2] + 1e-6:
            raise TargetError(path, "squares", f"board {board_w:g} x {board_h:g} mm does not fit face "
                              f"{f['name']} ({width:g} x {size[2]:g} mm)")
        faces.append(_face(i, f["name"], first, size, board_w, board_h))  # type: ignore[arg-type]
    return CuboidTarget(
        path=str(path), digest=hashlib.sha256(text).hexdigest(), name=raw["name"], size_mm=size,  # type: ignore[arg-type]
        dictionary=dictionary, legacy_pattern=raw["legacy_pattern"], squares=squares,  # type: ignore[arg-type]
        square_mm=square, marker_mm=marker, print_dpi=dpi, faces=tuple(faces))
