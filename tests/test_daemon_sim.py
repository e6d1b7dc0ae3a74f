"""Scans on the complete simulated rig (CANopen drive, ADB phones, depth cameras) in virtual time."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import pytest

from daemon.scan import ScanReport
from daemon.simulation import run_sim_scan
from daemon.states import ScanOutcome
from tests.daemon_rigs import PLAN_POINTS, capsule_subject, wait_captured

pytestmark = pytest.mark.slow


def _scan(store: Path, fault=None, **kwargs) -> ScanReport:
    tasks: list[asyncio.Task] = []

    def on_ready(controller, world) -> None:
        if fault is not None:
            tasks.append(asyncio.create_task(fault(controller, world)))

    return run_sim_scan(store=store, seed=1, plan_points=PLAN_POINTS, depth_decimation=4,
                        subject=capsule_subject(), panel=False, on_ready=on_ready, **kwargs)


def _images(report: ScanReport) -> list[dict]:
    return json.loads((report.folder / "manifest.json").read_text())["images"]


def test_a_phone_that_vanishes_mid_scan_is_recorded_missing_with_its_error(tmp_path: Path) -> None:
    async def unplug(controller, world) -> None:
        await wait_captured(controller, 120)
        world.phones[3].vanish()

    report = _scan(tmp_path, unplug)
    assert report.outcome is ScanOutcome.COMPLETED
    assert 0 < report.missing < 48
    missing = [i for i in _images(report) if i["status"] == "missing"]
    assert {i["camera_id"] for i in missing} == {"cam3"}
    assert all("PhoneDisconnected" in i["error"] or "ConnectionLost" in i["error"] for i in missing)
    captured = [i for i in _images(report) if i["status"] == "verified"]
    assert len(captured) == 336 - len(missing)
    assert all(abs(i["actual_angle_deg"] - i["planned_angle_deg"]) <= 0.2 for i in captured)


def test_a_phone_that_comes_back_is_retaken_in_a_second_pass(tmp_path: Path) -> None:
    async def replug(controller, world) -> None:
        await wait_captured(controller, 120)
        world.phones[5].vanish()
        await asyncio.sleep(5.0)
        world.phones[5].reappear()

    report = _scan(tmp_path, replug)
    assert report.outcome is ScanOutcome.COMPLETED
    assert report.missing == 0 and report.retaken > 0
    assert report.max_abs_angle_error_deg <= 0.2
    captures = json.loads((report.folder / "captures.json").read_text())
    retaken = [c for c in captures if c["capture_pass"] == "retake"]
    assert {c["camera_id"] for c in retaken} == {"cam5"}
