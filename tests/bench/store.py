"""Daemon infrastructure costs on the capture path: plan compilation, manifest rewrites, checksums.

Goals: compiling the plan fits in the 2 s between the depth sweep and the capture rotation
(<= 50 ms); rewriting the manifest after each of the 336 images blocks the loop <= 10 ms
(wall, fsync included; depends on the disk) and costs <= 4 s CPU per scan (5 % of the
80 s rotation, so a core stays idle); verifying
pulled images by SHA-256 keeps up with the phones (>= 200 MB/s, far above USB 2 ADB).
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from daemon.records.atomic import sha256_of
from daemon.records.manifest import ScanEnd
from daemon.records.store import ScanStore
from planner.rig import load_rig
from planner.schedule import compile_plan, phone_timings

REPEATS = 5


def _compile_ms(rig) -> float:
    focus = np.full(rig.n_poses, 600.0)
    phones = phone_timings(rig, trigger_latency_s=[0.03] * rig.n_cameras)
    runs = []
    for _ in range(REPEATS):
        t = time.perf_counter()
        compile_plan(focus, rig, phones)
        runs.append(time.perf_counter() - t)
    return 1e3 * statistics.median(runs)


def _manifest_costs(rig, root: Path) -> tuple[float, float, float]:
    """Median wall ms per rewrite, CPU s per scan, manifest size kB."""
    per_scan_cpu = []
    per_write = []
    size = 0.0
    for r in range(2):
        folder = ScanStore(root).create(rig, scan_id=f"bench{r}")
        folder.plan_images(rig.capture.angles_deg, np.full(rig.n_poses, 600.0))
        cpu0 = time.process_time()
        for k in range(rig.n_angles):
            for c in range(rig.n_cameras):
                t = time.perf_counter()
                folder.record_capture(c, k, sensor_timestamp_ns=k * 10**9, host_time_s=float(k),
                                      actual_angle_deg=float(rig.capture.angles_deg[k]),
                                      phone_path=f"/sdcard/DCIM/tbp/{c}_{k}.jpg",
                                      size_bytes=9_000_000)
                per_write.append(time.perf_counter() - t)
        per_scan_cpu.append(time.process_time() - cpu0)
        size = (folder.path / "manifest.json").stat().st_size / 1e3
        folder.finish(ScanEnd.COMPLETE)
    return 1e3 * statistics.median(per_write), statistics.median(per_scan_cpu), size


def _sha_mb_s(root: Path) -> float:
    path = root / "image.bin"
    path.write_bytes(os.urandom(32 << 20))
    runs = []
    for _ in range(REPEATS):
        t = time.perf_counter()
        sha256_of(path)
        runs.append(time.perf_counter() - t)
    return 32 * 1.048576 / statistics.median(runs)


def run() -> None:
    rig = load_rig()
    print(f"compile_plan ({rig.n_poses} poses): {_compile_ms(rig):.1f} ms median (goal <= 50 ms)")
    with tempfile.TemporaryDirectory(dir=os.environ.get("TBP_BENCH_DIR")) as tmp:
        write_ms, cpu_s, size_kb = _manifest_costs(rig, Path(tmp))
        print(f"manifest rewrite after each image: {write_ms:.2f} ms wall median (loop blocked, "
              f"mostly fsync), {1e3 * cpu_s / rig.n_poses:.2f} ms CPU, {size_kb:.0f} kB "
              f"(goal <= 10 ms)")
        print(f"manifest rewrites over a {rig.n_poses}-image scan: {cpu_s:.2f} s CPU "
              f"(goal <= 4 s)")
        print(f"sha256 verification: {_sha_mb_s(Path(tmp)):.0f} MB/s median (goal >= 200 MB/s)")
