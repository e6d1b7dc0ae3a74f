"""Per-camera intrinsics by Zhang's method (cv2.calibrateCamera) and per-picture poses (PnP).

Every (picture, face) with enough corners is one planar view of a board: the textbook input of
Zhang's method. The distortion model is OpenCV's k1, k2, p1, p2 (k3 held at 0: the phones'
and depth cameras' fields of view do not need it, and it trades off against k1/k2 on a sparse
corner set).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from planner.calibration.detect import Detection
from planner.calibration.geometry import invert, transform
from planner.calibration.model import Intrinsics
from planner.calibration.target import CuboidTarget
from planner.picklable import PicklableError

MIN_VIEWS = 4
"""Zhang's method needs several board orientations; fewer planar views than this are refused."""


class IntrinsicsError(PicklableError, ValueError):
    """A camera's pictures do not determine its lens."""

    def __init__(self, camera: str, problem: str) -> None:
        self.camera, self.problem = camera, problem
        super().__init__(f"camera {camera}: {problem}")


@dataclass(frozen=True)
class LensFit:
    """A camera's lens from Zhang's method: intrinsics, RMS reprojection (px), planar views used."""

    camera: str
    intrinsics: Intrinsics
    rms_px: float
    views: int


def planar_views(detections: Sequence[Detection], target: CuboidTarget) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Board-frame object points (N, 3) float32 and image points (N, 2) float32 of every (picture, face)."""
    objects, images = [], []
    for d in detections:
        for face in np.unique(d.faces):
            mine = d.faces == face
            local = d.corner_ids[mine] - face * target.corners_per_face
            objects.append(target.board_corners[local].astype(np.float32))
            images.append(d.points_px[mine].astype(np.float32))
    return objects, images


def calibrate_lens(camera: str, detections: Sequence[Detection], target: CuboidTarget, guess: Intrinsics) -> LensFit:
    """Zhang's method on every planar view of one camera; ``guess`` gives the image size and a start."""
    import cv2

    objects, images = planar_views(detections, target)
    if len(objects) < MIN_VIEWS:
        raise IntrinsicsError(camera, f"{len(objects)} board views with >= 6 corners; need {MIN_VIEWS}")
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K3
    rms, k, dist, _, _ = cv2.calibrateCamera(
        objects, images, (guess.width_px, guess.height_px), guess.matrix.copy(), np.zeros(5), flags=flags,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10))
    dist = np.asarray(dist, dtype=float).ravel()[:5]
    lens = Intrinsics(guess.width_px, guess.height_px, float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]),
                      tuple(float(v) for v in dist))  # type: ignore[arg-type]
    if not (0.5 < lens.fx / guess.fx < 2.0):
        raise IntrinsicsError(camera, f"focal length {lens.fx:.1f} px is far from the rig's {guess.fx:.1f} px")
    return LensFit(camera, lens, float(rms), len(objects))


def picture_pose(detection: Detection, corners: np.ndarray, lens: Intrinsics) -> tuple[np.ndarray, float]:
    """(4, 4) cuboid-from-camera pose of one picture from all its corners (cuboid-frame corners (C, 3)),
    and the RMS reprojection error (px)."""
    import cv2

    obj = corners[detection.corner_ids].astype(np.float64)
    img = detection.points_px.astype(np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, img, lens.matrix, lens.dist, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        raise IntrinsicsError(detection.camera, f"{detection.image}: no pose fits its corners")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, lens.matrix, lens.dist, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, lens.matrix, lens.dist)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))
    camera_from_cuboid = transform(cv2.Rodrigues(rvec)[0], tvec.ravel())
    return invert(camera_from_cuboid), rms
