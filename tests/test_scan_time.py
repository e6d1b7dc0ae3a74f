"""The running scan's elapsed and remaining time (daemon/jobs/scan_time.py), and the state machine's
recent-events buffer the console shows on load (daemon/rig/states.py)."""

from __future__ import annotations

import pytest

from daemon.jobs.scan_time import job_time, remaining_rig_s
from daemon.rig.states import ScanState, ScanStateMachine
from planner.schedule import RigTime

S = ScanState
RIG = RigTime(sweep_s=20.0, reposition_s=5.0, capture_s=60.0)


@pytest.mark.parametrize(("state", "in_state", "left"), [
    (S.PREPARING, 3.0, 85.0),
    (S.DEPTH_SWEEP, 8.0, 12.0 + 5.0 + 60.0),
    (S.DEPTH_SWEEP, 30.0, 65.0),  # a slow sweep never makes the time left negative
    (S.RECONSTRUCTING, 4.0, 60.0),
    (S.PLANNING, 9.0, 60.0),
    (S.CAPTURING, 45.0, 15.0),
    (S.CAPTURING, 70.0, 0.0),
    (S.RETAKING, 1.0, None),
    (S.STORING, 1.0, None),
    (S.ABORTING, 1.0, None),
])
def test_the_time_left_is_the_schedule_less_what_the_state_has_run(state, in_state, left):
    assert remaining_rig_s(state, in_state, RIG) == left


def test_elapsed_counts_from_the_job_start_and_a_rotation_has_no_time_left():
    assert job_time(S.CAPTURING, 100.0, 150.0, 160.0, RIG) == {"elapsed_s": 60.0, "state_s": 10.0, "remaining_s": 50.0}
    assert job_time(S.CALIBRATING, 100.0, 100.0, 130.0, None)["remaining_s"] is None


def test_the_machine_keeps_recent_events_without_per_image_counts_each_stamped_and_numbered():
    machine = ScanStateMachine()
    machine.transition(S.PREPARING, "scan requested")
    for n in range(1, 400):
        machine.progress("captured", captured=n)
        machine.progress("verified", verified=n)
    machine.progress("phone_dropped", camera="cam2")
    machine.transition(S.ABORTING, "abort")
    kept = list(machine.recent)
    assert [e.cause for e in kept] == ["scan requested", "phone_dropped", "abort"]
    assert [e.seq for e in kept] == [1, 800, 801]
    assert all(e.utc.endswith("+00:00") for e in kept)
    for n in range(machine.RECENT_SIZE + 5):
        machine.progress("capture_missed", pose=n)
    assert len(machine.recent) == machine.RECENT_SIZE and machine.recent[-1].data == {"pose": machine.RECENT_SIZE + 4}


def test_the_machine_holds_the_jobs_image_counts_until_the_next_job_leaves_idle():
    machine = ScanStateMachine()
    assert machine.counts == {}
    machine.transition(S.PREPARING, "scan requested")
    for n in range(1, 40):
        machine.progress("captured", captured=n)
    machine.progress("verified", verified=7)
    machine.progress("capture_missed", pose=3, captured=99)  # not a count of its own
    assert machine.counts == {"captured": 39, "verified": 7}
    machine.transition(S.ABORTING, "abort")
    machine.transition(S.IDLE, "stopped")
    assert machine.counts == {"captured": 39, "verified": 7}  # the last job's, after it
    machine.transition(S.PREPARING, "scan requested")
    assert machine.counts == {}
