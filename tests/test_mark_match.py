"""Matching the skin's pictures between scans: the correlation, the tangent frame, the vote."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from analysis import mark_match
from analysis.mark_match import _consensus, _peak, ncc_map, tangent_frame


def _speckle(seed: int, size: int) -> np.ndarray:
    from scipy.ndimage import gaussian_filter

    return gaussian_filter(np.random.default_rng(seed).normal(0.0, 30.0, (size, size)), 1.5)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10_000), st.integers(0, 16), st.integers(0, 16), st.floats(0.3, 3.0), st.floats(-50, 50))
def test_a_piece_of_the_search_is_found_where_it_was_cut(seed, row, col, gain, offset):
    search = _speckle(seed, 41)
    template = gain * search[row:row + 25, col:col + 25] + offset  # other exposure, same skin
    scores = ncc_map(template, search)
    assert scores.shape == (17, 17)
    assert np.unravel_index(np.argmax(scores), scores.shape) == (row, col)
    assert scores[row, col] == pytest.approx(1.0, abs=1e-6)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000), st.integers(0, 16), st.integers(0, 16))
def test_unknown_pixels_are_left_out_not_matched(seed, row, col):
    search = _speckle(seed, 41)
    template = search[row:row + 25, col:col + 25].copy()
    template[:8, :] = np.nan  # hidden behind a fold
    holed = search.copy()
    holed[36:, 36:] = np.nan  # outside the picture
    scores = ncc_map(template, holed)
    assert np.unravel_index(np.argmax(scores), scores.shape) == (row, col)
    assert np.all(scores <= 1.0) and np.all(scores >= -1.0)
    assert ncc_map(np.full((25, 25), np.nan), search).max() == -1.0  # nothing known: no score


def test_the_peak_is_found_between_samples():
    rows, cols = np.indices((17, 17))
    scores = 1.0 - 0.01 * ((rows - 7.3) ** 2 + (cols - 9.6) ** 2)
    row, col, best, runner_up = _peak(scores)
    assert row == pytest.approx(7.3, abs=0.05) and col == pytest.approx(9.6, abs=0.05)
    assert runner_up < best


@settings(max_examples=100, deadline=None)
@given(st.tuples(*[st.floats(-1, 1, allow_nan=False)] * 3).filter(lambda v: np.linalg.norm(v) > 0.1))
def test_the_tangent_frame_is_orthonormal_and_level_where_it_can_be(normal):
    n = np.array(normal) / np.linalg.norm(normal)
    e1, e2 = tangent_frame(n)
    assert np.allclose([e1 @ e1, e2 @ e2], 1.0) and np.allclose([e1 @ e2, e1 @ n, e2 @ n], 0.0, atol=1e-9)
    assert np.allclose(np.cross(e1, e2), n)
    if abs(n[2]) < 0.99:
        assert abs(e1[2]) < 1e-9  # across the vertical, so both scans agree on it


def test_the_pictures_must_agree():
    sure, weak = mark_match.SURE_SCORE, mark_match.MIN_SCORE
    assert _consensus([]) is None
    assert _consensus([(1.0, 2.0, weak + 0.05, 0.1)]) is None  # one weak picture says nothing
    assert _consensus([(1.0, 2.0, sure + 0.05, mark_match.SURE_MARGIN + 0.05)])[:2] == (1.0, 2.0)
    a, b, _ = _consensus([(1.0, 2.0, 0.6, 0.1), (1.4, 2.0, 0.6, 0.1), (-6.0, 4.0, 0.5, 0.1)])
    assert (a, b) == pytest.approx((1.2, 2.0))
    assert _consensus([(1.0, 2.0, 0.6, 0.1), (-6.0, 4.0, 0.55, 0.1)]) is None


def test_pictures_are_decoded_no_finer_than_needed_and_a_bad_one_is_skipped(tmp_path):
    from PIL import Image

    from analysis.mark_match import _grey

    big = tmp_path / "big.jpg"
    Image.fromarray(np.random.default_rng(0).integers(0, 255, (1600, 1200, 3), dtype=np.uint8)).save(big)
    assert _grey(big, 1200).shape == (1600, 1200)
    assert _grey(big, 280).shape == (400, 300)  # the JPEG's 1/4 scale: the smallest at least 280 wide
    broken = tmp_path / "broken.jpg"
    broken.write_bytes(big.read_bytes()[:100])
    assert _grey(broken, 1200) is None
    assert _grey(tmp_path / "gone.jpg", 1200) is None


@pytest.mark.slow
def test_marks_between_two_simulated_visits_move_onto_the_same_skin(tmp_path):
    """Two scans of one simulated adult (new seed, swayed, standing elsewhere): where the
    pictures place a carried mark, it lands within 5 mm of the same skin point, never more than
    3 mm further than the shapes put it, and closer on the whole. (The scanned meshes are off
    the skin by up to a few mm, and "the same skin point" with them: a millimetre or two either
    way is not a wrong match.)"""
    from tests.web_visits import carry_errors, two_visits

    carried = carry_errors(two_visits(tmp_path, person_seed=5), count=40)
    error, shape = carried["error_mm"], carried["shape_error_mm"]
    matched = np.isfinite(carried["picture_score"])
    assert matched.mean() >= 0.25, carried["picture_score"]
    assert np.all(error[matched] <= np.minimum(shape[matched] + 3.0, 5.0)), np.column_stack([shape, error])[matched]
    assert np.array_equal(error[~matched], shape[~matched])
    assert np.median(error[matched]) < np.median(shape[matched])
