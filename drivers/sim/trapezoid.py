"""Analytic trapezoidal motion for the simulated drive: piecewise constant acceleration.

A :class:`Trajectory` is evaluated at any time in O(segments), so the simulated drive can report
its position at each TPDO without integrating at a servo rate, and virtual time stays cheap.
Units are the caller's (the drive uses encoder counts, counts/s, counts/s^2; time in s).
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Segment:
    """Constant acceleration from ``t0``: p(t) = p0 + v0 dt + a dt^2 / 2."""

    t0: float
    p0: float
    v0: float
    a: float

    def at(self, t: float) -> tuple[float, float]:
        dt = t - self.t0
        return self.p0 + self.v0 * dt + 0.5 * self.a * dt * dt, self.v0 + self.a * dt


@dataclass(frozen=True)
class Trajectory:
    """Segments in time order; the last one lasts for ever (a = 0 once the profile is done).

    Attributes:
        end_time: when the last segment starts (the target is reached / speed settled), s.
    """

    segments: tuple[Segment, ...]

    @property
    def end_time(self) -> float:
        return self.segments[-1].t0

    def at(self, t: float) -> tuple[float, float]:
        """(position, velocity) at time t (clamped to the start)."""
        current = self.segments[0]
        for segment in self.segments[1:]:
            if segment.t0 > t:
                break
            current = segment
        return current.at(max(t, current.t0))


def hold(t0: float, p0: float) -> Trajectory:
    """Standing still at p0."""
    return Trajectory((Segment(t0, p0, 0.0, 0.0),))


class _Builder:
    def __init__(self, t0: float, p0: float, v0: float) -> None:
        self.segments: list[Segment] = []
        self.t, self.p, self.v = t0, p0, v0

    def ramp(self, v_to: float, rate: float) -> None:
        """Change speed to v_to at |acceleration| rate."""
        if v_to == self.v:
            return
        a = math.copysign(rate, v_to - self.v)
        duration = (v_to - self.v) / a
        self.segments.append(Segment(self.t, self.p, self.v, a))
        self.p += (self.v + v_to) / 2 * duration
        self.t += duration
        self.v = v_to

    def cruise(self, distance: float) -> None:
        if distance <= 0 or self.v == 0:
            return
        self.segments.append(Segment(self.t, self.p, self.v, 0.0))
        self.t += distance / abs(self.v)
        self.p += math.copysign(distance, self.v)

    def finish(self, p_exact: float | None = None) -> Trajectory:
        p = self.p if p_exact is None else p_exact
        self.segments.append(Segment(self.t, p, self.v, 0.0))
        return Trajectory(tuple(self.segments))


def _check(*rates: float) -> None:
    for rate in rates:
        if not rate > 0:
            raise ValueError(f"acceleration and speed limits must be positive, got {rate!r}")


def velocity_ramp(
    t0: float, p0: float, v0: float, v_target: float, acceleration: float, deceleration: float
) -> Trajectory:
    """Profile velocity mode: reach v_target (speeding up at ``acceleration``, slowing down at
    ``deceleration``, through zero when the direction reverses), then keep it."""
    _check(acceleration, deceleration)
    b = _Builder(t0, p0, v0)
    if v0 != 0 and (v_target == 0 or math.copysign(1, v0) != math.copysign(1, v_target)):
        b.ramp(0.0, deceleration)
    b.ramp(v_target, acceleration if abs(v_target) > abs(b.v) else deceleration)
    return b.finish()


def position_move(
    t0: float, p0: float, v0: float, p_target: float, speed: float, acceleration: float, deceleration: float
) -> Trajectory:
    """Profile position mode: a trapezoid (or triangle) from (p0, v0) to rest at p_target, cruising
    at most at ``speed``. A start moving away from the target, or too fast to stop in time, first
    brakes to rest."""
    _check(speed, acceleration, deceleration)
    b = _Builder(t0, p0, v0)
    distance = p_target - b.p
    if b.v != 0 and (
        distance == 0
        or math.copysign(1, b.v) != math.copysign(1, distance)
        or b.v**2 / (2 * deceleration) > abs(distance)
    ):
        b.ramp(0.0, deceleration)
        distance = p_target - b.p
    if distance == 0:
        return b.finish(p_target)
    direction = math.copysign(1, distance)
    span, u0 = abs(distance), abs(b.v)
    if u0 > speed:
        peak = speed
        b.ramp(direction * peak, deceleration)
    else:
        # Highest speed from which accelerating from u0 then braking covers exactly the span.
        triangle = math.sqrt(
            (span + u0**2 / (2 * acceleration)) / (1 / (2 * acceleration) + 1 / (2 * deceleration))
        )
        peak = min(speed, triangle)
        b.ramp(direction * peak, acceleration)
    b.cruise(abs(p_target - b.p) - peak**2 / (2 * deceleration))
    b.ramp(0.0, deceleration)
    return b.finish(p_target)
