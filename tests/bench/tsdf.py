"""TSDF shape estimate benchmark: fusion time, shape accuracy and the focus cost of planning on it.

For simulated adult bodies: a noisy default depth sweep (frames the TSDF keeps), then
- TSDF integration + extraction + cleaning time, median of several runs (goal <= 1.5 s; paper 5 s),
  with the process CPU time beside it (the machine is shared, so wall time varies with load);
- sweep coverage: share of the true surface some frame measured (the camera placement check);
- Chamfer true -> estimate and back (mean, 95th percentile) and coverage within 5 / 10 mm
  (goals: mean true -> estimate <= 5 mm, paper 9.31 mm; >= 97 % within 10 mm);
- both surfaces a scan makes from the sweep, the planner's mesh and the stored surface (fused again
  at ``tsdf.surface_voxel_mm`` while the capture runs; mesh.ply), against the truth: Chamfer and
  coverage as above, the share within 5 mm of the true body (goal >= 99 %) and the area more than
  10 mm off (webbing between arms and torso, hands and thighs);
- in-focus loss: the shape-aware plan made on the estimate and on the true body, both scored on the
  true body (goal <= 1 point; paper about 1 %).

    python -m tests.bench tsdf
"""

from __future__ import annotations

import logging
import resource
import statistics
import time

import structlog

RUNS = 5
BODIES = (0, 1)
GOAL_FUSION_S = 1.5
GOAL_CHAMFER_MM = 5.0
GOAL_COVERAGE_10MM = 0.97
GOAL_ESTIMATE_5MM = 0.99
GOAL_FOCUS_LOSS_POINTS = 1.0


def _body(seed: int):
    """A simulated adult (sim/body.py) or, before it exists, the planner's stand-in."""
    try:
        from sim.body import make_body
    except ImportError:
        from tests.planner_standin import standin_body

        return standin_body(scale=1.0 + 0.03 * seed), "stand-in"
    return make_body(seed=seed), "make_body"


def _mark(ok: bool) -> str:
    return "ok" if ok else "MISSED"


def _one_body(seed: int) -> None:
    from drivers.sim.depth import simulate_sweep
    from planner.mesh_metrics import sample_surface, shape_metrics
    from planner.plan import evaluate, plan_focus
    from planner.rig import load_rig
    from planner.sweep import observed
    from planner.tsdf import FRAME_SPACING_DEG, fuse

    rig = load_rig()
    body, source = _body(seed)
    started = time.perf_counter()
    sweep = simulate_sweep(body, rig, seed=seed, noise=True, frame_spacing_deg=FRAME_SPACING_DEG)
    simulate_s = time.perf_counter() - started
    print(f"body seed {seed} ({source}): {len(body.faces)} faces; simulated {len(sweep.frames)} frames in {simulate_s:.1f} s")

    fuse(sweep.frames, rig)  # warm Open3D
    walls, cpus, result = [], [], None
    for _ in range(RUNS):
        cpu = time.process_time()
        result = fuse(sweep.frames, rig)
        cpus.append(time.process_time() - cpu)
        walls.append(result.timings_s["total"])
    assert result is not None
    wall = statistics.median(walls)
    parts = {k: round(v, 3) for k, v in result.timings_s.items()}
    print(
        f"  fusion {wall:.3f} s median of {RUNS} (goal <= {GOAL_FUSION_S} s, paper 5 s) "
        f"[{_mark(wall <= GOAL_FUSION_S)}]; cpu {statistics.median(cpus):.3f} s; last run {parts}; "
        f"{result.frames_used} frames {result.per_camera}, {len(result.mesh.vertices)} vertices"
    )

    truth_points = sample_surface(body, 50_000, seed=seed)
    seen = observed(truth_points, sweep.frames)
    low, high = truth_points[:, 2] < 100.0, truth_points[:, 2] > truth_points[:, 2].max() - 100.0
    print(
        f"  sweep coverage: {100 * seen.mean():.1f} % of the true surface measured "
        f"(lowest 100 mm {100 * seen[low].mean():.1f} %, top 100 mm {100 * seen[high].mean():.1f} %)"
    )

    surface = fuse(sweep.frames, rig, surface=True)
    print(
        f"  stored surface (the sweep fused again at {rig.tsdf.surface_voxel_mm:g} mm while the capture runs): "
        f"{surface.timings_s['total']:.3f} s, {len(surface.mesh.vertices)} vertices"
    )
    for name, mesh in (("planner's mesh", result.mesh), ("stored surface", surface.mesh)):
        m = shape_metrics(body, mesh, seed=seed)
        print(
            f"  {name}: chamfer true->estimate mean {m.true_to_estimate_mean_mm:.2f} mm (goal <= {GOAL_CHAMFER_MM}, "
            f"paper 9.31) [{_mark(m.true_to_estimate_mean_mm <= GOAL_CHAMFER_MM)}], p95 "
            f"{m.true_to_estimate_p95_mm:.2f} mm; estimate->true mean {m.estimate_to_true_mean_mm:.2f} mm, "
            f"p95 {m.estimate_to_true_p95_mm:.2f} mm"
        )
        print(
            f"    true surface within 5 mm {100 * m.coverage_5mm:.2f} %, within 10 mm {100 * m.coverage_10mm:.2f} % "
            f"(goal >= {100 * GOAL_COVERAGE_10MM:.0f} %) [{_mark(m.coverage_10mm >= GOAL_COVERAGE_10MM)}]"
        )
        print(
            f"    estimate within 5 mm of the true body {100 * m.estimate_within_5mm:.2f} % (goal >= "
            f"{100 * GOAL_ESTIMATE_5MM:.0f} %) [{_mark(m.estimate_within_5mm >= GOAL_ESTIMATE_5MM)}]; "
            f"more than 10 mm off {m.estimate_off_10mm_cm2:.1f} cm^2 (webbing)"
        )

    on_truth = plan_focus(body, rig, seed=seed, methods=("shape-aware",))
    on_estimate = plan_focus(result.mesh, rig, seed=seed, methods=("shape-aware",))
    judge = seed + 1_000_003
    true_score = evaluate(on_truth.focus_mm, body, rig, seed=judge)
    estimate_score = evaluate(on_estimate.focus_mm, body, rig, seed=judge)
    loss = 100 * (true_score.in_focus_fraction - estimate_score.in_focus_fraction)
    print(
        f"  in focus on the true body: planned on truth {100 * true_score.in_focus_fraction:.2f} %, on the "
        f"estimate {100 * estimate_score.in_focus_fraction:.2f} %: loss {loss:.2f} points "
        f"(goal <= {GOAL_FOCUS_LOSS_POINTS}, paper ~1) [{_mark(loss <= GOAL_FOCUS_LOSS_POINTS)}]"
    )


def run() -> None:
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    for seed in BODIES:
        _one_body(seed)
    peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak memory (max RSS) {peak_mib:.0f} MiB")


if __name__ == "__main__":
    run()
