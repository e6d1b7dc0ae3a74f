"""Rig design: phone heights and tilts, depth camera placement and the angular pattern.

Given bodies (meshes in the rig frame with their surface samples) and a rig builder's
constraints, search the rig that sees the most skin, on average and on the worst body:

* phones: every (height, tilt) on a grid is a *configuration*; its visibility of each body at
  the capture angles is computed once (one ray-casting pass over the whole library), so a
  design's visible share is an OR of stored masks and the search (coordinate descent over the
  phones, never closer than the phones' own spacing) costs no ray casting;
* depth cameras: the same over (height, tilt) for each depth camera, scored by the skin some
  depth frame of the sweep sees within the camera's range and grazing limit (what the TSDF
  needs to reconstruct a surface);
* the angular pattern: how the fixed number of captures is split between the fast and slow
  sectors, scored by the robust focus plan itself (planner/plan.py).

Pure computation: bodies come in as meshes (analysis/design.py builds them).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
import trimesh

from planner.cost import cost_table
from planner.poses import column_poses, depth_sweep_poses
from planner.rig import Capture, DepthCamera, Rig
from planner.sampling import SurfaceSamples
from planner.visibility import RayScene, visible_pairs

Progress = Callable[[str, int, int], None]


class DesignError(ValueError):
    """The constraints leave no design (e.g. more phones than fit in the column)."""


class ConstraintValueError(DesignError):
    """A constraint is not a usable count or length (no phones, a negative or non-finite radius):
    names the constraint (``name``, a field of :class:`Constraints`), its value and what it must be."""

    def __init__(self, name: str, value: float, expected: str) -> None:
        self.name, self.value, self.expected = name, value, expected
        super().__init__(f"{name} {value!r}: expected {expected}")


@dataclass(frozen=True)
class Constraints:
    """What the rig builder fixes: phone count, ring (beam) radius and column height (mm);
    phones at least ``phone_spacing_mm`` apart (a portrait phone is ~160 mm tall) and at least
    ``lowest_mm`` above the floor; tilts tried (deg, > 0 looks up) and the height grid step."""

    phones: int
    ring_radius_mm: float
    column_height_mm: float
    phone_spacing_mm: float = 170.0
    lowest_mm: float = 80.0
    tilts_deg: tuple[float, ...] = (-35.0, -25.0, -15.0, 0.0, 15.0, 25.0, 35.0)
    height_step_mm: float = 30.0

    def __post_init__(self) -> None:
        if not 1 <= self.phones <= 64:
            raise ConstraintValueError("phones", self.phones, "1 to 64")
        for name in ("ring_radius_mm", "column_height_mm", "phone_spacing_mm", "height_step_mm"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConstraintValueError(name, value, "a positive length in mm")
        if not (math.isfinite(self.lowest_mm) and self.lowest_mm >= 0):
            raise ConstraintValueError("lowest_mm", self.lowest_mm, "a height in mm, 0 or more")

    def heights(self) -> np.ndarray:
        top = self.column_height_mm - 40.0
        if top < self.lowest_mm:
            raise DesignError(f"column height {self.column_height_mm:g} mm leaves no room for phones")
        span = (self.phones - 1) * self.phone_spacing_mm
        if span > top - self.lowest_mm:
            raise DesignError(
                f"{self.phones} phones {self.phone_spacing_mm:g} mm apart need {span:g} mm of column; "
                f"only {top - self.lowest_mm:g} mm between {self.lowest_mm:g} and {top:g} mm"
            )
        return np.arange(self.lowest_mm, top + 1e-9, self.height_step_mm)


@dataclass(frozen=True)
class Subject:
    """One design body: its mesh (mm, rig frame) and surface samples."""

    label: str
    mesh: trimesh.Trimesh
    samples: SurfaceSamples


@dataclass(frozen=True)
class Library:
    """Per subject, per configuration: seen (B, K, N) bool; best view cost (B, K, N), 1 if unseen."""

    configs: np.ndarray  # (K, 2): height mm, tilt deg
    seen: np.ndarray
    quality: np.ndarray


def phone_library(subjects: Sequence[Subject], rig: Rig, constraints: Constraints,
                  progress: Progress | None = None) -> Library:
    """Visibility of every (height, tilt) phone configuration at the rig's capture angles."""
    heights = constraints.heights()
    configs = np.array([(h, t) for h in heights for t in constraints.tilts_deg], dtype=float)
    angles = rig.capture.angles_deg
    poses = column_poses(constraints.ring_radius_mm, configs[:, 0], configs[:, 1], angles)
    k, n = len(configs), len(subjects[0].samples)
    seen = np.zeros((len(subjects), k, n), dtype=bool)
    quality = np.ones((len(subjects), k, n))
    for b, subject in enumerate(subjects):
        table = cost_table(visible_pairs(RayScene(subject.mesh), poses, subject.samples, rig.optics),
                           rig.cost, rig.optics)
        config = poses.camera_index[table.vis.pose]
        seen[b, config, table.vis.point] = True
        np.minimum.at(quality[b], (config, table.vis.point), table.base)
        if progress:
            progress("phone visibility", b + 1, len(subjects))
    return Library(configs, seen, quality)


def design_score(seen: np.ndarray, quality: np.ndarray) -> tuple[float, np.ndarray]:
    """Score of a design from its per-subject masks (B, N) and best view costs (B, N):
    mean visible + worst visible - 0.1 x mean best view cost (view quality breaks ties)."""
    visible = seen.mean(axis=1)
    return float(visible.mean() + visible.min() - 0.1 * quality.mean()), visible


def search_phones(library: Library, constraints: Constraints, start: np.ndarray,
                  rounds: int = 6, progress: Progress | None = None) -> np.ndarray:
    """Coordinate descent over the phones: (P,) configuration indices, heights kept apart."""
    chosen = np.array(start, dtype=int)
    heights = library.configs[:, 0]

    def score(choice: np.ndarray) -> float:
        return design_score(library.seen[:, choice].any(axis=1), library.quality[:, choice].min(axis=1))[0]

    best = score(chosen)
    for r in range(rounds):
        improved = False
        for i in range(len(chosen)):
            others = np.delete(chosen, i)
            clear = np.all(np.abs(heights[:, None] - heights[others][None, :]) >= constraints.phone_spacing_mm - 1e-9,
                           axis=1)
            rest_seen = library.seen[:, others].any(axis=1)  # (B, N)
            rest_quality = library.quality[:, others].min(axis=1)
            for j in np.flatnonzero(clear).tolist():
                s = design_score(rest_seen | library.seen[:, j], np.minimum(rest_quality, library.quality[:, j]))[0]
                if s > best + 1e-12:
                    best, chosen[i], improved = s, j, True
                    rest_seen = library.seen[:, np.delete(chosen, i)].any(axis=1)
                    rest_quality = library.quality[:, np.delete(chosen, i)].min(axis=1)
        if progress:
            progress("phone search", r + 1, rounds)
        if not improved:
            break
    return chosen[np.argsort(heights[chosen], kind="stable")]


def nearest_configs(library: Library, heights: Sequence[float], tilts: Sequence[float]) -> np.ndarray:
    """Library indices closest to given phones (a start for the search)."""
    c = library.configs
    return np.array([int(np.argmin(np.abs(c[:, 0] - h) + 10.0 * np.abs(c[:, 1] - t)))
                     for h, t in zip(heights, tilts)])


# ------------------------------------------------------------------------------ depth cameras


def depth_optics(rig: Rig):
    """The depth camera model as an Optics (image x axis = the 1280 px side) for frustum tests."""
    m = rig.depth_camera_model
    hfov = math.degrees(2.0 * math.atan(m.cx_px / m.fx_px))
    return replace(rig.optics, image_width_px=m.width_px, image_height_px=m.height_px, hfov_deg=hfov)


def depth_coverage(subject: Subject, rig: Rig, cameras: Sequence[DepthCamera], step_deg: float = 10.0) -> np.ndarray:
    """(len(cameras), N) bool: samples some frame of each camera's sweep sees in range and
    below the grazing limit."""
    sweep = rig.depth_sweep
    angles = np.arange(sweep.start_deg, sweep.end_deg + 1e-9, step_deg)
    model = rig.depth_camera_model
    optics = depth_optics(rig)
    scene = RayScene(subject.mesh)
    cos_limit = math.cos(math.radians(model.grazing_limit_deg))
    out = np.zeros((len(cameras), len(subject.samples)), dtype=bool)
    for i, camera in enumerate(cameras):
        vis = visible_pairs(scene, depth_sweep_poses(camera, angles), subject.samples, optics)
        ok = (vis.depth >= model.min_range_mm) & (vis.depth <= model.max_range_mm) & (vis.facing >= cos_limit)
        out[i, vis.point[ok]] = True
    return out


def search_depth_cameras(subjects: Sequence[Subject], rig: Rig, constraints: Constraints,
                         progress: Progress | None = None) -> tuple[tuple[DepthCamera, ...], np.ndarray]:
    """Height and tilt of each depth camera (radius, angle offset and roll kept) maximising the
    skin the sweep sees (mean + worst subject). Returns the cameras and coverage (B,)."""
    heights = np.arange(300.0, constraints.column_height_mm + 1e-9, 150.0)
    tilts = np.array([-60.0, -45.0, -30.0, -15.0, 0.0, 15.0])
    options = [[replace(cam, height_mm=float(h), tilt_deg=float(t)) for h in heights for t in tilts]
               for cam in rig.depth_cameras]
    masks = []  # per camera slot: (B, options, N)
    for slot, candidates in enumerate(options):
        masks.append(np.stack([depth_coverage(s, rig, candidates) for s in subjects]))
        if progress:
            progress("depth camera visibility", slot + 1, len(options))
    choice = [int(np.argmin([abs(c.height_mm - cam.height_mm) + abs(c.tilt_deg - cam.tilt_deg) for c in opts]))
              for cam, opts in zip(rig.depth_cameras, options)]

    def covered(ch: list[int]) -> np.ndarray:
        return np.stack([masks[i][:, ch[i]] for i in range(len(ch))]).any(axis=0).mean(axis=1)

    def score(ch: list[int]) -> float:
        c = covered(ch)
        return float(c.mean() + c.min())

    best = score(choice)
    for _ in range(4):
        improved = False
        for i in range(len(choice)):
            for j in range(len(options[i])):
                trial = list(choice)
                trial[i] = j
                s = score(trial)
                if s > best + 1e-12:
                    best, choice, improved = s, trial, True
        if not improved:
            break
    return tuple(options[i][choice[i]] for i in range(len(choice))), covered(choice)


# ------------------------------------------------------------------------------ angular pattern


def split_capture(capture: Capture, fast_captures: int, total: int) -> Capture:
    """The capture with ``fast_captures`` angles in each fast sector and the rest of ``total``
    shared by the slow ones, spread evenly over each sector's constant-speed stretch.

    Sectors alternate fast / slow as in the default rig (same speeds and spans)."""
    fastest = max(s.speed_deg_s for s in capture.sectors)
    fast = [s for s in capture.sectors if s.speed_deg_s == fastest]
    slow = [s for s in capture.sectors if s.speed_deg_s != fastest]
    if not fast or not slow:
        raise DesignError("the angular pattern search needs fast and slow sectors")
    rest = total - fast_captures * len(fast)
    if rest < len(slow) or rest % len(slow):
        raise DesignError(f"{total} captures cannot be split {fast_captures} per fast sector")
    per_slow = rest // len(slow)
    accel = capture.acceleration_deg_s2
    tol = capture.angle_tolerance_deg
    sectors = []
    for i, s in enumerate(capture.sectors):
        n = fast_captures if s in fast else per_slow
        lo, hi = s.start_deg, s.end_deg
        neighbours = [capture.sectors[i - 1]] if i > 0 else []
        neighbours += [capture.sectors[i + 1]] if i + 1 < len(capture.sectors) else []
        for other in neighbours:  # ramps sit in the slower sector at each boundary
            if other.speed_deg_s > s.speed_deg_s:
                ramp = (other.speed_deg_s**2 - s.speed_deg_s**2) / (2.0 * accel)
                if other.end_deg == s.start_deg:
                    lo = s.start_deg + ramp
                else:
                    hi = s.end_deg - ramp
        lo, hi = lo + 2 * tol, hi - 2 * tol
        step = (hi - lo) / n
        first = lo + step / 2
        sectors.append(replace(s, first_capture_deg=round(first, 3), capture_step_deg=round(step, 3), captures=n))
    return replace(capture, sectors=tuple(sectors))


def pattern_sector_dicts(capture: Capture) -> list[dict]:
    """Sectors as rig-file mappings."""
    return [
        {"name": s.name, "start_deg": s.start_deg, "end_deg": s.end_deg, "speed_deg_s": s.speed_deg_s,
         "first_capture_deg": s.first_capture_deg, "capture_step_deg": s.capture_step_deg, "captures": s.captures}
        for s in capture.sectors
    ]

