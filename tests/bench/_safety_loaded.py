"""Loaded loopback scans and SIGTERMs during scans, in real time.

* Scans on the loopback rig with one more process keeping a core busy: every scan's outcome, the
  safety trips and heartbeats lost (goal: none), the event loop's lag per state (goal: p99 <= 10
  ms, max <= 50 ms in every state). TBP_BENCH_SAFETY_SCANS sets how many (default 10).
* SIGTERM at a random moment of a scan (the daemon restarted for each): the exit time (goal:
  within TimeoutStopSec, 30 s), every scan folder closed, every image the manifest calls captured
  on disk with its recorded hash. TBP_BENCH_SAFETY_SIGTERMS sets how many (default 10).
"""

from __future__ import annotations

import hashlib
import os
import random
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from daemon.records.manifest import ImageStatus
from daemon.records.store import ScanStore
from sim.loopback import LoopbackRig

UNIT_STOP_TIMEOUT_S = 30.0


def _lost_images(store: Path) -> tuple[int, int, int]:
    """(folders, folders left in progress, images the manifest holds as on disk but which are not)."""
    scans = ScanStore(store)
    folders = scans.folders()
    open_, lost = 0, 0
    for folder in folders:
        manifest = scans.open(folder).manifest
        open_ += manifest.in_progress
        for image in manifest.images:
            if image.status is ImageStatus.VERIFIED and image.file:
                path = folder / image.file
                if not path.is_file() or (image.sha256 and hashlib.sha256(path.read_bytes()).hexdigest() != image.sha256):
                    lost += 1
    return len(folders), open_, lost


def loaded_scans(root: Path, scans: int) -> dict[str, Any]:
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    outcomes: list[str] = []
    try:
        with LoopbackRig(root, out=sys.stdout) as rig:
            assert rig.notify is not None
            rig.notify.wait("READY", "1", 180.0, alive=rig.procs["daemon"].alive)
            for n in range(scans):
                scan_id = rig.control("scan")["scan_id"]
                status = rig.wait_status(lambda s, i=scan_id: (s.get("last_scan") or {}).get("scan_id") == i,
                                         "the scan's end", 900.0)
                outcomes.append(status["last_scan"]["outcome"])
                print(f"  scan {n + 1}/{scans}: {outcomes[-1]}", flush=True)
                if status["state"] == "FAULT":
                    rig.control("reset")
            lag = rig.control("status")["loop_lag"]
            trips = rig.log_events("daemon", "safety_trip", stamp=None)
            lost = (len(rig.log_events("daemon", "drive_guard_tripped", stamp=None))
                    + len(rig.log_events("daemon", "panel_heartbeat_lost", stamp=None))
                    + len(rig.log_events("motor", "sim_node_heartbeat_lost", stamp=None)))
    finally:
        busy.kill()
    return {"outcomes": outcomes, "lag": lag, "trips": trips, "heartbeats_lost": lost}


def sigterms(root: Path, count: int, seed: int = 0) -> dict[str, Any]:
    rng = random.Random(seed)
    exits: list[float] = []
    codes: list[int | None] = []
    with LoopbackRig(root, out=sys.stdout) as rig:
        for n in range(count):
            if n:
                rig.start_daemon()
            daemon = rig.procs["daemon"]
            assert rig.notify is not None
            rig.notify.wait("READY", "1", 180.0, alive=daemon.alive)
            rig.control("scan")
            time.sleep(rng.uniform(0.0, 90.0))  # somewhere in the sweep, the plan or the capture
            sent = time.monotonic()
            daemon.popen.send_signal(signal.SIGTERM)
            try:
                codes.append(daemon.popen.wait(UNIT_STOP_TIMEOUT_S))
            except subprocess.TimeoutExpired:
                codes.append(None)
                daemon.popen.kill()
                daemon.popen.wait()
            exits.append(time.monotonic() - sent)
            print(f"  SIGTERM {n + 1}/{count}: exit {codes[-1]} after {exits[-1]:.2f} s", flush=True)
        folders, left_open, lost = _lost_images(rig.store)
    return {"exits": exits, "codes": codes, "folders": folders, "open": left_open, "lost": lost}


def run() -> None:
    scans = int(os.environ.get("TBP_BENCH_SAFETY_SCANS", "10"))
    terms = int(os.environ.get("TBP_BENCH_SAFETY_SIGTERMS", "10"))
    base = Path(tempfile.mkdtemp(prefix="tbp-bench-safety-loaded-"))
    r = loaded_scans(base / "loaded", scans)
    print(f"{scans} loaded loopback scans (a core kept busy): {', '.join(r['outcomes'])}")
    print(f"  safety trips {len(r['trips'])} (goal 0), heartbeats lost {r['heartbeats_lost']} (goal 0)")
    print("  event-loop lag per state (goal p99 <= 10 ms, max <= 50 ms):")
    for state, figures in r["lag"].items():
        print(f"    {state:15s} p50 {figures['p50_ms']:7.2f}  p99 {figures['p99_ms']:7.2f}  "
              f"max {figures['max_ms']:7.2f} ms  ({figures['samples']} samples)")
    t = sigterms(base / "sigterm", terms)
    print(f"{terms} SIGTERMs at random moments of loopback scans: exit codes {t['codes']}")
    print(f"  exit after SIGTERM median {statistics.median(t['exits']):.2f} s, worst {max(t['exits']):.2f} s "
          f"(goal <= {UNIT_STOP_TIMEOUT_S:g} s)")
    print(f"  scan folders {t['folders']}, left in progress {t['open']} (goal 0), "
          f"verified images missing or changed {t['lost']} (goal 0)")
    print(f"  logs in {base}")
