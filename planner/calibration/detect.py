"""ChArUco corner detection on calibration pictures (OpenCV's ArucoDetector + CharucoDetector).

Markers are found once per picture with the target's dictionary; the markers of each face go
to that face's ``CharucoDetector``, which interpolates the chessboard corners between them and
refines them to subpixel accuracy. Large pictures (a phone's 8192 x 6144) are decoded at 1/2,
1/4 or 1/8 by the JPEG decoder itself (DCT scaling, several times faster than a full decode) so
the long side is at most ``max_side_px``; corners come back in full-resolution pixels.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from planner.calibration.target import CuboidTarget

MIN_CORNERS_PER_FACE = 6
"""A face contributes to an image only with at least this many corners (a homography and some)."""


@dataclass(frozen=True)
class Detection:
    """The target's corners found in one picture.

    corner_ids: (K,) int global corner ids; points_px: (K, 2) float pixel positions (full
    resolution, OpenCV convention: pixel centres at integers); faces: (K,) int face of each.
    markers: markers decoded; sharpness: variance of the Laplacian (blur shows as a low value);
    scale: decode factor used (1, 2, 4 or 8); size_px: (width, height) of the full picture.
    """

    image: str
    camera: str
    angle_index: int
    corner_ids: np.ndarray
    points_px: np.ndarray
    faces: np.ndarray
    markers: int
    sharpness: float
    scale: int
    size_px: tuple[int, int]
    problem: str | None = None

    @property
    def n_corners(self) -> int:
        return len(self.corner_ids)


def _reduced_flag(cv2: Any, factor: int) -> int:
    result: int = {1: cv2.IMREAD_GRAYSCALE, 2: cv2.IMREAD_REDUCED_GRAYSCALE_2, 4: cv2.IMREAD_REDUCED_GRAYSCALE_4,
            8: cv2.IMREAD_REDUCED_GRAYSCALE_8}[factor]
    return result


def picture_size(path: Path) -> tuple[int, int]:
    """(width, height) of a JPEG or PNG from its header, without decoding the pixels."""
    from PIL import Image

    with Image.open(path) as im:
        return im.size


def load_grey(path: Path, max_side_px: int) -> tuple[np.ndarray, int, tuple[int, int]]:
    """The picture in grey at the smallest decode factor that brings its long side to max_side_px."""
    import cv2

    size = picture_size(path)
    factor = 1
    while max(size) / factor > max_side_px and factor < 8:
        factor *= 2
    grey = cv2.imread(str(path), _reduced_flag(cv2, factor))
    if grey is None:
        raise OSError(f"{path}: cannot decode the picture")
    return grey, factor, size


class CorneredTarget:
    """Detectors for one target (build once, use for every picture)."""

    def __init__(self, target: CuboidTarget) -> None:
        import cv2

        self.target = target
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE  # chessboard corners are refined instead
        self.markers = cv2.aruco.ArucoDetector(target.aruco_dictionary(), params)
        charuco = cv2.aruco.CharucoParameters()
        charuco.minMarkers = 2  # a corner counts only between two of its own markers
        self.boards = [cv2.aruco.CharucoDetector(target.board(f.index), charuco, params) for f in target.faces]

    def detect(self, grey: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """(K,) global corner ids, (K, 2) pixel positions in this image, (K,) faces, markers decoded."""
        corners, ids, _rejected = self.markers.detectMarkers(grey)
        if ids is None or len(ids) == 0:
            return np.zeros(0, int), np.zeros((0, 2)), np.zeros(0, int), 0
        ids = ids.ravel()
        face_of = self.target.face_of_marker(ids)
        out_ids, out_pts, out_faces = [], [], []
        for face in self.target.faces:
            mine = np.flatnonzero(face_of == face.index)
            if len(mine) < 2:
                continue
            ch_corners, ch_ids, _, _ = self.boards[face.index].detectBoard(
                grey, markerCorners=tuple(corners[int(i)] for i in mine), markerIds=ids[mine].reshape(-1, 1))
            if ch_ids is None or len(ch_ids) < MIN_CORNERS_PER_FACE:
                continue
            out_ids.append(ch_ids.ravel() + face.index * self.target.corners_per_face)
            out_pts.append(ch_corners.reshape(-1, 2).astype(float))
            out_faces.append(np.full(len(ch_ids), face.index))
        markers = int(np.count_nonzero(face_of >= 0))
        if not out_ids:
            return np.zeros(0, int), np.zeros((0, 2)), np.zeros(0, int), markers
        return np.concatenate(out_ids), np.concatenate(out_pts), np.concatenate(out_faces), markers


def sharpness(grey: np.ndarray) -> float:
    """Variance of the Laplacian: a sharp picture of the board scores high, a blurred one low."""
    import cv2

    return float(cv2.Laplacian(grey, cv2.CV_32F).var())


def detect_picture(detector: CorneredTarget, path: Path, camera: str, angle_index: int, name: str,
                   *, max_side_px: int = 2600) -> Detection:
    """Detect the target's corners in one picture file (no exception for a picture without the target)."""
    try:
        grey, factor, size = load_grey(path, max_side_px)
    except OSError as exc:
        return Detection(name, camera, angle_index, np.zeros(0, int), np.zeros((0, 2)), np.zeros(0, int), 0, 0.0,
                         1, (0, 0), problem=f"unreadable: {exc}")
    ids, pts, faces, markers = detector.detect(grey)
    if factor > 1:
        pts = (pts + 0.5) * factor - 0.5
    return Detection(name, camera, angle_index, ids, pts, faces, markers, sharpness(grey), factor, size)
