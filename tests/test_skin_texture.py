"""The simulated skin's freckles: fixed to the skin, not to the world, and something to see."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.sim.phone_render import PhoneRenderer, SubjectScene
from drivers.sim.skin_texture import (
    EDGE_MM,
    LAYERS,
    NAEVI,
    ChangedSpots,
    LesionChanges,
    LesionChangesError,
    changed_spots,
    pigment,
)
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


def _plane(count: int = 60_000, half_mm: float = 600.0, seed: int = 2) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-half_mm, half_mm, count), rng.uniform(-half_mm, half_mm, count),
                            np.full(count, 13.0)])


def _plane_changes(changes: LesionChanges, half_mm: float = 600.0) -> ChangedSpots:
    """The changed spots of the cells the plane z = 13 mm passes through."""
    side = NAEVI.cell_mm
    i = np.arange(np.floor(-half_mm / side), np.ceil(half_mm / side))
    cells = np.stack(np.meshgrid(i, i, [np.floor(13.0 / side)], indexing="ij"), axis=-1).reshape(-1, 3)
    _, spots = changed_spots(cells.astype(np.int64), changes)
    return spots


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(coordinate, coordinate, coordinate), min_size=1, max_size=50), st.integers(0, 2**40))
def test_without_lesion_changes_the_skin_is_as_it_is(points, change_seed):
    points = np.array(points)
    dark = pigment(points)
    assert np.array_equal(pigment(points, changes=None), dark)
    assert np.array_equal(pigment(points, changes=LesionChanges(change_seed, grown_share=0.0, appeared_share=0.0)),
                          dark)
    changed = pigment(points, changes=LesionChanges(change_seed))
    assert np.all((changed >= dark) & (changed < 1.0))  # changes only darken


def test_grown_spots_are_larger_and_darker_and_the_rest_of_the_skin_is_untouched():
    changes = LesionChanges(11)
    spots = _plane_changes(changes)
    grown = spots.rows(~spots.appeared)
    assert len(grown) >= 20
    assert np.all(grown.radius_after_mm >= grown.radius_before_mm + LesionChanges.GROW_AT_LEAST_MM)
    assert np.all(grown.darkness_after > grown.darkness_before)
    centre = grown.centre_mm
    assert np.all(pigment(centre, changes=changes) > pigment(centre) + 0.1)
    # a ring between the old edge and the new one: bare skin before, pigment after
    ring = grown.radius_before_mm + EDGE_MM + 0.5 * (grown.radius_after_mm - grown.radius_before_mm - 2 * EDGE_MM)
    beside = centre + np.column_stack([ring, np.zeros_like(ring), np.zeros_like(ring)])
    assert np.all(pigment(beside, changes=changes) > pigment(beside) + 0.2)
    # everywhere out of reach of a changed spot, the same darkness to the bit
    plane = _plane()
    reach = np.linalg.norm(plane[:, None, :] - spots.centre_mm[None], axis=2) - spots.radius_after_mm - EDGE_MM
    far = reach.min(axis=1) > 0.0
    assert far.mean() > 0.9
    assert np.array_equal(pigment(plane[far], changes=changes), pigment(plane[far]))
    assert not np.array_equal(pigment(plane[~far], changes=changes), pigment(plane[~far]))


def test_appeared_spots_are_dark_where_no_spot_was():
    changes = LesionChanges(11)
    spots = _plane_changes(changes)
    new = spots.rows(spots.appeared)
    assert len(new) >= 5
    before, after = pigment(new.centre_mm), pigment(new.centre_mm, changes=changes)
    assert np.all(before < max(layer.darkness[1] for layer in LAYERS[1:]) + 1e-6)  # at most a faint patch
    assert np.all(after >= 1.0 - (1.0 - before) * (1.0 - new.darkness_after) - 1e-6)
    assert np.all(after > before + 0.3)


def test_the_same_seed_makes_the_same_changes_and_another_seed_others():
    first, again, other = (_plane_changes(LesionChanges(seed)) for seed in (4, 4, 5))
    assert np.array_equal(first.centre_mm, again.centre_mm)
    assert np.array_equal(first.radius_after_mm, again.radius_after_mm)
    assert not np.array_equal(first.centre_mm[:, :2].round(), other.centre_mm[:, :2].round())
    plane = _plane(20_000)
    assert np.array_equal(pigment(plane, changes=LesionChanges(4)), pigment(plane, changes=LesionChanges(4)))


@pytest.mark.parametrize(("field", "value"), [("seed", -1), ("seed", 1.5), ("grown_share", 1.5),
                                              ("appeared_share", float("nan")), ("growth", 0.5),
                                              ("darkening", "dark")])
def test_lesion_changes_out_of_range_are_refused_naming_the_value(field, value):
    arguments = {"seed": 1, field: value}
    with pytest.raises(LesionChangesError) as caught:
        LesionChanges(**arguments)
    assert caught.value.field == field and repr(value) in str(caught.value)


def test_the_changes_listed_on_a_body_are_on_its_skin_and_in_its_pictures():
    """changed_lesions() lists the spots on a box's skin; a picture of the box at the follow-up
    visit (the scene the simulated phones render) is darker at them and the same elsewhere."""
    from sim.lesions import changed_lesions

    box = trimesh.creation.box((300.0, 300.0, 300.0))
    box.vertices = np.asarray(box.vertices) + [0.0, 0.0, 1000.0]
    changes = LesionChanges(3, grown_share=0.5, appeared_share=0.2)
    listed = changed_lesions(box, changes)
    assert len(listed) > 0 and listed.appeared.any() and not listed.appeared.all()
    on_face = np.abs(np.abs(listed.centre_mm - [0.0, 0.0, 1000.0]) - 150.0).min(axis=1)
    assert np.all(on_face < listed.radius_after_mm)
    optics = load_rig().optics
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2] = [1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]
    pose[:3, 3] = [0.0, -400.0, 1000.0]
    before = PhoneRenderer(SubjectScene(box), optics, 96, 128).render(pose, 400.0).astype(int)
    after = PhoneRenderer(SubjectScene(box, changes), optics, 96, 128).render(pose, 400.0).astype(int)
    assert np.all(after <= before + 1) and (before - after).max() > 30
