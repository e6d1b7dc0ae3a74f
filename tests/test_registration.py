"""The local fits that carry a mark: a step is kept only as far as the skin around holds it."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from analysis.registration import MarkCarrier, held_step


def _moved(transform: np.ndarray, point: np.ndarray) -> np.ndarray:
    return transform[:3, :3] @ point + transform[:3, 3]


def _translation(shift: tuple[float, float, float]) -> np.ndarray:
    out = np.eye(4)
    out[:3, 3] = shift
    return out


def _cylinder_patch(radius_mm: float, half_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points and outward normals of a cylinder (axis z through the origin) within about
    ``half_mm`` of the mark at (radius, 0, 0), and the mark."""
    angle, height = np.meshgrid(np.linspace(-half_mm / radius_mm, half_mm / radius_mm, 41),
                                np.linspace(-half_mm, half_mm, 41))
    normals = np.stack([np.cos(angle), np.sin(angle), np.zeros_like(angle)], axis=-1).reshape(-1, 3)
    points = normals * radius_mm + np.stack([0 * angle, 0 * angle, height], axis=-1).reshape(-1, 3)
    return points, normals, np.array([radius_mm, 0.0, 0.0])


@settings(max_examples=60, deadline=None)
@given(st.floats(60.0, 300.0), st.floats(-80.0, 80.0), st.floats(-5.0, 5.0))
def test_a_step_along_a_cylinders_axis_is_not_kept_a_step_off_its_skin_is(radius_mm, along_mm, off_mm):
    points, normals, mark = _cylinder_patch(radius_mm, 150.0)
    held = held_step(np.eye(4), _translation((off_mm, 0.0, along_mm)), mark, points, normals, 150.0,
                     MarkCarrier.HOLD_SHARE)
    step = _moved(held, mark) - mark
    assert abs(step[2]) < 1e-6 + 1e-3 * abs(along_mm), step  # nothing on a cylinder holds the mark along its axis
    assert abs(step[0] - off_mm) < 1e-6 + 1e-3 * abs(off_mm), step  # its skin holds it across


def _rotation(vector: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(vector).as_matrix()
    return out


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.lists(st.floats(-0.2, 0.2), min_size=3, max_size=3),
       st.lists(st.floats(-30.0, 30.0), min_size=3, max_size=3))
def test_a_step_the_patch_holds_every_way_is_kept_whole_and_no_step_stays_none(seed, turn, shift):
    """A patch whose normals point every way (a knobbly bit of skin) holds every direction: the
    fit's step is kept as it is, wherever the fit started from."""
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(400, 3)) * 60.0
    normals = rng.normal(size=(400, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    before = _rotation(rng.normal(size=3) * 0.3) @ _translation(tuple(rng.normal(size=3) * 40.0))
    after = _translation(tuple(shift)) @ _rotation(np.array(turn)) @ before
    mark = points[0]
    assert np.allclose(held_step(before, after, mark, points, normals, 150.0, MarkCarrier.HOLD_SHARE), after, atol=1e-6)
    assert np.allclose(held_step(before, before, mark, points, normals, 150.0, MarkCarrier.HOLD_SHARE), before, atol=1e-9)


def test_a_mark_in_a_groove_round_a_scanned_capsule_stays_in_it_and_is_in_doubt(web_store):
    """The capsule's scan again as a later visit whose surface is a centimetre too deep in a ring
    groove round the capsule: the local fits on its nearly cylindrical skin could slide the mark
    along the axis to skin the groove missed, 70 mm away and not in doubt. The mark stays in the
    groove and is in doubt; a mark elsewhere stays put and is not."""
    from analysis.scan_views import open_scan
    from tests.test_web import folder_of
    from tests.test_web_browser import front_vertex
    from tests.web_visits import dented

    scan_dir = web_store / folder_of(web_store)
    mesh = open_scan(scan_dir).mesh()
    v = np.asarray(mesh.vertices, dtype=float)
    front = v[front_vertex(scan_dir)]
    back = v[np.argmin(np.linalg.norm(v - (front * [-1.0, 1.0, 1.0] + [0.0, 0.0, 450.0]), axis=1))]
    later = dented(mesh, back, 40.0, 10.0, ring=True)
    carried = MarkCarrier(mesh, later).carry(np.array([front, back]))
    assert carried.in_doubt.tolist() == [False, True], (carried.surface_gap_mm, carried.fit_rmse_mm)
    assert np.linalg.norm(carried.points_mm[0] - front) < 1.0, carried.points_mm
    assert abs(carried.points_mm[1, 2] - back[2]) < 40.0, (carried.points_mm, back)
