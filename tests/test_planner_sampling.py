"""Area-uniform surface samples with inward normals."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from planner.focus_errors import EmptyMesh
from planner.sampling import SurfaceSamples, Triangles, sample_surface
from tests.planner_standin import sphere


def test_samples_are_area_uniform_and_seeded() -> None:
    # Two triangles, areas 0.5 and 1.5 mm^2.
    mesh = trimesh.Trimesh(
        [[0, 0, 0], [1, 0, 0], [0, 1, 0], [10, 0, 0], [13, 0, 0], [10, 1, 0]],
        [[0, 1, 2], [3, 4, 5]],
        process=False,
    )
    samples = sample_surface(mesh, 20_000, seed=1)
    share = (samples.face_index == 1).mean()
    assert share == pytest.approx(0.75, abs=0.015)
    np.testing.assert_array_equal(samples.points, sample_surface(mesh, 20_000, seed=1).points)
    assert not np.array_equal(samples.points, sample_surface(mesh, 20_000, seed=2).points)
    assert samples.area_mm2 == pytest.approx(2.0)


def test_points_lie_on_the_surface_with_inward_normals() -> None:
    ball = sphere(100.0, (0.0, 0.0, 0.0))
    samples = sample_surface(ball, 2000, seed=0)
    radius = np.linalg.norm(samples.points, axis=1)
    assert np.all(radius <= 100.0 + 1e-9) and np.all(radius > 98.0)  # on the facets
    inward = np.einsum("ij,ij->i", samples.normals, -samples.points / radius[:, None])
    assert np.all(inward > 0.95)


def test_bad_requests_are_refused() -> None:
    with pytest.raises(ValueError, match="sample count must be positive, got 0"):
        sample_surface(sphere(), 0)
    with pytest.raises(EmptyMesh, match="0 faces, surface area 0"):
        sample_surface(trimesh.Trimesh(), 10)
    with pytest.raises(ValueError, match="2 points but 1 normals"):
        SurfaceSamples.from_arrays(np.zeros((2, 3)), np.ones((1, 3)))
    with pytest.raises(ValueError, match="zero length"):
        SurfaceSamples.from_arrays(np.zeros((1, 3)), np.zeros((1, 3)))


def test_triangles_give_areas_and_the_signed_volume() -> None:
    ball = sphere(100.0, (0.0, 0.0, 0.0))
    triangles = Triangles.of(ball)
    np.testing.assert_allclose(triangles.doubled_areas, 2.0 * ball.area_faces, rtol=1e-12)
    assert triangles.signed_volume_mm3 == pytest.approx(ball.volume, rel=1e-9)
    inverted = trimesh.Trimesh(ball.vertices, ball.faces[:, ::-1], process=False)
    assert Triangles.of(inverted).signed_volume_mm3 == pytest.approx(-ball.volume, rel=1e-9)
    given = sample_surface(ball, 500, seed=4, triangles=triangles)
    np.testing.assert_array_equal(given.points, sample_surface(ball, 500, seed=4).points)
