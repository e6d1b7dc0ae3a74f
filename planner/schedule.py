"""The capture rotation on one time axis: the dual-speed motion profile and the capture schedule.

The beam starts at rest, runs up to the first sector's speed, crosses every sector at its
speed and runs out to rest after the last one. Speed changes sit in the slower of the two
sectors at a boundary (a deceleration starts at the boundary, an acceleration ends at it),
so the speed never dips below the sector profile: every capture in a fast sector sees the
full speed, every capture in a slow sector is taken at the slow speed, and a capture inside
a ramp is refused. Angles are beam degrees (continuous, unwrapped); times are seconds from
the start of the run-up (``t = 0``, beam at rest at :attr:`MotionProfile.start_deg`).

:func:`compile_plan` turns a focus plan into per-angle capture events (crossing time, and
for each camera when its focus may be sent, when its lens must be still, when to trigger)
and refuses an infeasible plan with a :class:`PlanInfeasible` that lists every offending
angle and value. Pure computation: no asyncio, no devices.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from planner.picklable import PicklableError
from planner.rig import Capture, Rig


class TimelineError(PicklableError, ValueError):
    """Base of the timeline errors."""


class ProfileError(TimelineError):
    """The rig's capture sectors cannot be driven as a dual-speed profile (a ramp hits a capture)."""


class OutsideProfile(TimelineError):
    """An angle lies outside the profile's rotation."""

    def __init__(self, angle_deg: float, start_deg: float, end_deg: float) -> None:
        self.angle_deg = angle_deg
        self.start_deg = start_deg
        self.end_deg = end_deg
        super().__init__(
            f"beam angle {angle_deg:.4f} deg is outside the capture rotation "
            f"[{start_deg:.4f}, {end_deg:.4f}] deg"
        )


@dataclass(frozen=True)
class Violation:
    """One reason a plan cannot be executed.

    kind: "focus_missing" | "focus_range" | "cycle" | "lens_settle" | "motion_blur" | "ramp" |
    "order".
    camera_index is -1 when the problem concerns every camera at that angle.
    """

    kind: str
    angle_index: int
    angle_deg: float
    camera_index: int
    value: float
    limit: float
    unit: str

    def describe(self) -> str:
        who = "all cameras" if self.camera_index < 0 else f"camera {self.camera_index}"
        words = {
            "focus_missing": "focus is not a finite positive distance",
            "focus_range": "focus outside the phone's focus range",
            "cycle": "time between captures shorter than the phone's capture cycle",
            "lens_settle": "lens cannot settle between the previous capture and this trigger",
            "motion_blur": "motion blur above the limit",
            "ramp": "beam speed differs from its sector's constant speed (capture in a speed ramp)",
            "order": "angle not after the previous capture angle",
        }[self.kind]
        where = f"angle {self.angle_index} ({self.angle_deg:.2f} deg), {who}: {words}"
        if self.kind == "focus_missing":
            return f"{where}: {self.value!r}"
        return f"{where}: {self.value:.4g} {self.unit} (limit {self.limit:.4g} {self.unit})"


class PlanInfeasible(TimelineError):
    """The plan cannot be executed on this rig; ``violations`` lists every offending capture."""

    MAX_LISTED = 20

    def __init__(self, violations: Sequence[Violation]) -> None:
        self.violations = tuple(violations)
        angles = sorted({v.angle_index for v in self.violations})
        lines = [v.describe() for v in self.violations[: self.MAX_LISTED]]
        more = len(self.violations) - len(lines)
        if more > 0:
            lines.append(f"... and {more} more")
        super().__init__(
            f"plan refused: {len(self.violations)} problem(s) at angle indices {angles}:\n  "
            + "\n  ".join(lines)
        )


# ---------------------------------------------------------------------------- motion profile


@dataclass(frozen=True)
class MotionProfile:
    """Piecewise constant-acceleration beam motion: time <-> angle <-> speed.

    Segment arrays are (S,) float: start time t0_s, start angle theta0_deg, start speed
    v0_deg_s, acceleration acc_deg_s2 and duration dur_s. Sector arrays (N,) hold each
    sector's start, end and nominal speed.
    """

    t0_s: np.ndarray
    theta0_deg: np.ndarray
    v0_deg_s: np.ndarray
    acc_deg_s2: np.ndarray
    dur_s: np.ndarray
    sector_start_deg: np.ndarray
    sector_end_deg: np.ndarray
    sector_speed_deg_s: np.ndarray

    @property
    def start_deg(self) -> float:
        """Where the run-up starts from rest."""
        return float(self.theta0_deg[0])

    @property
    def end_deg(self) -> float:
        """Where the run-out comes to rest."""
        return float(self.angle_at(self.duration_s))

    @property
    def duration_s(self) -> float:
        return float(self.t0_s[-1] + self.dur_s[-1])

    def _segment_of_time(self, t: np.ndarray) -> np.ndarray:
        return np.clip(np.searchsorted(self.t0_s, t, side="right") - 1, 0, len(self.t0_s) - 1)

    def angle_at(self, t_s: float | np.ndarray) -> np.ndarray:
        """Beam angle (deg) at time(s) t_s; before 0 and after the end the beam is at rest."""
        t = np.asarray(t_s, dtype=float)
        i = self._segment_of_time(t)
        dt = np.clip(t - self.t0_s[i], 0.0, self.dur_s[i])
        result: np.ndarray = self.theta0_deg[i] + self.v0_deg_s[i] * dt + 0.5 * self.acc_deg_s2[i] * dt**2
        return result

    def speed_at(self, t_s: float | np.ndarray) -> np.ndarray:
        """Beam speed (deg/s) at time(s) t_s; 0 outside the rotation."""
        t = np.asarray(t_s, dtype=float)
        i = self._segment_of_time(t)
        dt = np.clip(t - self.t0_s[i], 0.0, self.dur_s[i])
        inside = (t >= 0.0) & (t <= self.duration_s)
        return np.where(inside, self.v0_deg_s[i] + self.acc_deg_s2[i] * dt, 0.0)

    def time_at(self, angle_deg: float | np.ndarray) -> np.ndarray:
        """Time (s) the beam crosses angle(s); OutsideProfile when not on the rotation."""
        theta = np.asarray(angle_deg, dtype=float)
        start, end = self.start_deg, self.end_deg
        bad = (theta < start - 1e-9) | (theta > end + 1e-9)
        if np.any(bad):
            raise OutsideProfile(float(np.atleast_1d(theta)[np.argmax(np.atleast_1d(bad))]), start, end)
        i = np.clip(np.searchsorted(self.theta0_deg, theta, side="right") - 1, 0, len(self.t0_s) - 1)
        d = np.maximum(theta - self.theta0_deg[i], 0.0)
        v0, a = self.v0_deg_s[i], self.acc_deg_s2[i]
        # 2d / (v0 + sqrt(v0^2 + 2ad)): the stable root of d = v0 t + a t^2 / 2, also for a = 0.
        root = v0 + np.sqrt(np.maximum(v0**2 + 2.0 * a * d, 0.0))
        dt = np.divide(2.0 * d, root, out=np.zeros_like(d), where=root > 0)
        result: np.ndarray = self.t0_s[i] + np.minimum(dt, self.dur_s[i])
        return result

    def speed_at_angle(self, angle_deg: float | np.ndarray) -> np.ndarray:
        """Beam speed (deg/s) when it crosses angle(s)."""
        return self.speed_at(self.time_at(angle_deg))

    def nominal_speed(self, angle_deg: float | np.ndarray) -> np.ndarray:
        """The sector profile's speed (deg/s) at angle(s): the speed the beam must not dip below.

        At a boundary the slower sector's speed applies; outside the sectors it is 0.
        """
        theta = np.atleast_1d(np.asarray(angle_deg, dtype=float))
        inside = (theta[:, None] >= self.sector_start_deg) & (theta[:, None] <= self.sector_end_deg)
        speeds = np.where(inside, self.sector_speed_deg_s, np.inf).min(axis=1)
        out = np.where(np.isfinite(speeds), speeds, 0.0)
        return out if np.ndim(angle_deg) else out.reshape(())


def _ramp_length(v_from: float, v_to: float, acceleration: float) -> float:
    return abs(v_to**2 - v_from**2) / (2.0 * acceleration)


def motion_profile(capture: Capture, *, max_speed_deg_s: float | None = None,
                   max_acceleration_deg_s2: float | None = None) -> MotionProfile:
    """Build the dual-speed profile of ``capture`` (rig.capture) and check it.

    Raises:
        ProfileError: a ramp overlaps a capture angle (within angle_tolerance_deg), two ramps
            overlap inside a sector, or a speed/acceleration exceeds the drive's limits.
    """
    sectors = capture.sectors
    accel = capture.acceleration_deg_s2
    speeds = [s.speed_deg_s for s in sectors]
    if max_acceleration_deg_s2 is not None and accel > max_acceleration_deg_s2:
        raise ProfileError(
            f"capture acceleration {accel:g} deg/s^2 exceeds the drive's maximum "
            f"{max_acceleration_deg_s2:g} deg/s^2"
        )
    for s in sectors:
        if max_speed_deg_s is not None and s.speed_deg_s > max_speed_deg_s:
            raise ProfileError(
                f"sector {s.name!r} speed {s.speed_deg_s:g} deg/s exceeds the drive's maximum "
                f"{max_speed_deg_s:g} deg/s"
            )

    # Cruise span [lo, hi] of every sector once the ramps at its boundaries are taken out.
    lo = [s.start_deg for s in sectors]
    hi = [s.end_deg for s in sectors]
    for i in range(1, len(sectors)):
        ramp = _ramp_length(speeds[i - 1], speeds[i], accel)
        if speeds[i] < speeds[i - 1]:
            lo[i] += ramp
        elif speeds[i] > speeds[i - 1]:
            hi[i - 1] -= ramp
    tol = capture.angle_tolerance_deg
    for i, s in enumerate(sectors):
        if lo[i] > hi[i] + 1e-9:
            raise ProfileError(
                f"sector {s.name!r} [{s.start_deg:g}, {s.end_deg:g}] deg is too short for its "
                f"speed ramps at {accel:g} deg/s^2: they need {lo[i] - s.start_deg + s.end_deg - hi[i]:.3f} deg"
            )
        for angle in s.capture_angles_deg:
            if angle < lo[i] + tol - 1e-9 or angle > hi[i] - tol + 1e-9:
                raise ProfileError(
                    f"sector {s.name!r}: capture at {angle:g} deg lies within {tol:g} deg of a "
                    f"speed ramp (constant speed {s.speed_deg_s:g} deg/s only over "
                    f"[{lo[i]:.3f}, {hi[i]:.3f}] deg at {accel:g} deg/s^2)"
                )

    # Pieces in angle space: (theta_from, theta_to, v_from, v_to).
    run_up = _ramp_length(0.0, speeds[0], accel)
    pieces = [(sectors[0].start_deg - run_up, sectors[0].start_deg, 0.0, speeds[0])]
    for i, s in enumerate(sectors):
        if i > 0:
            a, b = (s.start_deg, lo[i]) if speeds[i] < speeds[i - 1] else (hi[i - 1], s.start_deg)
            pieces.append((a, b, speeds[i - 1], speeds[i]))
        pieces.append((lo[i], hi[i], speeds[i], speeds[i]))
    run_out = _ramp_length(speeds[-1], 0.0, accel)
    pieces.append((sectors[-1].end_deg, sectors[-1].end_deg + run_out, speeds[-1], 0.0))

    t0, th0, v0, acc, dur = [], [], [], [], []
    t = 0.0
    for a, b, va, vb in pieces:
        length = b - a
        if length <= 1e-12:
            continue
        d = 2.0 * length / (va + vb)
        t0.append(t)
        th0.append(a)
        v0.append(va)
        acc.append((vb - va) / d)
        dur.append(d)
        t += d
    return MotionProfile(
        t0_s=np.array(t0), theta0_deg=np.array(th0), v0_deg_s=np.array(v0),
        acc_deg_s2=np.array(acc), dur_s=np.array(dur),
        sector_start_deg=np.array([s.start_deg for s in sectors], dtype=float),
        sector_end_deg=np.array([s.end_deg for s in sectors], dtype=float),
        sector_speed_deg_s=np.array(speeds, dtype=float),
    )


def rig_profile(rig: Rig) -> MotionProfile:
    """The capture profile of a rig, checked against the drive's speed and acceleration limits."""
    return motion_profile(
        rig.capture,
        max_speed_deg_s=rig.motor.max_speed_deg_s,
        max_acceleration_deg_s2=rig.motor.max_acceleration_deg_s2,
    )


def move_duration(distance_deg: float, speed_deg_s: float, acceleration_deg_s2: float) -> float:
    """Time (s) of a rest-to-rest trapezoidal (or triangular) move over ``distance_deg``."""
    d = abs(distance_deg)
    if d == 0.0:
        return 0.0
    ramp = speed_deg_s**2 / acceleration_deg_s2  # both ramps together, deg
    if d <= ramp:
        return 2.0 * math.sqrt(d / acceleration_deg_s2)
    return 2.0 * speed_deg_s / acceleration_deg_s2 + (d - ramp) / speed_deg_s


# ---------------------------------------------------------------------------- schedule


@dataclass(frozen=True)
class PhoneTiming:
    """What the schedule needs to know about one phone.

    capture_cycle_s: trigger to ready for the next capture. lens_settle_s: focus command to
    lens stationary. trigger_latency_s: trigger command to start of exposure (measured).
    min_focus_mm / max_focus_mm: the focus range the lens can reach (mm).
    """

    capture_cycle_s: float
    lens_settle_s: float
    trigger_latency_s: float = 0.0
    min_focus_mm: float = 0.0
    max_focus_mm: float = math.inf


def phone_timings(rig: Rig, *, trigger_latency_s: Sequence[float] | None = None,
                  min_focus_mm: Sequence[float] | None = None) -> tuple[PhoneTiming, ...]:
    """One PhoneTiming per rig phone from rig.capture, with measured latencies and focus limits."""
    n = rig.n_cameras
    lat = list(trigger_latency_s) if trigger_latency_s is not None else [0.0] * n
    near = list(min_focus_mm) if min_focus_mm is not None else [0.0] * n
    if len(lat) != n or len(near) != n:
        raise TimelineError(f"need {n} latencies and focus limits, got {len(lat)} and {len(near)}")
    return tuple(
        PhoneTiming(rig.capture.capture_cycle_s, rig.capture.lens_settle_s, lat[c], near[c])
        for c in range(n)
    )


@dataclass(frozen=True)
class CameraEvent:
    """One camera's part of a capture angle (times in profile seconds)."""

    camera_index: int
    pose_index: int
    focus_mm: float
    focus_send_s: float
    lens_deadline_s: float
    trigger_s: float


@dataclass(frozen=True)
class AngleEvent:
    """Everything that happens at one capture angle."""

    angle_index: int
    angle_deg: float
    crossing_s: float
    speed_deg_s: float
    blur_px: float
    cameras: tuple[CameraEvent, ...]


@dataclass(frozen=True)
class CaptureSchedule:
    """The compiled plan. Arrays are (A,) per angle or (A, C) per angle and camera.

    crossing_s: when the beam is at the capture angle (mid-exposure). trigger_s: when to send
    the trigger so exposure is centred on the crossing (latency and half the exposure
    subtracted). focus_send_s: earliest moment the focus for this angle may be sent (the
    camera's previous capture is complete; 0 for the first angle, before the rotation).
    lens_deadline_s: the lens must report stationary by then (= trigger_s).
    """

    profile: MotionProfile
    angles_deg: np.ndarray
    crossing_s: np.ndarray
    speed_deg_s: np.ndarray
    blur_px: np.ndarray
    focus_mm: np.ndarray
    focus_send_s: np.ndarray
    lens_deadline_s: np.ndarray
    trigger_s: np.ndarray
    violations: tuple[Violation, ...]

    @property
    def n_angles(self) -> int:
        return len(self.angles_deg)

    @property
    def n_cameras(self) -> int:
        result: int = self.focus_mm.shape[1]
        return result

    def event(self, angle_index: int) -> AngleEvent:
        k = angle_index
        n_c = self.n_cameras
        return AngleEvent(
            angle_index=k,
            angle_deg=float(self.angles_deg[k]),
            crossing_s=float(self.crossing_s[k]),
            speed_deg_s=float(self.speed_deg_s[k]),
            blur_px=float(self.blur_px[k]),
            cameras=tuple(
                CameraEvent(
                    camera_index=c,
                    pose_index=k * n_c + c,
                    focus_mm=float(self.focus_mm[k, c]),
                    focus_send_s=float(self.focus_send_s[k, c]),
                    lens_deadline_s=float(self.lens_deadline_s[k, c]),
                    trigger_s=float(self.trigger_s[k, c]),
                )
                for c in range(n_c)
            ),
        )

    @property
    def events(self) -> tuple[AngleEvent, ...]:
        return tuple(self.event(k) for k in range(self.n_angles))


def compile_plan(focus_mm: np.ndarray, rig: Rig, phones: Sequence[PhoneTiming] | None = None, *,
                 profile: MotionProfile | None = None, check: bool = True,
                 angles_deg: np.ndarray | None = None) -> CaptureSchedule:
    """Compile a focus plan into per-angle capture events and check that it can be executed.

    Args:
        focus_mm: (P,) float focus distance per pose, angle-major (pose = k * C + c), mm.
        rig: the rig (capture angles, optics, limits).
        phones: one PhoneTiming per camera; default from rig.capture with zero latency.
        profile: the motion profile; default :func:`rig_profile`.
        check: raise PlanInfeasible on any violation (else they are in ``.violations``).
        angles_deg: (A,) capture angles of this plan (per-subject angles), in rotation order;
            default the rig's. Each must be crossed at its sector's constant speed.

    Raises:
        TimelineError: focus_mm has the wrong shape.
        OutsideProfile: an angle is not on the capture rotation.
        PlanInfeasible: focus missing or out of range, captures closer in time than a
            phone's cycle (+ lens settle), motion blur above rig.capture.max_motion_blur_px,
            angles out of order or inside a speed ramp.
    """
    phones = tuple(phones) if phones is not None else phone_timings(rig)
    profile = profile if profile is not None else rig_profile(rig)
    angles = rig.capture.angles_deg if angles_deg is None else np.asarray(angles_deg, dtype=float).reshape(-1)
    n_a, n_c = len(angles), rig.n_cameras
    focus = np.asarray(focus_mm, dtype=float)
    if focus.shape != (n_a * n_c,):
        raise TimelineError(f"focus plan has shape {focus.shape}; expected ({n_a * n_c},) poses")
    if len(phones) != n_c:
        raise TimelineError(f"got timings for {len(phones)} phones; the rig has {n_c}")
    focus = focus.reshape(n_a, n_c)
    exposure = rig.optics.exposure_s

    crossing = profile.time_at(angles)
    speed = profile.speed_at(crossing)
    blur = rig.optics.pixels_per_degree * speed * exposure
    latency = np.array([p.trigger_latency_s for p in phones])
    cycle = np.array([p.capture_cycle_s for p in phones])
    settle = np.array([p.lens_settle_s for p in phones])
    trigger = crossing[:, None] - 0.5 * exposure - latency[None, :]
    send = np.zeros_like(trigger)
    send[1:] = trigger[:-1] + cycle[None, :]
    deadline = trigger.copy()

    nominal = profile.nominal_speed(angles)
    violations: list[Violation] = []
    for k in range(n_a):
        a = float(angles[k])
        if k > 0 and not a > float(angles[k - 1]):
            violations.append(Violation("order", k, a, -1, a, float(angles[k - 1]), "deg"))
        if not math.isclose(float(speed[k]), float(nominal[k]), rel_tol=1e-6, abs_tol=1e-6) or nominal[k] <= 0:
            violations.append(Violation("ramp", k, a, -1, float(speed[k]), float(nominal[k]), "deg/s"))
        if blur[k] > rig.capture.max_motion_blur_px:
            violations.append(Violation("motion_blur", k, a, -1, float(blur[k]),
                                        rig.capture.max_motion_blur_px, "px"))
        for c, phone in enumerate(phones):
            f = focus[k, c]
            if not math.isfinite(f) or f <= 0.0:
                violations.append(Violation("focus_missing", k, a, c, float(f), phone.min_focus_mm, "mm"))
            elif f < phone.min_focus_mm:
                violations.append(Violation("focus_range", k, a, c, float(f), phone.min_focus_mm, "mm"))
            elif f > phone.max_focus_mm:
                violations.append(Violation("focus_range", k, a, c, float(f), phone.max_focus_mm, "mm"))
            if k == 0:
                continue
            interval = float(trigger[k, c] - trigger[k - 1, c])
            if interval < phone.capture_cycle_s:
                violations.append(Violation("cycle", k, a, c, interval, phone.capture_cycle_s, "s"))
            elif send[k, c] + settle[c] > deadline[k, c]:
                violations.append(Violation("lens_settle", k, a, c, interval,
                                            phone.capture_cycle_s + phone.lens_settle_s, "s"))
    schedule = CaptureSchedule(
        profile=profile, angles_deg=angles, crossing_s=crossing, speed_deg_s=speed, blur_px=blur,
        focus_mm=focus, focus_send_s=send, lens_deadline_s=deadline, trigger_s=trigger,
        violations=tuple(violations),
    )
    if check and violations:
        raise PlanInfeasible(violations)
    return schedule


# ---------------------------------------------------------------------------- rig time


@dataclass(frozen=True)
class RigTime:
    """Rig time of one scan (s): depth sweep, repositioning to the capture run-up, capture."""

    sweep_s: float
    reposition_s: float
    capture_s: float

    @property
    def total_s(self) -> float:
        return self.sweep_s + self.reposition_s + self.capture_s


def scan_rig_time(rig: Rig, profile: MotionProfile | None = None) -> RigTime:
    """Rig time of a scan: the sweep at its speed, the move to the run-up start, the capture.

    The sweep and the reposition are rest-to-rest moves at the drive's maximum acceleration;
    the reposition also at its maximum speed, the short way round (the beam's angle is
    renumbered by whole turns at rest). Compute time (TSDF, planning) is not rig time.
    """
    profile = profile if profile is not None else rig_profile(rig)
    sweep = rig.depth_sweep
    a_max = rig.motor.max_acceleration_deg_s2
    return RigTime(
        sweep_s=move_duration(sweep.end_deg - sweep.start_deg, sweep.speed_deg_s, a_max),
        reposition_s=move_duration(
            wrap_deg(profile.start_deg - sweep.end_deg), rig.motor.max_speed_deg_s, a_max
        ),
        capture_s=profile.duration_s,
    )


def wrap_deg(angle_deg: float) -> float:
    """An angle difference folded into [-180, 180) deg."""
    return (angle_deg + 180.0) % 360.0 - 180.0
