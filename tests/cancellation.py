"""Stopping scans at random points in virtual time: the harness of the cancellation test and of
``./dev bench safety``.

A trial starts a scan on the simulated rig of tests/daemon_rigs.py (the CANopen drive simulator,
ray-cast depth cameras, mock phones whose pulls take a little time) and stops it at a seeded
random rig time: at that time, or at the next encoder sample after it (in the loop turn that
resolves the waits for that sample), then a random number of loop turns later. So a stop also
lands between a future's result and the task that waits for it, where ``asyncio.wait_for``
loses a cancellation on Python 3.11. Four ways to stop a scan:

* ``abort``: the operator's abort (``controller.abort``);
* ``trip``: a safety trip (the panel's e-stop, ``controller.trip``), reset afterwards;
* ``cancel``: the job's task is cancelled from outside;
* ``stop``: the daemon stops (``RigService.stop``, the controller's close path).

The scan runs the real scan, capture, pull and store code on a short rig (a 123 deg depth sweep,
five capture angles over 45 deg with a speed change), so a trial costs well under a second of
machine time. After each trial the harness checks what the issue asks: the job ended (no hang),
within the exit bound, the rig is IDLE or FAULT, the scan folder is closed, and every image
captured before the stop is on disk and verified.
"""

from __future__ import annotations

import asyncio
import dataclasses
import hashlib
import json
import random
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from daemon.faults import AbortCause, AbortSource, FaultCause, FaultSource
from daemon.jobs.controller import RigController
from daemon.jobs.scan import ScanSettings
from daemon.records.store import ScanStore
from daemon.rig.states import ScanState
from daemon.server.service import RigService
from planner.rig import Rig, Sector
from sim.clock import TasksLeftPending, run_virtual
from tests.daemon_mocks import MockPhone
from tests.daemon_rigs import RIG, build_rig

KINDS = ("abort", "trip", "cancel", "stop")
EXIT_BOUND_S = 30.0
"""A stopped job must end within this (rig seconds): systemd/tbp-rig.service's TimeoutStopSec."""
BEAM_STOP_S = 3.0
"""The beam stands still this long after a stop at the latest (a controlled stop from the
sweep's 30 deg/s at 30 deg/s^2 takes 1 s)."""
LATE_S = 0.5
"""No picture is exposed later than this after a stop (one already triggered may finish)."""
HANG_S = 300.0
"""A job still running this long after its stop has hung."""
SPAN_S = 17.0
"""Stops land in the first this many rig seconds of a scan (the short scan takes about 18 s)."""
PLAN_POINTS = 300


def short_rig(rig: Rig = RIG) -> Rig:
    """``rig`` with a 123 deg depth sweep, five capture angles over 45 deg (two speeds) and a coarse
    TSDF (20 mm voxels, the stored surface's too)."""
    sectors = (
        Sector("front", -45.0, -15.0, 9.0, -40.0, 10.0, 3),
        Sector("left", -15.0, 0.0, 3.0, -12.0, 6.0, 2),
    )
    return dataclasses.replace(
        rig,
        capture=dataclasses.replace(rig.capture, sectors=sectors),
        depth_sweep=dataclasses.replace(rig.depth_sweep, start_deg=-170.0),
        tsdf=dataclasses.replace(rig.tsdf, voxel_mm=20.0, surface_voxel_mm=20.0),
    )


SHORT_RIG = short_rig()


class SlowPullPhone(MockPhone):
    """A mock phone whose pulls take 50 ms, so stops also land while pulls are in flight."""

    async def pull(self, phone_path: str, dest: Path) -> tuple[int, str]:
        await asyncio.sleep(0.05)
        return await super().pull(phone_path, dest)


ANCHORS = (ScanState.DEPTH_SWEEP, ScanState.RECONSTRUCTING, ScanState.PLANNING, ScanState.CAPTURING)
"""States whose first moments (the beam starting, a step handing over to the next) get trials of
their own: a stop at a uniform time lands there too rarely."""
NEAR_S = 0.3
"""Trials anchored at a state stop within this many rig seconds of entering it, most of them
in its first tens of milliseconds."""


@dataclass(frozen=True)
class Trial:
    """Stop the ``index``-th scan ``at_s`` rig seconds after its start, or after it entered
    ``anchor`` (``on_sample``: at the next encoder sample after that), ``turns`` loop turns later."""

    index: int
    kind: str
    anchor: ScanState | None
    at_s: float
    on_sample: bool
    turns: int


@dataclass
class TrialResult:
    trial: Trial
    state_at: str = ""
    """The rig's state when the stop landed ("done": the scan had ended before it)."""
    end_state: str = ""
    outcome: str = ""
    """The job's outcome and reason (its report)."""
    hung: bool = False
    exit_s: float | None = None
    """Rig seconds from the stop to the end of the job (``stop``: to the daemon stopped)."""
    beam_moving_s: float = 0.0
    """Rig seconds from the stop to the last encoder sample of a moving beam."""
    late: int = 0
    """Pictures exposed more than LATE_S after the stop."""
    folder_open: bool = False
    captured_before: int = 0
    lost: list[str] = field(default_factory=list)
    """Images captured before the stop that are not verified on disk."""
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return (not self.hung and not self.folder_open and not self.lost and not self.problems
                and self.exit_s is not None and self.exit_s <= EXIT_BOUND_S
                and self.beam_moving_s <= BEAM_STOP_S and not self.late)


def make_trials(n: int, seed: int, kinds: Sequence[str] = KINDS, span_s: float = SPAN_S) -> list[Trial]:
    """``n`` seeded trials, kinds in turn: half stop at a uniform time in the first ``span_s`` of
    a scan, half within :data:`NEAR_S` of entering one of the :data:`ANCHORS`."""
    rng = random.Random(seed)
    trials = []
    for i in range(n):
        anchor = rng.choice(ANCHORS) if rng.random() < 0.5 else None
        at_s = rng.uniform(0.0, span_s) if anchor is None else NEAR_S * rng.random() ** 3
        trials.append(Trial(i, kinds[i % len(kinds)], anchor, at_s, rng.random() < 0.75, rng.randrange(4)))
    return trials


def run_trials(trials: Sequence[Trial], store: Path, *, seed: int = 0) -> list[TrialResult]:
    """Every trial, in order; trials share one rig (and one virtual-time loop) until a daemon
    stop or a hang ends it, then the next trials get a fresh one."""
    results: list[TrialResult] = []
    todo = list(trials)
    while todo:
        done = len(results)
        try:
            run_virtual(_session(todo, store, results, seed))
        except TasksLeftPending as exc:  # a broken trial's tasks: already counted there
            if results and results[-1].problems:
                results[-1].problems.append(f"left running: {exc}")
            else:
                raise
        if len(results) == done:  # the session ran nothing: do not loop for ever
            raise RuntimeError(f"the harness could not run trial {todo[0]}")
    return results


async def _session(todo: list[Trial], store: Path, results: list[TrialResult], seed: int) -> None:
    hardware, _world = await build_rig(SHORT_RIG, seed, phone=SlowPullPhone, depth_decimation=16)
    with ThreadPoolExecutor(max_workers=1) as executor:
        controller = RigController(SHORT_RIG, hardware, ScanStore(store), settings=ScanSettings(
            executor=executor, seed=seed, plan_points=PLAN_POINTS))
        service = RigService(controller)
        await service.start()
        end = "next"
        while todo and end == "next":
            trial = todo.pop(0)
            result = TrialResult(trial)
            results.append(result)
            end = await _one(trial, controller, service, result)
        if end == "next":
            await service.stop()
        elif end == "broken":
            await _abandon(controller)


async def _one(trial: Trial, controller: RigController, service: RigService, result: TrialResult) -> str:
    """Run one trial: "next" (the rig can take the next one), "stopped" (the daemon stopped) or
    "broken" (a hang, or the rig cannot scan again: a fresh rig for the next trial)."""
    loop = asyncio.get_running_loop()
    try:
        task = await controller.start_scan(f"t{trial.index}")
    except Exception as exc:  # the last trial left the rig unable to scan: counted there
        results_note = f"not started: {type(exc).__name__}: {exc}"
        result.problems.append(results_note)
        return "broken"
    job = controller.current
    ended: list[float] = []
    task.add_done_callback(lambda _t: ended.append(loop.time()))
    if trial.anchor is not None:
        entered = asyncio.create_task(controller.machine.wait_for(trial.anchor), name="harness-anchor")
        await asyncio.wait([entered, task], return_when=asyncio.FIRST_COMPLETED)
        entered.cancel()
        await asyncio.wait([entered])
    await asyncio.sleep(trial.at_s)
    if trial.on_sample:
        await controller.tracker.next_sample()
    for _ in range(trial.turns):
        await asyncio.sleep(0)
    before = _captured(job)
    result.captured_before = len(before)
    result.state_at = "done" if task.done() else controller.machine.state.value
    acted = loop.time()
    mark = controller.tracker.mark()
    stopping: asyncio.Task[Any] | None = None
    if trial.kind == "abort":
        controller.abort(AbortCause(AbortSource.CONTROL_API, "harness", "abort"))
    elif trial.kind == "trip":
        await controller.trip(FaultCause(FaultSource.ESTOP, "panel", "e-stop pressed"))
    elif trial.kind == "cancel":
        task.cancel()
    else:
        stopping = asyncio.create_task(service.stop(), name="harness-stop")
    waits: list[asyncio.Future[Any]] = [task] if stopping is None else [task, stopping]
    _, pending = await asyncio.wait(waits, timeout=HANG_S)
    if pending:
        result.hung = True
        result.problems.append(f"still running {HANG_S:g} s after the {trial.kind}: "
                               + ", ".join(t.get_name() for t in pending if isinstance(t, asyncio.Task)))
        return "broken"
    result.exit_s = (loop.time() if stopping is not None else ended[0]) - acted
    if not task.cancelled() and task.exception() is not None:
        result.problems.append(f"job raised {type(task.exception()).__name__}: {task.exception()}")
    result.end_state = controller.machine.state.value
    result.outcome = f"{job.report.outcome.value}: {job.report.reason}"
    if controller.machine.state not in (ScanState.IDLE, ScanState.FAULT):
        result.problems.append(f"ended in {result.end_state}")
    moving = [float(t) for t, _, v in controller.tracker.trace(mark) if abs(v) > 0.01]
    result.beam_moving_s = max(moving[-1] - acted, 0.0) if moving else 0.0
    _check_folder(job, before, result, acted)
    if stopping is not None:
        return "stopped"
    if controller.machine.state is ScanState.FAULT:
        try:
            await controller.reset("harness")
        except Exception as exc:  # the rig cannot be reset: named, fresh rig next
            result.problems.append(f"reset failed: {type(exc).__name__}: {exc}")
            return "broken"
    return "broken" if result.problems else "next"


def _captured(job: Any) -> set[tuple[int, int]]:
    """Images the job's manifest records as captured or verified now."""
    return {(i.camera_index, i.angle_index) for i in job.folder.manifest.images
            if i.status.value in ("captured", "verified")}


def _check_folder(job: Any, before: set[tuple[int, int]], result: TrialResult, acted: float) -> None:
    folder = job.folder.path
    manifest = json.loads((folder / "manifest.json").read_text())
    result.folder_open = bool(manifest["in_progress"])
    images = {(i["camera_index"], i["angle_index"]): i for i in manifest["images"]}
    result.late = sum(i["host_time_s"] is not None and i["host_time_s"] > acted + LATE_S for i in images.values())
    for key in sorted(before):
        image = images.get(key)
        if image is None or image["status"] != "verified":
            result.lost.append(f"{key}: {None if image is None else image['status']}")
            continue
        data = (folder / image["file"]).read_bytes()
        if hashlib.sha256(data).hexdigest() != image["sha256"]:
            result.lost.append(f"{key}: sha256 differs")


async def _abandon(controller: RigController) -> None:
    """After a hang: cancel what still runs and close the devices, each wait bounded."""
    current = asyncio.current_task()
    tasks = [t for t in asyncio.all_tasks() if t is not current]
    for t in tasks:
        t.cancel()
    await asyncio.wait(tasks, timeout=10.0)
    closing = asyncio.create_task(controller.hw.close())
    await asyncio.wait([closing], timeout=10.0)


def summary(results: Sequence[TrialResult]) -> dict[str, Any]:
    """The counts the bench prints and the test asserts on."""
    exits = [r.exit_s for r in results if r.exit_s is not None]
    states: dict[str, int] = {}
    for r in results:
        states[r.state_at] = states.get(r.state_at, 0) + 1
    return {
        "runs": len(results),
        "hangs": sum(r.hung for r in results),
        "over_bound": sum(r.exit_s is not None and r.exit_s > EXIT_BOUND_S for r in results),
        "beam_late": sum(bool(r.beam_moving_s > BEAM_STOP_S) for r in results),
        "late_pictures": sum(r.late for r in results),
        "folders_open": sum(r.folder_open for r in results),
        "images_lost": sum(len(r.lost) for r in results),
        "captured_before": sum(r.captured_before for r in results),
        "problems": sum(bool(r.problems) for r in results),
        "max_exit_s": max(exits, default=0.0),
        "max_beam_moving_s": max((r.beam_moving_s for r in results), default=0.0),
        "states": states,
    }
