"""Evaluation benchmark: a corpus of simulated adults with every study, on 2 worker processes.

Goal: 20 bodies with all studies in <= 10 min on this 2-core machine. By default 4 bodies are
run and the time for 20 extrapolated (the per-body work is independent); set
TBP_BENCH_BODIES=20 to run the whole corpus, TBP_BENCH_EXTREMES=1 to add the tall (2.1 m) and
short (1.5 m) adults. Prints issue 12's goals beside the measured numbers.

    python -m tests.bench evaluate
"""

from __future__ import annotations

import os
import time

GOAL_S = 600.0


def _mark(ok: bool) -> str:
    return "ok" if ok else "MISSED"


def run() -> None:
    from analysis.evaluation import StudyOptions, run_corpus

    bodies = int(os.environ.get("TBP_BENCH_BODIES", "4"))
    extremes = os.environ.get("TBP_BENCH_EXTREMES", "") not in ("", "0")
    load = os.getloadavg()[0]
    started = time.perf_counter()
    results = run_corpus(bodies, seed=0, jobs=2, options=StudyOptions(extremes=extremes))
    wall = time.perf_counter() - started
    for_20 = wall * 20 / results["bodies"]
    s = results["summary"]
    m = s["methods"]
    print(f"{results['bodies']} bodies, all studies, 2 processes: {wall:.0f} s wall, "
          f"{s['body_seconds']['mean']:.1f} s per body per process (load average {load:.1f} at the start)")
    print(f"20 bodies: {for_20:.0f} s{' (extrapolated)' if results['bodies'] != 20 else ''}   goal <= {GOAL_S:.0f} s "
          f"[{_mark(for_20 <= GOAL_S)}]")
    print(f"{'method':<14} {'planning':>8} {'fresh':>7} {'calib':>7} {'sway':>7} {'shape':>7}")
    for name, row in m.items():
        cells = [row.get(k, {}).get("mean") for k in
                 ("in_focus_fraction", "fresh_in_focus", "calibration_in_focus", "sway_in_focus", "shape_in_focus")]
        print(f"{name:<14} " + " ".join(f"{100 * c:>7.2f}" if c is not None else f"{'-':>7}" for c in cells))
    robust, today = m["robust"], m["shape-aware"]
    worst = robust["fresh_share_of_visible"]["min"]
    gain = robust["fresh_in_focus"]["mean"] - today["fresh_in_focus"]["mean"]
    print(f"robust on fresh samples, worst body: {100 * worst:.2f} % of visible (goal >= 99 %) [{_mark(worst >= 0.99)}]")
    print(f"robust - shape-aware on fresh samples: {100 * gain:+.2f} points (goal >= +1.5) [{_mark(gain >= 0.015)}]; "
          f"certified bound on fresh samples {100 * s['bound_fresh']['mean']:.2f} %: at most "
          f"{100 * (s['bound_fresh']['mean'] - today['fresh_in_focus']['mean']):+.2f} points for any plan of the rig's poses")
    if "robust-angles" in m:
        angles = m["robust-angles"]["fresh_in_focus"]["mean"] - robust["fresh_in_focus"]["mean"]
        print(f"per-subject angles - robust on fresh samples: {100 * angles:+.2f} points (goal >= +1) "
              f"[{_mark(angles >= 0.01)}]; same images, same rotation")
    print(f"losses of the robust plan (points): calibration {100 * s['calibration_loss']['mean']:.2f}, "
          f"shape {100 * s['shape_loss']['mean']:.2f}, sway {100 * s['sway_loss']['mean']:.2f}")
