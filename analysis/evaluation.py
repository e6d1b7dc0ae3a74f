"""The paper's evaluation on a corpus of simulated bodies, with its robustness studies.

One body is one job (:func:`evaluate_body`): plan every method on the true body, re-score the
shape-aware plan on a fresh sample, then the studies of SPEC section 6:

* calibration noise: plan on poses perturbed by ~2.5 mm / 0.3 deg, score on the true poses;
* shape error: plan on the TSDF estimate of a simulated noisy sweep, score on the true body;
* postural sway: plan on the still pose, score on swayed poses of the same person (the loss is
  against a plan made for the swayed pose itself, on the same samples).

Every random source is seeded from (corpus seed, body index), so the numbers do not depend on
how many worker processes run the corpus.
"""

from __future__ import annotations

import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from daemon.logs import configure_logging
from planner.rig import Rig, load_rig

METHOD_ORDER = ("closest", "average", "fixed", "autofocus", "em", "shape-aware")

PAPER = {
    "methods": {
        "closest": {"total_cost": 4710.0, "in_focus_pct": 31.6},
        "average": {"total_cost": 3871.0, "in_focus_pct": 68.5},
        "shape-aware": {"total_cost": 2986.0, "in_focus_pct": 84.9},
    },
    "visible_pct": 93.2,
    "calibration_loss_pts": 0.06,
    "shape_loss_pts": 1.0,
    "sway_loss_pts": 2.0,
    "mean_resolution_mm_per_px": 0.068,
}


@dataclass(frozen=True)
class StudyOptions:
    """How much of each study to run per body (the defaults are the paper's)."""

    points: int = 10_000
    calibration_trials: int = 30
    calibration_translation_mm: float = 2.5
    calibration_rotation_deg: float = 0.3
    sway_poses: int = 10
    sway_deg: float = 2.0
    shape: bool = True


def body_seed(corpus_seed: int, index: int) -> int:
    return corpus_seed * 10_007 + index


def evaluate_body(index: int, corpus_seed: int, options: StudyOptions, rig_path: str | None = None) -> dict[str, Any]:
    """All numbers for body ``index`` of the corpus (a plain dict, JSON-ready)."""
    from planner.plan import evaluate, plan_focus
    from planner.pose_noise import perturb_poses
    from planner.poses import rgb_poses
    from planner.sampling import sample_surface
    from sim.body import make_body

    rig = load_rig(rig_path) if rig_path else load_rig()
    seed = body_seed(corpus_seed, index)
    timings: dict[str, float] = {}
    started = time.perf_counter()
    body = make_body(seed=seed)
    timings["body"] = time.perf_counter() - started

    t = time.perf_counter()
    plan = plan_focus(body, rig, points=options.points, seed=seed)
    timings["plan"] = time.perf_counter() - t
    aware = plan.methods["shape-aware"]
    # Plans are judged on a fresh, independent sample: scoring on the planning samples would
    # favour the plan optimised for exactly those points over the plans of the studies.
    fresh_samples = sample_surface(body, options.points, seed=seed + 1)
    fresh = evaluate(aware.focus_mm, body, rig, points=fresh_samples)
    result: dict[str, Any] = {
        "index": index,
        "seed": seed,
        "height_mm": float(body.bounds[1][2] - body.bounds[0][2]),
        "visible_fraction": plan.visible_fraction,
        "resolution_mm_per_px": plan.resolution,
        "methods": {
            name: {"total_cost": m.total_cost, "in_focus_fraction": m.in_focus_fraction, "seconds": m.seconds}
            for name, m in plan.methods.items()
        },
        "fresh_sample": {"total_cost": fresh.total_cost, "in_focus_fraction": fresh.in_focus_fraction},
        "plan_timing_s": plan.timing_s,
    }

    if options.calibration_trials:
        t = time.perf_counter()
        true_poses = rgb_poses(rig)
        losses = []
        for trial in range(options.calibration_trials):
            noisy = perturb_poses(
                true_poses,
                translation_mm=options.calibration_translation_mm,
                rotation_deg=options.calibration_rotation_deg,
                seed=seed * 1000 + trial,
            )
            noisy_plan = plan_focus(body, rig, points=plan.samples, poses=noisy, methods=("shape-aware",))
            scored = evaluate(noisy_plan.focus_mm, body, rig, points=fresh_samples, poses=true_poses)
            losses.append(fresh.in_focus_fraction - scored.in_focus_fraction)
        result["calibration_loss"] = _spread(losses)
        timings["calibration"] = time.perf_counter() - t

    if options.shape:
        from drivers.sim.depth import simulate_sweep
        from planner.mesh_metrics import shape_metrics
        from planner.tsdf import FRAME_SPACING_DEG, fuse

        t = time.perf_counter()
        sweep = simulate_sweep(body, rig, seed=seed, noise=True, frame_spacing_deg=FRAME_SPACING_DEG)
        estimate = fuse(list(sweep.frames), rig).mesh
        estimate_plan = plan_focus(estimate, rig, points=options.points, seed=seed, methods=("shape-aware",))
        scored = evaluate(estimate_plan.focus_mm, body, rig, points=fresh_samples)
        metrics = shape_metrics(body, estimate)
        result["shape_error"] = {
            "in_focus_loss": fresh.in_focus_fraction - scored.in_focus_fraction,
            "chamfer_true_to_estimate_mm": float(metrics.true_to_estimate_mean_mm),
            "coverage_10mm": float(metrics.coverage_10mm),
        }
        timings["shape"] = time.perf_counter() - t

    if options.sway_poses:
        t = time.perf_counter()
        losses = []
        for k in range(options.sway_poses):
            swayed = make_body(seed=seed, sway_deg=options.sway_deg, sway_seed=seed * 100 + k)
            own = plan_focus(swayed, rig, points=options.points, seed=seed + 2 + k, methods=("shape-aware",))
            judge = sample_surface(swayed, options.points, seed=seed + 3 + k)
            ideal = evaluate(own.focus_mm, swayed, rig, points=judge)
            scored = evaluate(aware.focus_mm, swayed, rig, points=judge)
            losses.append(ideal.in_focus_fraction - scored.in_focus_fraction)
        result["sway_loss"] = _spread(losses)
        timings["sway"] = time.perf_counter() - t

    timings["total"] = time.perf_counter() - started
    result["timing_s"] = timings
    return result


def _quiet_worker() -> None:
    """Worker processes log warnings and errors only (the planner logs every plan at info)."""
    configure_logging(level="warning", stream=sys.stderr)


def _spread(values: list[float]) -> dict[str, float]:
    array = np.asarray(values, dtype=float)
    return {"mean": float(array.mean()), "std": float(array.std()), "max": float(array.max()), "n": len(array)}


def motion_blur(rig: Rig) -> dict[str, Any]:
    """Motion blur (px) of every capture of the rig's dual-speed profile, by angle index."""
    from planner.schedule import rig_profile

    profile = rig_profile(rig)
    angles = rig.capture.angles_deg
    speed = np.abs(profile.speed_at_angle(angles))
    blur = rig.optics.pixels_per_degree * speed * rig.optics.exposure_s
    return {
        "angles_deg": angles.tolist(),
        "speed_deg_s": speed.tolist(),
        "blur_px": blur.tolist(),
        "max_px": float(blur.max()),
        "limit_px": rig.capture.max_motion_blur_px,
    }


def run_corpus(
    bodies: int,
    *,
    seed: int = 0,
    jobs: int = 2,
    options: StudyOptions = StudyOptions(),
    rig_path: str | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Evaluate ``bodies`` simulated adults in ``jobs`` processes; results ordered by body index."""
    if bodies < 1:
        raise ValueError(f"bodies must be at least 1, got {bodies}")
    started = time.perf_counter()
    results: list[dict[str, Any]] = []
    if jobs <= 1:
        for i in range(bodies):
            results.append(evaluate_body(i, seed, options, rig_path))
            if progress:
                progress(len(results), bodies)
    else:
        with ProcessPoolExecutor(max_workers=jobs, initializer=_quiet_worker) as pool:
            futures = [pool.submit(evaluate_body, i, seed, options, rig_path) for i in range(bodies)]
            for future in futures:
                results.append(future.result())
                if progress:
                    progress(len(results), bodies)
    rig = load_rig(rig_path) if rig_path else load_rig()
    return {
        "bodies": bodies,
        "seed": seed,
        "options": options.__dict__,
        "summary": summarise(results),
        "motion_blur": motion_blur(rig),
        "per_body": results,
        "paper": PAPER,
        "wall_time_s": time.perf_counter() - started,
        "jobs": jobs,
    }


def summarise(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Mean and std over bodies of every headline number."""

    def stat(values: list[float]) -> dict[str, float]:
        array = np.asarray(values, dtype=float)
        return {"mean": float(array.mean()), "std": float(array.std())}

    methods = {}
    for name in METHOD_ORDER:
        rows = [r["methods"][name] for r in results if name in r["methods"]]
        if rows:
            methods[name] = {
                "total_cost": stat([r["total_cost"] for r in rows]),
                "in_focus_fraction": stat([r["in_focus_fraction"] for r in rows]),
                "seconds": stat([r["seconds"] for r in rows]),
            }
    summary: dict[str, Any] = {
        "methods": methods,
        "visible_fraction": stat([r["visible_fraction"] for r in results]),
        "fresh_sample_in_focus": stat([r["fresh_sample"]["in_focus_fraction"] for r in results]),
        "resolution_mean_mm_per_px": stat([r["resolution_mm_per_px"]["mean"] for r in results]),
        "resolution_std_mm_per_px": stat([r["resolution_mm_per_px"]["std"] for r in results]),
        "resolution_share_at_most_0.075": stat(
            [r["resolution_mm_per_px"]["share_at_most_0.075"] for r in results]
        ),
        "body_seconds": stat([r["timing_s"]["total"] for r in results]),
    }
    for key in ("calibration_loss", "sway_loss"):
        if all(key in r for r in results):
            summary[key] = stat([r[key]["mean"] for r in results])
    if all("shape_error" in r for r in results):
        summary["shape_loss"] = stat([r["shape_error"]["in_focus_loss"] for r in results])
        summary["shape_chamfer_mm"] = stat([r["shape_error"]["chamfer_true_to_estimate_mm"] for r in results])
    return summary
