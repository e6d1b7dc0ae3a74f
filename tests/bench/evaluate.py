"""Evaluation benchmark: a corpus of simulated adults with every study, on 2 worker processes.

Goal: 20 bodies with all studies in <= 10 min on this 2-core machine. By default 4 bodies are
run and the time for 20 extrapolated (the per-body work is independent); set
TBP_BENCH_BODIES=20 to run the whole corpus.

    python -m tests.bench evaluate
"""

from __future__ import annotations

import os
import time

GOAL_S = 600.0


def run() -> None:
    from analysis.evaluation import StudyOptions, run_corpus

    bodies = int(os.environ.get("TBP_BENCH_BODIES", "4"))
    started = time.perf_counter()
    results = run_corpus(bodies, seed=0, jobs=2, options=StudyOptions())
    wall = time.perf_counter() - started
    for_20 = wall * 20 / bodies
    s = results["summary"]
    aware = s["methods"]["shape-aware"]["in_focus_fraction"]["mean"]
    print(f"{bodies} bodies, all studies, 2 processes: {wall:.0f} s wall, "
          f"{s['body_seconds']['mean']:.1f} s per body per process")
    print(f"20 bodies: {for_20:.0f} s{' (extrapolated)' if bodies != 20 else ''}   goal <= {GOAL_S:.0f} s "
          f"{'OK' if for_20 <= GOAL_S else 'MISSED'}")
    print(f"shape-aware in focus {100 * aware:.1f} %, visible {100 * s['visible_fraction']['mean']:.1f} %; "
          f"losses (points): calibration {100 * s['calibration_loss']['mean']:.2f}, "
          f"shape {100 * s['shape_loss']['mean']:.2f}, sway {100 * s['sway_loss']['mean']:.2f}")
