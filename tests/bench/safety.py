"""Safety benchmark (issue 28): ``./dev bench safety [PART ...]`` through TBP_BENCH_SAFETY_PARTS
(comma-separated; default every part, about an hour and a half on a 2-core machine).

reactions (tests/bench/_safety_react.py): every stop path's reaction time on the loopback rig.
loaded (tests/bench/_safety_loaded.py): loaded loopback scans, then SIGTERMs mid-scan.
idle (tests/bench/_safety_idle.py): the real daemon idling with devices missing.
subscribers (tests/bench/_safety_subscribers.py): the control API under silent and flooding subscribers.
cancellation: 1,000 scans on the short simulated rig of tests/cancellation.py, each stopped once
at a seeded random point of its sweep or capture (or the steps between) in virtual time: the
operator's abort, an e-stop, the job's task cancelled, the daemon stopped (RigService.stop).
Every run must end (no hang), within systemd's TimeoutStopSec, with the rig IDLE or FAULT, the
scan folder closed, the beam still within 3 s and every image captured before the stop verified
on disk.
"""

from __future__ import annotations

import importlib
import os
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path

from daemon.logs import configure_logging
from tests.cancellation import BEAM_STOP_S, EXIT_BOUND_S, make_trials, run_trials, summary

RUNS = 1000
SEED = 1028


def cancellation() -> None:
    shm = Path("/dev/shm")
    with tempfile.TemporaryDirectory(dir=shm if shm.is_dir() and os.access(shm, os.W_OK) else None) as tmp:
        started = time.perf_counter()
        results = run_trials(make_trials(RUNS, SEED), Path(tmp), seed=SEED)
        wall = time.perf_counter() - started
    s = summary(results)
    kinds = Counter(r.trial.kind for r in results)
    rows = [
        ("runs", f"{s['runs']} ({', '.join(f'{k} {n}' for k, n in sorted(kinds.items()))}); stopped in "
                 + ", ".join(f"{k} {n}" for k, n in sorted(s["states"].items())), ""),
        ("hangs", s["hangs"], "0"),
        (f"exits over {EXIT_BOUND_S:g} s", f"{s['over_bound']} (slowest {s['max_exit_s']:.2f} s of rig time from "
                                          "the stop to the job's end)", "0"),
        (f"beam moving > {BEAM_STOP_S:g} s after", f"{s['beam_late']} (longest {s['max_beam_moving_s']:.2f} s)", "0"),
        ("folders left open", s["folders_open"], "0"),
        ("images lost", f"{s['images_lost']} of {s['captured_before']} captured before the stops", "0"),
        ("pictures after the stop", s["late_pictures"], "0"),
        ("other problems", s["problems"], "0"),
        ("wall time", f"{wall:.0f} s ({wall / max(len(results), 1):.2f} s a run)", ""),
    ]
    for name, value, goal in rows:
        print(f"{name:<26} {value}" + (f"   goal {goal}" if goal else ""))
    for r in results:
        if not r.ok:
            print(f"  {r.trial}: {r.state_at} -> {r.end_state}, {r.outcome}; exit {r.exit_s}; lost {r.lost[:2]}; "
                  f"{r.problems[:2]}")


def _part(module: str) -> Callable[[], None]:
    def run_part() -> None:
        importlib.import_module(f"tests.bench.{module}").run()

    return run_part


PARTS: dict[str, Callable[[], None]] = {
    "reactions": _part("_safety_react"),
    "loaded": _part("_safety_loaded"),
    "idle": _part("_safety_idle"),
    "subscribers": _part("_safety_subscribers"),
    "cancellation": cancellation,
}


def run() -> None:
    configure_logging(level="critical", stream=sys.stderr)
    chosen = [p for p in os.environ.get("TBP_BENCH_SAFETY_PARTS", ",".join(PARTS)).split(",") if p]
    unknown = sorted(set(chosen) - set(PARTS))
    if unknown:
        raise SystemExit(f"unknown safety part {unknown[0]!r}; parts: {', '.join(PARTS)}")
    for name in chosen:
        print(f"-- {name}", flush=True)
        PARTS[name]()
