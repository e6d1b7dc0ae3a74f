"""Reaction times of the rig's stop paths on the loopback rig, in real time.

The real daemon (the unit's command line) turns the beam in a scan's depth sweep; then one fault is
injected into a simulator process (a key on its stdin, acknowledged with its monotonic time) or the
daemon itself is frozen (SIGSTOP), and the time to the reaction is read from the simulators' and the
daemon's logs, which all stamp time.monotonic() (the daemon's real-time loop clock is that clock):

* e-stop pressed on the panel -> the quick stop controlword on the drive (goal <= 50 ms)
* the drive raises a fault (EMCY) -> the daemon latches FAULT (goal <= 50 ms)
* the drive's heartbeat stops -> the guard's quick stop on the drive (goal <= 400 ms)
* the daemon frozen -> the drive stops by itself (its reaction begins; goal <= 400 ms), and the
  beam at a standstill
* the panel's heartbeat stops -> the quick stop on the drive (goal <= 700 ms)

Then the fault is cleared and the operator's reset brings the rig back for the next trial.
TBP_BENCH_SAFETY_TRIALS sets the trials per kind (default 20).
"""

from __future__ import annotations

import os
import signal
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from daemon.server.control import CommandFailed
from sim.loopback import LoopbackError, LoopbackRig

QUICK_STOP = "0x0002"
GOALS_MS = {"e-stop -> quick stop on the bus": 50, "drive EMCY -> FAULT": 50,
            "drive heartbeat stopped -> quick stop": 400, "daemon frozen -> drive stopping": 400,
            "daemon frozen -> beam at a standstill": None, "panel heartbeat stopped -> quick stop": 700}


def _turning(status: dict) -> bool:
    return status["state"] == "DEPTH_SWEEP" and abs(status.get("beam_speed_deg_s") or 0.0) > 1.0


def _quick_stop_after(rig: LoopbackRig, t0: float) -> float:
    record = rig.wait_log("motor", "sim_drive_controlword", after_mono_s=t0, timeout_s=10.0,
                          where=lambda r: r.get("word") == QUICK_STOP)
    return float(record["mono_s"])


def _ack(rig: LoopbackRig, name: str, action: str, after: float) -> float:
    return float(rig.wait_log(name, action, after_mono_s=after, timeout_s=10.0)["mono_s"])


def _recover(rig: LoopbackRig, scan_id: str, undo: Callable[[], None]) -> None:
    """Clear the fault's cause, wait for the scan's end in FAULT, reset until IDLE and READY."""
    undo()
    rig.wait_status(lambda s: (s.get("last_scan") or {}).get("scan_id") == scan_id, "the scan's end", 120.0)
    deadline = time.monotonic() + 60.0
    while True:
        try:
            rig.control("reset")
        except CommandFailed:  # the e-stop or panel not back yet, or the drive's fault still held
            if time.monotonic() > deadline:
                raise
            time.sleep(0.3)
            continue
        break
    rig.wait_status(lambda s: s["state"] == "IDLE" and s["ready"], "IDLE and READY after the reset", 60.0)


def _trial(rig: LoopbackRig, kind: str) -> dict[str, float]:
    scan_id = rig.control("scan")["scan_id"]
    rig.wait_status(_turning, "the beam turning", 120.0)
    time.sleep(0.5)
    t = time.monotonic()
    if kind == "estop":
        rig.press("e")
        t0 = _ack(rig, "panel", "e-stop pressed", t)
        out = {"e-stop -> quick stop on the bus": _quick_stop_after(rig, t0) - t0}
        _recover(rig, scan_id, lambda: rig.press("r"))
    elif kind == "emcy":
        rig.inject("f")
        t0 = _ack(rig, "motor", "fault 0x2310 raised", t)
        trip = rig.wait_log("daemon", "safety_trip", after_mono_s=t0, stamp="loop_s", timeout_s=10.0)
        out = {"drive EMCY -> FAULT": float(trip["loop_s"]) - t0}
        _recover(rig, scan_id, lambda: None)
    elif kind == "drive heartbeat":
        rig.inject("h")
        t0 = _ack(rig, "motor", "heartbeat stopped", t)
        out = {"drive heartbeat stopped -> quick stop": _quick_stop_after(rig, t0) - t0}
        _recover(rig, scan_id, lambda: rig.inject("H"))
    elif kind == "frozen":
        daemon = rig.procs["daemon"].popen
        t0 = time.monotonic()
        os.kill(daemon.pid, signal.SIGSTOP)
        try:
            reaction = rig.wait_log("motor", "sim_drive_abort_connection", after_mono_s=t0, timeout_s=10.0)
            standstill = rig.wait_log("motor", "sim_drive_standstill", after_mono_s=t0, timeout_s=10.0)
        finally:
            os.kill(daemon.pid, signal.SIGCONT)
        out = {"daemon frozen -> drive stopping": float(reaction["mono_s"]) - t0,
               "daemon frozen -> beam at a standstill": float(standstill["mono_s"]) - t0}
        _recover(rig, scan_id, lambda: None)
    elif kind == "panel heartbeat":
        rig.press("h")
        t0 = _ack(rig, "panel", "heartbeats stopped", t)
        out = {"panel heartbeat stopped -> quick stop": _quick_stop_after(rig, t0) - t0}
        _recover(rig, scan_id, lambda: rig.press("H"))
    else:
        raise ValueError(kind)
    return out


KINDS = ("estop", "emcy", "drive heartbeat", "frozen", "panel heartbeat")


def measure(root: Path, trials: int) -> dict[str, list[float]]:
    times: dict[str, list[float]] = {name: [] for name in GOALS_MS}
    with LoopbackRig(root, out=sys.stdout) as rig:
        assert rig.notify is not None
        rig.notify.wait("READY", "1", 180.0, alive=rig.procs["daemon"].alive)
        for n in range(trials):
            for kind in KINDS:
                for name, value in _trial(rig, kind).items():
                    times[name].append(value)
            print(f"  trial {n + 1}/{trials} done", flush=True)
        false_faults = len(rig.log_events("daemon", "safety_trip", after_mono_s=0.0, stamp="loop_s"))
    times["_trips"] = [float(false_faults)]
    return times


def run() -> None:
    trials = int(os.environ.get("TBP_BENCH_SAFETY_TRIALS", "20"))
    root = Path(tempfile.mkdtemp(prefix="tbp-bench-safety-react-"))
    try:
        times = measure(root, trials)
    except LoopbackError as exc:
        print(f"reaction times: the loopback rig failed: {exc} (logs in {root / 'logs'})")
        raise
    print(f"reaction times on the loopback rig, {trials} trials each, the beam turning (ms):")
    for name, goal in GOALS_MS.items():
        values = [v * 1000 for v in times[name]]
        goal_text = f"goal <= {goal} ms" if goal is not None else ""
        print(f"  {name:40s} median {statistics.median(values):7.1f}  worst {max(values):7.1f}  "
              f"best {min(values):7.1f}   {goal_text}")
    print(f"  safety trips in the daemon's log: {int(times['_trips'][0])} "
          f"(one or more per trial; {len(KINDS) * trials} trials)")
    print(f"  logs in {root / 'logs'}")
