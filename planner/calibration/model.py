"""The calibration file (``calibration.yaml``): every camera's intrinsics and pose on the beam, the
beam's pose at every capture angle, the target's pose, residual statistics; save, load, validate.

World frame (SPEC): z along the rotation axis, origin where the axis meets the floor, x where
the beam frame's x points when the encoder reads 0. A camera's pose at beam angle theta is
``world_from_beam(theta) @ beam_from_camera``; ``world_from_beam(theta) = Rz(theta) @
wobble(theta)``, the wobble (bearing tilt and runout) measured at each capture angle and
interpolated around the turn in between. Camera axes are OpenCV's (x right, y down, z forward).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from planner.calibration.geometry import from_rotvec, rot_z, to_rotvec
from planner.schema import ConfigError
from planner.schema.tables import CALIBRATION_FILE, CALIBRATION_FORMAT

MAX_FILE_BYTES = CALIBRATION_FILE.max_bytes


class CalibrationFileError(ConfigError):
    """A calibration file is unreadable or a key is missing, unknown or out of range."""


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole + Brown-Conrady distortion (OpenCV's k1, k2, p1, p2, k3) for images of width x height px."""

    width_px: int
    height_px: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    @property
    def matrix(self) -> np.ndarray:
        """(3, 3) float camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist(self) -> np.ndarray:
        return np.asarray(self.distortion, dtype=float)

    def scaled(self, factor: float) -> Intrinsics:
        """The same lens for images resampled by ``factor`` (pixel centres kept)."""
        return Intrinsics(int(round(self.width_px * factor)), int(round(self.height_px * factor)),
                          self.fx * factor, self.fy * factor, (self.cx + 0.5) * factor - 0.5,
                          (self.cy + 0.5) * factor - 0.5, self.distortion)


@dataclass(frozen=True)
class CameraCalibration:
    """One camera on the beam. kind: "phone" or "depth"; beam_from_camera: (4, 4) float, mm."""

    id: str
    kind: str
    intrinsics: Intrinsics
    beam_from_camera: np.ndarray


@dataclass(frozen=True)
class BeamPose:
    """The beam at one capture: encoder reading, calibrated angle and wobble (tilt rad, shift mm)."""

    angle_index: int
    encoder_deg: float
    angle_deg: float
    tilt_rad: tuple[float, float]
    shift_mm: tuple[float, float, float]

    def wobble(self) -> np.ndarray:
        """(4, 4) the beam's deviation from a pure rotation about z, in the beam frame."""
        return from_rotvec(np.array([self.tilt_rad[0], self.tilt_rad[1], 0.0]), np.asarray(self.shift_mm))

    def world_from_beam(self) -> np.ndarray:
        result: np.ndarray = rot_z(math.radians(self.angle_deg)) @ self.wobble()
        return result


@dataclass(frozen=True)
class Residuals:
    """Reprojection residuals (px) of the final bundle adjustment, over the kept observations."""

    count: int
    discarded: int
    mean_px: float
    median_px: float
    rms_px: float
    p95_px: float
    max_px: float
    per_camera_mean_px: dict[str, float] = field(default_factory=dict)
    per_camera_count: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class Calibration:
    """A whole rig calibration (see the module docstring for frames)."""

    created_utc: str
    rig_digest: str
    target_name: str
    source: str
    cameras: tuple[CameraCalibration, ...]
    beam: tuple[BeamPose, ...]
    world_from_cuboid: np.ndarray
    cuboid_from_boards: tuple[np.ndarray, ...]
    residuals: Residuals | None = None
    path: str = "<memory>"
    digest: str = ""

    # ------------------------------------------------------------------ lookups
    def camera(self, camera_id: str) -> CameraCalibration:
        for c in self.cameras:
            if c.id == camera_id:
                return c
        raise KeyError(f"calibration {self.path} has no camera {camera_id!r}; it has "
                       f"{', '.join(c.id for c in self.cameras)}")

    def camera_ids(self, kind: str) -> list[str]:
        return [c.id for c in self.cameras if c.kind == kind]

    def world_from_beam(self, angle_deg: float) -> np.ndarray:
        """(4, 4) the beam's pose at any angle: rotation about z, wobble interpolated around the turn."""
        result: np.ndarray = rot_z(math.radians(angle_deg)) @ self._wobble_at(angle_deg)
        return result

    def world_from_camera(self, camera_id: str, angle_deg: float) -> np.ndarray:
        """(4, 4) camera-to-world pose of a camera at a beam angle (deg)."""
        result: np.ndarray = self.world_from_beam(angle_deg) @ self.camera(camera_id).beam_from_camera
        return result

    def capture_pose(self, camera_id: str, capture: int) -> np.ndarray:
        """(4, 4) camera-to-world pose of a camera at one calibration capture (its measured beam pose)."""
        result: np.ndarray = self.beam[capture].world_from_beam() @ self.camera(camera_id).beam_from_camera
        return result

    def _wobble_at(self, angle_deg: float) -> np.ndarray:
        if not self.beam:
            return np.eye(4)
        encoder = np.array([b.encoder_deg for b in self.beam])
        params = np.array([[*b.tilt_rad, *b.shift_mm] for b in self.beam])
        order = np.argsort(encoder)
        ang, params = encoder[order], params[order]
        # periodic linear interpolation over the turn
        ext_ang = np.r_[ang[-1] - 360.0, ang, ang[0] + 360.0]
        ext = np.vstack([params[-1], params, params[0]])
        a = (angle_deg - ang[0]) % 360.0 + ang[0]
        if a > ext_ang[-1]:
            a -= 360.0
        p = np.array([np.interp(a, ext_ang, ext[:, i]) for i in range(5)])
        return from_rotvec(np.array([p[0], p[1], 0.0]), p[2:])

    # ------------------------------------------------------------------ file
    def to_mapping(self) -> dict[str, Any]:
        return {
            "format": CALIBRATION_FORMAT,
            "created_utc": self.created_utc,
            "rig_digest": self.rig_digest,
            "target": self.target_name,
            "source": self.source,
            "cameras": [_camera_out(c) for c in self.cameras],
            "beam": [{"angle_index": b.angle_index, "encoder_deg": _f(b.encoder_deg), "angle_deg": _f(b.angle_deg),
                      "tilt_deg": [_f(math.degrees(t)) for t in b.tilt_rad],
                      "shift_mm": [_f(s) for s in b.shift_mm]} for b in self.beam],
            "world_from_cuboid": _pose_out(self.world_from_cuboid),
            "cuboid_from_boards": [_pose_out(m) for m in self.cuboid_from_boards],
            "residuals": None if self.residuals is None else _residuals_out(self.residuals),
        }

    def save(self, path: Path | str) -> Calibration:
        """Write the YAML file (atomically: temp file, then rename); returns the calibration as loaded."""
        path = Path(path)
        text = ("# Rig calibration written by `tbp calibrate` (planner/calibration/model.py documents "
                "the frames).\n" + yaml.safe_dump(self.to_mapping(), sort_keys=False, width=120))
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(text)
        tmp.replace(path)
        return load_calibration(path)


def _f(x: float) -> float:
    return float(round(float(x), 9))


def _pose_out(m: np.ndarray) -> dict[str, Any]:
    rotvec, t = to_rotvec(m)
    return {"rotation_deg": [_f(math.degrees(v)) for v in rotvec], "translation_mm": [_f(v) for v in t]}


def _camera_out(c: CameraCalibration) -> dict[str, Any]:
    k = c.intrinsics
    return {"id": c.id, "kind": c.kind,
            "intrinsics": {"image_size_px": [k.width_px, k.height_px], "fx": _f(k.fx), "fy": _f(k.fy),
                           "cx": _f(k.cx), "cy": _f(k.cy), "distortion": [_f(v) for v in k.distortion]},
            "beam_from_camera": _pose_out(c.beam_from_camera)}


def _residuals_out(r: Residuals) -> dict[str, Any]:
    return {"count": r.count, "discarded": r.discarded, "mean_px": _f(r.mean_px), "median_px": _f(r.median_px),
            "rms_px": _f(r.rms_px), "p95_px": _f(r.p95_px), "max_px": _f(r.max_px),
            "per_camera_mean_px": {k: _f(v) for k, v in r.per_camera_mean_px.items()},
            "per_camera_count": dict(r.per_camera_count)}


# ---------------------------------------------------------------------------- loading


def _pose(v: dict[str, Any]) -> np.ndarray:
    return from_rotvec(np.radians(v["rotation_deg"]), np.array(v["translation_mm"]))


def load_calibration(path: Path | str) -> Calibration:
    """Load and validate a calibration file (its table: planner/schema/tables.py); CalibrationFileError
    names the file and the key."""
    v, digest = CALIBRATION_FILE.load(path, CalibrationFileError)
    cameras = []
    for c in v["cameras"]:
        k = c["intrinsics"]
        width, height = k["image_size_px"]  # the table reads 2 integers and 5 distortion numbers
        k1, k2, p1, p2, k3 = k["distortion"]
        intr = Intrinsics(width, height, k["fx"], k["fy"], k["cx"], k["cy"], (k1, k2, p1, p2, k3))
        cameras.append(CameraCalibration(c["id"], c["kind"], intr, _pose(c["beam_from_camera"])))
    ids = [c.id for c in cameras]
    if len(set(ids)) != len(ids):
        raise CalibrationFileError(str(path), "cameras", f"duplicate camera ids in {ids}")
    beam = tuple(BeamPose(b["angle_index"], b["encoder_deg"], b["angle_deg"],
                          (math.radians(b["tilt_deg"][0]), math.radians(b["tilt_deg"][1])), tuple(b["shift_mm"]))
                 for b in v["beam"])
    res = v["residuals"]
    residuals = None if res is None else Residuals(
        res["count"], res["discarded"], res["mean_px"], res["median_px"], res["rms_px"], res["p95_px"], res["max_px"],
        per_camera_mean_px=res["per_camera_mean_px"] or {}, per_camera_count=res["per_camera_count"] or {})
    return Calibration(
        created_utc=v["created_utc"], rig_digest=v["rig_digest"] or "", target_name=v["target"], source=v["source"],
        cameras=tuple(cameras), beam=beam, world_from_cuboid=_pose(v["world_from_cuboid"]),
        cuboid_from_boards=tuple(_pose(m) for m in v["cuboid_from_boards"]),
        residuals=residuals, path=str(path), digest=digest)
