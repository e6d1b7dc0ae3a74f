"""Scans on the complete simulated rig (CANopen drive, ADB phones, depth cameras) in virtual time."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
from pathlib import Path

import pytest

from analysis.body_texture import report_and_body
from daemon.jobs.scan import ScanReport
from daemon.rig.states import ScanOutcome, ScanState
from sim.run import run_sim_scan
from tests.daemon_rigs import PLAN_POINTS, capsule_subject, wait_captured

pytestmark = pytest.mark.slow

TBP = str(Path(sys.executable).with_name("tbp"))


def _scan(store: Path, fault=None, **kwargs) -> ScanReport:
    tasks: list[asyncio.Task] = []

    def on_ready(controller, world) -> None:
        if fault is not None:
            tasks.append(asyncio.create_task(fault(controller, world)))

    return run_sim_scan(store=store, seed=1, plan_points=PLAN_POINTS, depth_decimation=4,
                        subject=capsule_subject(), panel=False, on_ready=on_ready, **kwargs)


def _images(report: ScanReport) -> list[dict]:
    return json.loads((report.folder / "manifest.json").read_text())["images"]


def _without_wall_clock(manifest: dict) -> dict:
    return {k: v for k, v in manifest.items() if k not in ("created_utc", "ended_utc")}


def test_tbp_scan_sim_with_the_rig_defaults_is_complete_and_reproducible(tmp_path: Path) -> None:
    """The main scan: `tbp scan --sim` with every default (body, panel, 10,000 planning points),
    then the same seed in-process with stretches paced at 1x and 40x real time: same scan."""
    cli = subprocess.run([TBP, "scan", "--sim", "--store", str(tmp_path / "a")],
                         capture_output=True, text=True, timeout=900)
    assert cli.returncode == 0, cli.stderr[-2000:]
    lines = cli.stdout.strip().splitlines()
    fast = Path(lines[-1])
    assert any("CAPTURING" in line for line in lines[:-1])
    manifest = json.loads((fast / "manifest.json").read_text())
    assert manifest["state"] == "complete" and manifest["in_progress"] is False
    assert manifest["counts"]["verified"] == 336
    for image in manifest["images"]:
        data = (fast / image["file"]).read_bytes()
        assert len(data) == image["size_bytes"]
        assert abs(image["actual_angle_deg"] - image["planned_angle_deg"]) <= 0.2
    qa = json.loads((fast / "qa.json").read_text())
    assert qa["lens_late"] == 0 and qa["min_speed_ratio"] >= 0.999
    assert qa["phase_s"]["total"] <= 100.0
    plan = json.loads((fast / "plan.json").read_text())
    assert plan["points"] == 10_000
    aware, average = plan["methods"]["shape-aware"], plan["methods"]["average"]
    assert aware["total_cost"] <= average["total_cost"]

    async def pace(controller, world) -> None:
        loop = asyncio.get_running_loop()
        await controller.machine.wait_for(ScanState.DEPTH_SWEEP)
        loop.time_scale = 1.0
        await asyncio.sleep(1.0)
        loop.time_scale = None
        await wait_captured(controller, 50)
        loop.time_scale = 40.0
        await asyncio.sleep(4.0)
        loop.time_scale = None

    tasks: list[asyncio.Task] = []
    paced = run_sim_scan(store=tmp_path / "b", qa_report=report_and_body,  # the hook tbp scan --sim runs
                         on_ready=lambda c, w: tasks.append(asyncio.create_task(pace(c, w)))).folder
    again = json.loads((paced / "manifest.json").read_text())
    assert _without_wall_clock(manifest) == _without_wall_clock(again)
    angles = [[c["exposure_angle_deg"] for c in json.loads((f / "captures.json").read_text())]
              for f in (fast, paced)]
    assert angles[0] == angles[1]


def test_phones_lost_mid_scan_are_dropped_and_the_scan_ends_partial(tmp_path: Path) -> None:
    """cam3 is unplugged for good; cam5 drops out and comes back before the retake pass; cam1
    fails two captures (not three: it stays). Both lost phones are dropped, cam1's two angles are
    retaken, and cam5, back by then, rides along at those two angles only."""

    async def unplug(controller, world) -> None:
        await wait_captured(controller, 120)
        world.phones[3].vanish()
        world.phones[5].vanish()
        world.phones[1].fail_captures = 2
        await asyncio.sleep(5.0)
        world.phones[5].reappear()

    report = _scan(tmp_path, unplug)
    assert report.outcome is ScanOutcome.PARTIAL
    assert [d["camera"] for d in report.dropped_phones if not d["rejoined"]] == ["cam3", "cam5"]
    images = _images(report)
    missing = [i for i in images if i["status"] == "missing"]
    assert {i["camera_id"] for i in missing} == {"cam3", "cam5"}
    assert {i["missing_reason"] for i in missing} == {"capture_missed", "phone_dropped"}
    assert set(report.missing_by_phone) == {"cam3", "cam5"}
    assert report.reason.startswith(f"{len(missing)} of 336 images missing: cam3 ")
    verified = [i for i in images if i["status"] == "verified"]
    assert len(verified) == 336 - len(missing)
    assert all(abs(i["actual_angle_deg"] - i["planned_angle_deg"]) <= 0.2 for i in verified)
    captures = json.loads((report.folder / "captures.json").read_text())
    retaken = [c for c in captures if c["capture_pass"] == "retake" and c["status"] == "captured"]
    by_camera = {camera: sorted(c["angle_index"] for c in retaken if c["camera_id"] == camera)
                 for camera in ("cam1", "cam5")}
    assert len(by_camera["cam1"]) == 2 and by_camera["cam5"] == by_camera["cam1"]
    assert report.retaken == len(retaken) == 4


def test_the_planner_is_warmed_up_before_the_first_plan(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Like the daemon's worker, the simulated scan's compute thread compiles (or loads) the
    planner's loops first, so the first plan does not compile them between the sweep and the capture."""
    import threading

    import daemon.jobs.scan_steps
    import sim.run

    calls: list[tuple[str, str]] = []
    warm_up, plan_capture = sim.run.warm_up, daemon.jobs.scan_steps.plan_capture

    def warming(rig):
        calls.append(("warm_up", threading.current_thread().name))
        return warm_up(rig)

    def planning(*args, **kwargs):
        calls.append(("plan", threading.current_thread().name))
        return plan_capture(*args, **kwargs)

    monkeypatch.setattr(sim.run, "warm_up", warming)
    monkeypatch.setattr(daemon.jobs.scan_steps, "plan_capture", planning)
    assert _scan(tmp_path).outcome is ScanOutcome.COMPLETED
    assert [name for name, _ in calls][:2] == ["warm_up", "plan"]
    assert calls[0][1] == calls[1][1] and calls[0][1].startswith("compute")
