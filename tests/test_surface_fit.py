"""The stored surface moved onto the depth frames: onto the skin, and only where frames see it."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import trimesh

from drivers.sim.depth import simulate_sweep
from planner.surface_fit import BAND_MM, MIN_VIEWS, fit_to_frames, normal_offsets, vertex_normals
from tests.depth_helpers import small_rig, sphere

CENTRE = np.array([0.0, 0.0, 1000.0])


@functools.cache
def _sweep(scale: int, noise: bool) -> tuple:
    """The 200 mm sphere swept by the rig's depth cameras at 1/scale of their resolution."""
    return tuple(simulate_sweep(sphere(200.0, centre=tuple(CENTRE)), small_rig(scale=scale), seed=0, noise=noise,
                                frame_spacing_deg=9.0).frames)


def _off(vertices: np.ndarray) -> np.ndarray:
    return np.linalg.norm(vertices - CENTRE, axis=1) - 200.0


def _placed(radius: float) -> trimesh.Trimesh:
    """The sphere's surface as a fusion might place it: ``radius`` instead of 200 mm."""
    return trimesh.creation.icosphere(subdivisions=4, radius=radius).apply_translation(CENTRE)


def _fitted(radius: float, frames: tuple) -> tuple[np.ndarray, np.ndarray]:
    """|distance from the sphere| (V,) of the surface placed at ``radius`` after the fit, and which
    vertices enough frames measured."""
    surface = _placed(radius)
    _, views = normal_offsets(np.asarray(surface.vertices), vertex_normals(surface.vertices, surface.faces), frames)
    return np.abs(_off(fit_to_frames(surface.vertices, surface.faces, frames))), views >= MIN_VIEWS


def test_a_surface_placed_off_the_skin_moves_onto_it():
    """A surface 1.5 mm outside the sphere and one 1.5 mm inside both land on it wherever the
    noise-free sweep measured them (its depth in 1 mm units)."""
    for start in (201.5, 198.5):
        off, measured = _fitted(start, _sweep(2, False))
        assert measured.mean() > 0.85
        assert np.median(off[measured]) < 0.1 and np.percentile(off[measured], 90) < 0.2, \
            np.percentile(off[measured], [50, 90])


@pytest.mark.slow
def test_with_the_cameras_depth_noise_the_surface_lands_within_a_fraction_of_a_millimetre():
    """The rig's depth cameras at full resolution, with their depth noise (ray casting the sweep
    takes about 25 s)."""
    for start in (201.5, 198.5):
        off, measured = _fitted(start, _sweep(1, True))
        assert np.median(off[measured]) < 0.15 and np.percentile(off[measured], 90) < 0.4, \
            np.percentile(off[measured], [50, 90])


def test_a_vertex_no_frame_measures_and_skin_beyond_the_band_stay_put():
    """The sphere's underside faces the floor, which no camera sees from below; and a surface
    further off the skin than BAND_MM is another surface as far as the frames can tell."""
    surface = _placed(200.0)
    moved = fit_to_frames(surface.vertices, surface.faces, _sweep(2, False))
    below = np.flatnonzero(vertex_normals(surface.vertices, surface.faces)[:, 2] < -0.99)
    assert len(below) and np.array_equal(moved[below], surface.vertices[below])
    far = _placed(200.0 + BAND_MM + 1.0)
    assert np.array_equal(fit_to_frames(far.vertices, far.faces, _sweep(2, False)), far.vertices)
