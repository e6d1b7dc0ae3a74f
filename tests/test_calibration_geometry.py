"""Transforms of the calibration: Umeyama similarity, pose distance, the calibration file round trip."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from planner.calibration.geometry import from_rotvec, invert, pose_error, umeyama
from planner.calibration.model import CalibrationFileError, load_calibration

finite = st.floats(-500, 500, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(0.2, 5.0), st.lists(finite, min_size=3, max_size=3))
def test_umeyama_recovers_a_similarity(seed: int, scale: float, t: list[float]) -> None:
    rng = np.random.default_rng(seed)
    src = rng.normal(0, 300, (12, 3))
    rot = Rotation.random(random_state=seed).as_matrix()
    dst = scale * src @ rot.T + np.array(t)
    s, r, tr = umeyama(src, dst)
    assert s == pytest.approx(scale, rel=1e-9)
    assert np.allclose(r, rot, atol=1e-9) and np.allclose(tr, t, atol=1e-6)


def test_umeyama_refuses_too_few_points() -> None:
    with pytest.raises(ValueError, match="N >= 3"):
        umeyama(np.zeros((2, 3)), np.zeros((2, 3)))


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-1, 1), min_size=3, max_size=3), st.lists(finite, min_size=3, max_size=3))
def test_pose_error_measures_a_known_offset(rotvec: list[float], t: list[float]) -> None:
    a = from_rotvec(np.array(rotvec), np.array(t))
    delta = from_rotvec(np.array([0.0, 0.0, math.radians(0.3)]), np.zeros(3))
    b = a @ delta
    b[:3, 3] += [2.0, 0.0, 0.0]
    mm, deg = pose_error(a, b)
    assert mm == pytest.approx(2.0, abs=1e-9) and deg == pytest.approx(0.3, abs=1e-6)
    assert np.allclose(invert(a) @ a, np.eye(4), atol=1e-12)


def test_calibration_file_round_trip_and_errors(tmp_path: Path) -> None:
    from planner.calibration.target import load_target
    from planner.rig import load_rig
    from sim.calibration import true_rig

    rig = load_rig()
    truth = true_rig(rig, load_target(), seed=3)
    loaded = truth.save(tmp_path / "c.yaml")
    assert len(loaded.digest) == 64
    for cam in ("cam0", "cam6", "depth2"):
        for angle in (-40.0, 0.0, 100.0, 312.0):
            mm, deg = pose_error(truth.world_from_camera(cam, angle), loaded.world_from_camera(cam, angle))
            assert mm < 1e-6 and deg < 1e-5  # acos resolves ~1e-6 deg near 0
    raw = yaml.safe_load((tmp_path / "c.yaml").read_text())
    raw["cameras"][2]["intrinsics"]["fx"] = -3
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(raw))
    with pytest.raises(CalibrationFileError, match=r"cameras\[2\]\.intrinsics\.fx"):
        load_calibration(tmp_path / "bad.yaml")


def test_beam_pose_between_captures_interpolates_the_wobble_around_the_turn() -> None:
    from planner.calibration.target import load_target
    from planner.rig import load_rig
    from sim.calibration import true_rig

    truth = true_rig(load_rig(), load_target(), seed=4)
    b = truth.beam[5]
    assert np.allclose(truth.world_from_beam(b.encoder_deg)[:3, :3],
                       (from_rotvec(np.array([0, 0, math.radians(b.encoder_deg)]), np.zeros(3)) @ b.wobble())[:3, :3])
    # across the gap between the last capture (312 deg) and the first (-40 deg = 320 deg)
    m = truth.world_from_beam(316.0)
    first, last = truth.beam[0].wobble(), truth.beam[-1].wobble()
    wob = from_rotvec(np.array([0, 0, -math.radians(316.0)]), np.zeros(3)) @ m
    w = (316.0 - truth.beam[-1].encoder_deg) / (truth.beam[0].encoder_deg + 360.0 - truth.beam[-1].encoder_deg)
    assert np.allclose(wob[:3, 3], (1 - w) * last[:3, 3] + w * first[:3, 3], atol=1e-9)


def test_a_calibration_file_larger_than_any_rig_needs_is_refused(tmp_path):
    from planner.calibration.model import MAX_FILE_BYTES, CalibrationFileError, load_calibration

    big = tmp_path / "calibration.yaml"
    with open(big, "wb") as f:
        f.truncate(MAX_FILE_BYTES + 1)
    with pytest.raises(CalibrationFileError, match="larger than"):
        load_calibration(big)
