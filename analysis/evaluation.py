"""The paper's evaluation on a corpus of simulated bodies, with its robustness studies.

One body is one job (:func:`evaluate_body`): plan every method on the true body (and per-subject
capture angles), then judge every plan side by side, as SPEC section 6 and issue 12 ask:

* planning: on the samples it was planned on;
* fresh: on a fresh, independent sample of the same body;
* calibration: on that fresh sample seen from poses off by ~2.5 mm / 0.3 deg (equivalent in
  distribution to planning on noisy poses and judging on the true ones);
* sway: on fresh samples of the same person swayed by 2 deg at six joints;
* shape: planned on the TSDF estimate of a simulated noisy sweep, judged on the true body.

It also computes the certified in-focus bound (planner/bound.py) on the planning and the fresh
samples, and (with per-subject angles) on the fresh samples seen from every candidate capture
angle at once: no choice of angles among the candidates, with any number of images, can hold
more of the skin sharp, so it caps what per-subject angles can add. Every random source is
seeded from (corpus seed, body label), so the numbers do not depend on how many worker
processes run the corpus.
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

METHOD_ORDER = ("closest", "average", "fixed", "autofocus", "em", "shape-aware", "robust", "robust-angles")
#: The plan the rig captures with (the robustness losses are reported for it).
CAPTURE_METHOD = "robust"
#: Judged conditions, in report order: the planning samples, then plans judged elsewhere.
CONDITIONS = ("planning", "fresh", "calibration", "sway", "shape")
#: Subjects at the ends of the adult range (SPEC goals): (label, stature m, gender).
EXTREMES = (("tall", 2.1, 0.0), ("short", 1.5, 1.0))

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
    """How much of each study to run per body.

    Every method is judged on fresh samples of the same body, on camera poses perturbed by
    calibration noise, on swayed bodies and (shape) after planning on the TSDF estimate.
    angles: also plan per-subject capture angles ("robust-angles"); extremes: add a tall
    (2.1 m) and a short (1.5 m) adult to the corpus.
    """

    points: int = 10_000
    calibration_trials: int = 10
    calibration_translation_mm: float = 2.5
    calibration_rotation_deg: float = 0.3
    sway_poses: int = 5
    sway_deg: float = 2.0
    shape: bool = True
    angles: bool = True
    extremes: bool = False

    def __post_init__(self) -> None:
        if self.points < 100 or self.calibration_trials < 0 or self.sway_poses < 0:
            raise ValueError(f"points {self.points} (at least 100), calibration_trials {self.calibration_trials} "
                             f"and sway_poses {self.sway_poses} (0 or more: 0 skips the study)")


def body_seed(corpus_seed: int, index: int) -> int:
    return corpus_seed * 10_007 + index


def corpus_labels(bodies: int, options: StudyOptions) -> list[str]:
    """Body labels: "0".."N-1" (random adults of the corpus seed), then "tall" and "short"."""
    return [str(i) for i in range(bodies)] + ([label for label, _, _ in EXTREMES] if options.extremes else [])


def _subject(label: str, corpus_seed: int) -> tuple[dict[str, Any], int]:
    """make_body keyword arguments and the random seed of a corpus label."""
    from sim.body import adult_of_stature

    for index, (name, stature, gender) in enumerate(EXTREMES):
        if label == name:
            return {"phenotype": adult_of_stature(stature, gender)}, body_seed(corpus_seed, 1_000 + index)
    seed = body_seed(corpus_seed, int(label))
    return {"seed": seed}, seed


class _Judge:
    """Scores focus plans of every method on one sample set of one body, from the rig's poses
    (or a perturbation of them) and, for per-subject angles, from that plan's own poses."""

    def __init__(self, mesh: Any, rig: Rig, samples: Any, poses: Any, angle_poses: Any | None) -> None:
        from planner.cost import cost_table
        from planner.visibility import RayScene, visible_pairs

        self.scene = scene = RayScene(mesh)
        self.rig_table = cost_table(visible_pairs(scene, poses, samples, rig.optics), rig.cost, rig.optics)
        self.angle_table = None
        if angle_poses is not None:
            self.angle_table = cost_table(visible_pairs(scene, angle_poses, samples, rig.optics), rig.cost, rig.optics)

    def in_focus(self, plans: dict[str, Any]) -> dict[str, float]:
        out = {}
        for name, focus in plans.items():
            table = self.angle_table if name == "robust-angles" else self.rig_table
            if table is not None:
                out[name] = table.in_focus_fraction(focus)
        return out


def _perturbed(poses: Any, options: StudyOptions, seed: int) -> Any:
    from planner.pose_noise import perturb_poses

    return perturb_poses(poses, translation_mm=options.calibration_translation_mm,
                         rotation_deg=options.calibration_rotation_deg, seed=seed)


def evaluate_body(label: str | int, corpus_seed: int, options: StudyOptions, rig_path: str | None = None) -> dict[str, Any]:
    """All numbers for one body of the corpus (a plain dict, JSON-ready)."""
    from planner.bound import in_focus_bound
    from planner.plan import METHODS, candidate_table, plan_focus
    from planner.poses import rgb_poses
    from planner.sampling import sample_surface
    from sim.body import make_body

    label = str(label)
    rig = load_rig(rig_path) if rig_path else load_rig()
    timings: dict[str, float] = {}
    started = time.perf_counter()
    subject, seed = _subject(label, corpus_seed)
    body = make_body(**subject)
    timings["body"] = time.perf_counter() - started

    t = time.perf_counter()
    methods = METHODS if options.angles else tuple(m for m in METHODS if m != "robust-angles")
    plan = plan_focus(body, rig, points=options.points, seed=seed, methods=methods)
    timings["plan"] = time.perf_counter() - t
    plans = {name: m.focus_mm for name, m in plan.methods.items()}
    planning = {name: m.in_focus_fraction for name, m in plan.methods.items()}
    costs = {name: m.total_cost for name, m in plan.methods.items()}
    seconds = {name: m.seconds for name, m in plan.methods.items()}
    chosen_angles = plan.methods["robust-angles"].angles_deg if options.angles else None
    angle_poses = rgb_poses(rig, chosen_angles) if chosen_angles is not None else None
    true_poses = rgb_poses(rig)

    # Plans are judged on a fresh, independent sample: scoring on the planning samples would
    # favour a plan optimised for exactly those points.
    t = time.perf_counter()
    fresh_samples = sample_surface(body, options.points, seed=seed + 1)
    fresh_judge = _Judge(body, rig, fresh_samples, true_poses, angle_poses)
    conditions: dict[str, dict[str, float]] = {"planning": planning, "fresh": fresh_judge.in_focus(plans)}
    timings["fresh"] = time.perf_counter() - t
    bound = in_focus_bound(plan.table)
    fresh_bound = in_focus_bound(fresh_judge.rig_table)
    bounds = {"planning": bound.fraction, "fresh": fresh_bound.fraction}
    any_angle_visible = None
    if chosen_angles is not None:
        t = time.perf_counter()
        any_angle = in_focus_bound(candidate_table(fresh_judge.scene, rig, fresh_samples)[1])
        bounds["fresh_any_angle"], any_angle_visible = any_angle.fraction, any_angle.visible_fraction
        timings["any_angle_bound"] = time.perf_counter() - t

    if options.calibration_trials:
        # Planning on noisy poses and judging on the true ones is, in distribution, planning on
        # the calibrated poses and judging on poses off by the calibration error: one visibility
        # per trial then serves every method.
        t = time.perf_counter()
        trials = []
        for trial in range(options.calibration_trials):
            noise_seed = seed * 1000 + trial
            judge = _Judge(body, rig, fresh_samples, _perturbed(true_poses, options, noise_seed),
                           _perturbed(angle_poses, options, noise_seed) if angle_poses is not None else None)
            trials.append(judge.in_focus(plans))
        conditions["calibration"] = _mean_by_method(trials)
        timings["calibration"] = time.perf_counter() - t

    if options.sway_poses:
        t = time.perf_counter()
        swayed = []
        for k in range(options.sway_poses):
            mesh = make_body(**subject, sway_deg=options.sway_deg, sway_seed=seed * 100 + k)
            judge = _Judge(mesh, rig, sample_surface(mesh, options.points, seed=seed + 3 + k), true_poses, angle_poses)
            swayed.append(judge.in_focus(plans))
        conditions["sway"] = _mean_by_method(swayed)
        timings["sway"] = time.perf_counter() - t

    shape_error: dict[str, Any] = {}
    if options.shape:
        from drivers.sim.depth import simulate_sweep
        from planner.mesh_metrics import shape_metrics
        from planner.shape_errors import ShapeEstimateError
        from planner.tsdf import FRAME_SPACING_DEG, fuse

        t = time.perf_counter()
        sweep = simulate_sweep(body, rig, seed=seed, noise=True, frame_spacing_deg=FRAME_SPACING_DEG)
        try:
            estimate = fuse(list(sweep.frames), rig).mesh
        except ShapeEstimateError as exc:
            # The rig refuses this subject before the capture (e.g. skin within the camera
            # ring's clearance): there is no estimate to plan on; the report names why.
            shape_error = {"refused": f"{type(exc).__name__}: {exc}"}
        else:
            estimate_plan = plan_focus(estimate, rig, points=options.points, seed=seed, methods=methods)
            on_estimate = {name: m.focus_mm for name, m in estimate_plan.methods.items()}
            scores = _Judge(body, rig, fresh_samples, true_poses, None).in_focus(
                {k: v for k, v in on_estimate.items() if k != "robust-angles"})
            if "robust-angles" in estimate_plan.methods:
                own = estimate_plan.methods["robust-angles"]
                scores["robust-angles"] = _Judge(body, rig, fresh_samples, rgb_poses(rig, own.angles_deg), None) \
                    .rig_table.in_focus_fraction(own.focus_mm)
            conditions["shape"] = scores
            metrics = shape_metrics(body, estimate)
            shape_error = {
                "chamfer_true_to_estimate_mm": float(metrics.true_to_estimate_mean_mm),
                "coverage_10mm": float(metrics.coverage_10mm),
            }
        timings["shape"] = time.perf_counter() - t

    methods = {
        name: {"total_cost": costs[name], "in_focus_fraction": planning[name], "seconds": seconds[name]}
        | {f"{c}_in_focus": conditions[c][name] for c in conditions if c != "planning" and name in conditions[c]}
        for name in plans
    }
    capture = methods[CAPTURE_METHOD]
    result: dict[str, Any] = {
        "label": label,
        "seed": seed,
        "height_mm": float(body.bounds[1][2] - body.bounds[0][2]),
        "visible_fraction": plan.visible_fraction,
        "fresh_visible_fraction": fresh_judge.rig_table.visible_fraction,
        "bound": bounds,
        "resolution_mm_per_px": plan.resolution,
        "methods": methods,
        "plan_timing_s": plan.timing_s,
    }
    if chosen_angles is not None:
        result["angles_deg"] = chosen_angles.tolist()
        result["angles_visible_fraction"] = fresh_judge.angle_table.visible_fraction
        result["any_angle_visible_fraction"] = any_angle_visible
    for study, key in (("calibration", "calibration_loss"), ("sway", "sway_loss"), ("shape", "shape_loss")):
        if study in conditions:
            result[key] = capture["fresh_in_focus"] - capture[f"{study}_in_focus"]
    if shape_error:
        result["shape_error"] = shape_error
    timings["total"] = time.perf_counter() - started
    result["timing_s"] = timings
    return result


def _mean_by_method(rows: list[dict[str, float]]) -> dict[str, float]:
    return {name: float(np.mean([r[name] for r in rows])) for name in rows[0]}


def _quiet_worker() -> None:
    """Worker processes log warnings and errors only (the planner logs every plan at info)."""
    configure_logging(level="warning", stream=sys.stderr)


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
    labels = corpus_labels(bodies, options)
    results: list[dict[str, Any]] = []
    if jobs <= 1:
        for label in labels:
            results.append(evaluate_body(label, seed, options, rig_path))
            if progress:
                progress(len(results), len(labels))
    else:
        with ProcessPoolExecutor(max_workers=jobs, initializer=_quiet_worker) as pool:
            futures = [pool.submit(evaluate_body, label, seed, options, rig_path) for label in labels]
            for future in futures:
                results.append(future.result())
                if progress:
                    progress(len(results), len(labels))
    rig = load_rig(rig_path) if rig_path else load_rig()
    return {
        "bodies": len(labels),
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
    """Mean, std and worst body of every headline number."""

    def stat(values: list[float]) -> dict[str, float]:
        array = np.asarray(values, dtype=float)
        return {"mean": float(array.mean()), "std": float(array.std()), "min": float(array.min()),
                "max": float(array.max())}

    methods = {}
    for name in METHOD_ORDER:
        rows = [r["methods"][name] for r in results if name in r["methods"]]
        if not rows:
            continue
        keys = {key for r in rows for key in r}  # a study a body could not run is left out of its mean
        methods[name] = {key: stat([r[key] for r in rows if key in r]) for key in sorted(keys)}
        fresh = [r["methods"][name].get("fresh_in_focus") for r in results if name in r["methods"]]
        if all(f is not None for f in fresh):
            methods[name]["fresh_share_of_visible"] = stat(
                [r["methods"][name]["fresh_in_focus"] / r["fresh_visible_fraction"] for r in results])
            methods[name]["fresh_over_bound"] = stat(
                [r["methods"][name]["fresh_in_focus"] / r["bound"]["fresh"] for r in results])
    summary: dict[str, Any] = {
        "methods": methods,
        "visible_fraction": stat([r["visible_fraction"] for r in results]),
        "fresh_visible_fraction": stat([r["fresh_visible_fraction"] for r in results]),
        "bound_planning": stat([r["bound"]["planning"] for r in results]),
        "bound_fresh": stat([r["bound"]["fresh"] for r in results]),
        # How much of its visible skin any plan could hold sharp, and the bodies where no plan of
        # the rig's poses holds 99 % of it (issue 12's goal, certified out of reach there).
        "bound_share_of_visible": stat([r["bound"]["fresh"] / r["fresh_visible_fraction"] for r in results]),
        "bound_below_99_of_visible": {r["label"]: r["bound"]["fresh"] / r["fresh_visible_fraction"]
                                      for r in results if r["bound"]["fresh"] < 0.99 * r["fresh_visible_fraction"]},
        "resolution_mean_mm_per_px": stat([r["resolution_mm_per_px"]["mean"] for r in results]),
        "resolution_std_mm_per_px": stat([r["resolution_mm_per_px"]["std"] for r in results]),
        "resolution_share_at_most_0.075": stat(
            [r["resolution_mm_per_px"]["share_at_most_0.075"] for r in results]
        ),
        "body_seconds": stat([r["timing_s"]["total"] for r in results]),
    }
    angled = [r for r in results if "fresh_any_angle" in r["bound"]]
    if angled:
        # What per-subject angles add over the rig's angles, and the most any angles could add.
        summary["bound_fresh_any_angle"] = stat([r["bound"]["fresh_any_angle"] for r in angled])
        summary["any_angle_visible_fraction"] = stat([r["any_angle_visible_fraction"] for r in angled])
        capture = [r["methods"][CAPTURE_METHOD]["fresh_in_focus"] for r in angled]
        summary["angles_gain"] = stat([r["methods"]["robust-angles"]["fresh_in_focus"] - c
                                       for r, c in zip(angled, capture)])
        summary["angles_headroom"] = stat([r["bound"]["fresh_any_angle"] - c for r, c in zip(angled, capture)])
    for key in ("calibration_loss", "sway_loss", "shape_loss"):
        if any(key in r for r in results):
            summary[key] = stat([r[key] for r in results if key in r])
    chamfer = [r["shape_error"]["chamfer_true_to_estimate_mm"] for r in results
               if "chamfer_true_to_estimate_mm" in r.get("shape_error", {})]
    if chamfer:
        summary["shape_chamfer_mm"] = stat(chamfer)
    refused = {r["label"]: r["shape_error"]["refused"] for r in results if "refused" in r.get("shape_error", {})}
    if refused:
        summary["shape_refused"] = refused
    return summary
