"""The rig description (``calibration_data/rig.yaml``): load, validate, expose as dataclasses.

Every field is checked against its allowed range and unknown keys are refused, so a typo in
a clinic's rig file stops the daemon with a message naming the file, the key and the range
instead of producing a silently wrong scan. The keys, ranges, defaults and the bounds on a hostile
file (size, string lengths, ids safe as file names, aliases) are the rig file's table in
planner/schema/tables.py; this module checks the relations between keys (sectors continuous,
motion blur, the planning sample count within a memory budget) and builds the dataclasses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from planner.schema import ConfigError, show
from planner.schema.tables import RIG_FILE

CALIBRATION_DIR = Path(__file__).resolve().parent.parent / "calibration_data"
DEFAULT_RIG_PATH = CALIBRATION_DIR / "rig.yaml"
MAX_FILE_BYTES = RIG_FILE.max_bytes  # the default rig is 6 KB
# Planning memory: the visibility and cost tables take about this many bytes per (pose, sample)
# candidate (measured: 336 poses x 200k samples peaked at 1.26 GiB, 4.9 KiB a sample); the rig's
# planner.points is refused when the estimate passes the budget.
PLAN_BYTES_PER_POSE_SAMPLE = 16
PLAN_MEMORY_BUDGET_BYTES = 4 * 1024**3


def planning_memory_bytes(points: int, poses: int) -> int:
    """Estimated peak memory (bytes) of planning ``points`` samples for ``poses`` camera poses."""
    return int(points) * int(poses) * PLAN_BYTES_PER_POSE_SAMPLE


class RigConfigError(ConfigError):
    """A rig file is unreadable or a field is missing, unknown or out of range."""


# ---------------------------------------------------------------------------- dataclasses


@dataclass(frozen=True)
class Optics:
    focal_length_mm: float
    f_number: float
    hyperfocal_mm: float
    image_width_px: int
    image_height_px: int
    hfov_deg: float
    exposure_s: float
    iso: int

    @property
    def vfov_deg(self) -> float:
        half = math.radians(self.hfov_deg) / 2
        return math.degrees(2 * math.atan(math.tan(half) * self.image_height_px / self.image_width_px))

    @property
    def focal_length_px(self) -> float:
        """Pinhole focal length in pixels (square pixels)."""
        return (self.image_width_px / 2) / math.tan(math.radians(self.hfov_deg) / 2)

    @property
    def pixels_per_degree(self) -> float:
        return self.image_width_px / self.hfov_deg


@dataclass(frozen=True)
class Phone:
    id: str
    serial: str
    height_mm: float
    tilt_deg: float
    focus_calibration: str


@dataclass(frozen=True)
class Sector:
    name: str
    start_deg: float
    end_deg: float
    speed_deg_s: float
    first_capture_deg: float
    capture_step_deg: float
    captures: int

    @property
    def capture_angles_deg(self) -> list[float]:
        return [self.first_capture_deg + k * self.capture_step_deg for k in range(self.captures)]


@dataclass(frozen=True)
class Capture:
    sectors: tuple[Sector, ...]
    acceleration_deg_s2: float
    max_motion_blur_px: float
    lens_settle_s: float
    capture_cycle_s: float
    angle_tolerance_deg: float

    @property
    def angles_deg(self) -> np.ndarray:
        """(A,) float: capture angles in rotation order."""
        return np.array([a for s in self.sectors for a in s.capture_angles_deg], dtype=float)

    @property
    def start_deg(self) -> float:
        return self.sectors[0].start_deg

    @property
    def end_deg(self) -> float:
        return self.sectors[-1].end_deg

@dataclass(frozen=True)
class Cost:
    w_area: float
    w_axis: float
    w_focus: float
    area_reference_distance_mm: float
    area_reference_incidence_deg: float
    axis_deviation_mm: float

    @property
    def eps_area(self) -> float:
        """eps1 (1/mm^2): the projected-area term reaches 1 at the reference distance and incidence."""
        cos_i = math.cos(math.radians(self.area_reference_incidence_deg))
        return cos_i / self.area_reference_distance_mm**2


@dataclass(frozen=True)
class PlannerSettings:
    points: int
    em_relative_tolerance: float
    em_max_iterations: int
    refine_max_sweeps: int
    redundancy_weight: float
    view_miss_probability: float
    robust_max_sweeps: int
    per_subject_angles: bool
    angle_step_deg: float
    importance_density: float
    importance_views: int
    importance_radius_mm: float


@dataclass(frozen=True)
class DepthCamera:
    id: str
    serial: str
    radius_mm: float
    angle_offset_deg: float
    height_mm: float
    tilt_deg: float
    roll_deg: float


@dataclass(frozen=True)
class DepthCameraModel:
    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    fps: float
    min_range_mm: float
    max_range_mm: float
    depth_unit_mm: float
    baseline_mm: float
    subpixel_px: float
    grazing_limit_deg: float

    @property
    def intrinsic_matrix(self) -> np.ndarray:
        """(3, 3) float pinhole matrix K."""
        return np.array(
            [[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]]
        )


@dataclass(frozen=True)
class DepthSweep:
    start_deg: float
    end_deg: float
    speed_deg_s: float


@dataclass(frozen=True)
class Tsdf:
    voxel_mm: float
    truncation_voxels: float
    weight_threshold: float
    volume_radius_mm: float
    volume_height_mm: float
    floor_clearance_mm: float
    camera_clearance_mm: float
    surface_voxel_mm: float


@dataclass(frozen=True)
class Motor:
    node_id: int
    bitrate: int
    gear_ratio: float
    encoder_counts_per_rev: int
    max_speed_deg_s: float
    max_acceleration_deg_s2: float
    heartbeat_producer_ms: int
    host_heartbeat_ms: int
    heartbeat_timeout_ms: int
    following_error_deg: float
    position_rate_hz: float
    host_stall_ms: int = 500
    """The host's event loop not running for this long quick-stops the beam (drivers/motor/guard.py)."""

    @property
    def counts_per_degree(self) -> float:
        """Encoder counts per degree of beam rotation."""
        return self.encoder_counts_per_rev * self.gear_ratio / 360.0


@dataclass(frozen=True)
class CalibrationSettings:
    """Where the rig's system calibration lives and how old it may get before scans warn."""

    file: str = "calibration.yaml"
    max_age_days: float = 180.0


@dataclass(frozen=True)
class Rig:
    """The whole validated rig description."""

    path: str
    digest: str
    optics: Optics
    ring_radius_mm: float
    phones: tuple[Phone, ...]
    capture: Capture
    cost: Cost
    planner: PlannerSettings
    depth_cameras: tuple[DepthCamera, ...]
    depth_camera_model: DepthCameraModel
    depth_sweep: DepthSweep
    tsdf: Tsdf
    motor: Motor
    calibration: CalibrationSettings = CalibrationSettings()

    @property
    def n_cameras(self) -> int:
        return len(self.phones)

    @property
    def n_angles(self) -> int:
        return len(self.capture.angles_deg)

    @property
    def n_poses(self) -> int:
        return self.n_cameras * self.n_angles

    def pose_index(self, angle_index: int, camera_index: int) -> int:
        """Pose order is angle-major: angle_index * n_cameras + camera_index."""
        return angle_index * self.n_cameras + camera_index

    def resolve(self, relative: str) -> Path:
        """A path named in the rig file, relative to the rig file's folder."""
        return (Path(self.path).parent / relative).resolve()


# ---------------------------------------------------------------------------- reading


def _unique(path: str, key: str, items: tuple[Any, ...], attr: str) -> None:
    seen: set[str] = set()
    for i, item in enumerate(items):
        value = getattr(item, attr)
        if value in seen:
            raise RigConfigError(path, f"{key}[{i}].{attr}", f"duplicate value {show(value)}; must be unique")
        seen.add(value)


def _capture(path: str, values: dict[str, Any], optics: Optics) -> Capture:
    sectors: list[Sector] = []
    for i, raw_sector in enumerate(values["sectors"]):
        key = f"capture.sectors[{i}]"
        sector = Sector(**raw_sector)
        if sector.end_deg <= sector.start_deg:
            raise RigConfigError(path, f"{key}.end_deg",
                                 f"got {sector.end_deg:g}; must be greater than start_deg {sector.start_deg:g}")
        last = sector.capture_angles_deg[-1]
        if sector.first_capture_deg < sector.start_deg or last > sector.end_deg:
            raise RigConfigError(path, f"{key}.first_capture_deg",
                                 f"captures span {sector.first_capture_deg:g}..{last:g} deg; must lie inside "
                                 f"[{sector.start_deg:g}, {sector.end_deg:g}]")
        if sectors and abs(sector.start_deg - sectors[-1].end_deg) > 1e-9:
            raise RigConfigError(path, f"{key}.start_deg",
                                 f"got {sector.start_deg:g}; must equal the previous sector's end_deg "
                                 f"{sectors[-1].end_deg:g} (the rotation is continuous)")
        sectors.append(sector)
    _unique(path, "capture.sectors", tuple(sectors), "name")
    span = sectors[-1].end_deg - sectors[0].start_deg
    if span > 360.0 + 1e-9:
        raise RigConfigError(path, "capture.sectors", f"span {span:g} deg; allowed at most 360")
    capture = Capture(**{**values, "sectors": tuple(sectors)})
    for i, sector in enumerate(sectors):
        blur = optics.pixels_per_degree * sector.speed_deg_s * optics.exposure_s
        if blur > capture.max_motion_blur_px:
            raise RigConfigError(path, f"capture.sectors[{i}].speed_deg_s",
                                 f"{sector.speed_deg_s:g} deg/s blurs {blur:.2f} px at exposure "
                                 f"{optics.exposure_s:g} s; allowed at most max_motion_blur_px "
                                 f"{capture.max_motion_blur_px:g}")
    return capture


def load_rig(path: Path | str = DEFAULT_RIG_PATH) -> Rig:
    """Load and validate a rig file (the keys, ranges and defaults: planner/schema/tables.py).

    Raises:
        RigConfigError: the file is missing or unparsable, or a key is missing, unknown or out of
            range. The message names the file, the key and the allowed range.
    """
    values, digest = RIG_FILE.load(path, RigConfigError)
    return _rig(values, str(path), digest)


def rig_from_mapping(raw: Any, path: Path | str = "<memory>", digest: str = "") -> Rig:
    """Validate an already-parsed rig mapping (see :func:`load_rig`)."""
    return _rig(RIG_FILE.check(raw, path, RigConfigError), str(path), digest)


def _rig(v: dict[str, Any], path: str, digest: str) -> Rig:
    """The rig of validated values, once the relations between keys hold."""
    optics = Optics(**v["optics"])
    if optics.hyperfocal_mm <= 2 * optics.focal_length_mm:
        raise RigConfigError(path, "optics.hyperfocal_mm", "must exceed twice the focal length")
    phones = tuple(Phone(**p) for p in v["phones"])
    _unique(path, "phones", phones, "id")
    _unique(path, "phones", phones, "serial")
    depth_cameras = tuple(DepthCamera(**d) for d in v["depth_cameras"])
    _unique(path, "depth_cameras", depth_cameras, "id")
    model = DepthCameraModel(**v["depth_camera_model"])
    if model.max_range_mm <= model.min_range_mm:
        raise RigConfigError(path, "depth_camera_model.max_range_mm", "must exceed min_range_mm")
    sweep = DepthSweep(**v["depth_sweep"])
    if sweep.end_deg <= sweep.start_deg:
        raise RigConfigError(path, "depth_sweep.end_deg", "must exceed start_deg")
    motor = Motor(**v["motor"])
    if motor.heartbeat_timeout_ms <= motor.host_heartbeat_ms:
        raise RigConfigError(path, "motor.heartbeat_timeout_ms", f"got {motor.heartbeat_timeout_ms}; must exceed "
                                                                 f"host_heartbeat_ms {motor.host_heartbeat_ms}")
    capture = _capture(path, v["capture"], optics)
    cost = Cost(**v["cost"])
    if cost.w_area + cost.w_axis + cost.w_focus <= 0:
        raise RigConfigError(path, "cost", "w_area, w_axis and w_focus are all 0: at least one weight must be positive")
    planner = PlannerSettings(**v["planner"])
    poses = len(phones) * len(capture.angles_deg)
    need = planning_memory_bytes(planner.points, poses)
    if need > PLAN_MEMORY_BUDGET_BYTES:
        most = PLAN_MEMORY_BUDGET_BYTES // (poses * PLAN_BYTES_PER_POSE_SAMPLE)
        raise RigConfigError(
            path, "planner.points",
            f"got {planner.points}: planning {poses} poses needs about {need / 1024**3:.1f} GiB, more than "
            f"the {PLAN_MEMORY_BUDGET_BYTES / 1024**3:g} GiB budget; allowed at most {most} points")
    return Rig(path=path, digest=digest, optics=optics, ring_radius_mm=v["ring"]["radius_mm"], phones=phones,
               capture=capture, cost=cost, planner=planner, depth_cameras=depth_cameras, depth_camera_model=model,
               depth_sweep=sweep, tsdf=Tsdf(**v["tsdf"]), motor=motor,
               calibration=CalibrationSettings(**v["calibration"]))
