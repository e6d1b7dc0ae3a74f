"""The lesion list's coarse body regions (analysis/body_regions.py) on a simulated adult."""

from __future__ import annotations

import numpy as np
import pytest

from analysis.body_regions import REGIONS, BodyFrame


@pytest.fixture(scope="module")
def body() -> np.ndarray:
    from sim.body import generate_body

    return np.asarray(generate_body(seed=0).mesh.vertices, dtype=float)


def test_the_frame_is_the_body_s_height_and_trunk_axis(body):
    frame = BodyFrame.of_vertices(body)
    assert frame.z_min_mm == body[:, 2].min() and frame.z_max_mm == body[:, 2].max()
    trunk = body[(body[:, 2] > 0.6 * frame.z_max_mm) & (body[:, 2] < 0.7 * frame.z_max_mm)]
    assert np.allclose(frame.centre_xy, np.median(trunk[:, :2], axis=0), atol=30.0)


def test_points_fall_in_the_region_their_place_on_the_body_says(body):
    frame = BodyFrame.of_vertices(body)
    cx, cy = frame.centre_xy
    height = frame.z_max_mm - frame.z_min_mm
    z = lambda f: frame.z_min_mm + f * height
    points = [[cx, cy, z(0.95)], [cx + 120, cy, z(0.65)], [cx - 120, cy, z(0.65)], [cx, cy + 0.2 * height, z(0.6)],
              [cx, cy - 0.2 * height, z(0.6)], [cx, cy + 80, z(0.2)], [cx, cy - 80, z(0.2)]]
    assert frame.regions(np.array(points)) == list(REGIONS)


def test_landmarks_of_a_simulated_adult_are_in_their_regions(body):
    """The crown, the chest, the middle of the back, the outermost point of each arm at the elbow's
    height and each foot (the subject faces +x, their left is +y)."""
    frame = BodyFrame.of_vertices(body)
    h = (body[:, 2] - frame.z_min_mm) / (frame.z_max_mm - frame.z_min_mm)
    chest = np.flatnonzero((h > 0.70) & (h < 0.72))
    elbows = np.flatnonzero((h > 0.60) & (h < 0.64))
    feet = np.flatnonzero(h < 0.03)
    landmarks = [int(np.argmax(body[:, 2])), chest[np.argmax(body[chest, 0])], chest[np.argmin(body[chest, 0])],
                 elbows[np.argmax(body[elbows, 1])], elbows[np.argmin(body[elbows, 1])],
                 feet[np.argmax(body[feet, 1])], feet[np.argmin(body[feet, 1])]]
    assert frame.regions(body[landmarks]) == list(REGIONS)
    regions = frame.regions(body)
    assert set(regions) == set(REGIONS) and len(regions) == len(body)
