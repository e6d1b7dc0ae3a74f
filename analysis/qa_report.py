"""The scan QA report: an offline HTML page with PNG figures, written into the scan folder.

What an operator and a dermatologist check at a glance: how the scan ended (a partial,
aborted, faulted or interrupted scan says so first, with its missing images per phone and
why), the sharp skin (analysis/skin_map.py: the share of the surface's area a verified image
holds in focus, the figure the viewer and the scan lists show), which skin is sharp (green),
blurred (red) or never seen (grey) in the images actually captured, seen from the front, back
and both sides; each camera's focus against the angle for each planned method; the beam's
speed with the capture marks; planned vs actual capture angles; the resolution of the skin in
its best image; and every missing or failed image.
"""

from __future__ import annotations

import html
import io
import time
from pathlib import Path
from typing import Any

import numpy as np

from analysis.scan_views import ScanRecord, open_scan
from analysis.skin_map import skin_status_at, write_skin_mesh
from daemon.records.manifest import ImageStatus, Manifest, ScanEnd

REPORT_DIR = "report"
SAMPLES = 20_000
GREEN, RED, GREY = "#2e9d4b", "#d43c2f", "#9a9a9a"


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


class _Figures:
    """Writes the report's files into the scan folder through the store (atomically)."""

    def __init__(self, scan: ScanRecord) -> None:
        self.folder = scan.folder

    def save(self, fig: Any, name: str) -> str:
        fig.tight_layout()
        buffer = io.BytesIO()
        fig.savefig(buffer, format="png", dpi=100)
        _pyplot().close(fig)
        self.folder.write_derived(f"{REPORT_DIR}/{name}", buffer.getvalue())
        return name


def skin_status(scan: ScanRecord, samples: int = SAMPLES, seed: int = 0) -> dict[str, np.ndarray]:
    """Surface samples of the scan's mesh and their state in the captured images.

    Returns points (N, 3) mm, inward normals (N, 3), status (N,) int (2 sharp, 1 seen but blurred, 0 not seen) and
    resolution (N,) mm/px in each point's best sharp-or-seen image (NaN if unseen).
    """
    from planner.sampling import sample_surface

    mesh = scan.mesh()
    points = sample_surface(mesh, samples, seed=seed)
    skin = skin_status_at(scan, mesh, points)
    return {"points": points.points, "normals": points.normals, "status": skin["status"].astype(int),
            "resolution": skin["resolution"]}


def _body_views(skin: dict[str, np.ndarray], shares: dict[str, float], out: _Figures) -> str:
    """Orthographic point splats from four sides, nearest points drawn last; titled with the
    scan's shares (:func:`analysis.skin_map.skin_shares`)."""
    plt = _pyplot()
    points, normals, status = skin["points"], skin["normals"], skin["status"]
    colours = np.array([GREY, RED, GREEN])[status]
    views = (("front", np.array([1.0, 0, 0])), ("left side", np.array([0, 1.0, 0])),
             ("back", np.array([-1.0, 0, 0])), ("right side", np.array([0, -1.0, 0])))
    fig, axes = plt.subplots(1, 4, figsize=(12, 6))
    for ax, (name, towards) in zip(axes, views):
        across = np.cross(np.array([0, 0, 1.0]), towards)
        facing = np.flatnonzero(normals @ towards < 0)  # inward normals: outward faces the viewer
        order = facing[np.argsort(points[facing] @ towards)]
        ax.scatter(points[order] @ across, points[order, 2], c=colours[order], s=2.5, linewidths=0)
        ax.set_title(name)
        ax.set_aspect("equal")
        ax.axis("off")
    fig.suptitle(f"sharp skin {100 * shares['sharp']:.1f} %   blurred {100 * shares['blurred']:.1f} %   "
                 f"not seen {100 * shares['unseen']:.1f} %   (of the estimated skin surface)")
    return out.save(fig, "body.png")


def _focus_by_angle(scan: ScanRecord, out: _Figures) -> str | None:
    if not scan.plan:
        return None
    plt = _pyplot()
    rig = scan.rig
    fig, axes = plt.subplots(rig.n_cameras, 1, figsize=(9, 1.6 * rig.n_cameras), sharex=True)
    for c, ax in enumerate(np.atleast_1d(axes)):
        for name, method in scan.plan["methods"].items():
            angles = np.asarray(method.get("angles_deg", rig.capture.angles_deg), dtype=float)
            focus = np.asarray(method["focus_mm"]).reshape(len(angles), rig.n_cameras)[:, c]
            ax.plot(angles, focus, ".-", ms=3, lw=1, label=name)
        ax.set_ylabel(f"{rig.phones[c].id}\nmm", fontsize=8)
    np.atleast_1d(axes)[0].legend(fontsize=7, ncol=4)
    np.atleast_1d(axes)[-1].set_xlabel("capture angle, deg")
    fig.suptitle("focus distance of each camera against the angle")
    return out.save(fig, "focus.png")


def _speed_profile(scan: ScanRecord, out: _Figures) -> str | None:
    trace = scan.folder.read_trace()
    if trace is None:
        return None
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(9, 3))
    ax.plot(trace["angle_deg"], trace["speed_deg_s"], lw=0.8, color="#35608c")
    actual = [i.actual_angle_deg for i in scan.images if i.actual_angle_deg is not None]
    for angle in sorted(set(np.round(actual, 1))):
        ax.axvline(angle, color=GREEN, lw=0.3, alpha=0.6)
    ax.set_xlabel("beam angle, deg")
    ax.set_ylabel("speed, deg/s")
    ax.set_title("beam speed with the capture marks")
    return out.save(fig, "speed.png")


def _angle_errors(scan: ScanRecord, out: _Figures) -> str | None:
    rows = [(i.planned_angle_deg, i.actual_angle_deg - i.planned_angle_deg)
            for i in scan.images if i.actual_angle_deg is not None]
    if not rows:
        return None
    plt = _pyplot()
    planned, error = np.array(rows).T
    tolerance = scan.rig.capture.angle_tolerance_deg
    fig, ax = plt.subplots(figsize=(9, 3))
    ax.scatter(planned, error, s=6)
    ax.axhline(tolerance, color=RED, ls="--", lw=1)
    ax.axhline(-tolerance, color=RED, ls="--", lw=1)
    ax.set_xlabel("planned angle, deg")
    ax.set_ylabel("actual - planned, deg")
    ax.set_title(f"exposure angle error (max {np.abs(error).max():.3f} deg, tolerance {tolerance} deg)")
    return out.save(fig, "angles.png")


def _resolution_histogram(skin: dict[str, np.ndarray], out: _Figures) -> str:
    plt = _pyplot()
    resolution = skin["resolution"][np.isfinite(skin["resolution"])]
    fig, ax = plt.subplots(figsize=(6, 3))
    ax.hist(resolution, bins=60, color="#35608c")
    ax.axvline(0.075, color=RED, ls="--", lw=1, label="0.075 mm/px (1.5 mm lesion)")
    ax.set_xlabel("mm per pixel in the best image")
    ax.set_ylabel("skin samples")
    ax.legend(fontsize=8)
    return out.save(fig, "resolution.png")


def _how_it_ended(manifest: Manifest) -> list[str]:
    """The headline's banner for a scan that is not complete: how it ended and its missing
    images per phone and why (nothing for a complete scan)."""
    state = manifest.state
    if state is ScanEnd.COMPLETE and not manifest.in_progress:
        return []
    what = {ScanEnd.PARTIAL: "Partial scan: the rotation finished with images missing",
            ScanEnd.ABORTED: "Aborted scan", ScanEnd.FAULT: "Scan stopped by a fault",
            ScanEnd.INCOMPLETE: "Incomplete scan (interrupted)"}.get(state, state.value)
    if manifest.in_progress:
        what = "Scan in progress (or left by a daemon that stopped): this report is not final"
    parts = [f"<p class='ended{' fault' if state is ScanEnd.FAULT else ''}' id='ended'><b>{html.escape(what)}</b>"]
    if manifest.reason and state is not ScanEnd.PARTIAL:
        parts.append(f": {html.escape(manifest.reason)}")
    parts.append("</p>")
    by_phone = manifest.missing_by_phone()
    if by_phone:
        missing = sum(sum(r.values()) for r in by_phone.values())
        parts.append(f"<p>{missing} of {len(manifest.images)} images missing:</p><table id='missing-by-phone'>"
                     "<tr><th>camera</th><th>missing</th><th>why</th></tr>")
        for camera, reasons in by_phone.items():
            why = ", ".join(f"{n} {reason.replace('_', ' ')}" for reason, n in reasons.items())
            parts.append(f"<tr><td>{html.escape(camera)}</td><td>{sum(reasons.values())}</td>"
                         f"<td>{html.escape(why)}</td></tr>")
        parts.append("</table>")
    return ["".join(parts)]


def generate_report(scan_dir: Path | str, *, rig_path: Path | str | None = None) -> Path:
    """Write ``<scan_dir>/report/index.html`` and its figures; returns the HTML path.

    Works on incomplete and aborted scans too (sections without data are left out).
    """
    started = time.perf_counter()
    scan = open_scan(scan_dir, rig_path)
    out = _Figures(scan)
    figures: list[tuple[str, str | None]] = []
    skin = shares = None
    if "mesh" in scan.manifest.files and np.isfinite(scan.captured_focus_mm()).any():
        skin = skin_status(scan)
        shares = write_skin_mesh(scan)  # the web viewer's coloured mesh and the sharp skin
        figures.append(("Skin in focus in the captured images", _body_views(skin, shares, out)))
    figures.append(("Focus plan", _focus_by_angle(scan, out)))
    figures.append(("Speed profile", _speed_profile(scan, out)))
    figures.append(("Planned vs actual capture angles", _angle_errors(scan, out)))
    if skin is not None:
        figures.append(("Resolution", _resolution_histogram(skin, out)))

    manifest = scan.manifest
    problems = [i for i in scan.images if i.status is not ImageStatus.VERIFIED]
    counts = ", ".join(f"{k} {v}" for k, v in manifest.counts().items() if v)
    parts = [
        "<!doctype html><meta charset='utf-8'>",
        f"<title>Scan {html.escape(manifest.scan_id)}</title>",
        "<style>body{font-family:sans-serif;max-width:1200px;margin:auto}img{max-width:100%}"
        "td,th{padding:2px 8px;text-align:left}.ended{padding:8px 12px;border-radius:6px;background:#fdebd3;"
        "color:#6b3a06}.ended.fault{background:#fbdcdc;color:#8e1b1b}</style>",
        f"<h1>Scan {html.escape(manifest.scan_id)}: {html.escape(manifest.state.value)}</h1>",
        *_how_it_ended(manifest),
        f"<p>Images: {html.escape(counts)}.</p>",
    ]
    if shares is not None:
        parts.append(f"<p>Sharp skin: <b>{100 * shares['sharp']:.1f} %</b> of the estimated skin surface "
                     "is held in focus by a verified image.</p>")
    for title, name in figures:
        if name:
            parts.append(f"<h2>{html.escape(title)}</h2><img src='{name}' alt='{html.escape(title)}'>")
    parts.append("<h2>Missing or failed images</h2>")
    if problems:
        parts.append("<table><tr><th>camera</th><th>angle</th><th>status</th><th>why</th><th>error</th></tr>")
        for image in problems:
            why = image.why_missing() if not manifest.in_progress else image.missing_reason
            parts.append(
                f"<tr><td>{html.escape(image.camera_id)}</td><td>{image.planned_angle_deg:.1f}</td>"
                f"<td>{html.escape(image.status.value)}</td><td>{why.words if why else ''}</td>"
                f"<td>{html.escape(image.error or '')}</td></tr>"
            )
        parts.append("</table>")
    else:
        parts.append("<p>None: every planned image is on disk and verified.</p>")
    parts.append(f"<p><small>Report generated in {time.perf_counter() - started:.1f} s.</small></p>")
    return scan.folder.write_derived(f"{REPORT_DIR}/index.html", "\n".join(parts).encode())
