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
    """Zhang's method on every planar view of one camera; ``guess`` gives the image size and a start.

    The boards' planes all contain the cuboid's vertical axis, close to Sturm and Maybank's
    degenerate set for Zhang's method, and on some cameras the planar fit runs away (an RMS of
    10^13 px was seen on the simulated rig, seed 3). Then the lens is fitted instead to whole
    pictures in the cuboid's frame (its nominal geometry): a picture that sees two faces is a
    non-planar view, which fixes the focal length. The bundle adjustment refines either."""
    objects, images = planar_views(detections, target)
    if len(objects) < MIN_VIEWS:
        raise IntrinsicsError(camera, f"{len(objects)} board views with >= 6 corners; need {MIN_VIEWS}")
    fit = _zhang(camera, objects, images, guess)
    if _plausible(fit, guess):
        return fit
    views = [d for d in detections if len(d.corner_ids) >= 6]
    whole = _zhang(camera, [target.corners[d.corner_ids].astype(np.float32) for d in views],
                   [d.points_px.astype(np.float32) for d in views], guess)
    if _plausible(whole, guess):
        return whole
    raise IntrinsicsError(camera, f"focal length {fit.intrinsics.fx:.1f} px (RMS {fit.rms_px:.3g} px) is far from the "
                                  f"rig's {guess.fx:.1f} px, also fitted on whole pictures ({whole.intrinsics.fx:.1f} px)")


MAX_LENS_RMS_PX = 3.0
"""A lens fit whose corners reproject worse than this (RMS) has not converged."""


def _plausible(fit: LensFit, guess: Intrinsics) -> bool:
    k = fit.intrinsics
    return bool(np.isfinite(fit.rms_px) and fit.rms_px <= MAX_LENS_RMS_PX and 0.5 < k.fx / guess.fx < 2.0
                and 0.5 < k.fy / guess.fy < 2.0 and 0 <= k.cx <= guess.width_px and 0 <= k.cy <= guess.height_px)


def _zhang(camera: str, objects: list[np.ndarray], images: list[np.ndarray], guess: Intrinsics) -> LensFit:
    import cv2

    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K3
    rms, k, dist, _, _ = cv2.calibrateCamera(
        objects, images, (guess.width_px, guess.height_px), guess.matrix.copy(), np.zeros(5), flags=flags,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10))
    dist = np.asarray(dist, dtype=float).ravel()[:5]
    lens = Intrinsics(guess.width_px, guess.height_px, float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]),
                      tuple(float(v) for v in dist))  # type: ignore[arg-type]
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
