"""The simulated rig as built, for calibration: true camera poses off nominal, true lenses, a wobbling
beam, the cuboid where the operator put it, and the calibration rotation's pictures of it.

Errors are seeded and sized like a hand-built rig: phones a few mm and a few tenths of a degree
off their nominal mount, lenses a percent off in focal length with real distortion, the
encoder's zero a little off the phone column, a bearing that tilts the beam by a few hundredths
of a degree and runs out by a tenth of a millimetre around the turn, boards glued a fraction of
a millimetre off. The truth is a :class:`Calibration` in the same format the pipeline writes.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from planner.calibration.bundle import normalise_azimuth
from planner.calibration.geometry import from_rotvec
from planner.calibration.model import BeamPose, Calibration, CameraCalibration, Intrinsics
from planner.calibration.nominal import nominal_cameras
from planner.calibration.target import CuboidTarget
from planner.rig import Rig

PHONE_SIZE = (768, 1024)
"""Simulated calibration pictures: 1/8 of the phones' 6144 x 8192 sensor, the whole field of view."""


@dataclass(frozen=True)
class TrueRigErrors:
    """1-sigma sizes of the simulated rig's deviations from nominal."""

    phone_mm: float = 2.0
    phone_deg: float = 0.3
    depth_mm: float = 3.0
    depth_deg: float = 0.4
    focal_rel: float = 0.01
    principal_rel: float = 0.01
    k1: float = 0.04
    encoder_zero_deg: float = 0.3
    stop_deg: float = 0.05
    encoder_to_beam_deg: float = 0.01
    wobble_deg: float = 0.03
    runout_mm: float = 0.15
    board_mm: float = 0.3
    board_deg: float = 0.05
    cuboid_offset_mm: float = 6.0
    cuboid_turn_deg: float = 4.0
    floor_tilt_deg: float = 0.1


def _jitter(rng: np.random.Generator, mm: float, deg: float) -> np.ndarray:
    return from_rotvec(np.radians(rng.normal(0.0, deg, 3)), rng.normal(0.0, mm, 3))


def _lens(rng: np.random.Generator, k: Intrinsics, e: TrueRigErrors, distortion_scale: float) -> Intrinsics:
    f = k.fx * (1.0 + rng.normal(0.0, e.focal_rel))
    return Intrinsics(k.width_px, k.height_px, f, f * (1.0 + rng.normal(0.0, 1e-3)),
                      k.cx + rng.normal(0.0, e.principal_rel * k.width_px),
                      k.cy + rng.normal(0.0, e.principal_rel * k.height_px),
                      (float(rng.normal(0.0, e.k1) * distortion_scale), float(rng.normal(0.0, e.k1 / 2) * distortion_scale),
                       float(rng.normal(0.0, 3e-4)), float(rng.normal(0.0, 3e-4)), 0.0))


def true_rig(rig: Rig, target: CuboidTarget, seed: int, *, errors: TrueRigErrors = TrueRigErrors(),
             phone_size: tuple[int, int] = PHONE_SIZE) -> Calibration:
    """The simulated rig's truth for a seed, as a calibration (beam poses at the rig's capture angles)."""
    rng = np.random.default_rng([seed, 0xCA1])
    e = errors
    zero = from_rotvec(np.array([0.0, 0.0, math.radians(rng.normal(0.0, e.encoder_zero_deg))]), np.zeros(3))
    cameras = []
    for cam in nominal_cameras(rig, phone_size):
        phone = cam.kind == "phone"
        mount = _jitter(rng, e.phone_mm if phone else e.depth_mm, e.phone_deg if phone else e.depth_deg)
        # the mount error acts at the camera (a rotation about its own centre), the encoder zero on the beam
        # a depth camera's infrared image is rectified and its intrinsics come calibrated from the
        # factory (the depth frames carry them): its lens is the one it reports
        lens = _lens(rng, cam.intrinsics, e, 1.0) if phone else cam.intrinsics
        cameras.append(CameraCalibration(cam.id, cam.kind, lens, zero @ cam.beam_from_camera @ mount))
    phase = rng.uniform(0, 2 * math.pi, 4)
    beam = []
    for i, planned in enumerate(rig.capture.angles_deg):
        encoder = float(planned + rng.normal(0.0, e.stop_deg))
        a = math.radians(encoder)
        tilt = (math.radians(e.wobble_deg) * math.cos(a + phase[0]) + math.radians(e.wobble_deg / 2) * math.cos(2 * a + phase[1]),
                math.radians(e.wobble_deg) * math.sin(a + phase[0]) + math.radians(e.wobble_deg / 2) * math.sin(2 * a + phase[2]))
        shift = (e.runout_mm * math.cos(a + phase[3]), e.runout_mm * math.sin(a + phase[3]), e.runout_mm / 3 * math.sin(a))
        beam.append(BeamPose(i, encoder, encoder + float(rng.normal(0.0, e.encoder_to_beam_deg)), tilt, shift))
    # The cuboid stands on the floor, which is a little off perpendicular to the axis: the world
    # origin (axis meets floor) stays in the cuboid's bottom plane.
    tilt = np.radians(rng.normal(0.0, e.floor_tilt_deg, 2))
    turn = math.radians(rng.uniform(-e.cuboid_turn_deg, e.cuboid_turn_deg))
    rotation = from_rotvec(np.array([tilt[0], tilt[1], 0.0]), np.zeros(3)) @ from_rotvec(np.array([0.0, 0.0, turn]), np.zeros(3))
    offset = rng.normal(0.0, e.cuboid_offset_mm, 2)
    n = rotation[:3, 2]
    height = -(n[0] * offset[0] + n[1] * offset[1]) / n[2]
    world_from_cuboid = rotation.copy()
    world_from_cuboid[:3, 3] = [offset[0], offset[1], height]
    boards = [target.faces[0].cuboid_from_board] + [f.cuboid_from_board @ _jitter(rng, e.board_mm, e.board_deg)
                                                    for f in target.faces[1:]]
    # the world frame the calibration uses: the phone column faces +x at beam angle 0 (the encoder's
    # zero error is a turn of the whole world about the axis, which no picture can tell)
    phones = [i for i, c in enumerate(cameras) if c.kind == "phone"]
    poses, world_from_cuboid, tilts, shifts = normalise_azimuth(
        [c.beam_from_camera for c in cameras], phones, world_from_cuboid,
        np.array([b.tilt_rad for b in beam]), np.array([b.shift_mm for b in beam]))
    cameras = [replace(c, beam_from_camera=m) for c, m in zip(cameras, poses)]
    beam = [replace(b, tilt_rad=tuple(t), shift_mm=tuple(s)) for b, t, s in zip(beam, tilts, shifts)]
    return Calibration(created_utc="simulated", rig_digest=rig.digest, target_name=target.name,
                       source=f"simulated rig truth, seed {seed}", cameras=tuple(cameras), beam=tuple(beam),
                       world_from_cuboid=world_from_cuboid, cuboid_from_boards=tuple(boards))


@dataclass(frozen=True)
class CalibrationFaults:
    """Pictures spoiled on purpose: (camera id, angle index) pairs.

    blurred: the picture is badly out of focus. blind: cameras that see nothing (lens cap on).
    hidden_faces: face indices covered (missing faces). A board mounted upside down is a fact of
    the target, not of a picture: :func:`mount_upside_down` turns it in the truth.
    """

    blurred: frozenset[tuple[str, int]] = frozenset()
    blind: frozenset[str] = frozenset()
    hidden_faces: frozenset[int] = frozenset()


def render_calibration_captures(rig: Rig, target: CuboidTarget, truth: Calibration, out: Path, *, seed: int,
                                faults: CalibrationFaults = CalibrationFaults(), jobs: int = 2,
                                progress: Callable[[int, int], None] | None = None) -> Path:
    """Render the stop-and-go calibration rotation into ``out``: one JPEG per phone and angle, one PNG per
    depth camera's infrared frame and angle, and ``captures.json`` (camera, angle index, encoder angle,
    file, focus) as the daemon's calibration rotation writes it. Cameras render in ``jobs`` processes.
    Returns the captures file."""
    from concurrent.futures import ProcessPoolExecutor, as_completed

    out.mkdir(parents=True, exist_ok=True)
    records: list[dict] = []
    total, done = len(truth.cameras) * len(truth.beam), 0
    with ProcessPoolExecutor(max_workers=max(1, jobs)) as pool:
        futures = [pool.submit(_render_camera, rig, target, truth, i, out, seed, faults)
                   for i in range(len(truth.cameras))]
        for future in as_completed(futures):
            records += future.result()
            done += len(truth.beam)
            if progress is not None:
                progress(done, total)
    order = {c.id: i for i, c in enumerate(truth.cameras)}
    records.sort(key=lambda r: (order[r["camera"]], r["angle_index"]))
    path = out / "captures.json"
    path.write_text(json.dumps({"rig_digest": rig.digest, "target": target.name, "captures": records}, indent=1))
    return path


def _render_camera(rig: Rig, target: CuboidTarget, truth: Calibration, index: int, out: Path, seed: int,
                   faults: CalibrationFaults) -> list[dict]:
    """Every picture of one camera (runs in a worker process)."""
    import cv2

    from drivers.sim.cuboid_render import SIDE_GREY, CuboidCamera, CuboidScene

    scene = CuboidScene(target, truth.world_from_cuboid, truth.cuboid_from_boards, texture_px_per_mm=4.0)
    for face in faults.hidden_faces:  # covered with plain card
        scene.textures[face] = np.full_like(scene.textures[face], SIDE_GREY)
    cam = truth.cameras[index]
    rng = np.random.default_rng([seed, 0x1A6, index])
    phone = cam.kind == "phone"
    camera = CuboidCamera(scene, cam.intrinsics, optics=rig.optics if phone else None,
                          psf_sigma_px=0.6 if phone else 0.8, noise_sigma=2.0 if phone else 3.0)
    (out / cam.id).mkdir(exist_ok=True)
    records = []
    for b in truth.beam:
        pose = b.world_from_beam() @ cam.beam_from_camera
        centre, forward = pose[:3, 3], pose[:3, 2]
        # the focus the calibration plan sets: the cuboid's near face along the optical axis
        radial = -centre[:2] / np.hypot(*centre[:2])
        focus = float(np.clip((np.hypot(*centre[:2]) - 140.0) / max(abs(forward[:2] @ radial), 0.3), 150.0, 2000.0))
        blur = 6.0 if (cam.id, b.angle_index) in faults.blurred else 0.0
        if cam.id in faults.blind:
            shape = (cam.intrinsics.height_px, cam.intrinsics.width_px)
            image = np.clip(rng.normal(12.0, 2.0, shape), 0, 255).astype(np.uint8)
        else:
            image = camera.render(pose, rng, focus_mm=focus if phone else None, extra_blur_px=blur)
        if phone:
            name = f"{cam.id}/a{b.angle_index:02d}.jpg"
            cv2.imwrite(str(out / name), cv2.cvtColor(image, cv2.COLOR_GRAY2BGR), [cv2.IMWRITE_JPEG_QUALITY, 92])
        else:
            name = f"{cam.id}/a{b.angle_index:02d}.png"
            cv2.imwrite(str(out / name), image)
        record = {"camera": cam.id, "kind": cam.kind, "angle_index": b.angle_index,
                  "encoder_deg": b.encoder_deg, "file": name, "focus_mm": focus if phone else None}
        if not phone:  # the device's own intrinsics, as the infrared frame reports them
            k = cam.intrinsics
            record["intrinsics"] = {"fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy}
        records.append(record)
    return records


def mount_upside_down(truth: Calibration, target: CuboidTarget, face: int) -> Calibration:
    """The truth with one board glued turned by 180 deg about its centre (a mounting mistake)."""
    w, h = target.squares[0] * target.square_mm, target.squares[1] * target.square_mm
    turn = np.diag([-1.0, -1.0, 1.0, 1.0])
    turn[:2, 3] = [w, h]
    boards = list(truth.cuboid_from_boards)
    boards[face] = boards[face] @ turn
    return replace(truth, cuboid_from_boards=tuple(boards))
