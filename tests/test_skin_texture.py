"""The simulated skin's freckles: fixed to the skin, not to the world, and something to see."""

from __future__ import annotations

import numpy as np
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.sim.phone_render import PhoneRenderer, SubjectScene
from drivers.sim.skin_texture import LAYERS, pigment
from planner.rig import load_rig

coordinate = st.floats(-3000.0, 3000.0, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(coordinate, coordinate, coordinate), min_size=1, max_size=50))
def test_pigment_is_a_darkness_and_depends_only_on_the_skin_point(points):
    points = np.array(points)
    dark = pigment(points)
    assert dark.shape == (len(points),) and np.all((dark >= 0.0) & (dark < 1.0))
    assert np.array_equal(pigment(points[::-1]), dark[::-1])


def test_spots_cover_some_skin_and_have_edges():
    rng = np.random.default_rng(1)
    plane = np.column_stack([rng.uniform(-400, 400, 40_000), rng.uniform(-400, 400, 40_000), np.full(40_000, 13.0)])
    dark = pigment(plane)
    assert 0.03 < np.mean(dark > 0.1) < 0.3  # freckled, not painted over
    assert np.max(dark) > max(layer.darkness[0] for layer in LAYERS)
    assert not np.array_equal(pigment(plane, seed=1), dark)


def _picture(mesh: trimesh.Trimesh, camera_x_mm: float) -> np.ndarray:
    optics = load_rig().optics
    renderer = PhoneRenderer(SubjectScene(mesh), optics, width_px=96, height_px=128)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2] = [1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]  # right, down, forward
    pose[:3, 3] = [camera_x_mm, -400.0, 1000.0]
    return renderer.render(pose, 400.0)


def test_the_freckles_move_with_the_skin():
    """A box moved 37 mm with its skin coordinates, seen from a camera moved the same: the same
    picture. Moved without them (a new skin): other freckles."""
    box = trimesh.creation.box((300.0, 300.0, 300.0))
    box.vertices = np.asarray(box.vertices) + [0.0, 0.0, 1000.0]
    box.vertex_attributes["skin_mm"] = np.asarray(box.vertices).copy()
    moved = box.copy()
    moved.vertices = np.asarray(box.vertices) + [37.0, 0.0, 0.0]
    bare = trimesh.Trimesh(moved.vertices, moved.faces, process=False)
    middle = np.s_[32:96, 24:72]  # the box's face (the floor does not move)
    here = _picture(box, 0.0)[middle].astype(int)
    assert here.std() > 5.0  # spots on the box
    assert np.abs(_picture(moved, 37.0)[middle].astype(int) - here).max() <= 2
    assert np.abs(_picture(bare, 37.0)[middle].astype(int) - here).mean() > 1.0
