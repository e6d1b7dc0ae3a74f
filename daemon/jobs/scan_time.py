"""How long the running job has taken and how much of the beam's schedule is left (the console,
``tbp status``).

Elapsed is event-loop time since the job left IDLE. Remaining is the rig time the scan's schedule
still holds (:func:`planner.schedule.scan_rig_time`: the depth sweep, the move to the capture
run-up, the capture rotation at the rig's capture profile, the one the plan is compiled on) less
what the current state has already run. Computing (fusion, planning) and storing are not rig time
and are not counted; a retake pass, whose extent is only known when it starts, a calibration
rotation and the end of a job leave it unknown (None).
"""

from __future__ import annotations

from typing import Any

from daemon.rig.states import ScanState
from planner.schedule import RigTime

S = ScanState


def remaining_rig_s(state: ScanState, in_state_s: float, rig_time: RigTime) -> float | None:
    """Rig time (s) left in a scan in ``state``, which began ``in_state_s`` ago; None when unknown."""
    if state is S.PREPARING:
        return rig_time.total_s
    if state is S.DEPTH_SWEEP:
        return max(0.0, rig_time.sweep_s - in_state_s) + rig_time.reposition_s + rig_time.capture_s
    if state in (S.RECONSTRUCTING, S.PLANNING):  # the beam repositions while the mesh and the plan are computed
        return rig_time.capture_s
    if state is S.CAPTURING:
        return max(0.0, rig_time.capture_s - in_state_s)
    return None


def job_time(state: ScanState, started_s: float, entered_s: float, now_s: float,
             rig_time: RigTime | None) -> dict[str, Any]:
    """``elapsed_s`` since the job started, ``state_s`` in the current state, ``remaining_s`` (None
    when unknown or ``rig_time`` is None: not a scan)."""
    in_state = now_s - entered_s
    return {"elapsed_s": now_s - started_s, "state_s": in_state,
            "remaining_s": None if rig_time is None else remaining_rig_s(state, in_state, rig_time)}
