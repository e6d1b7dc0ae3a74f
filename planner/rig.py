"""The rig description (``calibration_data/rig.yaml``): load, validate, expose as dataclasses.

Every field is checked against its allowed range and unknown keys are refused, so a typo in
a clinic's rig file stops the daemon with a message naming the file, the key and the range
instead of producing a silently wrong scan. Hostile files are bounded too: the file size, the
length of every string, ids (they name files in the scan folder) to a safe pattern, the planning
sample count to a memory budget, and an offending value is quoted in at most a few dozen
characters (a YAML alias bomb or a 400-digit number is described, never expanded).
"""

from __future__ import annotations

import hashlib
import math
import re
import reprlib
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from planner.picklable import PicklableError
from planner.yaml_files import read_yaml

CALIBRATION_DIR = Path(__file__).resolve().parent.parent / "calibration_data"
DEFAULT_RIG_PATH = CALIBRATION_DIR / "rig.yaml"
MAX_FILE_BYTES = 1024 * 1024  # the default rig is 6 KB
MAX_STRING = 256
# Camera ids and sector names become file and folder names in a scan: letters, digits, '_', '-'
# and '.', starting with a letter or digit (so never '..', '/', or a hidden file).
ID_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,31}")
# Planning memory: the visibility and cost tables take about this many bytes per (pose, sample)
# candidate (measured: 336 poses x 200k samples peaked at 1.26 GiB, 4.9 KiB a sample); the rig's
# planner.points is refused when the estimate passes the budget.
PLAN_BYTES_PER_POSE_SAMPLE = 16
PLAN_MEMORY_BUDGET_BYTES = 4 * 1024**3


def planning_memory_bytes(points: int, poses: int) -> int:
    """Estimated peak memory (bytes) of planning ``points`` samples for ``poses`` camera poses."""
    return int(points) * int(poses) * PLAN_BYTES_PER_POSE_SAMPLE


class _ShortRepr(reprlib.Repr):
    """repr() bounded in length and depth; huge integers are described by their size."""

    def __init__(self) -> None:
        super().__init__()
        self.maxlevel, self.maxlist, self.maxtuple, self.maxdict = 2, 4, 4, 4
        self.maxstring, self.maxother = 40, 40

    def repr_int(self, x: int, level: int) -> str:
        if x.bit_length() > 64:  # str() of a huge int is slow, and refused past 4300 digits
            return f"<integer of about {int(x.bit_length() * math.log10(2)) + 1} digits>"
        return repr(x)


_SHORT = _ShortRepr()


def show(value: Any) -> str:
    """A short, bounded rendering of a value from a file, for error messages."""
    return _SHORT.repr(value)


def _key_name(key: Any) -> str:
    """A mapping key as written in the file (bounded like :func:`show` when it is not a short string)."""
    return key if isinstance(key, str) and len(key) <= 40 else show(key)


class RigConfigError(PicklableError, ValueError):
    """A rig file is unreadable or a field is missing, unknown or out of range."""

    def __init__(self, path: Path | str, key: str, problem: str) -> None:
        self.path = str(path)
        self.key = key
        self.problem = problem
        super().__init__(f"{self.path}: {key}: {problem}")


@dataclass(frozen=True)
class _Field:
    kind: type
    low: float | None = None
    high: float | None = None
    default: Any = None
    required: bool = True
    pattern: re.Pattern[str] | None = None

    def allowed(self) -> str:
        if self.kind is str and self.pattern is ID_PATTERN:
            return "an id of 1 to 32 letters, digits, '_', '-' or '.', starting with a letter or digit"
        if self.kind is str:
            return f"a non-empty string of at most {MAX_STRING} characters"
        if self.kind is bool:
            return "true or false"
        lo = "-inf" if self.low is None else f"{self.low:g}"
        hi = "inf" if self.high is None else f"{self.high:g}"
        name = "an integer" if self.kind is int else "a number"
        return f"{name} in [{lo}, {hi}]"


def _num(low: float | None = None, high: float | None = None, **kw: Any) -> _Field:
    return _Field(float, low, high, **kw)


def _int(low: int | None = None, high: int | None = None, **kw: Any) -> _Field:
    return _Field(int, low, high, **kw)


def _str(**kw: Any) -> _Field:
    return _Field(str, **kw)


def _id(**kw: Any) -> _Field:
    return _Field(str, pattern=ID_PATTERN, **kw)


class _Reader:
    """Validates one mapping of the rig file against a field table."""

    def __init__(self, path: Path | str) -> None:
        self.path = path

    def error(self, key: str, problem: str) -> RigConfigError:
        return RigConfigError(self.path, key, problem)

    def mapping(self, value: Any, key: str) -> dict[str, Any]:
        if not isinstance(value, dict):
            raise self.error(key, f"expected a mapping, got {type(value).__name__} {show(value)}")
        return value

    def sequence(self, value: Any, key: str, min_len: int, max_len: int) -> list[Any]:
        if not isinstance(value, list):
            raise self.error(key, f"expected a list, got {type(value).__name__} {show(value)}")
        if not min_len <= len(value) <= max_len:
            raise self.error(key, f"has {len(value)} entries, allowed {min_len} to {max_len}")
        return value

    def section(self, raw: Any, key: str, table: dict[str, _Field]) -> dict[str, Any]:
        raw = self.mapping(raw, key)
        unknown = sorted((k for k in raw if k not in table), key=_key_name)
        if unknown:
            raise self.error(
                f"{key}.{_key_name(unknown[0])}", f"unknown key; allowed keys: {', '.join(sorted(table))}"
            )
        out: dict[str, Any] = {}
        for name, spec in table.items():
            full = f"{key}.{name}"
            if name not in raw:
                if spec.required:
                    raise self.error(full, f"missing; expected {spec.allowed()}")
                out[name] = spec.default
                continue
            out[name] = self.value(raw[name], full, spec)
        return out

    def value(self, value: Any, key: str, spec: _Field) -> Any:
        if spec.kind is list:
            return value
        refused = self.error(key, f"got {show(value)}; expected {spec.allowed()}")
        if spec.kind is str:
            if not isinstance(value, str) or not 0 < len(value) <= MAX_STRING:
                raise refused
            if spec.pattern is not None and not spec.pattern.fullmatch(value):
                raise refused
            return value
        if spec.kind is bool:
            if not isinstance(value, bool):
                raise refused
            return value
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise refused
        # Compared before any conversion: an int and a float compare exactly, while float() of a
        # 400-digit integer overflows.
        if isinstance(value, float) and not math.isfinite(value):
            raise refused
        if (spec.low is not None and value < spec.low) or (spec.high is not None and value > spec.high):
            raise refused
        if spec.kind is int and isinstance(value, float) and not value.is_integer():
            raise refused
        return spec.kind(value)


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

    def sector_at(self, angle_deg: float) -> Sector:
        for sector in self.sectors:
            if sector.start_deg <= angle_deg <= sector.end_deg:
                return sector
        raise ValueError(f"beam angle {angle_deg:g} deg is outside the capture rotation")


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


# ---------------------------------------------------------------------------- tables

_OPTICS = {
    "focal_length_mm": _num(1.0, 100.0),
    "f_number": _num(0.7, 32.0),
    "hyperfocal_mm": _num(100.0, 1e6),
    "image_width_px": _int(64, 100_000),
    "image_height_px": _int(64, 100_000),
    "hfov_deg": _num(5.0, 120.0),
    "exposure_s": _num(1e-5, 1.0),
    "iso": _int(25, 25_600),
}
_PHONE = {
    "id": _id(),
    "serial": _str(),
    "height_mm": _num(0.0, 2600.0),
    "tilt_deg": _num(-60.0, 60.0),
    "focus_calibration": _str(),
}
_SECTOR = {
    "name": _id(),
    "start_deg": _num(-360.0, 720.0),
    "end_deg": _num(-360.0, 720.0),
    "speed_deg_s": _num(0.1, 90.0),
    "first_capture_deg": _num(-360.0, 720.0),
    "capture_step_deg": _num(0.1, 180.0),
    "captures": _int(1, 720),
}
_CAPTURE = {
    "sectors": _Field(list),
    "acceleration_deg_s2": _num(0.1, 1000.0),
    "max_motion_blur_px": _num(0.1, 100.0),
    "lens_settle_s": _num(0.0, 5.0),
    "capture_cycle_s": _num(0.0, 60.0),
    "angle_tolerance_deg": _num(0.001, 10.0),
}
_COST = {
    "w_area": _num(0.0, 1.0),
    "w_axis": _num(0.0, 1.0),
    "w_focus": _num(0.0, 1.0),
    "area_reference_distance_mm": _num(1.0, 1e5),
    "area_reference_incidence_deg": _num(0.0, 89.9),
    "axis_deviation_mm": _num(1.0, 1e5),
}
_PLANNER = {
    "points": _int(100, 10_000_000),
    "em_relative_tolerance": _num(0.0, 0.5),
    "em_max_iterations": _int(1, 10_000),
    "refine_max_sweeps": _int(0, 10_000),
    # Robust focus (planner/redundancy.py): cost of one expected missed point, and the chance
    # that one sharp view of a sample fails on the real skin (calibration, sway, between samples).
    "redundancy_weight": _num(0.0, 100.0, default=1.0, required=False),
    "view_miss_probability": _num(0.01, 0.99, default=0.2, required=False),
    "robust_max_sweeps": _int(0, 10_000, default=2, required=False),
    # Per-subject capture angles (planner/angles.py): off unless a rig file asks for them.
    "per_subject_angles": _Field(bool, default=False, required=False),
    "angle_step_deg": _num(0.1, 30.0, default=1.0, required=False),
    # Importance samples (planner/importance.py): the skin few poses see, sampled this many
    # times finer (1: off) within a radius of samples seen by at most importance_views poses.
    "importance_density": _num(1.0, 16.0, default=1.0, required=False),
    "importance_views": _int(1, 1_000, default=6, required=False),
    "importance_radius_mm": _num(1.0, 500.0, default=20.0, required=False),
}
_DEPTH_CAMERA = {
    "id": _id(),
    "serial": _str(),
    "radius_mm": _num(100.0, 5000.0),
    "angle_offset_deg": _num(-360.0, 360.0),
    "height_mm": _num(0.0, 3000.0),
    "tilt_deg": _num(-89.0, 89.0),
    "roll_deg": _num(-180.0, 180.0),
}
_DEPTH_MODEL = {
    "width_px": _int(16, 10_000),
    "height_px": _int(16, 10_000),
    "fx_px": _num(1.0, 1e5),
    "fy_px": _num(1.0, 1e5),
    "cx_px": _num(0.0, 1e4),
    "cy_px": _num(0.0, 1e4),
    "fps": _num(0.1, 1000.0),
    "min_range_mm": _num(0.0, 1e4),
    "max_range_mm": _num(1.0, 1e5),
    "depth_unit_mm": _num(1e-3, 100.0),
    "baseline_mm": _num(1.0, 1000.0),
    "subpixel_px": _num(0.0, 10.0),
    "grazing_limit_deg": _num(1.0, 90.0),
}
_SWEEP = {
    "start_deg": _num(-360.0, 720.0),
    "end_deg": _num(-360.0, 720.0),
    "speed_deg_s": _num(0.1, 180.0),
}
_TSDF = {
    "voxel_mm": _num(0.5, 50.0),
    "truncation_voxels": _num(1.0, 50.0),
    "weight_threshold": _num(0.0, 1000.0),
    "volume_radius_mm": _num(100.0, 5000.0),
    "volume_height_mm": _num(100.0, 5000.0),
    "floor_clearance_mm": _num(0.0, 200.0),
    "camera_clearance_mm": _num(0.0, 400.0, default=50.0, required=False),
}
_MOTOR = {
    "node_id": _int(1, 127),
    "bitrate": _int(10_000, 1_000_000),
    "gear_ratio": _num(0.01, 10_000.0),
    "encoder_counts_per_rev": _int(1, 1 << 24),
    "max_speed_deg_s": _num(0.1, 360.0),
    "max_acceleration_deg_s2": _num(0.1, 10_000.0),
    "heartbeat_producer_ms": _int(10, 10_000),
    "host_heartbeat_ms": _int(10, 10_000),
    "heartbeat_timeout_ms": _int(20, 60_000),
    "following_error_deg": _num(0.01, 90.0),
    "position_rate_hz": _num(1.0, 10_000.0),
    "host_stall_ms": _int(100, 5_000, default=500, required=False),
}
_CALIBRATION = {
    "file": _str(required=False, default="calibration.yaml"),
    "max_age_days": _num(1.0, 3650.0, required=False, default=180.0),
}
_OPTIONAL = {"calibration"}
_TOP = {
    "calibration",
    "optics",
    "ring",
    "phones",
    "capture",
    "cost",
    "planner",
    "depth_cameras",
    "depth_camera_model",
    "depth_sweep",
    "tsdf",
    "motor",
}


def _build(cls: type, values: dict[str, Any]) -> Any:
    return cls(**{f.name: values[f.name] for f in fields(cls)})


def _unique(reader: _Reader, key: str, items: list[Any], attr: str) -> None:
    seen: set[str] = set()
    for i, item in enumerate(items):
        value = getattr(item, attr)
        if value in seen:
            raise reader.error(f"{key}[{i}].{attr}", f"duplicate value {show(value)}; must be unique")
        seen.add(value)


def _capture(reader: _Reader, raw: Any, optics: Optics) -> Capture:
    values = reader.section(raw, "capture", _CAPTURE)
    raw_sectors = reader.sequence(values["sectors"], "capture.sectors", 1, 64)
    sectors = []
    for i, raw_sector in enumerate(raw_sectors):
        key = f"capture.sectors[{i}]"
        sector = _build(Sector, reader.section(raw_sector, key, _SECTOR))
        if sector.end_deg <= sector.start_deg:
            raise reader.error(
                f"{key}.end_deg",
                f"got {sector.end_deg:g}; must be greater than start_deg {sector.start_deg:g}",
            )
        last = sector.capture_angles_deg[-1]
        if sector.first_capture_deg < sector.start_deg or last > sector.end_deg:
            raise reader.error(
                f"{key}.first_capture_deg",
                f"captures span {sector.first_capture_deg:g}..{last:g} deg; must lie inside "
                f"[{sector.start_deg:g}, {sector.end_deg:g}]",
            )
        if sectors and abs(sector.start_deg - sectors[-1].end_deg) > 1e-9:
            raise reader.error(
                f"{key}.start_deg",
                f"got {sector.start_deg:g}; must equal the previous sector's end_deg "
                f"{sectors[-1].end_deg:g} (the rotation is continuous)",
            )
        sectors.append(sector)
    _unique(reader, "capture.sectors", sectors, "name")
    span = sectors[-1].end_deg - sectors[0].start_deg
    if span > 360.0 + 1e-9:
        raise reader.error("capture.sectors", f"span {span:g} deg; allowed at most 360")
    values["sectors"] = tuple(sectors)
    capture = _build(Capture, values)
    for i, sector in enumerate(sectors):
        blur = optics.pixels_per_degree * sector.speed_deg_s * optics.exposure_s
        if blur > capture.max_motion_blur_px:
            raise reader.error(
                f"capture.sectors[{i}].speed_deg_s",
                f"{sector.speed_deg_s:g} deg/s blurs {blur:.2f} px at exposure "
                f"{optics.exposure_s:g} s; allowed at most max_motion_blur_px "
                f"{capture.max_motion_blur_px:g}",
            )
    return capture


def load_rig(path: Path | str = DEFAULT_RIG_PATH) -> Rig:
    """Load and validate a rig file.

    Raises:
        RigConfigError: the file is missing or unparsable, or a key is missing, unknown or out of
            range. The message names the file, the key and the allowed range.
    """
    path = Path(path)
    raw, text = read_yaml(path, max_bytes=MAX_FILE_BYTES, what="rig file",
                          error=lambda problem: RigConfigError(path, "<file>", problem),
                          key_error=lambda key, problem: RigConfigError(path, key, problem))
    return rig_from_mapping(raw, path, hashlib.sha256(text).hexdigest())


def rig_from_mapping(raw: Any, path: Path | str = "<memory>", digest: str = "") -> Rig:
    """Validate an already-parsed rig mapping (see :func:`load_rig`)."""
    reader = _Reader(path)
    raw = reader.mapping(raw, "<top>")
    unknown = sorted((k for k in raw if k not in _TOP), key=_key_name)
    if unknown:
        raise reader.error(_key_name(unknown[0]), f"unknown section; allowed: {', '.join(sorted(_TOP))}")
    for name in sorted(_TOP - _OPTIONAL - set(raw)):
        raise reader.error(name, "missing section")

    optics = _build(Optics, reader.section(raw["optics"], "optics", _OPTICS))
    if optics.hyperfocal_mm <= 2 * optics.focal_length_mm:
        raise reader.error("optics.hyperfocal_mm", "must exceed twice the focal length")
    ring = reader.section(raw["ring"], "ring", {"radius_mm": _num(100.0, 5000.0)})

    phones = tuple(
        _build(Phone, reader.section(p, f"phones[{i}]", _PHONE))
        for i, p in enumerate(reader.sequence(raw["phones"], "phones", 1, 64))
    )
    _unique(reader, "phones", list(phones), "id")
    _unique(reader, "phones", list(phones), "serial")

    depth_cameras = tuple(
        _build(DepthCamera, reader.section(d, f"depth_cameras[{i}]", _DEPTH_CAMERA))
        for i, d in enumerate(reader.sequence(raw["depth_cameras"], "depth_cameras", 1, 16))
    )
    _unique(reader, "depth_cameras", list(depth_cameras), "id")
    model = _build(
        DepthCameraModel, reader.section(raw["depth_camera_model"], "depth_camera_model", _DEPTH_MODEL)
    )
    if model.max_range_mm <= model.min_range_mm:
        raise reader.error("depth_camera_model.max_range_mm", "must exceed min_range_mm")
    sweep = _build(DepthSweep, reader.section(raw["depth_sweep"], "depth_sweep", _SWEEP))
    if sweep.end_deg <= sweep.start_deg:
        raise reader.error("depth_sweep.end_deg", "must exceed start_deg")
    motor = _build(Motor, reader.section(raw["motor"], "motor", _MOTOR))
    if motor.heartbeat_timeout_ms <= motor.host_heartbeat_ms:
        raise reader.error(
            "motor.heartbeat_timeout_ms",
            f"got {motor.heartbeat_timeout_ms}; must exceed host_heartbeat_ms {motor.host_heartbeat_ms}",
        )

    capture = _capture(reader, raw["capture"], optics)
    cost = _build(Cost, reader.section(raw["cost"], "cost", _COST))
    if cost.w_area + cost.w_axis + cost.w_focus <= 0:
        raise reader.error("cost", "w_area, w_axis and w_focus are all 0: at least one weight must be positive")
    planner = _build(PlannerSettings, reader.section(raw["planner"], "planner", _PLANNER))
    poses = len(phones) * len(capture.angles_deg)
    need = planning_memory_bytes(planner.points, poses)
    if need > PLAN_MEMORY_BUDGET_BYTES:
        most = PLAN_MEMORY_BUDGET_BYTES // (poses * PLAN_BYTES_PER_POSE_SAMPLE)
        raise reader.error(
            "planner.points",
            f"got {planner.points}: planning {poses} poses needs about {need / 1024**3:.1f} GiB, more than "
            f"the {PLAN_MEMORY_BUDGET_BYTES / 1024**3:g} GiB budget; allowed at most {most} points",
        )

    return Rig(
        path=str(path),
        digest=digest,
        optics=optics,
        ring_radius_mm=ring["radius_mm"],
        phones=phones,
        capture=capture,
        cost=cost,
        planner=planner,
        depth_cameras=depth_cameras,
        depth_camera_model=model,
        depth_sweep=sweep,
        tsdf=_build(Tsdf, reader.section(raw["tsdf"], "tsdf", _TSDF)),
        motor=motor,
        calibration=_build(CalibrationSettings, reader.section(raw.get("calibration", {}), "calibration", _CALIBRATION)),
    )
