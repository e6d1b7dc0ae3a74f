"""The calibration pipeline: pictures of the cuboid from a calibration rotation -> a :class:`Calibration`.

1. detect the ChArUco corners in every picture (two threads: OpenCV releases the GIL);
2. each camera's lens by Zhang's method over its board views;
3. each picture's pose from its corners (PnP), which also catches a board mounted upside down;
4. a first rig: the similarity (Umeyama) that puts the pictures' camera centres onto the rig
   file's nominal ones gives the cuboid's place in the world; each camera's pose on the beam is
   the mean of its pictures' poses turned back by the encoder angle;
5. bundle adjustment (bundle.py) with a robust loss, residuals over ``discard_px`` dropped (the
   seed drops those over 4 px), adjusted again;
6. the world turned so the phone column faces +x at beam angle 0.

Pictures that cannot be used (unreadable, blurred, no board, a board upside down, a camera that
saw nothing) become :class:`Problem` entries naming the picture; the rest still calibrates.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from planner.calibration import bundle
from planner.calibration.detect import CorneredTarget, Detection, detect_picture
from planner.calibration.geometry import from_rotvec, rot_z, umeyama
from planner.calibration.intrinsics import IntrinsicsError, calibrate_lens, picture_pose
from planner.calibration.model import BeamPose, Calibration, CameraCalibration, Intrinsics, Residuals
from planner.calibration.nominal import depth_intrinsics, nominal_cameras, phone_intrinsics
from planner.calibration.target import CuboidTarget
from planner.picklable import PicklableError
from planner.rig import Rig

BLUR_RATIO = 0.3
"""A picture whose sharpness is below this share of its camera's median is refused as blurred."""


class CalibrationFailed(PicklableError, RuntimeError):
    """Too little usable data for a calibration; ``problems`` says what was wrong with which picture."""

    def __init__(self, reason: str, problems: Sequence[Problem]) -> None:
        self.reason, self.problems = reason, list(problems)
        super().__init__(reason + "".join(f"\n  {p}" for p in self.problems[:20]))


@dataclass(frozen=True)
class Picture:
    """One picture of the calibration rotation: camera id and kind, capture index, encoder angle, file."""

    camera: str
    kind: str
    angle_index: int
    encoder_deg: float
    path: Path
    name: str
    intrinsics: tuple[float, float, float, float] | None = None


@dataclass(frozen=True)
class Problem:
    """Something wrong with one picture, a camera or a face (None where it does not apply)."""

    message: str
    image: str | None = None
    camera: str | None = None

    def __str__(self) -> str:
        where = self.image or (f"camera {self.camera}" if self.camera else "target")
        return f"{where}: {self.message}"


@dataclass
class CalibrationRun:
    """Everything the report shows: the calibration, detections, residuals, problems, timings."""

    calibration: Calibration
    detections: list[Detection]
    problems: list[Problem]
    obs_camera: np.ndarray
    obs_capture: np.ndarray
    obs_px: np.ndarray
    obs_error_px: np.ndarray
    camera_ids: list[str]
    timings_s: dict[str, float] = field(default_factory=dict)
    lens_rms_px: dict[str, float] = field(default_factory=dict)
    similarity_scale: float = 1.0
    evaluations: int = 0


def read_captures(path: Path | str) -> list[Picture]:
    """The pictures listed in a calibration rotation's ``captures.json`` (files relative to it).

    Raises CalibrationFailed naming the file and the entry when it cannot be read."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
        entries = doc["captures"]
    except OSError as exc:
        raise CalibrationFailed(f"{path}: cannot read: {exc.strerror or exc}", []) from exc
    except (ValueError, KeyError, TypeError) as exc:
        raise CalibrationFailed(f"{path}: not a captures file (a 'captures' list): {exc}", []) from exc
    pictures = []
    for i, c in enumerate(entries):
        try:
            if c["kind"] not in ("phone", "depth"):
                raise ValueError(f"kind {c['kind']!r} is not phone or depth")
            k = c.get("intrinsics")
            lens = None if k is None else (float(k["fx"]), float(k["fy"]), float(k["cx"]), float(k["cy"]))
            pictures.append(Picture(str(c["camera"]), c["kind"], int(c["angle_index"]), float(c["encoder_deg"]),
                                    path.parent / c["file"], str(c["file"]), lens))
        except (KeyError, TypeError, ValueError) as exc:
            raise CalibrationFailed(f"{path}: captures[{i}]: {exc!r}; expected camera, kind, angle_index, "
                                    "encoder_deg and file", []) from exc
    if not pictures:
        raise CalibrationFailed(f"{path}: lists no picture", [])
    return pictures


def _lens_guess(rig: Rig, kind: str, size: tuple[int, int]) -> Intrinsics:
    return phone_intrinsics(rig, *size) if kind == "phone" else depth_intrinsics(rig, *size)


def detect_pictures(target: CuboidTarget, pictures: Sequence[Picture], *, jobs: int = 2, max_side_px: int = 2600,
                    progress: Callable[[str, int, int], None] | None = None) -> list[Detection]:
    """Corners of the target in every picture, in the pictures' order (``jobs`` threads)."""
    detector = CorneredTarget(target)
    done = [0]

    def one(p: Picture) -> Detection:
        d = detect_picture(detector, p.path, p.camera, p.angle_index, p.name, max_side_px=max_side_px)
        done[0] += 1
        if progress is not None:
            progress("detect", done[0], len(pictures))
        return d

    with ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
        return list(pool.map(one, pictures))


def calibrate(rig: Rig, target: CuboidTarget, pictures: Sequence[Picture], *, created_utc: str, source: str,
              jobs: int = 2, settings: bundle.Settings = bundle.Settings(), discard_px: float = 4.0,
              max_side_px: int = 2600, progress: Callable[[str, int, int], None] | None = None) -> CalibrationRun:
    """Calibrate the rig from its pictures of the target (see the module docstring)."""
    t0 = time.perf_counter()
    detections = detect_pictures(target, pictures, jobs=jobs, max_side_px=max_side_px, progress=progress)
    run = calibrate_detections(rig, target, pictures, detections, created_utc=created_utc, source=source,
                               settings=settings, discard_px=discard_px, progress=progress)
    run.timings_s = {"detection": time.perf_counter() - t0 - sum(run.timings_s.values()), **run.timings_s}
    return run


def calibrate_detections(rig: Rig, target: CuboidTarget, pictures: Sequence[Picture], detections: list[Detection], *,
                         created_utc: str, source: str, settings: bundle.Settings = bundle.Settings(),
                         discard_px: float = 4.0, progress: Callable[[str, int, int], None] | None = None
                         ) -> CalibrationRun:
    """Steps 2 to 6 on detections already made (one per picture, in the same order)."""
    timings: dict[str, float] = {}
    problems: list[Problem] = []
    say = progress or (lambda stage, done, total: None)
    known = {c.id for c in nominal_cameras(rig, (2, 2))}
    for cam in sorted({p.camera for p in pictures} - known):
        problems.append(Problem("not a camera of the rig file; its pictures are left out", camera=cam))
    for cam in sorted(known - {p.camera for p in pictures}):
        problems.append(Problem("no picture in the captures file; left out of the calibration", camera=cam))
    detections = [d for d in detections if d.camera in known]
    usable = _screen(detections, problems)
    _missing_faces(target, usable, problems)

    # 2. lenses
    t0 = time.perf_counter()
    kinds = {p.camera: p.kind for p in pictures}
    order = [c.id for c in nominal_cameras(rig, (2, 2)) if c.id in kinds]
    lenses: dict[str, Intrinsics] = {}
    lens_rms: dict[str, float] = {}
    held: set[str] = set()
    for cam in order:
        mine = [d for d in usable if d.camera == cam]
        all_mine = [d for d in detections if d.camera == cam]
        if not mine:
            problems.append(Problem(f"saw no board in any of its {len(all_mine)} pictures (lens covered, camera "
                                    "facing away or unplugged?); left out of the calibration", camera=cam))
            continue
        size = mine[0].size_px
        if kinds[cam] == "depth":
            # the depth frames carry the device's factory intrinsics and the TSDF uses them: the
            # pose must fit those, so they are held (from the pictures, else the rig file's model)
            reported = next((p.intrinsics for p in pictures if p.camera == cam and p.intrinsics), None)
            lenses[cam] = (Intrinsics(size[0], size[1], *reported) if reported is not None
                           else _lens_guess(rig, "depth", size))
            held.add(cam)
            continue
        try:
            fit = calibrate_lens(cam, mine, target, _lens_guess(rig, kinds[cam], size))
        except IntrinsicsError as exc:
            problems.append(Problem(f"{exc.problem}; left out of the calibration", camera=cam))
            continue
        lenses[cam], lens_rms[cam] = fit.intrinsics, fit.rms_px
    timings["intrinsics"] = time.perf_counter() - t0

    # 3. per-picture poses, upside-down boards
    t0 = time.perf_counter()
    nominal = {c.id: c for c in nominal_cameras(rig, (2, 2))}
    usable = [d for d in usable if d.camera in lenses]
    usable = _upside_down(target, usable, lenses, nominal, problems)
    poses: dict[tuple[str, int], np.ndarray] = {}
    for d in usable:
        pose, rms = picture_pose(d, target.corners, lenses[d.camera])
        if rms > discard_px:
            problems.append(Problem(f"its corners fit no single camera pose (RMS {rms:.1f} px); left out", image=d.image))
            continue
        poses[(d.camera, d.angle_index)] = pose
    usable = [d for d in usable if (d.camera, d.angle_index) in poses]
    cameras = [c for c in order if any(d.camera == c for d in usable)]
    if not cameras or not any(kinds[c] == "phone" for c in cameras):
        raise CalibrationFailed("no phone picture shows the target well enough to calibrate", problems)

    # 4. first rig
    encoder = _encoder_angles(pictures)
    state, scale = _initial_state(rig, target, cameras, lenses, nominal, poses, encoder)
    timings["initial_poses"] = time.perf_counter() - t0

    # 5. bundle adjustment, outliers dropped, again
    t0 = time.perf_counter()
    index = {c: i for i, c in enumerate(cameras)}
    obs = bundle.Observations(
        np.concatenate([np.full(d.n_corners, index[d.camera]) for d in usable]),
        np.concatenate([np.full(d.n_corners, d.angle_index) for d in usable]),
        np.concatenate([d.corner_ids for d in usable]), np.concatenate([d.points_px for d in usable]))
    boards = [f.cuboid_from_board for f in target.faces]
    evaluations = 0
    for round_ in range(2):
        say("bundle adjustment", round_, 2)
        problem = bundle.BundleProblem(obs, target.board_corners, boards, target.corners_per_face, encoder,
                                       len(cameras), settings, held_lenses=[c in held for c in cameras])
        state, err, nfev = problem.solve(state, robust=round_ == 0)
        evaluations += nfev
        if round_ == 0:
            discarded = int(np.count_nonzero(err > discard_px))
            obs = obs.subset(err <= discard_px)
    say("bundle adjustment", 2, 2)
    timings["bundle_adjustment"] = time.perf_counter() - t0

    # 6. world frame and the file
    phones = [i for i, c in enumerate(cameras) if kinds[c] == "phone"]
    cams, cuboid, tilt, shift = bundle.normalise_azimuth(state.beam_from_camera, phones, state.world_from_cuboid(),
                                                         state.tilt_rad, state.shift_mm)
    board_poses = tuple(m @ from_rotvec(d[:3], d[3:]) for m, d in zip(boards, state.board_delta))
    beam = tuple(BeamPose(k, float(encoder[k]), float(encoder[k] + math.degrees(state.angle_offset_rad[k])),
                          (float(tilt[k, 0]), float(tilt[k, 1])), (float(shift[k, 0]), float(shift[k, 1]), float(shift[k, 2])))
                 for k in range(len(encoder)))
    residuals = _residual_stats(err, obs, cameras, discarded)
    calibration = Calibration(
        created_utc=created_utc, rig_digest=rig.digest, target_name=target.name, source=source,
        cameras=tuple(CameraCalibration(c, kinds[c], state.lenses[i], cams[i]) for i, c in enumerate(cameras)),
        beam=beam, world_from_cuboid=cuboid, cuboid_from_boards=board_poses, residuals=residuals)
    return CalibrationRun(calibration, detections, problems, obs.camera, obs.capture, obs.px, err, cameras,
                          timings, lens_rms, scale, evaluations)


# ---------------------------------------------------------------------------- steps


def _screen(detections: list[Detection], problems: list[Problem]) -> list[Detection]:
    """Pictures worth using: readable, not blurred, with corners. Each refusal names the picture."""
    by_camera: dict[str, list[float]] = {}
    for d in detections:
        if d.problem is None and d.n_corners:
            by_camera.setdefault(d.camera, []).append(d.sharpness)
    usable = []
    for d in detections:
        median = float(np.median(by_camera[d.camera])) if d.camera in by_camera else 0.0
        if d.problem is not None:
            problems.append(Problem(d.problem, image=d.image, camera=d.camera))
        elif median > 0 and d.sharpness < BLUR_RATIO * median:
            problems.append(Problem(f"blurred: sharpness {d.sharpness:.0f}, {d.sharpness / median:.0%} of camera "
                                    f"{d.camera}'s median {median:.0f} (out of focus or moving?); left out",
                                    image=d.image, camera=d.camera))
        elif not d.n_corners:
            what = f"{d.markers} markers but too few corners" if d.markers else "no marker of the target"
            problems.append(Problem(f"{what} (sharpness {d.sharpness:.0f}); left out", image=d.image, camera=d.camera))
        else:
            usable.append(d)
    return usable


def _missing_faces(target: CuboidTarget, usable: list[Detection], problems: list[Problem]) -> None:
    seen = np.zeros(len(target.faces), dtype=int)
    for d in usable:
        seen[np.unique(d.faces)] += 1
    for f in target.faces:
        if seen[f.index] == 0:
            problems.append(Problem(f"face {f.name}: no corner of its board in any picture (board missing or "
                                    f"covered?); calibrating on the other faces"))


def _upside_down(target: CuboidTarget, usable: list[Detection], lenses: dict[str, Intrinsics],
                 nominal: dict[str, CameraCalibration], problems: list[Problem]) -> list[Detection]:
    """Drop the corners of boards that read upside down. A board glued turned by 180 deg decodes
    fine but puts the camera upside down: its image axes point the other way up than the rig's."""
    import cv2

    flagged: dict[int, list[str]] = {}
    views = np.zeros(len(target.faces), dtype=int)
    bad: set[tuple[str, int]] = set()
    for d in usable:
        expected = nominal[d.camera].beam_from_camera[2, :2]  # z of the camera's right and down axes
        for face in np.unique(d.faces):
            mine = d.faces == face
            ok, rvec, _ = cv2.solvePnP(target.corners[d.corner_ids[mine]], d.points_px[mine], lenses[d.camera].matrix,
                                       lenses[d.camera].dist, flags=cv2.SOLVEPNP_IPPE)
            if not ok:
                continue
            views[face] += 1
            measured = cv2.Rodrigues(rvec)[0][:2, 2]  # cuboid z of the camera's right and down axes
            if float(measured @ expected) < 0:
                flagged.setdefault(int(face), []).append(d.image)
                bad.add((d.image, int(face)))
    out = []
    for face, images in flagged.items():
        name = target.faces[face].name
        if len(images) > views[face] / 2:
            problems.append(Problem(f"face {name}: the board reads upside down in {len(images)} of {views[face]} "
                                    f"pictures (e.g. {images[0]}): it is mounted turned by 180 deg; its corners are "
                                    "left out, turn the board over"))
        else:
            for image in images:
                problems.append(Problem(f"board {name} reads upside down in this picture only; its corners are left out",
                                        image=image))
    for d in usable:
        keep = np.array([(d.image, int(f)) not in bad for f in d.faces], dtype=bool)
        if keep.all():
            out.append(d)
        elif keep.sum() >= 6:
            out.append(Detection(d.image, d.camera, d.angle_index, d.corner_ids[keep], d.points_px[keep],
                                 d.faces[keep], d.markers, d.sharpness, d.scale, d.size_px))
    return out


def _encoder_angles(pictures: Sequence[Picture]) -> np.ndarray:
    """(K,) encoder angle of each capture index (the pictures of one capture share the beam's stop)."""
    n = max(p.angle_index for p in pictures) + 1
    out = np.full(n, np.nan)
    for p in pictures:
        out[p.angle_index] = p.encoder_deg
    if np.isnan(out).any():
        raise CalibrationFailed(f"captures {np.flatnonzero(np.isnan(out)).tolist()} have no picture", [])
    return out


def _initial_state(rig: Rig, target: CuboidTarget, cameras: list[str], lenses: dict[str, Intrinsics],
                   nominal: dict[str, CameraCalibration], poses: dict[tuple[str, int], np.ndarray],
                   encoder: np.ndarray) -> tuple[bundle.RigState, float]:
    """A first rig from the per-picture poses (see the module docstring, step 4)."""
    keys = sorted(poses)
    measured = np.array([poses[k][:3, 3] for k in keys])
    expected = np.array([(rot_z(math.radians(encoder[a])) @ nominal[c].beam_from_camera)[:3, 3] for c, a in keys])
    scale, rotation, translation = umeyama(measured, expected)
    world_from_cuboid = np.eye(4)
    world_from_cuboid[:3, :3], world_from_cuboid[:3, 3] = rotation, translation
    cams = []
    for c in cameras:
        mine = [world_from_cuboid @ _unscaled(poses[k], scale) for k in keys if k[0] == c]
        on_beam = [rot_z(-math.radians(encoder[a])) @ m for (cc, a), m in zip([k for k in keys if k[0] == c], mine)]
        m = np.eye(4)
        m[:3, :3] = Rotation.from_matrix(np.array([b[:3, :3] for b in on_beam])).mean().as_matrix()
        m[:3, 3] = np.mean([b[:3, 3] for b in on_beam], axis=0)
        cams.append(m)
    n = world_from_cuboid[:3, 2]
    axis = np.cross([0.0, 0.0, 1.0], n)
    angle = math.asin(min(1.0, float(np.linalg.norm(axis))))
    tilt = axis / max(np.linalg.norm(axis), 1e-12) * angle
    untilted = Rotation.from_rotvec(tilt).as_matrix().T @ world_from_cuboid[:3, :3]
    yaw = math.atan2(untilted[1, 0], untilted[0, 0])
    k = len(encoder)
    state = bundle.RigState(cams, [lenses[c] for c in cameras], np.zeros(k), np.zeros((k, 2)), np.zeros((k, 3)),
                            tilt[:2], yaw, world_from_cuboid[:2, 3].copy(), np.zeros((len(target.faces), 6)))
    return state, scale


def _unscaled(cuboid_from_camera: np.ndarray, scale: float) -> np.ndarray:
    """A picture's pose with its centre scaled like the similarity (the boards are metric: scale ~ 1)."""
    m = cuboid_from_camera.copy()
    m[:3, 3] *= scale
    return m


def _residual_stats(err: np.ndarray, obs: bundle.Observations, cameras: list[str], discarded: int) -> Residuals:
    per_mean = {c: float(err[obs.camera == i].mean()) for i, c in enumerate(cameras) if np.any(obs.camera == i)}
    per_count = {c: int(np.count_nonzero(obs.camera == i)) for i, c in enumerate(cameras)}
    return Residuals(len(err), discarded, float(err.mean()), float(np.median(err)), float(np.sqrt(np.mean(err**2))),
                     float(np.percentile(err, 95)), float(err.max()), per_mean, per_count)

