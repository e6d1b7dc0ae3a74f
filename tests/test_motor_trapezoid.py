"""The simulated drive's analytic trapezoids: continuous, within limits, ending where asked."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.sim.trapezoid import Trajectory, hold, position_move, velocity_ramp

pos = st.floats(-1e6, 1e6)
vel = st.floats(-5e4, 5e4)
rate = st.floats(1.0, 1e5)


def _check_continuous(traj: Trajectory) -> None:
    for before, after in zip(traj.segments, traj.segments[1:]):
        assert after.t0 >= before.t0
        p, v = before.at(after.t0)
        # Rounding of the segment start times (t up to ~1e6 s) scales with t * |v| and t * |a|.
        slack = (
            1e-14
            * abs(after.t0)
            * (abs(before.v0) + abs(before.a) * abs(after.t0 - before.t0) + abs(before.a))
        )
        assert p == pytest.approx(after.p0, abs=1e-6 * max(1.0, abs(p)) + slack * abs(after.t0))
        assert v == pytest.approx(
            after.v0, abs=1e-6 * max(1.0, abs(v)) + 1e-14 * abs(after.t0) * abs(before.a)
        )


@given(pos, vel, pos, st.floats(1.0, 5e4), rate, rate)
def test_position_move_ends_at_rest_on_target(
    p0: float, v0: float, target: float, speed: float, acc: float, dec: float
) -> None:
    traj = position_move(2.0, p0, v0, target, speed, acc, dec)
    _check_continuous(traj)
    assert traj.at(traj.end_time) == (target, 0.0)
    assert traj.at(traj.end_time + 100.0) == (target, 0.0)
    for segment in traj.segments:
        assert abs(segment.a) in (0.0, acc, dec)
    # After any initial braking the speed never exceeds the cruise limit.
    for segment in traj.segments[1:]:
        assert abs(segment.v0) <= max(speed, abs(v0)) * (1 + 1e-9)


@given(pos, vel, vel, rate, rate)
def test_velocity_ramp_settles_at_target(p0: float, v0: float, target: float, acc: float, dec: float) -> None:
    traj = velocity_ramp(0.0, p0, v0, target, acc, dec)
    _check_continuous(traj)
    _, v_end = traj.at(traj.end_time + 1.0)
    assert v_end == pytest.approx(target, abs=1e-9 * max(1.0, abs(target)))
    expected = abs(target - v0) / acc if v0 * target >= 0 and abs(target) > abs(v0) else None
    if expected is not None:
        assert traj.end_time == pytest.approx(expected, rel=1e-9, abs=1e-12)


def test_trapezoid_timing_by_hand() -> None:
    traj = position_move(0.0, 0.0, 0.0, 100.0, 10.0, 5.0, 5.0)
    assert [s.t0 for s in traj.segments] == [0.0, 2.0, 10.0, 12.0]
    assert traj.at(1.0) == (2.5, 5.0)
    assert traj.at(6.0) == (50.0, 10.0)
    triangle = position_move(0.0, 0.0, 0.0, 10.0, 100.0, 10.0, 10.0)
    assert triangle.end_time == pytest.approx(2.0)
    assert triangle.at(1.0) == pytest.approx((5.0, 10.0))


def test_reversal_brakes_through_zero() -> None:
    traj = velocity_ramp(0.0, 0.0, 5.0, -5.0, 2.0, 4.0)
    assert traj.at(1.25) == pytest.approx((3.125, 0.0))
    assert traj.at(3.75) == pytest.approx((-3.125, -5.0))
    back = position_move(0.0, 0.0, 20.0, 10.0, 10.0, 5.0, 5.0)
    assert max(back.at(t)[0] for t in (3.9, 4.0, 4.1)) == pytest.approx(40.0, abs=0.1)
    assert back.at(back.end_time) == (10.0, 0.0)


def test_hold_and_bad_limits() -> None:
    assert hold(3.0, 7.0).at(10.0) == (7.0, 0.0)
    assert hold(3.0, 7.0).at(0.0) == (7.0, 0.0)
    for bad in (0.0, -1.0, math.nan):
        with pytest.raises(ValueError, match="must be positive"):
            position_move(0.0, 0.0, 0.0, 1.0, bad, 1.0, 1.0)
        with pytest.raises(ValueError, match="must be positive"):
            velocity_ramp(0.0, 0.0, 0.0, 1.0, 1.0, bad)
