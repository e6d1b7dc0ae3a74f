"""Write an evaluation (``analysis.evaluation.run_corpus``) as report.md, results.json and PNG figures."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from analysis.evaluation import CAPTURE_METHOD, CONDITIONS, METHOD_ORDER, PAPER


def _pct(stat: dict[str, float]) -> str:
    return f"{100 * stat['mean']:.1f} ± {100 * stat['std']:.1f}"


def _pts(stat: dict[str, float]) -> str:
    return f"{100 * stat['mean']:.2f} ± {100 * stat['std']:.2f}"


CONDITION_LABELS = {
    "planning": "planning samples",
    "fresh": "fresh samples",
    "calibration": "calibration noise",
    "sway": "postural sway",
    "shape": "TSDF estimate",
}


def _conditions(methods: dict[str, Any]) -> list[str]:
    present = {k[: -len("_in_focus")] for m in methods.values() for k in m if k.endswith("_in_focus")}
    return ["planning"] + [c for c in CONDITIONS[1:] if c in present]


def _cell(m: dict[str, Any], condition: str) -> str:
    key = "in_focus_fraction" if condition == "planning" else f"{condition}_in_focus"
    return f"{100 * m[key]['mean']:.2f} ± {100 * m[key]['std']:.2f}" if key in m else "–"


def _any_angle_lines(s: dict[str, Any]) -> list[str]:
    if "bound_fresh_any_angle" not in s:
        return []
    return [
        f"- Certified bound with every candidate capture angle at once (any choice of angles, any number "
        f"of images): {_pct(s['bound_fresh_any_angle'])} % on the fresh samples (visible from some candidate: "
        f"{_pct(s['any_angle_visible_fraction'])} %). Per-subject angles add "
        f"{100 * s['angles_gain']['mean']:+.2f} points to the {CAPTURE_METHOD} plan; no choice of angles can "
        f"add more than {100 * s['angles_headroom']['mean']:.2f} on average "
        f"({100 * s['angles_headroom']['min']:.2f}-{100 * s['angles_headroom']['max']:.2f} by body).",
    ]


def markdown(results: dict[str, Any]) -> str:
    s = results["summary"]
    methods = s["methods"]
    conditions = _conditions(methods)
    lines = [
        f"# Focus planning on {results['bodies']} simulated adults (seed {results['seed']})",
        "",
        f"{results['options']['points']:,} surface samples per body, default rig "
        f"(7 phones x 48 angles = 336 poses). Mean ± std over bodies; the seed paper's "
        "simulation (400 scanned bodies) beside it.",
        "",
        "| method | K (of 10,000) | paper K | in focus % | paper % | seconds |",
        "|---|---|---|---|---|---|",
    ]
    scale = 10_000 / results["options"]["points"]
    for name in METHOD_ORDER:
        if name not in methods:
            continue
        m = methods[name]
        paper = PAPER["methods"].get(name)
        paper_k = f"{paper['total_cost']:.0f}" if paper else "–"
        paper_pct = f"{paper['in_focus_pct']}" if paper else "–"
        lines.append(
            f"| {name} | {scale * m['total_cost']['mean']:.0f} ± {scale * m['total_cost']['std']:.0f} "
            f"| {paper_k} | {_pct(m['in_focus_fraction'])} | {paper_pct} | {m['seconds']['mean']:.4f} |"
        )
    lines += [
        "",
        "## Every method judged where it was not planned (in focus, % of the surface)",
        "",
        "Planned on the planning samples (rig angles, or per-subject angles for robust-angles), then "
        "judged on a fresh independent sample, on poses off by the calibration noise, on swayed "
        "bodies, and (TSDF estimate) planned on the estimated mesh and judged on the true body.",
        "",
        "| method | " + " | ".join(CONDITION_LABELS[c] for c in conditions) + " | fresh / visible, worst body |",
        "|---|" + "---|" * (len(conditions) + 1),
    ]
    for name in METHOD_ORDER:
        if name in methods:
            m = methods[name]
            worst = f"{100 * m['fresh_share_of_visible']['min']:.2f} %" if "fresh_share_of_visible" in m else "–"
            lines.append(f"| {name} | " + " | ".join(_cell(m, c) for c in conditions) + f" | {worst} |")
    capture = methods[CAPTURE_METHOD]
    lines += [
        "",
        f"- Visible: {_pct(s['visible_fraction'])} % (paper {PAPER['visible_pct']} %); on the fresh "
        f"samples {_pct(s['fresh_visible_fraction'])} %.",
        f"- Certified bound on the in-focus share any plan of the rig's poses can reach: "
        f"{_pct(s['bound_planning'])} % on the planning samples, {_pct(s['bound_fresh'])} % on the fresh "
        f"ones; the {CAPTURE_METHOD} plan reaches {100 * capture['fresh_over_bound']['mean']:.2f} % of it on "
        f"fresh samples (worst body {100 * capture['fresh_over_bound']['min']:.2f} %).",
        _short_of_99_line(s, len(results["per_body"])),
        *_any_angle_lines(s),
        f"- Shape-aware / average: {capture_ratio(methods, 'shape-aware', 'average'):.2f} "
        f"(paper 84.9 / 68.5 = 1.24); shape-aware / closest: "
        f"{capture_ratio(methods, 'shape-aware', 'closest'):.2f} (paper 84.9 / 31.6 = 2.69).",
        f"- Resolution: {s['resolution_mean_mm_per_px']['mean']:.4f} ± "
        f"{s['resolution_std_mm_per_px']['mean']:.4f} mm/px (paper mean 0.068); share of visible "
        f"skin at or below 0.075 mm/px (a 1.5 mm lesion): {_pct(s['resolution_share_at_most_0.075'])} %.",
        "",
        f"## Robustness of the {CAPTURE_METHOD} plan (in-focus loss against fresh samples, points; paper beside)",
        "",
        "| study | loss | paper |",
        "|---|---|---|",
    ]
    o = results["options"]
    if "calibration_loss" in s:
        lines.append(
            f"| calibration noise ({o['calibration_translation_mm']} mm, {o['calibration_rotation_deg']} deg, "
            f"{o['calibration_trials']} trials) | {_pts(s['calibration_loss'])} | {PAPER['calibration_loss_pts']} |"
        )
    if "shape_loss" in s:
        lines.append(
            f"| shape error (plan on the TSDF estimate; Chamfer {s['shape_chamfer_mm']['mean']:.2f} mm) "
            f"| {_pts(s['shape_loss'])} | about {PAPER['shape_loss_pts']} |"
        )
    if "sway_loss" in s:
        lines.append(
            f"| postural sway ({o['sway_deg']} deg on six joints, {o['sway_poses']} poses) "
            f"| {_pts(s['sway_loss'])} | under {PAPER['sway_loss_pts']} |"
        )
    for label, reason in s.get("shape_refused", {}).items():
        lines.append(f"\nBody {label}: no TSDF estimate, the rig refuses the subject before the capture ({reason}).")
    lines += ["", "## Per body (fresh samples, %)", "",
              "| body | height mm | visible | bound | shape-aware | robust | robust-angles | bound, any angles |",
              "|---|---|---|---|---|---|---|---|"]
    for b in results["per_body"]:
        cells = [f"{100 * b['methods'][n]['fresh_in_focus']:.2f}" if n in b["methods"] else "–"
                 for n in ("shape-aware", "robust", "robust-angles")]
        any_angle = b["bound"].get("fresh_any_angle")
        lines.append(f"| {b['label']} | {b['height_mm']:.0f} | {100 * b['fresh_visible_fraction']:.2f} "
                     f"| {100 * b['bound']['fresh']:.2f} | " + " | ".join(cells)
                     + f" | {'–' if any_angle is None else f'{100 * any_angle:.2f}'} |")
    blur = results["motion_blur"]
    lines += [
        "",
        "## Motion blur of the default profile",
        "",
        f"Every one of the {len(blur['blur_px'])} capture angles: at most {blur['max_px']:.2f} px "
        f"(limit {blur['limit_px']} px; the paper computes about 2.3 px at 9 deg/s).",
        "",
        "## Time",
        "",
        f"{results['bodies']} bodies with every study in {results['wall_time_s']:.0f} s on "
        f"{results['jobs']} processes; {s['body_seconds']['mean']:.1f} s per body on average.",
        "",
        "![in focus per method](in_focus.png)",
        "",
        "![judged elsewhere](conditions.png)",
        "",
        "![robustness](robustness.png)",
        "",
        "![motion blur](motion_blur.png)",
        "",
    ]
    return "\n".join(lines)


def capture_ratio(methods: dict[str, Any], a: str, b: str) -> float:
    if a not in methods or b not in methods:
        return float("nan")
    return methods[a]["in_focus_fraction"]["mean"] / methods[b]["in_focus_fraction"]["mean"]


def figures(results: dict[str, Any], out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    written = []
    per_body = results["per_body"]
    names = [n for n in METHOD_ORDER if n in results["summary"]["methods"]]

    fig, ax = plt.subplots(figsize=(8, 4))
    data = [[100 * b["methods"][n]["in_focus_fraction"] for b in per_body if n in b["methods"]] for n in names]
    ax.boxplot(data, tick_labels=names)
    for name in names:
        paper = PAPER["methods"].get(name)
        if paper:
            ax.plot(names.index(name) + 1, paper["in_focus_pct"], "r_", markersize=20)
    ax.axhline(100 * results["summary"]["visible_fraction"]["mean"], color="grey", ls="--", lw=1)
    ax.set_ylabel("in focus, % of the surface")
    ax.set_title("In focus per method on the planning samples (red: paper; dashed: visible)")
    ax.tick_params(axis="x", labelrotation=20)
    written.append(_save(fig, out / "in_focus.png"))

    methods = results["summary"]["methods"]
    conditions = _conditions(methods)
    shown = [n for n in ("em", "shape-aware", "robust", "robust-angles") if n in methods]
    fig, ax = plt.subplots(figsize=(8, 4))
    width = 0.8 / max(len(shown), 1)
    for i, name in enumerate(shown):
        m = methods[name]
        values = [100 * m["in_focus_fraction" if c == "planning" else f"{c}_in_focus"]["mean"]
                  if ("in_focus_fraction" if c == "planning" else f"{c}_in_focus") in m else np.nan
                  for c in conditions]
        ax.bar(np.arange(len(conditions)) + i * width, values, width, label=name)
    ax.axhline(100 * results["summary"]["bound_fresh"]["mean"], color="k", ls=":", lw=1, label="bound (fresh)")
    ax.set_xticks(np.arange(len(conditions)) + 0.4 - width / 2, [CONDITION_LABELS[c] for c in conditions])
    low = min(100 * methods[n]["in_focus_fraction"]["mean"] for n in shown) if shown else 0
    ax.set_ylim(low - 4, 100 * results["summary"]["bound_fresh"]["mean"] + 1)
    ax.set_ylabel("in focus, % (mean over bodies)")
    ax.legend(fontsize=8, loc="lower left")
    ax.set_title("Plans judged where they were not planned")
    written.append(_save(fig, out / "conditions.png"))

    fig, ax = plt.subplots(figsize=(6, 3.5))
    studies = [(k, label) for k, label in (("calibration_loss", "calibration"), ("sway_loss", "sway"),
                                           ("shape_loss", "shape")) if any(k in b for b in per_body)]
    values = [[100 * b[k] for b in per_body if k in b] for k, _ in studies]
    if values:
        ax.boxplot(values, tick_labels=[label for _, label in studies])
    ax.set_ylabel("in-focus loss, points")
    ax.set_title(f"Robustness studies ({CAPTURE_METHOD} plan)")
    written.append(_save(fig, out / "robustness.png"))

    blur = results["motion_blur"]
    fig, ax = plt.subplots(figsize=(7, 3))
    ax.plot(blur["angles_deg"], blur["blur_px"], "o-", ms=3)
    ax.axhline(blur["limit_px"], color="r", ls="--", lw=1)
    ax.set_xlabel("capture angle, deg")
    ax.set_ylabel("motion blur, px")
    written.append(_save(fig, out / "motion_blur.png"))
    return written


def _save(fig: Any, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path


def _short_of_99_line(s: dict[str, Any], bodies: int) -> str:
    share = s["bound_share_of_visible"]
    below = s["bound_below_99_of_visible"]
    if not below:
        return (f"- The bound leaves every body room to hold 99 % of its visible fresh skin sharp "
                f"(bound / visible: mean {100 * share['mean']:.2f} %, worst body {100 * share['min']:.2f} %).")
    named = ", ".join(f"{label} ({100 * v:.2f} %)" for label, v in below.items())
    return (f"- Certified: no plan of the rig's poses holds 99 % of the visible fresh skin sharp on "
            f"{len(below)} of {bodies} bodies, at most (bound / visible): {named}.")


def write(results: dict[str, Any], out: Path) -> list[Path]:
    """report.md, results.json and the figures in ``out`` (created)."""
    out.mkdir(parents=True, exist_ok=True)
    paths = figures(results, out)
    (out / "results.json").write_text(json.dumps(results, indent=1, sort_keys=True))
    (out / "report.md").write_text(markdown(results))
    return [out / "report.md", out / "results.json", *paths]
