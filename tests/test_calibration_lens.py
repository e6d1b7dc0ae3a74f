"""The lens fit: Zhang's method on the boards, and its fallback when the planar fit runs away."""

from __future__ import annotations

import math

import numpy as np
import pytest

from planner.calibration import intrinsics
from planner.calibration.detect import Detection
from planner.calibration.geometry import invert
from planner.calibration.intrinsics import IntrinsicsError, LensFit, calibrate_lens
from planner.calibration.model import Intrinsics
from planner.calibration.target import load_target

TARGET = load_target()
LENS = Intrinsics(768, 1024, 871.0, 872.0, 380.0, 518.0, (0.03, -0.01, 0.0, 0.0, 0.0))
GUESS = Intrinsics(768, 1024, 869.4, 869.4, 383.5, 511.5)


def _views() -> list[Detection]:
    """The cuboid seen from 450 mm at several turns (two faces in most pictures), through LENS."""
    import cv2

    views = []
    for i, turn in enumerate(np.radians(np.arange(-40.0, 41.0, 10.0))):
        # camera on a circle around the cuboid, looking at its axis 900 mm up, tilted a little
        centre = np.array([450.0 * math.cos(turn), 450.0 * math.sin(turn), 950.0])
        forward = np.array([0.0, 0.0, 900.0]) - centre
        forward /= np.linalg.norm(forward)
        down = np.array([0.0, 0.0, -1.0])
        right = np.cross(down, forward)
        right /= np.linalg.norm(right)
        pose = np.eye(4)
        pose[:3, :3] = np.c_[right, np.cross(forward, right), forward]
        pose[:3, 3] = centre
        cam = invert(pose)
        pts = TARGET.corners @ cam[:3, :3].T + cam[:3, 3]
        ids = np.flatnonzero(pts[:, 2] > 50.0)
        u, v = pts[ids, 0] / pts[ids, 2] * LENS.fx + LENS.cx, pts[ids, 1] / pts[ids, 2] * LENS.fy + LENS.cy
        ids = ids[(u > 0) & (u < 768) & (v > 0) & (v < 1024)]  # in the field of view (before distortion)
        img, _ = cv2.projectPoints(pts[ids], np.zeros(3), np.zeros(3), LENS.matrix, LENS.dist)
        img = img.reshape(-1, 2)
        # what the camera sees: in the picture, on a face turned towards it
        faces = ids // TARGET.corners_per_face
        normals = np.array([f.cuboid_from_board[:3, 2] for f in TARGET.faces])[faces]
        facing = np.einsum("ij,ij->i", centre - TARGET.corners[ids], -normals) > 0  # board z points inwards
        inside = (img[:, 0] > 0) & (img[:, 0] < 768) & (img[:, 1] > 0) & (img[:, 1] < 1024) & facing
        for face in np.unique(faces[inside]):  # a face counts with 6 corners or more, as detection keeps it
            if np.count_nonzero(inside & (faces == face)) < 6:
                inside &= faces != face
        views.append(Detection(f"v{i}", "cam0", i, ids[inside], img[inside], faces[inside], 10, 500.0, 1, (768, 1024)))
    return views


def test_zhang_recovers_the_lens() -> None:
    fit = calibrate_lens("cam0", _views(), TARGET, GUESS)
    assert abs(fit.intrinsics.fx - LENS.fx) < 2.0 and abs(fit.intrinsics.cy - LENS.cy) < 2.0
    assert fit.rms_px < 0.01


def test_a_runaway_planar_fit_falls_back_to_whole_pictures(monkeypatch: pytest.MonkeyPatch) -> None:
    real = intrinsics._zhang
    calls = []

    def runaway_when_planar(camera, objects, images, guess):  # type: ignore[no-untyped-def]
        calls.append(len(objects))
        fit = real(camera, objects, images, guess)
        if len(calls) == 1:  # the planar fit diverges, as it did on a simulated camera
            return LensFit(camera, Intrinsics(768, 1024, 415.7, -1e11, 1.9e8, 1.4e9), 2.1e13, fit.views)
        return fit

    monkeypatch.setattr(intrinsics, "_zhang", runaway_when_planar)
    fit = calibrate_lens("cam0", _views(), TARGET, GUESS)
    assert len(calls) == 2
    assert abs(fit.intrinsics.fx - LENS.fx) < 2.0 and abs(fit.intrinsics.cx - LENS.cx) < 2.0


def test_a_lens_no_fit_explains_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(intrinsics, "_zhang", lambda camera, objects, images, guess: LensFit(
        camera, Intrinsics(768, 1024, 300.0, 300.0, 380.0, 510.0), 0.2, len(objects)))
    with pytest.raises(IntrinsicsError, match="cam0: focal length 300.0 px .* far from the rig's 869.4 px"):
        calibrate_lens("cam0", _views(), TARGET, GUESS)
