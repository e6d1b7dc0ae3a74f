"""Depth of field, focus intervals and resolution of the phone camera (SPEC 2)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from planner.optics import depth_of_field, focus_interval, in_depth_of_field, resolution_mm_per_px
from planner.rig import load_rig

H, F = 5720.0, 6.0


def test_depth_of_field_hand_computed() -> None:
    near, far = depth_of_field(np.array([450.0, 1000.0]), H, F)
    # near(450) = 450 * 5714 / (5720 + 450 - 12) = 2571300 / 6158
    assert near[0] == pytest.approx(2571300 / 6158)
    assert far[0] == pytest.approx(450 * 5714 / 5270)
    assert near[1] == pytest.approx(1000 * 5714 / 6708)
    assert far[1] == pytest.approx(1000 * 5714 / 4720)
    assert near[0] == pytest.approx(417.55, abs=0.01)
    assert far[0] == pytest.approx(487.91, abs=0.01)


def test_far_limit_is_infinite_at_and_beyond_hyperfocal() -> None:
    near, far = depth_of_field(np.array([H, 2 * H]), H, F)
    assert np.all(np.isinf(far))
    assert near[0] == pytest.approx(H * (H - F) / (2 * H - 2 * F))


def test_focus_interval_upper_end_infinite_for_far_depths() -> None:
    lo, hi = focus_interval(np.array([H - F, 10_000.0]), H, F)
    assert np.all(np.isinf(hi))
    assert np.all(lo < H)


@given(
    z=st.floats(min_value=50.0, max_value=20_000.0),
    s=st.floats(min_value=50.0, max_value=20_000.0),
)
def test_interval_agrees_with_near_far(z: float, s: float) -> None:
    lo, hi = focus_interval(z, H, F)
    near, far = depth_of_field(s, H, F)
    inside = bool(lo <= s <= hi)
    sharp = bool(near <= z <= far)
    if inside != sharp:
        # Only float rounding exactly at a boundary may disagree.
        assert min(abs(s - lo), abs(s - hi) if math.isfinite(hi) else 1.0) < 1e-9 * s + 1e-9
    assert bool(in_depth_of_field(z, s, H, F)) == inside


def test_resolution_matches_spec() -> None:
    optics = load_rig().optics
    # SPEC 2: z * 2 tan(HFOV/2) / 6144; 0.075 mm/px at about 521 mm.
    expected = 500.0 * 2 * math.tan(math.radians(47.66 / 2)) / 6144
    assert resolution_mm_per_px(500.0, optics) == pytest.approx(expected)
    assert resolution_mm_per_px(521.5, optics) == pytest.approx(0.075, abs=1e-4)
