"""Scan store: atomic writes, manifest, recover(), background pulls, disk full (daemon/records/store.py)."""

from __future__ import annotations

import asyncio
import errno
import hashlib
import json
import os
import subprocess
import threading
import uuid
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest

from daemon.faults import AbortCause, AbortSource, FaultCause, FaultSource
from daemon.jobs.pulls import PullPolicy, PullQueue, ScanImages
from daemon.records.atomic import AtomicWriter, StoreError, StoreFull
from daemon.records.manifest import ManifestError, ScanEnd
from daemon.records.store import ScanStore, _writer_thread
from planner.rig import load_rig

NOW = datetime(2026, 11, 22, 9, 30, 0, tzinfo=UTC)


@pytest.fixture(scope="module")
def rig():
    return load_rig()


def _manifest(folder) -> dict:
    return json.loads((folder.path / "manifest.json").read_text())


def _planned(store: ScanStore, rig, scan_id="abc123"):
    folder = store.create(rig, scan_id=scan_id, now=NOW)
    folder.plan_images(rig.capture.angles_deg, np.full(rig.n_poses, 500.0))
    return folder


class CrashingWriter(AtomicWriter):
    """Writes half of the file, then fails like a full disk or a crash mid-write."""

    def __init__(self, errno_: int) -> None:
        self.armed = False
        self.errno_ = errno_

    def _write_all(self, fd: int, data: bytes) -> None:
        if self.armed:
            os.write(fd, data[: len(data) // 2])
            raise OSError(self.errno_, os.strerror(self.errno_))
        super()._write_all(fd, data)


def test_new_folder_is_incomplete_and_in_progress(tmp_path, rig):
    folder = ScanStore(tmp_path).create(rig, scan_id="s1", now=NOW)
    assert folder.path == tmp_path / "20261122-093000-s1"
    m = _manifest(folder)
    assert m["state"] == "incomplete" and m["in_progress"] is True
    assert m["format_version"] == 1 and m["rig_digest"] == rig.digest
    assert len(m["calibration_digest"]) == 64
    assert m["cameras"] == [p.id for p in rig.phones]


def test_scan_id_must_be_opaque_token(tmp_path, rig):
    with pytest.raises(StoreError, match="scan id"):
        ScanStore(tmp_path).create(rig, scan_id="Jane Doe/1985", now=NOW)


def test_full_lifecycle_writes_every_file(tmp_path, rig):
    folder = _planned(ScanStore(tmp_path), rig)
    asyncio.run(folder.write_plan({"focus_mm": [500.0] * rig.n_poses}, {"in_focus_fraction": 0.8}))
    asyncio.run(folder.write_mesh(b"ply\nformat ascii 1.0\nend_header\n"))
    asyncio.run(folder.write_trace(np.arange(5.0), np.arange(5.0) * 3))
    asyncio.run(folder.write_depth_sweep({"frames": 120}))
    asyncio.run(folder.write_json("qa", "qa.json", {"captured": 1, "angle_error_deg": [0.01, float("inf")]}))
    folder.log_event("capture_start", angle_index=0)
    folder.log_event("capture_end", value=float("nan"))
    folder.record_capture(2, 7, sensor_timestamp_ns=123, host_time_s=4.5, actual_angle_deg=48.01,
                          phone_path="/sdcard/x.jpg", size_bytes=10)
    folder.finish(ScanEnd.COMPLETE)
    m = _manifest(folder)
    # a scan asked to end complete without every image is partial, its missing images named
    assert m["state"] == "partial" and m["in_progress"] is False
    assert set(m["files"]) == {"plan", "mesh", "trace", "depth_sweep", "events", "qa"}
    img = next(i for i in m["images"] if i["camera_index"] == 2 and i["angle_index"] == 7)
    assert img["status"] == "captured" and img["actual_angle_deg"] == 48.01
    assert img["missing_reason"] == "not_pulled"
    assert m["missing_by_phone"]["cam2"] == {"not_reached": rig.n_angles - 1, "not_pulled": 1}
    assert m["reason"].startswith(f"{rig.n_poses} of {rig.n_poses} images missing: cam0 48 (48 not reached); ")
    assert img["focus_diopters"] == pytest.approx(2.0)
    assert m["counts"]["missing"] == rig.n_poses - 1
    lines = (folder.path / "events.jsonl").read_text().splitlines()
    assert [json.loads(x)["event"] for x in lines] == ["capture_start", "capture_end"]
    assert json.loads(lines[1])["value"] is None
    assert m["plan_summary"] == {"in_focus_fraction": 0.8}
    qa = json.loads((folder.path / "qa.json").read_text())
    assert qa == {"captured": 1, "angle_error_deg": [0.01, None]}
    trace = np.load(folder.path / "trace.npz")
    np.testing.assert_array_equal(trace["angle_deg"], np.arange(5.0) * 3)


def test_crash_mid_write_keeps_the_previous_manifest(tmp_path, rig):
    writer = CrashingWriter(errno.EIO)
    folder = _planned(ScanStore(tmp_path, writer=writer), rig)
    before = (folder.path / "manifest.json").read_bytes()
    writer.armed = True
    with pytest.raises(StoreError, match="errno 5") as info:
        folder.record_capture(0, 0, sensor_timestamp_ns=1, host_time_s=1.0, actual_angle_deg=-40.0,
                              phone_path="/p.jpg", size_bytes=1)
    assert not isinstance(info.value, StoreFull)
    assert (folder.path / "manifest.json").read_bytes() == before
    assert not list(folder.path.glob(".*.tmp"))


def test_enospc_is_a_typed_error_naming_path_and_bytes(tmp_path, rig):
    writer = CrashingWriter(errno.ENOSPC)
    folder = _planned(ScanStore(tmp_path, writer=writer), rig)
    before = _manifest(folder)
    writer.armed = True
    with pytest.raises(StoreFull) as info:
        folder.record_capture(0, 0, sensor_timestamp_ns=1, host_time_s=1.0, actual_angle_deg=-40.0,
                              phone_path="/p.jpg", size_bytes=1)
    assert info.value.path.endswith("manifest.json") and info.value.bytes_needed > 1000
    assert "bytes needed" in str(info.value)
    assert _manifest(folder) == before  # still valid JSON, nothing lost


def test_recover_marks_in_progress_folders_incomplete(tmp_path, rig):
    store = ScanStore(tmp_path)
    live = _planned(store, rig, "killed")
    live.record_capture(1, 0, sensor_timestamp_ns=1, host_time_s=1.0, actual_angle_deg=-40.0,
                        phone_path="/p.jpg", size_bytes=3)
    # a verified-in-file-but-not-in-manifest pull, a leftover temp file
    (live.path / "images" / "cam0-a00.jpg").write_bytes(b"abc")
    live.update_image(0, 0, status="pulled", file="images/cam0-a00.jpg", size_bytes=3,
                      sha256=hashlib.sha256(b"abc").hexdigest())
    (live.path / ".manifest.json.tmp").write_bytes(b"{torn")
    asyncio.run(live.write_trace(np.array([0.0, 0.1]), np.array([-40.0, -39.1])))  # saved mid-scan, not yet listed
    del live.manifest.files["trace"]
    live.save()
    done = store.create(rig, scan_id="done", now=NOW)
    done.finish(ScanEnd.ABORTED, [AbortCause(AbortSource.STOP_BUTTON, "panel", "stop button")])
    (tmp_path / "20261122-093001-nomanifest").mkdir()

    recovered = store.recover("killed by test")
    assert sorted(f.scan_id for f in recovered) == ["killed", "nomanifest"]
    m = _manifest(live)
    assert m["state"] == "incomplete" and m["in_progress"] is False
    assert m["reason"] == "killed by test"
    statuses = {(i["camera_index"], i["angle_index"]): i for i in m["images"]}
    assert statuses[(0, 0)]["status"] == "verified"
    assert statuses[(1, 0)]["status"] == "captured" and "not pulled" in statuses[(1, 0)]["error"]
    assert statuses[(2, 0)]["status"] == "missing"
    assert statuses[(1, 0)]["missing_reason"] == "not_pulled" and statuses[(2, 0)]["missing_reason"] == "not_reached"
    assert m["missing_by_phone"]["cam1"] == {"not_pulled": 1, "not_reached": rig.n_angles - 1}
    assert not list(live.path.glob(".*.tmp"))
    assert m["files"]["trace"] == "trace.npz"  # the trace saved before the kill is kept
    events = [json.loads(line) for line in (live.path / "events.jsonl").read_text().splitlines()]
    assert events[-1]["event"] == "scan_recovered" and events[-1]["reason"] == "killed by test"
    assert events[-1]["verified"] == 1 and events[-1]["captured"] == 1
    assert _manifest(done)["state"] == "aborted"
    assert _manifest(done)["reason"] == "panel: stop button"
    assert _manifest(done)["causes"] == [{"source": "stop_button", "device": "panel",
                                          "detail": "stop button", "text": "panel: stop button"}]
    assert store.open(done.path).manifest.causes == [AbortCause(AbortSource.STOP_BUTTON, "panel", "stop button")]
    assert "no manifest" in _manifest(store.open(tmp_path / "20261122-093001-nomanifest"))["reason"]
    assert store.recover() == []


def test_unreadable_manifest_is_a_typed_error(tmp_path, rig):
    folder = ScanStore(tmp_path).create(rig, scan_id="x", now=NOW)
    (folder.path / "manifest.json").write_text('{"format_version": 99}')
    with pytest.raises(ManifestError, match="format_version 99"):
        ScanStore(tmp_path).open(folder.path)


@pytest.mark.parametrize("damage", ["cut short", "not an archive", "one array"])
def test_a_damaged_trace_is_a_typed_error_naming_it(tmp_path, rig, damage):
    folder = ScanStore(tmp_path).create(rig, scan_id="x", now=NOW)
    path = asyncio.run(folder.write_trace(np.arange(5.0), np.arange(5.0) * 3))
    assert ScanStore(tmp_path).open(folder.path).read_trace()["angle_deg"][-1] == 12.0
    if damage == "cut short":
        path.write_bytes(path.read_bytes()[:40])  # the zip's directory, at its end, is gone
    elif damage == "not an archive":
        path.write_bytes(b"bit rot")
    else:
        np.save(path.open("wb"), np.arange(3.0))  # an .npy where the .npz was
    with pytest.raises(StoreError, match="trace.npz: unreadable"):
        ScanStore(tmp_path).open(folder.path).read_trace()


class FakePhone:
    """pull(phone_path, dest) like PhoneCamera.pull, with injected failures."""

    def __init__(self, fail_first: int = 0, corrupt: bool = False, error: OSError | None = None):
        self.fail_first = fail_first
        self.corrupt = corrupt
        self.error = error
        self.calls = 0

    async def pull(self, phone_path: str, dest: Path) -> tuple[int, str]:
        self.calls += 1
        if self.error is not None:
            raise self.error
        if self.calls <= self.fail_first:
            raise ConnectionError(f"adb stream closed pulling {phone_path}")
        data = phone_path.encode() * 10
        dest.write_bytes(data[:-1] + b"X" if self.corrupt else data)
        return len(data), hashlib.sha256(data).hexdigest()


async def test_background_pulls_verify_retry_and_record(tmp_path, rig):
    folder = _planned(ScanStore(tmp_path), rig)
    good, flaky, broken = FakePhone(), FakePhone(fail_first=1), FakePhone(corrupt=True)
    images = ScanImages(folder)
    async with PullQueue(images, workers=2, policy=PullPolicy(retry_delay_s=0.0)) as q:
        q.submit(images.pull(0, 0, "/sdcard/a.jpg", good.pull, expected_size=130))
        q.submit(images.pull(1, 0, "/sdcard/b.jpg", flaky.pull))
        q.submit(images.pull(2, 0, "/sdcard/c.jpg", broken.pull))
        await q.join()
    m = _manifest(folder)
    img = {(i["camera_index"], i["angle_index"]): i for i in m["images"]}
    assert img[(0, 0)]["status"] == "verified" and img[(0, 0)]["file"] == "images/cam0-a00.jpg"
    assert (folder.path / "images/cam0-a00.jpg").read_bytes() == b"/sdcard/a.jpg" * 10
    assert img[(1, 0)]["status"] == "verified" and img[(1, 0)]["attempts"] == 2
    assert img[(2, 0)]["status"] == "failed" and "sha256" in img[(2, 0)]["error"]
    assert broken.calls == PullPolicy().retries + 1
    assert not (folder.path / "images/cam2-a00.jpg").exists()
    assert [f.camera_id for f in q.failures] == ["cam2"]


async def test_a_hanging_pull_times_out_and_is_retried(tmp_path, rig):
    folder = _planned(ScanStore(tmp_path), rig)
    calls = []

    async def stuck_then_fine(phone_path: str, dest: Path) -> tuple[int, str]:
        calls.append(phone_path)
        if len(calls) == 1:
            await asyncio.Event().wait()  # the phone never answers
        return await FakePhone().pull(phone_path, dest)

    images = ScanImages(folder)
    async with PullQueue(images, policy=PullPolicy(timeout_s=0.05, retry_delay_s=0.0)) as q:
        q.submit(images.pull(5, 2, "/sdcard/e.jpg", stuck_then_fine))
        await q.join()
    image = _manifest(folder)["images"][rig.pose_index(2, 5)]
    assert image["status"] == "verified" and image["attempts"] == 2 and len(calls) == 2


async def test_pull_onto_a_full_disk_keeps_the_image_captured(tmp_path, rig):
    folder = _planned(ScanStore(tmp_path), rig)
    folder.record_capture(3, 4, sensor_timestamp_ns=1, host_time_s=1.0, actual_angle_deg=0.0,
                          phone_path="/sdcard/d.jpg", size_bytes=100)
    phone = FakePhone(error=OSError(errno.ENOSPC, "No space left on device"))
    images = ScanImages(folder)
    async with PullQueue(images) as q:
        q.submit(images.pull(3, 4, "/sdcard/d.jpg", phone.pull, expected_size=100))
        with pytest.raises(StoreFull):
            await q.join()
    image = _manifest(folder)["images"][rig.pose_index(4, 3)]
    assert image["status"] == "captured" and "disk full" in image["error"]
    assert phone.calls == 1  # a full disk is not retried


async def test_unwritable_manifest_during_pulls_is_raised_not_hung(tmp_path, rig):
    writer = CrashingWriter(errno.EIO)
    folder = _planned(ScanStore(tmp_path, writer=writer, reserve_bytes=0), rig)
    writer.armed = True
    images = ScanImages(folder)
    async with PullQueue(images, workers=1) as q:
        q.submit(images.pull(0, 0, "/sdcard/a.jpg", FakePhone().pull))
        q.submit(images.pull(1, 0, "/sdcard/b.jpg", FakePhone().pull))
        with pytest.raises(StoreError, match="errno 5"):
            await asyncio.wait_for(q.join(), 30.0)


async def test_not_enough_free_space_refused_before_pulling(tmp_path, rig):
    folder = _planned(ScanStore(tmp_path), rig)
    phone = FakePhone()
    images = ScanImages(folder)
    async with PullQueue(images) as q:
        q.submit(images.pull(0, 1, "/sdcard/huge.dng", phone.pull, expected_size=1 << 60))
        with pytest.raises(StoreFull) as info:
            await q.join()
    assert info.value.bytes_needed > 1 << 60 and phone.calls == 0


@pytest.fixture
def tiny_tmpfs(tmp_path):
    mnt = tmp_path / "tiny"
    mnt.mkdir()
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", f"tbp-{uuid.uuid4().hex[:6]}",
                          str(mnt)], capture_output=True, text=True)
    if res.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root): {res.stderr.strip()}")
    yield mnt
    subprocess.run(["umount", str(mnt)], check=True)


def _fill(folder: Path) -> None:
    """Fill a file system to its last block."""
    with pytest.raises(OSError) as info:
        with open(folder / "filler", "wb") as f:
            while True:
                f.write(b"x" * 4096)
                f.flush()
    assert info.value.errno == errno.ENOSPC


def test_real_enospc_on_a_tiny_tmpfs(tiny_tmpfs, rig):
    folder = _planned(ScanStore(tiny_tmpfs, reserve_bytes=300_000), rig)
    folder.record_capture(0, 0, sensor_timestamp_ns=5, host_time_s=1.0, actual_angle_deg=-40.0,
                          phone_path="/p.jpg", size_bytes=1)
    with pytest.raises(StoreFull) as info:
        asyncio.run(folder.write_mesh(os.urandom(800_000)))
    assert info.value.path.endswith("mesh.ply") and info.value.bytes_needed == 800_000
    assert not list(folder.path.glob(".*.tmp"))
    # fill the disk to the last block, then the scan still ends with a valid manifest
    _fill(tiny_tmpfs)
    folder.record_capture(1, 0, sensor_timestamp_ns=6, host_time_s=1.1, actual_angle_deg=-40.0,
                          phone_path="/q.jpg", size_bytes=1)
    assert not folder.reserve_path.exists()
    folder.finish(ScanEnd.FAULT, [FaultCause(FaultSource.ESTOP, "panel", "e-stop pressed")])
    m = _manifest(folder)
    assert m["state"] == "fault"
    assert [i["status"] for i in m["images"][:2]] == ["captured", "captured"]


def test_without_reserve_a_full_disk_leaves_the_previous_manifest(tiny_tmpfs, rig):
    folder = _planned(ScanStore(tiny_tmpfs, reserve_bytes=0), rig)
    before = (folder.path / "manifest.json").read_bytes()
    _fill(tiny_tmpfs)
    with pytest.raises(StoreFull):
        folder.finish(ScanEnd.COMPLETE)
    assert (folder.path / "manifest.json").read_bytes() == before


def test_check_and_tbp_scans_find_a_damaged_image(tmp_path, rig, capsys):
    from cli import main as tbp_main

    store = ScanStore(tmp_path)
    folder = _planned(store, rig, "good")
    image = folder.path / "images" / "cam0-a00.jpg"
    image.write_bytes(b"pixels")
    folder.update_image(0, 0, status="verified", file="images/cam0-a00.jpg", size_bytes=6,
                        sha256=hashlib.sha256(b"pixels").hexdigest())
    folder.finish(ScanEnd.COMPLETE)
    assert folder.check() == []
    assert tbp_main(["scans", "--store", str(tmp_path), "--check"]) == 0
    out = capsys.readouterr().out
    assert "partial" in out
    listed = len(folder.manifest.files)
    assert (f"    checked: 1 verified images re-read (size and SHA-256), {listed} listed files present: "
            "all as the manifest records") in out
    assert out.splitlines()[-1] == (f"--check: 1 scans, 1 verified images re-read (size and SHA-256), "
                                    f"{listed} listed files present; 0 problems")

    image.write_bytes(b"pixelz")  # bit rot
    asyncio.run(folder.write_plan({}, {}))
    (folder.path / "plan.json").unlink()
    live = _planned(store, rig, "live")
    assert live.check() == ["still marked in progress (running, or left by a killed daemon)"]
    problems = folder.check()
    assert problems == ["plan file plan.json is listed but missing",
                        "cam0 angle 0: images/cam0-a00.jpg does not match its SHA-256"]
    assert tbp_main(["scans", "--store", str(tmp_path), "--check", "--json"]) == 1
    rows = [json.loads(x) for x in capsys.readouterr().out.splitlines() if x.startswith("{")]
    assert {r["scan_id"]: len(r["problems"]) for r in rows} == {"good": 2, "live": 1}


class CountingWriter(AtomicWriter):
    """Counts manifest writes, can fail the next one like a full disk, checks that every file a
    manifest lists is already on disk, and records the order in which files reach the disk
    (whole files by name, appended lines as ``events.jsonl+``)."""

    def __init__(self) -> None:
        self.manifest_writes = 0
        self.fail_next = False
        self.order: list[str] = []
        self.gate: threading.Event | None = None  # when set: writes wait for it

    def write(self, path: Path, data: bytes) -> None:
        if self.gate is not None:
            self.gate.wait(10.0)
        if path.name == "manifest.json":
            if self.fail_next:
                self.fail_next = False
                raise StoreFull(path, len(data), 0)
            self.manifest_writes += 1
            files = json.loads(data)["files"]
            missing = [name for name in files.values() if not (path.parent / name).is_file()]
            assert not missing, f"the manifest lists {missing} before they are on disk"
        super().write(path, data)
        self.order.append(path.name)

    def append_lines(self, path: Path, lines: list[bytes]) -> None:
        if self.gate is not None:
            self.gate.wait(10.0)
        super().append_lines(path, lines)
        self.order.append(path.name + "+")


async def test_background_saves_coalesce_and_the_closed_manifest_holds_the_last_state(tmp_path, rig):
    writer = CountingWriter()
    folder = _planned(ScanStore(tmp_path, writer=writer, reserve_bytes=0), rig)
    before = writer.manifest_writes
    folder.save_in_background()
    for angle in range(rig.n_angles):
        for camera in range(rig.n_cameras):
            folder.update_image(camera, angle, status="verified", size_bytes=angle * 10 + camera)
    await folder.close(ScanEnd.COMPLETE)
    on_disk = _manifest(folder)
    assert on_disk["in_progress"] is False and on_disk["state"] == "complete"
    sizes = sorted(i["size_bytes"] for i in on_disk["images"])
    assert sizes == sorted(a * 10 + c for a in range(rig.n_angles) for c in range(rig.n_cameras))
    # every save rendered a snapshot, far fewer reached the disk (each an fdatasync and a folder fsync)
    assert writer.manifest_writes - before < rig.n_poses


async def test_a_failed_background_write_is_raised_by_the_next_save_and_the_close_writes_again(tmp_path, rig):
    writer = CountingWriter()
    folder = _planned(ScanStore(tmp_path, writer=writer, reserve_bytes=0), rig)
    folder.save_in_background()
    writer.fail_next = True
    folder.update_image(0, 0, status="verified")
    with pytest.raises(StoreFull):
        await folder._ordered.drain()  # the failing write has run in the writer thread
    writer.fail_next = True
    folder.update_image(0, 1, status="verified")
    await asyncio.wrap_future(_writer_thread().submit(lambda: None))  # the failing write has run
    with pytest.raises(StoreFull):
        folder.update_image(0, 2, status="verified")
    await folder.close(ScanEnd.COMPLETE)  # the final save writes the whole manifest
    status = {(i["camera_index"], i["angle_index"]): i["status"] for i in _manifest(folder)["images"]}
    assert status[0, 0] == status[0, 1] == status[0, 2] == "verified"
    assert _manifest(folder)["in_progress"] is False


async def test_background_writes_leave_the_loop_in_order_and_list_a_file_once_it_is_durable(tmp_path, rig):
    """Events, a whole file and manifest saves queue in the writer thread in the order asked;
    nothing waits for the disk on the loop; the manifest never names a file not yet written."""
    writer = CountingWriter()
    folder = _planned(ScanStore(tmp_path, writer=writer, reserve_bytes=0), rig)
    folder.save_in_background()
    writer.order.clear()
    writer.gate = threading.Event()  # the disk stalls
    folder.log_event("scan_started")
    folder.write_calibration(b"cameras: {}\n")
    folder.log_event("prepared", phones=7)
    folder.log_event("depth_sweep", frames=3)
    folder.update_image(0, 0, status="captured")
    assert "calibration" not in folder.manifest.files and "events" not in folder.manifest.files
    assert not (folder.path / "events.jsonl").exists()  # nothing was written on the loop
    writer.gate.set()
    await folder._ordered.drain()
    await folder.close(ScanEnd.COMPLETE)
    assert writer.order[:2] == ["events.jsonl+", "calibration.yaml"]
    assert writer.order.count("events.jsonl+") == 2  # the two lines queued together shared one fdatasync
    events = [json.loads(x)["event"] for x in (folder.path / "events.jsonl").read_text().splitlines()]
    assert events == ["scan_started", "prepared", "depth_sweep"]
    assert _manifest(folder)["files"] == {"events": "events.jsonl", "calibration": "calibration.yaml"}
    assert _manifest(folder)["images"][0]["status"] == "captured"
    assert not folder.check()


async def test_a_file_the_background_could_not_write_is_never_listed(tmp_path, rig):
    class FullForYaml(CountingWriter):
        def write(self, path: Path, data: bytes) -> None:
            if path.suffix == ".yaml":
                raise StoreFull(path, len(data), 0)
            super().write(path, data)

    writer = FullForYaml()
    folder = _planned(ScanStore(tmp_path, writer=writer, reserve_bytes=0), rig)
    folder.save_in_background()
    folder.write_calibration(b"cameras: {}\n")
    with pytest.raises(StoreFull):  # the folder's next write, or a drain, raises it
        await folder._ordered.drain()
    folder.save()  # raised once
    await folder.close(ScanEnd.INCOMPLETE)
    assert "calibration" not in _manifest(folder)["files"] and not folder.check()
