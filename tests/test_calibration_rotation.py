"""The daemon's calibration rotation: stop and go, every camera at every stop, the folder always
consistent, faults and aborts handled like a scan's.

The drive (CANopen over the loopback bus) and the depth cameras are the protocol-level simulators;
the phones are the mock tier so a fault lands on an exact picture. Virtual time throughout.
"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from daemon.errors import ScanBusy
from daemon.faults import AbortCause, AbortSource
from daemon.jobs.calibration_rotation import create_rotation_folder, focus_on_cuboid_mm
from daemon.jobs.controller import RigController
from daemon.jobs.scan import ScanSettings
from daemon.records.store import ScanStore, StoreError
from daemon.rig.states import ScanOutcome, ScanState
from planner.calibration.target import load_target
from planner.poses import rgb_poses
from sim.clock import run_virtual
from tests.daemon_rigs import RIG, build_rig, run_job

TARGET = load_target()
N_ANGLES = len(RIG.capture.angles_deg)


def _infrared(camera_index: int, model: Any) -> Any:
    """A synthetic infrared picture that encodes the camera and the beam angle (checked below)."""

    def source(frame_number: int, angle_deg: float) -> np.ndarray:
        image = np.zeros((model.height_px, model.width_px), dtype=np.uint8)
        image[0, 0] = camera_index
        image[0, 1] = int(round(angle_deg % 360.0)) % 256
        image[1:, :] = (frame_number * 7) % 256
        return image

    return source


def rotate(store: Path, *, during: Any = None, prepare: Any = None, infrared: bool = True) -> tuple[Any, RigController, Any]:
    def set_up(world: Any) -> None:
        for i, camera in enumerate(world.depth_cameras):
            camera.infrared_source = _infrared(i, camera.model) if infrared else None
        if prepare is not None:
            prepare(world)

    async def calibration(controller: RigController) -> Any:
        return await (await controller.start_calibration("cal-test"))

    return run_job(store, calibration, during=during, prepare=set_up)


@pytest.fixture(scope="module")
def nominal(tmp_path_factory: pytest.TempPathFactory) -> tuple[Any, RigController, Any]:
    """One rotation where nothing goes wrong, shared by the tests that only read its outcome."""
    return rotate(tmp_path_factory.mktemp("nominal"))


def captures_of(report: Any) -> dict[str, Any]:
    import hashlib

    doc = json.loads((report.folder / "captures.json").read_text())
    for c in doc["captures"]:  # the folder is consistent: every listed picture is on disk, as recorded
        data = (report.folder / c["file"]).read_bytes()
        assert len(data) == c["size_bytes"] and hashlib.sha256(data).hexdigest() == c["sha256"], c["file"]
    return doc


@pytest.mark.slow
@pytest.mark.xdist_group("calibration-nominal")  # one worker makes the shared rotation
def test_every_camera_photographs_at_every_stop(nominal: tuple[Any, RigController, Any]) -> None:
    report, controller, world = nominal
    assert report.outcome is ScanOutcome.COMPLETED, report.problems
    doc = captures_of(report)
    assert doc["state"] == "complete" and doc["rig_digest"] == RIG.digest and doc["target"] == TARGET.name
    phones = [c for c in doc["captures"] if c["kind"] == "phone"]
    depth = [c for c in doc["captures"] if c["kind"] == "depth"]
    assert len(phones) == RIG.n_cameras * N_ANGLES and len(depth) == len(RIG.depth_cameras) * N_ANGLES
    assert report.pictures == len(doc["captures"]) and report.missing == 0
    # the beam stood at each capture angle (within the drive's position window) for its pictures
    for c in doc["captures"]:
        planned = RIG.capture.angles_deg[c["angle_index"]]
        assert abs(c["encoder_deg"] - planned) < 0.05, c
    # every phone focused on the cuboid's near face along its axis, and every picture was deleted
    for phone in world.phones:
        assert len(phone.deleted) == N_ANGLES
    # the infrared frame kept is one taken at the stop (it encodes the beam angle it saw)
    import cv2

    for c in depth:
        image = cv2.imread(str(report.folder / c["file"]), cv2.IMREAD_GRAYSCALE)
        assert image[0, 1] == int(round(c["encoder_deg"] % 360.0)) % 256
        assert c["intrinsics"]["fx"] > 0
    states = [e.state for e in controller.machine.history if e.kind == "transition"]
    assert states[-3:] == [ScanState.CALIBRATING, ScanState.STORING, ScanState.IDLE]
    assert controller.status()["last_calibration_rotation"]["outcome"] == "COMPLETED"
    assert controller.store.folders() == []  # a rotation is not a scan


@pytest.mark.slow
@pytest.mark.xdist_group("calibration-nominal")  # one worker makes the shared rotation
def test_the_pipeline_reads_the_rotation(nominal: tuple[Any, RigController, Any]) -> None:
    from planner.calibration.calibrate import read_captures

    report, _, _ = nominal
    pictures = read_captures(report.folder / "captures.json")
    assert len(pictures) == (RIG.n_cameras + len(RIG.depth_cameras)) * N_ANGLES
    assert all(p.path.is_file() for p in pictures)
    assert {p.intrinsics is not None for p in pictures if p.kind == "depth"} == {True}


@pytest.mark.slow
def test_a_phone_that_vanishes_is_named_and_the_rest_goes_on(tmp_path: Path) -> None:
    def prepare(world: Any) -> None:
        world.phones[2].fail_after = 5  # gone after 5 pictures (of the warm-up free rotation)

    report, _, _ = rotate(tmp_path, prepare=prepare)
    assert report.outcome is ScanOutcome.COMPLETED
    doc = captures_of(report)
    lost = RIG.phones[2].id
    assert len([c for c in doc["captures"] if c["camera"] == lost]) == 5
    assert len([c for c in doc["captures"] if c["kind"] == "phone"]) == (RIG.n_cameras - 1) * N_ANGLES + 5
    assert any(lost in p and "left out" in p for p in doc["problems"])
    assert report.missing == N_ANGLES - 5


@pytest.mark.slow
def test_a_depth_camera_without_infrared_is_named_and_the_phones_go_on(tmp_path: Path) -> None:
    report, _, _ = rotate(tmp_path, infrared=False)
    assert report.outcome is ScanOutcome.COMPLETED
    doc = captures_of(report)
    assert not [c for c in doc["captures"] if c["kind"] == "depth"]
    assert len(doc["captures"]) == RIG.n_cameras * N_ANGLES
    for camera in RIG.depth_cameras:
        assert any(camera.id in p and "InfraredUnavailable" in p for p in doc["problems"])


@pytest.mark.slow
def test_a_depth_camera_that_stalls_is_named_and_the_others_keep_their_own_frames(tmp_path: Path) -> None:
    async def during(controller: RigController, world: Any) -> None:
        while controller.current is None or len(controller.current.captures) < 60:
            await asyncio.sleep(0.05)
        controller.hw.depth_cameras[1].stop_streaming()  # its USB link stalls

    report, _, _ = rotate(tmp_path, during=during)
    assert report.outcome is ScanOutcome.COMPLETED
    doc = captures_of(report)
    stalled = RIG.depth_cameras[1].id
    assert any(stalled in p and "left out" in p for p in doc["problems"])
    kept = [c for c in doc["captures"] if c["camera"] == stalled]
    assert 0 < len(kept) < N_ANGLES
    import cv2

    for c in doc["captures"]:
        if c["kind"] == "depth":  # each frame is filed under the camera that took it
            image = cv2.imread(str(report.folder / c["file"]), cv2.IMREAD_GRAYSCALE)
            assert RIG.depth_cameras[int(image[0, 0])].id == c["camera"]
    others = [c for c in doc["captures"] if c["kind"] == "depth" and c["camera"] != stalled]
    assert len(others) == 2 * N_ANGLES


@pytest.mark.slow
@pytest.mark.parametrize("fault", ["estop", "drive_fault", "heartbeat_lost"])
def test_a_safety_fault_mid_rotation_latches_and_keeps_the_pictures(tmp_path: Path, fault: str) -> None:
    async def during(controller: RigController, world: Any) -> None:
        while controller.current is None or len(controller.current.captures) < 40:
            await asyncio.sleep(0.05)
        if fault == "estop":
            world.sim_drive.press_estop()
        elif fault == "drive_fault":
            world.sim_drive.inject_fault(0x2310)  # continuous over-current
        else:
            world.sim_drive.stop_heartbeat()

    report, controller, world = rotate(tmp_path, during=during)
    assert report.outcome is ScanOutcome.FAULTED, report.problems
    assert controller.machine.state is ScanState.FAULT  # latched: only a reset leaves it
    assert abs(world.sim_drive.true_speed_deg_s) < 1e-6
    doc = captures_of(report)
    assert doc["state"] == "fault" and 40 <= len(doc["captures"]) < (RIG.n_cameras + 3) * N_ANGLES
    assert doc["reason"]  # the latched causes, named


@pytest.mark.slow
def test_abort_stops_the_beam_and_keeps_the_pictures(tmp_path: Path) -> None:
    async def during(controller: RigController, world: Any) -> None:
        while controller.current is None or len(controller.current.captures) < 20:
            await asyncio.sleep(0.05)
        controller.abort(AbortCause(AbortSource.CONTROL_API, "test", "abort"))

    report, controller, world = rotate(tmp_path, during=during)
    assert report.outcome is ScanOutcome.ABORTED
    assert controller.machine.state is ScanState.IDLE
    assert abs(world.sim_drive.true_speed_deg_s) < 1e-6
    doc = captures_of(report)
    assert doc["state"] == "aborted" and len(doc["captures"]) >= 20


@pytest.mark.slow
def test_refused_while_a_rotation_runs(tmp_path: Path) -> None:
    async def during(controller: RigController, world: Any) -> None:
        while controller.current is None:  # the rotation has started
            await asyncio.sleep(0.05)
        with pytest.raises(ScanBusy):
            await controller.start_calibration("second")
        with pytest.raises(ScanBusy):
            await controller.start_scan("a-scan")
        controller.abort(AbortCause(AbortSource.CONTROL_API, "test", "done"))

    report, _, _ = rotate(tmp_path, during=during)
    assert report.outcome is ScanOutcome.ABORTED
    assert [p.name for p in (tmp_path / "calibration").iterdir()][0].endswith("-cal-test")
    assert len(list((tmp_path / "calibration").iterdir())) == 1


@pytest.mark.slow
def test_tbp_calibrate_follows_the_daemons_rotation_over_the_socket(tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    from cli.calibrate import _follow_rotation
    from daemon.server.service import RigService

    sock = tmp_path / "control.sock"

    async def main() -> Path | None:
        hardware, _world = await build_rig(RIG, 0)
        for i, camera in enumerate(hardware.depth_cameras):
            camera.infrared_source = _infrared(i, camera.model)
        controller = RigController(RIG, hardware, ScanStore(tmp_path / "store"), settings=ScanSettings())
        service = RigService(controller, socket_path=sock)
        await service.start()
        try:
            return await _follow_rotation(sock)
        finally:
            await service.stop()

    captures = run_virtual(main())
    assert captures is not None and captures.is_file()
    assert captures.parent.parent == tmp_path / "store" / "calibration"
    assert json.loads(captures.read_text())["state"] == "complete"
    out = capsys.readouterr().out
    assert "stop 0:" in out and "IDLE" in out


def test_rotation_folder_ids_are_checked(tmp_path: Path) -> None:
    with pytest.raises(StoreError, match="must be 1-64"):
        create_rotation_folder(tmp_path, "../escape")
    rotation_id, folder = create_rotation_folder(tmp_path, "ok-1")
    assert folder.parent == tmp_path / "calibration" and folder.name.endswith("-ok-1")
    with pytest.raises(StoreError, match="already exists"):
        create_rotation_folder(tmp_path, "ok-1", now=_stamp(folder))


def _stamp(folder: Path) -> Any:
    from datetime import datetime, timezone

    return datetime.strptime(folder.name[:15], "%Y%m%d-%H%M%S").replace(tzinfo=timezone.utc)


@settings(max_examples=40, deadline=None)
@given(st.floats(-720.0, 720.0))
def test_focus_lands_on_the_cuboid(angle: float) -> None:
    """Where a phone's optical axis meets the cuboid (standing at the centre), the focus distance
    puts the focal point on the cuboid's surface, on the face nearest the phone."""
    focus = focus_on_cuboid_mm(RIG, TARGET, angle)
    poses = rgb_poses(RIG, np.array([angle]))
    half = TARGET.size_mm[0] / 2
    hits = 0
    for c in range(RIG.n_cameras):
        pose = poses.camera_to_world(c)
        point = pose[:3, 3] + focus[c] * pose[:3, 2]
        if 0 < point[2] < TARGET.size_mm[2]:
            hits += 1
            assert np.isclose(np.max(np.abs(point[:2])), half, atol=1e-6)
            nearer = pose[:3, 3] + (focus[c] - 5.0) * pose[:3, 2]
            assert np.max(np.abs(nearer[:2])) > half  # outside just before: the near face
        assert focus[c] > 0
    assert hits >= RIG.n_cameras - 2  # the column's phones look at the cuboid


@pytest.mark.slow
def test_the_whole_loop_on_the_simulated_rig_recovers_the_true_poses(tmp_path: Path) -> None:
    """The daemon's rotation on the simulated rig (phones over ADB, the cuboid seen from the true
    poses), then the pipeline: the issue's accuracy goals against the simulated truth."""
    from planner.calibration.calibrate import calibrate, read_captures
    from planner.calibration.compare import compare
    from sim.calibration import true_rig
    from sim.cuboid_stage import CuboidStage
    from sim.run import sim_calibration_rotation

    truth = true_rig(RIG, TARGET, 3)
    report = run_virtual(sim_calibration_rotation(RIG, CuboidStage(RIG, TARGET, truth, seed=3),
                                                  store=tmp_path, seed=3))
    assert report.outcome is ScanOutcome.COMPLETED and report.missing == 0, report.problems
    run = calibrate(RIG, TARGET, read_captures(report.folder / "captures.json"), created_utc="test", source="test")
    assert run.calibration.residuals is not None and run.calibration.residuals.mean_px <= 0.5
    for kind in ("phone", "depth"):
        ids = [c.id for c in run.calibration.cameras if c.kind == kind]
        assert len(ids) == (RIG.n_cameras if kind == "phone" else len(RIG.depth_cameras))
        s = compare(run.calibration, truth, RIG.capture.angles_deg, ids).summary()
        assert s["median_mm"] <= 1.0 and s["median_deg"] <= 0.1, (kind, s)
        assert s["max_mm"] <= 2.0 and s["max_deg"] <= 0.2, (kind, s)


def test_a_phone_looking_past_the_cuboid_focuses_where_its_axis_nears_the_rigs() -> None:
    """A cuboid too short for the top phone: its focus is the closest approach of its axis to z."""
    import dataclasses

    short = dataclasses.replace(TARGET, size_mm=(TARGET.size_mm[0], TARGET.size_mm[1], 300.0))
    poses = rgb_poses(RIG, np.array([0.0]))
    top = int(np.argmax([poses.camera_to_world(c)[2, 3] for c in range(RIG.n_cameras)]))
    pose = poses.camera_to_world(top)
    focus = focus_on_cuboid_mm(RIG, short, 0.0)[top]
    point = pose[:3, 3] + focus * pose[:3, 2]
    assert point[2] > 300.0  # it does not reach the cuboid
    # no point of the axis comes nearer to the rig's axis than this one
    for t in (focus - 20.0, focus + 20.0):
        other = pose[:3, 3] + t * pose[:3, 2]
        assert np.hypot(*other[:2]) > np.hypot(*point[:2])
