"""The calibration report: an offline HTML page with PNG figures next to ``calibration.yaml``.

What the person calibrating checks: the residuals of every camera at every angle (a bad
picture stands out), the detected corners over a few pictures with their reprojection, how far
each camera sits from the rig file's nominal pose, the beam's wobble around the turn, the
lenses, and every picture that could not be used and why. With the simulated rig's truth, the
errors against it too.
"""

from __future__ import annotations

import html
import math
from pathlib import Path
from typing import Any

import numpy as np

from planner.calibration.calibrate import CalibrationRun, Picture
from planner.calibration.compare import PoseDifferences, compare
from planner.calibration.geometry import pose_error
from planner.calibration.model import Calibration
from planner.calibration.nominal import nominal_cameras
from planner.calibration.target import load_target
from planner.rig import Rig

REPORT_DIR = "report"


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: Path) -> str:
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    _pyplot().close(fig)
    return path.name


def _residual_map(run: CalibrationRun, out: Path) -> str:
    plt = _pyplot()
    n_cap = int(run.obs_capture.max()) + 1 if len(run.obs_capture) else 1
    grid = np.full((len(run.camera_ids), n_cap), np.nan)
    for c in range(len(run.camera_ids)):
        for k in range(n_cap):
            mine = (run.obs_camera == c) & (run.obs_capture == k)
            if mine.any():
                grid[c, k] = run.obs_error_px[mine].mean()
    fig, (ax, hist) = plt.subplots(1, 2, figsize=(13, 3.8), gridspec_kw={"width_ratios": [3, 1]})
    im = ax.imshow(grid, aspect="auto", cmap="viridis", vmin=0, vmax=max(0.5, float(np.nanmax(grid))))
    ax.set_yticks(range(len(run.camera_ids)), run.camera_ids)
    ax.set_xlabel("capture (angle index); blank: no usable corners")
    ax.set_title("mean reprojection error per camera and capture, px")
    fig.colorbar(im, ax=ax)
    hist.hist(run.obs_error_px, bins=60, color="#35608c")
    hist.set_xlabel("reprojection error, px")
    hist.set_title(f"{len(run.obs_error_px)} corners, mean {run.obs_error_px.mean():.3f} px")
    return _save(fig, out / "residuals.png")


def _corner_overlays(run: CalibrationRun, pictures: list[Picture], out: Path, limit: int = 4) -> str | None:
    """A few pictures with the detected corners (green) and the calibration's reprojection (red)."""
    import cv2

    plt = _pyplot()
    by_name = {p.name: p for p in pictures}
    chosen = []
    for cam in run.camera_ids[:: max(1, len(run.camera_ids) // limit)][:limit]:
        mine = [d for d in run.detections if d.camera == cam and d.n_corners]
        if mine:
            chosen.append(max(mine, key=lambda d: d.n_corners))
    if not chosen:
        return None
    cal = run.calibration
    corners_world = None
    fig, axes = plt.subplots(1, len(chosen), figsize=(4 * len(chosen), 5))
    for ax, d in zip(np.atleast_1d(axes), chosen):
        grey = cv2.imread(str(by_name[d.image].path), cv2.IMREAD_REDUCED_GRAYSCALE_2
                          if max(d.size_px) > 2000 else cv2.IMREAD_GRAYSCALE)
        shrink = d.size_px[0] / grey.shape[1]
        ax.imshow(grey, cmap="gray")
        ax.scatter(d.points_px[:, 0] / shrink, d.points_px[:, 1] / shrink, s=14, facecolors="none",
                   edgecolors="#2e9d4b", linewidths=1.0, label="detected")
        if corners_world is None:
            target = load_target()
            corners_world = _world_corners(cal, target)
        cam = cal.camera(d.camera)
        proj = _project(corners_world[d.corner_ids], cal.capture_pose(d.camera, d.angle_index), cam)
        ax.scatter(proj[:, 0] / shrink, proj[:, 1] / shrink, s=3, color="#d43c2f", label="reprojected")
        ax.set_title(f"{d.image}: {d.n_corners} corners", fontsize=9)
        ax.axis("off")
    np.atleast_1d(axes)[0].legend(fontsize=7, loc="lower left")
    return _save(fig, out / "corners.png")


def _world_corners(cal: Calibration, target: Any) -> np.ndarray:
    local = np.c_[target.board_corners, np.ones(len(target.board_corners))]
    return np.concatenate([(local @ (cal.world_from_cuboid @ m).T)[:, :3] for m in cal.cuboid_from_boards])


def _project(points: np.ndarray, camera_to_world: np.ndarray, cam: Any) -> np.ndarray:
    import cv2

    w2c = np.linalg.inv(camera_to_world)
    rvec, _ = cv2.Rodrigues(w2c[:3, :3])
    proj, _ = cv2.projectPoints(points, rvec, w2c[:3, 3], cam.intrinsics.matrix, cam.intrinsics.dist)
    return proj.reshape(-1, 2)


def _deviation_from_nominal(rig: Rig, cal: Calibration) -> list[tuple[str, float, float, np.ndarray]]:
    """(camera, mm, deg, (3,) centre offset mm) of each calibrated camera's pose on the beam vs the rig file."""
    nominal = {c.id: c for c in nominal_cameras(rig, (2, 2))}
    rows = []
    for c in cal.cameras:
        n = nominal[c.id].beam_from_camera
        mm, deg = pose_error(c.beam_from_camera, n)
        rows.append((c.id, mm, deg, c.beam_from_camera[:3, 3] - n[:3, 3]))
    return rows


def _deviation_figure(rows: list[tuple[str, float, float, np.ndarray]], cal: Calibration, out: Path) -> str:
    plt = _pyplot()
    fig, (ax, wob) = plt.subplots(1, 2, figsize=(13, 3.8))
    ids = [r[0] for r in rows]
    offsets = np.array([r[3] for r in rows])
    for i, axis in enumerate("xyz"):
        ax.bar(np.arange(len(ids)) + (i - 1) * 0.27, offsets[:, i], width=0.27, label=f"{axis} (beam frame)")
    ax.set_xticks(range(len(ids)), ids)
    ax.set_ylabel("mm")
    ax.legend(fontsize=8)
    ax.set_title("camera centre minus the rig file's nominal, on the beam")
    angles = np.array([b.encoder_deg for b in cal.beam])
    tilt = np.degrees(np.array([b.tilt_rad for b in cal.beam]))
    shift = np.array([b.shift_mm for b in cal.beam])
    wob.plot(angles, tilt[:, 0] * 100, ".-", label="tilt about x, 1/100 deg")
    wob.plot(angles, tilt[:, 1] * 100, ".-", label="tilt about y, 1/100 deg")
    wob.plot(angles, shift[:, 0] * 10, ".-", label="shift x, 1/10 mm")
    wob.plot(angles, shift[:, 1] * 10, ".-", label="shift y, 1/10 mm")
    wob.set_xlabel("beam angle, deg")
    wob.legend(fontsize=7, ncol=2)
    wob.set_title("beam wobble around the turn (relative to the capture the adjustment holds still)")
    return _save(fig, out / "deviation.png")


def _truth_figure(diff: PoseDifferences, out: Path) -> str:
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(13, 3.5))
    for ax, values, unit in ((axes[0], diff.translation_mm, "mm"), (axes[1], diff.rotation_deg, "deg")):
        for i, cam in enumerate(diff.cameras):
            ax.plot(diff.angles_deg, values[i], ".-", ms=3, lw=0.8, label=cam)
        ax.set_xlabel("capture angle, deg")
        ax.set_ylabel(unit)
        ax.set_title(f"calibrated minus true pose, {unit} (median {np.median(values):.3f}, max {values.max():.3f})")
    axes[0].legend(fontsize=7, ncol=5)
    return _save(fig, out / "truth.png")


def _zhang(run: CalibrationRun, camera: str) -> str:
    rms = run.lens_rms_px.get(camera)
    return "device's" if rms is None else f"{rms:.3f}"


def write_report(run: CalibrationRun, pictures: list[Picture], rig: Rig, out_dir: Path,
                 truth: Calibration | None = None) -> Path:
    """Write ``out_dir/report/index.html`` and its figures; returns the page."""
    out = out_dir / REPORT_DIR
    out.mkdir(parents=True, exist_ok=True)
    cal = run.calibration
    r = cal.residuals
    rows = _deviation_from_nominal(rig, cal)
    figures = [("Reprojection residuals", _residual_map(run, out)),
               ("Detected corners (green) and their reprojection (red)", _corner_overlays(run, pictures, out)),
               ("Pose deviations from nominal, beam wobble", _deviation_figure(rows, cal, out))]
    parts = ["<!doctype html><meta charset='utf-8'>", f"<title>Calibration {html.escape(cal.created_utc)}</title>",
             "<style>body{font-family:sans-serif;max-width:1300px;margin:auto}img{max-width:100%}"
             "td,th{padding:2px 8px;text-align:right}td:first-child{text-align:left}</style>",
             f"<h1>Rig calibration {html.escape(cal.created_utc)}</h1>",
             f"<p>{html.escape(cal.source)}; target {html.escape(cal.target_name)}; rig digest "
             f"<code>{html.escape(cal.rig_digest[:16])}</code>.</p>"]
    if r is not None:
        parts.append(f"<p>Reprojection error over {r.count} corners: <b>mean {r.mean_px:.3f} px</b>, median "
                     f"{r.median_px:.3f}, RMS {r.rms_px:.3f}, 95th percentile {r.p95_px:.3f}, max {r.max_px:.2f} px; "
                     f"{r.discarded} residuals over 4 px discarded. (Seed paper: 0.58 px mean.)</p>")
    parts.append("<p>Time: " + ", ".join(f"{k.replace('_', ' ')} {v:.1f} s" for k, v in run.timings_s.items()) + "</p>")
    if truth is not None:
        diff = compare(cal, truth, rig.capture.angles_deg)
        parts.append("<h2>Against the simulated rig's truth</h2>")
        for kind, words in (("phone", "Phones"), ("depth", "Depth cameras")):
            ids = [c for c in diff.cameras if cal.camera(c).kind == kind]
            if ids:
                s = compare(cal, truth, rig.capture.angles_deg, ids).summary()
                parts.append(f"<p>{words} at the rig's capture angles: median <b>{s['median_mm']:.3f} mm / "
                             f"{s['median_deg']:.4f} deg</b>, worst {s['max_mm']:.3f} mm / {s['max_deg']:.4f} deg "
                             "(goal: 1.0 mm / 0.1 deg median, 2 mm / 0.2 deg worst).</p>")
        figures.append(("Calibrated minus true poses", _truth_figure(diff, out)))
    for title, name in figures:
        if name:
            parts.append(f"<h2>{html.escape(title)}</h2><img src='{name}' alt='{html.escape(title)}'>")
    parts.append("<h2>Cameras</h2><table><tr><th>camera</th><th>fx px</th><th>fy px</th><th>cx px</th><th>cy px</th>"
                 "<th>k1</th><th>k2</th><th>lens: Zhang RMS px</th><th>mean residual px</th><th>corners</th>"
                 "<th>off nominal mm</th><th>off nominal deg</th></tr>")
    for (cid, mm, deg, _), c in zip(rows, cal.cameras):
        k = c.intrinsics
        mean = r.per_camera_mean_px.get(cid, math.nan) if r else math.nan
        count = r.per_camera_count.get(cid, 0) if r else 0
        parts.append(f"<tr><td>{html.escape(cid)} ({c.kind})</td><td>{k.fx:.1f}</td><td>{k.fy:.1f}</td><td>{k.cx:.1f}</td>"
                     f"<td>{k.cy:.1f}</td><td>{k.distortion[0]:.4f}</td><td>{k.distortion[1]:.4f}</td>"
                     f"<td>{_zhang(run, cid)}</td><td>{mean:.3f}</td><td>{count}</td>"
                     f"<td>{mm:.2f}</td><td>{deg:.3f}</td></tr>")
    parts.append("</table><h2>Pictures and cameras not used</h2>")
    if run.problems:
        parts.append("<ul>" + "".join(f"<li>{html.escape(str(p))}</li>" for p in run.problems) + "</ul>")
    else:
        parts.append("<p>None: every picture contributed.</p>")
    page = out / "index.html"
    tmp = page.with_suffix(".tmp")
    tmp.write_text("\n".join(parts))
    tmp.replace(page)
    return page
