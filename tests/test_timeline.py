"""Dual-speed motion profile and the compiled capture schedule (planner/schedule.py)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from planner.rig import Capture, Sector, load_rig
from planner.schedule import (
    OutsideProfile,
    PhoneTiming,
    PlanInfeasible,
    ProfileError,
    TimelineError,
    compile_plan,
    motion_profile,
    move_duration,
    phone_timings,
    rig_profile,
    scan_rig_time,
    wrap_deg,
)


@pytest.fixture(scope="module")
def rig():
    return load_rig()


def _capture(spans, speeds, step=2.0, accel=30.0, tol=0.2) -> Capture:
    sectors = []
    start = 0.0
    for i, (span, v) in enumerate(zip(spans, speeds)):
        n = max(1, int((span - 2 * step) // step))
        first = start + (span - (n - 1) * step) / 2
        sectors.append(Sector(f"s{i}", start, start + span, v, first, step, n))
        start += span
    return Capture(tuple(sectors), accel, 3.0, 0.05, 0.3, tol)


def test_default_profile_matches_the_seed_capture_time(rig):
    p = rig_profile(rig)
    # 180 deg at 9 deg/s + 180 deg at 3 deg/s = 80 s, minus what the ramps gain.
    assert 79.0 < p.duration_s < 81.0
    assert p.start_deg < rig.capture.start_deg and p.end_deg > rig.capture.end_deg
    assert p.speed_at(0.0) == 0.0 and p.speed_at(p.duration_s) == pytest.approx(0.0, abs=1e-9)


def test_every_default_capture_is_at_its_sector_speed(rig):
    p = rig_profile(rig)
    angles = rig.capture.angles_deg
    expected = [s.speed_deg_s for s in rig.capture.sectors for _ in range(s.captures)]
    np.testing.assert_allclose(p.speed_at_angle(angles), expected, rtol=1e-9)


@settings(max_examples=60, deadline=None)
@given(
    spans=st.lists(st.floats(20.0, 100.0), min_size=1, max_size=4),
    speeds=st.lists(st.floats(1.0, 12.0), min_size=4, max_size=4),
    accel=st.floats(5.0, 60.0),
)
def test_profile_is_continuous_and_never_below_the_sector_speed(spans, speeds, accel):
    capture = _capture(spans, speeds[: len(spans)], accel=accel)
    try:
        p = motion_profile(capture)
    except ProfileError:
        return
    t = np.linspace(0.0, p.duration_s, 4001)
    theta = p.angle_at(t)
    speed = p.speed_at(t)
    assert np.all(np.diff(theta) >= -1e-9)
    # continuity: no jump larger than what the top speed covers in one step
    dt = t[1] - t[0]
    assert np.max(np.abs(np.diff(theta))) <= max(speeds) * dt * 1.001 + 1e-9
    assert np.max(np.abs(np.diff(speed))) <= accel * dt * 1.001 + 1e-9
    inside = (theta >= capture.start_deg) & (theta <= capture.end_deg)
    assert np.all(speed[inside] >= p.nominal_speed(theta[inside]) - 1e-6)
    # angle -> time -> angle round trip
    np.testing.assert_allclose(p.angle_at(p.time_at(theta)), theta, atol=1e-6)
    # every capture at exactly its sector's speed
    for s in capture.sectors:
        np.testing.assert_allclose(p.speed_at_angle(s.capture_angles_deg), s.speed_deg_s, rtol=1e-9)


def test_capture_inside_a_ramp_is_refused():
    fast_slow = Capture(
        (
            Sector("fast", 0.0, 40.0, 9.0, 5.0, 10.0, 4),
            Sector("slow", 40.0, 80.0, 3.0, 40.5, 6.0, 6),  # decel 9->3 covers 40..41.2
        ),
        30.0, 3.0, 0.05, 0.3, 0.2,
    )
    with pytest.raises(ProfileError, match=r"capture at 40.5 deg"):
        motion_profile(fast_slow)


def test_sector_too_short_for_its_ramps_is_refused():
    capture = Capture(
        (
            Sector("a", 0.0, 20.0, 9.0, 5.0, 5.0, 2),
            Sector("b", 20.0, 21.0, 1.0, 20.5, 1.0, 1),
            Sector("c", 21.0, 60.0, 9.0, 30.0, 5.0, 2),
        ),
        30.0, 3.0, 0.05, 0.3, 0.2,
    )
    with pytest.raises(ProfileError, match="too short"):
        motion_profile(capture)


def test_drive_limits_are_enforced(rig):
    with pytest.raises(ProfileError, match="acceleration"):
        motion_profile(rig.capture, max_acceleration_deg_s2=10.0)
    with pytest.raises(ProfileError, match="speed 9"):
        motion_profile(rig.capture, max_speed_deg_s=5.0)


def test_time_at_outside_the_rotation_raises(rig):
    p = rig_profile(rig)
    with pytest.raises(OutsideProfile, match="outside"):
        p.time_at(p.end_deg + 1.0)


def test_compile_default_plan(rig):
    focus = np.full(rig.n_poses, 450.0)
    s = compile_plan(focus, rig, phone_timings(rig, trigger_latency_s=[0.02] * rig.n_cameras))
    assert s.violations == ()
    assert np.all(np.diff(s.crossing_s) > 0)
    ev = s.event(5)
    cam = ev.cameras[3]
    assert cam.pose_index == rig.pose_index(5, 3)
    assert cam.trigger_s == pytest.approx(ev.crossing_s - 0.02 - rig.optics.exposure_s / 2)
    prev = s.event(4).cameras[3]
    assert cam.focus_send_s == pytest.approx(prev.trigger_s + rig.capture.capture_cycle_s)
    assert cam.focus_send_s + rig.capture.lens_settle_s <= cam.lens_deadline_s
    # blur: pixels per degree * speed * exposure (the seed's ~2.3 px at 9 deg/s)
    assert s.blur_px.max() == pytest.approx(2.32, abs=0.01)
    assert len(s.events) == rig.n_angles


def test_incomplete_and_out_of_range_plans_list_offending_angles(rig):
    focus = np.full(rig.n_poses, 450.0)
    focus[rig.pose_index(3, 2)] = np.nan
    focus[rig.pose_index(10, 0)] = 50.0
    phones = phone_timings(rig, min_focus_mm=[100.0] * rig.n_cameras)
    with pytest.raises(PlanInfeasible) as info:
        compile_plan(focus, rig, phones)
    kinds = {(v.kind, v.angle_index, v.camera_index) for v in info.value.violations}
    assert kinds == {("focus_missing", 3, 2), ("focus_range", 10, 0)}
    assert "angle indices [3, 10]" in str(info.value)
    assert "angle 3 (-10.00 deg), camera 2: focus is not a finite positive distance: nan" in str(info.value)
    assert "angle 10 (54.00 deg), camera 0: focus outside the phone's focus range: 50 mm (limit 100 mm)" in str(info.value)


def test_wrong_plan_shape_is_refused(rig):
    with pytest.raises(TimelineError, match=r"shape \(10,\)"):
        compile_plan(np.ones(10), rig)


def test_slow_phone_cycle_is_refused(rig):
    phones = list(phone_timings(rig))
    phones[4] = dataclasses.replace(phones[4], capture_cycle_s=1.5)
    with pytest.raises(PlanInfeasible) as info:
        compile_plan(np.full(rig.n_poses, 450.0), rig, phones)
    bad = info.value.violations
    assert {v.kind for v in bad} == {"cycle"} and {v.camera_index for v in bad} == {4}
    # the fast sectors (10 deg at 9 deg/s = 1.11 s) are too quick for a 1.5 s cycle
    assert all(v.value < 1.5 for v in bad)
    assert sum(abs(v.value - 10.0 / 9.0) < 1e-6 for v in bad) == 16
    s = compile_plan(np.full(rig.n_poses, 450.0), rig, phones, check=False)
    assert len(s.violations) == len(bad)


def test_slow_lens_is_refused(rig):
    phones = [PhoneTiming(0.35, 0.9) for _ in range(rig.n_cameras)]
    with pytest.raises(PlanInfeasible) as info:
        compile_plan(np.full(rig.n_poses, 450.0), rig, phones)
    assert {v.kind for v in info.value.violations} == {"lens_settle"}


def test_motion_blur_limit(rig):
    rig2 = dataclasses.replace(
        rig, capture=dataclasses.replace(rig.capture, max_motion_blur_px=2.0)
    )
    with pytest.raises(PlanInfeasible) as info:
        compile_plan(np.full(rig.n_poses, 450.0), rig2)
    blur = [v for v in info.value.violations if v.kind == "motion_blur"]
    assert len(blur) == 18  # the front and back sectors at 9 deg/s
    assert all(math.isclose(v.value, 2.32, abs_tol=0.01) for v in blur)


@given(d=st.floats(0.0, 400.0), v=st.floats(1.0, 60.0), a=st.floats(1.0, 100.0))
def test_move_duration_bounds(d, v, a):
    t = move_duration(d, v, a)
    assert t >= d / v - 1e-9
    assert t <= d / v + 2 * v / a + 2 * math.sqrt(d / a) + 1e-9


@given(a=st.floats(-1000.0, 1000.0))
def test_wrap_deg(a):
    w = wrap_deg(a)
    assert -180.0 <= w < 180.0 and math.isclose(math.remainder(w - a, 360.0), 0.0, abs_tol=1e-9)


def test_scan_rig_time_under_the_paper_figure(rig):
    t = scan_rig_time(rig)
    assert t.capture_s == pytest.approx(rig_profile(rig).duration_s)
    gap = abs(wrap_deg(rig_profile(rig).start_deg - rig.depth_sweep.end_deg))
    assert gap <= 180.0
    assert t.reposition_s == pytest.approx(
        move_duration(gap, rig.motor.max_speed_deg_s, rig.motor.max_acceleration_deg_s2))
    assert t.total_s == pytest.approx(t.sweep_s + t.reposition_s + t.capture_s)
    assert t.total_s < 100.0


@settings(max_examples=25, deadline=None)
@given(cycle=st.floats(0.1, 2.5), settle=st.floats(0.0, 0.5), latency=st.floats(0.0, 0.2))
def test_feasibility_refuses_exactly_the_too_close_captures(rig, cycle, settle, latency):
    phones = [PhoneTiming(cycle, settle, latency) for _ in range(rig.n_cameras)]
    s = compile_plan(np.full(rig.n_poses, 450.0), rig, phones, check=False)
    gaps = np.diff(s.crossing_s)  # the same for every camera (equal latencies)
    too_close = {k + 1 for k in np.flatnonzero(gaps < cycle + settle)}
    assert {v.angle_index for v in s.violations} == too_close
    for v in s.violations:
        assert v.kind == ("cycle" if gaps[v.angle_index - 1] < cycle else "lens_settle")
    if too_close:
        with pytest.raises(PlanInfeasible):
            compile_plan(np.full(rig.n_poses, 450.0), rig, phones)
