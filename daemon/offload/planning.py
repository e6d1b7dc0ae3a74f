"""The scan's focus plan, computed in the compute worker (daemon/offload/compute.py).

Only what the worker needs lives here: the worker imports this module when it starts, so a
scan's first plan does not first import the daemon (``daemon.jobs.scan`` and what it pulls in took
0.3 s on this machine, inside the first scan's gap between the sweep and the capture).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from planner.calibration.model import Calibration
from planner.plan import plan_focus
from planner.rig import Rig

CAPTURE_METHODS = ("robust",)
"""Planned before the capture: the robust plan it uses; with per-subject angles (rig
planner.per_subject_angles) also "robust-angles", which then captures (the plan names its capture
method and angles)."""
BASELINES = ("average", "shape-aware")
"""Planned while the beam turns, for the QA report: the seed's usual baseline and the seed's method,
on the same samples; plan.json gets them as soon as they are done."""


@dataclass(frozen=True)
class PlannedCapture:
    """What the scan keeps of a plan: plan.json's content, the focus (P,) mm and angles (A,) deg to
    capture with. The plan's cost table (tens of MB) stays where it was computed: unpickling it
    in the daemon would hold the interpreter lock the heartbeats need."""

    json: dict[str, Any]
    focus_mm: np.ndarray
    angles_deg: np.ndarray


def plan_capture(mesh: Any, rig: Rig, seed: int, points: int | None, calibration: Calibration | None,
                 methods: tuple[str, ...] | None = None) -> PlannedCapture:
    """In the executor: the capture's plan (default ``methods``: :data:`CAPTURE_METHODS`,
    robust-angles when the rig asks)."""
    if methods is None:
        methods = CAPTURE_METHODS + (("robust-angles",) if rig.planner.per_subject_angles else ())
    plan = plan_focus(mesh, rig, seed=seed, points=points, methods=methods, calibration=calibration)
    return PlannedCapture(plan.to_json(), np.asarray(plan.focus_mm, dtype=float),
                          np.asarray(plan.capture_angles_deg, dtype=float))

