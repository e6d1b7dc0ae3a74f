"""The tracker's encoder trace (daemon/rig/beam.py TraceBuffer): bounded, numbered rows, exact lookups."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from daemon.rig.beam import TraceBuffer


def _filled(n: int, capacity: int) -> TraceBuffer:
    trace = TraceBuffer(capacity)
    for i in range(n):
        trace.append(0.005 * i, 0.1 * i, 20.0 + i)
    return trace


@given(n=st.integers(1, 3000), capacity=st.integers(2, 700), start=st.integers(0, 3200))
@settings(max_examples=60, deadline=None)
def test_rows_are_numbered_from_the_start_and_bounded(n: int, capacity: int, start: int) -> None:
    trace = _filled(n, capacity)
    assert trace.end == n
    assert n - trace.first <= capacity
    rows = trace.rows(start)
    expected = np.arange(max(start, trace.first), n)
    np.testing.assert_array_equal(rows[:, 1], 0.1 * expected)
    np.testing.assert_array_equal(rows[:, 2], 20.0 + expected)


@given(n=st.integers(1, 2000), capacity=st.integers(2, 500),
       times=st.lists(st.floats(-1.0, 12.0), min_size=1, max_size=20))
@settings(max_examples=60, deadline=None)
def test_interpolation_matches_the_whole_kept_trace(n: int, capacity: int, times: list[float]) -> None:
    trace = _filled(n, capacity)
    kept = trace.rows()
    t = np.array(times)
    np.testing.assert_allclose(trace.interpolate(t, 1), np.interp(t, kept[:, 0], kept[:, 1]))
    for one in times[:3]:
        assert trace.interpolate(one, 2) == pytest.approx(float(np.interp(one, kept[:, 0], kept[:, 2])))


def test_a_service_running_for_a_day_keeps_a_bounded_trace() -> None:
    trace = TraceBuffer(1024)
    for i in range(200 * 60):  # a minute at 200 Hz stands in for the day: the bound is what counts
        trace.append(0.005 * i, 0.0, 0.0)
    assert trace.end == 12000
    assert len(trace.rows()) <= 1024
    assert trace.rows(trace.end - 10).shape == (10, 3)


def test_an_empty_trace_and_a_silly_capacity_are_refused() -> None:
    with pytest.raises(ValueError, match="empty"):
        TraceBuffer().interpolate(1.0, 1)
    with pytest.raises(ValueError, match="capacity"):
        TraceBuffer(1)
