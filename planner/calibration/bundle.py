"""Sparse bundle adjustment of the whole rig on the cuboid's corners (scipy least_squares, robust loss).

Unknowns (see model.py for the frames):
- per camera: beam_from_camera (rotation vector, translation) and its lens (fx, fy, cx, cy, k1, k2,
  p1, p2);
- per capture: the beam angle's offset from the encoder reading (prior: ``angle_sigma_deg``) and
  the wobble (tilt about the beam's x and y, shift; prior: ``tilt_sigma_deg``, ``shift_sigma_mm``);
- the cuboid: its tilt and its offset from the axis; its turn about z is held (a turn of the
  whole world about the axis changes no picture), and its bottom plane passes through the origin
  (the floor is z = 0);
- optionally the boards' placement on the cuboid (face 0 defines the cuboid frame).

The world keeps the axis as z by construction (every beam pose is a turn about z times a small
wobble), and the metric scale comes from the printed boards. Residuals: pixel errors of every
corner observation plus the priors; ``jac_sparsity`` tells least_squares which unknowns each
residual touches, so the finite-difference Jacobian costs about 30 evaluations whatever the
number of pictures.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.spatial.transform import Rotation

from planner.calibration.geometry import from_rotvec, rot_z, to_rotvec
from planner.calibration.model import Intrinsics

N_CAM = 14
N_CAP = 6
N_CUBOID = 4
N_BOARD = 6


@dataclass(frozen=True)
class Observations:
    """N corner observations: camera (N,), capture (N,), global corner id (N,), pixel (N, 2)."""

    camera: np.ndarray
    capture: np.ndarray
    corner: np.ndarray
    px: np.ndarray

    def __len__(self) -> int:
        return len(self.camera)

    def subset(self, keep: np.ndarray) -> Observations:
        return Observations(self.camera[keep], self.capture[keep], self.corner[keep], self.px[keep])


@dataclass(frozen=True)
class RigState:
    """The unknowns in readable form (see the module docstring)."""

    beam_from_camera: list[np.ndarray]
    lenses: list[Intrinsics]
    angle_offset_rad: np.ndarray  # (K,)
    tilt_rad: np.ndarray  # (K, 2)
    shift_mm: np.ndarray  # (K, 3)
    cuboid_tilt_rad: np.ndarray  # (2,)
    cuboid_yaw_rad: float
    cuboid_offset_mm: np.ndarray  # (2,)
    board_delta: np.ndarray  # (F, 6) rotation vector and translation applied to each nominal board pose

    def world_from_cuboid(self) -> np.ndarray:
        return cuboid_pose(self.cuboid_tilt_rad, self.cuboid_yaw_rad, self.cuboid_offset_mm)


@dataclass(frozen=True)
class Settings:
    angle_sigma_deg: float = 0.05
    tilt_sigma_deg: float = 0.2
    shift_sigma_mm: float = 1.0
    refine_boards: bool = True
    loss: str = "huber"
    loss_scale_px: float = 1.0
    max_evaluations: int = 60


def cuboid_pose(tilt: np.ndarray, yaw: float, offset: np.ndarray) -> np.ndarray:
    """(4, 4) world_from_cuboid: tilted, turned, offset, its bottom plane through the world origin."""
    m = from_rotvec(np.array([tilt[0], tilt[1], 0.0]), np.zeros(3)) @ rot_z(yaw)
    n = m[:3, 2]
    m[:3, 3] = [offset[0], offset[1], -(n[0] * offset[0] + n[1] * offset[1]) / n[2]]
    return m


class BundleProblem:
    """The residual function of one rig over fixed observations (pack/unpack the unknowns)."""

    def __init__(self, obs: Observations, board_corners: np.ndarray, nominal_boards: list[np.ndarray],
                 corners_per_face: int, encoder_deg: np.ndarray, n_cameras: int, settings: Settings) -> None:
        self.obs = obs
        self.board_corners = np.c_[board_corners, np.ones(len(board_corners))]
        self.nominal_boards = nominal_boards
        self.corners_per_face = corners_per_face
        self.encoder_rad = np.radians(encoder_deg)
        self.n_cameras, self.n_captures, self.n_faces = n_cameras, len(encoder_deg), len(nominal_boards)
        self.settings = settings
        self.free_boards = list(range(1, self.n_faces)) if settings.refine_boards else []
        self.cap0 = n_cameras * N_CAM
        self.cub0 = self.cap0 + self.n_captures * N_CAP
        self.brd0 = self.cub0 + N_CUBOID
        self.n_params = self.brd0 + len(self.free_boards) * N_BOARD
        self.face = obs.corner // corners_per_face
        self.local = obs.corner % corners_per_face
        self.yaw = 0.0

    # ------------------------------------------------------------------ packing
    def pack(self, s: RigState) -> np.ndarray:
        x = np.zeros(self.n_params)
        for c, (m, k) in enumerate(zip(s.beam_from_camera, s.lenses)):
            rv, t = to_rotvec(m)
            x[c * N_CAM:(c + 1) * N_CAM] = [*rv, *t, k.fx, k.fy, k.cx, k.cy, *k.distortion[:4]]
        caps = np.c_[s.angle_offset_rad, s.tilt_rad, s.shift_mm]
        x[self.cap0:self.cub0] = caps.ravel()
        x[self.cub0:self.brd0] = [*s.cuboid_tilt_rad, *s.cuboid_offset_mm]
        for j, f in enumerate(self.free_boards):
            x[self.brd0 + j * N_BOARD:self.brd0 + (j + 1) * N_BOARD] = s.board_delta[f]
        self.yaw = s.cuboid_yaw_rad
        self._template = s
        return x

    def unpack(self, x: np.ndarray) -> RigState:
        cams = x[:self.cap0].reshape(self.n_cameras, N_CAM)
        caps = x[self.cap0:self.cub0].reshape(self.n_captures, N_CAP)
        deltas = np.zeros((self.n_faces, 6))
        for j, f in enumerate(self.free_boards):
            deltas[f] = x[self.brd0 + j * N_BOARD:self.brd0 + (j + 1) * N_BOARD]
        lenses = [replace(k, fx=p[6], fy=p[7], cx=p[8], cy=p[9], distortion=(p[10], p[11], p[12], p[13], 0.0))
                  for k, p in zip(self._template.lenses, cams)]
        return RigState([from_rotvec(p[:3], p[3:6]) for p in cams], lenses, caps[:, 0].copy(), caps[:, 1:3].copy(),
                        caps[:, 3:6].copy(), x[self.cub0:self.cub0 + 2].copy(), self.yaw,
                        x[self.cub0 + 2:self.brd0].copy(), deltas)

    # ------------------------------------------------------------------ residuals
    def world_corners(self, x: np.ndarray) -> np.ndarray:
        """(F * corners_per_face, 3) every corner in the world."""
        c = cuboid_pose(x[self.cub0:self.cub0 + 2], self.yaw, x[self.cub0 + 2:self.brd0])
        out = []
        for f in range(self.n_faces):
            m = self.nominal_boards[f]
            if f in self.free_boards:
                j = self.free_boards.index(f)
                p = x[self.brd0 + j * N_BOARD:self.brd0 + (j + 1) * N_BOARD]
                m = m @ from_rotvec(p[:3], p[3:])
            out.append((self.board_corners @ (c @ m).T)[:, :3])
        return np.concatenate(out)

    def project(self, x: np.ndarray) -> np.ndarray:
        """(N, 2) predicted pixel of every observation."""
        o = self.obs
        cams = x[:self.cap0].reshape(self.n_cameras, N_CAM)
        caps = x[self.cap0:self.cub0].reshape(self.n_captures, N_CAP)
        # world_from_beam per capture: Rz(encoder + offset) @ wobble
        theta = self.encoder_rad + caps[:, 0]
        wob = Rotation.from_rotvec(np.c_[caps[:, 1:3], np.zeros(self.n_captures)]).as_matrix()
        cz, sz = np.cos(theta), np.sin(theta)
        rz = np.zeros((self.n_captures, 3, 3))
        rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1], rz[:, 2, 2] = cz, -sz, sz, cz, 1.0
        r_beam = rz @ wob
        t_beam = np.einsum("kij,kj->ki", rz, caps[:, 3:6])
        r_cam = Rotation.from_rotvec(cams[:, :3]).as_matrix()
        t_cam = cams[:, 3:6]
        xw = self.world_corners(x)[o.corner]
        # beam frame, then camera frame
        xb = np.einsum("nji,nj->ni", r_beam[o.capture], xw - t_beam[o.capture])
        xc = np.einsum("nji,nj->ni", r_cam[o.camera], xb - t_cam[o.camera])
        k = cams[o.camera, 6:]
        z = np.where(np.abs(xc[:, 2]) < 1e-6, 1e-6, xc[:, 2])
        u, v = xc[:, 0] / z, xc[:, 1] / z
        r2 = u * u + v * v
        radial = 1.0 + k[:, 4] * r2 + k[:, 5] * r2 * r2
        ud = u * radial + 2 * k[:, 6] * u * v + k[:, 7] * (r2 + 2 * u * u)
        vd = v * radial + k[:, 6] * (r2 + 2 * v * v) + 2 * k[:, 7] * u * v
        return np.c_[k[:, 0] * ud + k[:, 2], k[:, 1] * vd + k[:, 3]]

    def residuals(self, x: np.ndarray) -> np.ndarray:
        s = self.settings
        caps = x[self.cap0:self.cub0].reshape(self.n_captures, N_CAP)
        prior = np.r_[caps[:, 0] / math.radians(s.angle_sigma_deg),
                      caps[:, 1:3].ravel() / math.radians(s.tilt_sigma_deg),
                      caps[:, 3:6].ravel() / s.shift_sigma_mm]
        return np.r_[(self.project(x) - self.obs.px).ravel(), prior]

    def sparsity(self) -> coo_matrix:
        """Which unknowns each residual row touches."""
        o, n = self.obs, len(self.obs)
        rows, cols = [], []
        obs_rows = np.repeat(np.arange(n) * 2, 2) + np.tile([0, 1], n)
        per_obs = np.repeat(np.arange(n), 2)

        def touch(col_start: np.ndarray, width: int, mask: np.ndarray | None = None) -> None:
            r = obs_rows if mask is None else obs_rows[mask[per_obs]]
            c0 = col_start[per_obs] if mask is None else col_start[per_obs][mask[per_obs]]
            rows.append(np.repeat(r, width))
            cols.append((c0[:, None] + np.arange(width)[None, :]).ravel())

        touch(o.camera * N_CAM, N_CAM)
        touch(self.cap0 + o.capture * N_CAP, N_CAP)
        touch(np.full(n, self.cub0), N_CUBOID)
        for j, f in enumerate(self.free_boards):
            touch(np.full(n, self.brd0 + j * N_BOARD), N_BOARD, self.face == f)
        base = 2 * n
        k = self.n_captures
        rows += [base + np.arange(k), base + k + np.arange(2 * k), base + 3 * k + np.arange(3 * k)]
        cols += [self.cap0 + np.arange(k) * N_CAP,
                 self.cap0 + (np.arange(k)[:, None] * N_CAP + np.array([1, 2])[None, :]).ravel(),
                 self.cap0 + (np.arange(k)[:, None] * N_CAP + np.array([3, 4, 5])[None, :]).ravel()]
        r, c = np.concatenate(rows), np.concatenate(cols)
        return coo_matrix((np.ones(len(r), dtype=np.int8), (r, c)), shape=(base + 6 * k, self.n_params))

    def solve(self, state: RigState) -> tuple[RigState, np.ndarray, int]:
        """Adjusted state, (N,) pixel error of each observation, function evaluations used."""
        s = self.settings
        x0 = self.pack(state)
        result = least_squares(self.residuals, x0, jac_sparsity=self.sparsity(), method="trf", loss=s.loss,
                               f_scale=s.loss_scale_px, x_scale="jac", max_nfev=s.max_evaluations,
                               xtol=1e-10, ftol=1e-10, gtol=1e-10)
        err = np.linalg.norm(self.project(result.x) - self.obs.px, axis=1)
        return self.unpack(result.x), err, int(result.nfev)


def normalise_azimuth(beam_from_camera: list[np.ndarray], phones: list[int], world_from_cuboid: np.ndarray,
                      tilt: np.ndarray, shift: np.ndarray) -> tuple[list[np.ndarray], np.ndarray, np.ndarray, np.ndarray]:
    """Turn the world about the axis so the phones' mean azimuth at beam angle 0 is 0 (the column faces
    the subject's front at angle 0). The only freedom the pictures leave; wobble turns with it."""
    az = [math.atan2(beam_from_camera[i][1, 3], beam_from_camera[i][0, 3]) for i in phones]
    alpha = math.atan2(np.mean(np.sin(az)), np.mean(np.cos(az)))
    turn = rot_z(-alpha)
    c, s = math.cos(-alpha), math.sin(-alpha)
    r2 = np.array([[c, -s], [s, c]])
    shift = shift.copy()
    shift[:, :2] = shift[:, :2] @ r2.T
    return [turn @ m for m in beam_from_camera], turn @ world_from_cuboid, tilt @ r2.T, shift
