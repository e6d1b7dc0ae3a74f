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
corner observation plus the priors. The Jacobian is analytic and sparse (each corner touches
one camera, one capture, the cuboid and its board: 30 of the ~500 unknowns); rotations are
differentiated through SO(3)'s right Jacobian. tests/test_calibration_bundle.py checks it
against finite differences.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix, csr_matrix, diags, vstack
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
    max_evaluations: int = 30


def cuboid_pose(tilt: np.ndarray, yaw: float, offset: np.ndarray) -> np.ndarray:
    """(4, 4) world_from_cuboid: tilted, turned, offset, its bottom plane through the world origin."""
    m = from_rotvec(np.array([tilt[0], tilt[1], 0.0]), np.zeros(3)) @ rot_z(yaw)
    n = m[:3, 2]
    m[:3, 3] = [offset[0], offset[1], -(n[0] * offset[0] + n[1] * offset[1]) / n[2]]
    return m


class BundleProblem:
    """The residual function of one rig over fixed observations (pack/unpack the unknowns)."""

    def __init__(self, obs: Observations, board_corners: np.ndarray, nominal_boards: list[np.ndarray],
                 corners_per_face: int, encoder_deg: np.ndarray, n_cameras: int, settings: Settings,
                 held_lenses: list[bool] | None = None) -> None:
        self.obs = obs
        self.board_corners = np.c_[board_corners, np.ones(len(board_corners))]
        self.nominal_boards = nominal_boards
        self.corners_per_face = corners_per_face
        self.encoder_rad = np.radians(encoder_deg)
        self.n_cameras, self.n_captures, self.n_faces = n_cameras, len(encoder_deg), len(nominal_boards)
        self.settings = settings
        self.free_boards = list(range(1, self.n_faces)) if settings.refine_boards else []
        # The beam poses and the cameras' poses on the beam share a rigid freedom (the beam frame
        # is a convention): the capture seen most is held at the encoder angle with no wobble.
        self.reference = int(np.argmax(np.bincount(obs.capture, minlength=self.n_captures)))
        self.free_caps = np.delete(np.arange(self.n_captures), self.reference)
        self.cap_pos = np.full(self.n_captures, -1)
        self.cap_pos[self.free_caps] = np.arange(len(self.free_caps))
        self.cap0 = n_cameras * N_CAM
        self.cub0 = self.cap0 + len(self.free_caps) * N_CAP
        self.brd0 = self.cub0 + N_CUBOID
        self.n_params = self.brd0 + len(self.free_boards) * N_BOARD
        self.face = obs.corner // corners_per_face
        self.local = obs.corner % corners_per_face
        self.yaw = 0.0
        # unknowns held at their start: the lens of cameras whose intrinsics come from the device
        self.free = np.ones(self.n_params)
        for c, held in enumerate(held_lenses or []):
            if held:
                self.free[c * N_CAM + 6:(c + 1) * N_CAM] = 0.0

    # ------------------------------------------------------------------ packing
    def pack(self, s: RigState) -> np.ndarray:
        x = np.zeros(self.n_params)
        for c, (m, k) in enumerate(zip(s.beam_from_camera, s.lenses)):
            rv, t = to_rotvec(m)
            x[c * N_CAM:(c + 1) * N_CAM] = [*rv, *t, k.fx, k.fy, k.cx, k.cy, *k.distortion[:4]]
        caps = np.c_[s.angle_offset_rad, s.tilt_rad, s.shift_mm]
        x[self.cap0:self.cub0] = caps[self.free_caps].ravel()
        x[self.cub0:self.brd0] = [*s.cuboid_tilt_rad, *s.cuboid_offset_mm]
        for j, f in enumerate(self.free_boards):
            x[self.brd0 + j * N_BOARD:self.brd0 + (j + 1) * N_BOARD] = s.board_delta[f]
        self.yaw = s.cuboid_yaw_rad
        self._template = s
        return x

    def unpack(self, x: np.ndarray) -> RigState:
        cams = x[:self.cap0].reshape(self.n_cameras, N_CAM)
        caps = self._caps(x)
        deltas = np.zeros((self.n_faces, 6))
        for j, f in enumerate(self.free_boards):
            deltas[f] = x[self.brd0 + j * N_BOARD:self.brd0 + (j + 1) * N_BOARD]
        lenses = [replace(k, fx=p[6], fy=p[7], cx=p[8], cy=p[9], distortion=(p[10], p[11], p[12], p[13], 0.0))
                  for k, p in zip(self._template.lenses, cams)]
        return RigState([from_rotvec(p[:3], p[3:6]) for p in cams], lenses, caps[:, 0].copy(), caps[:, 1:3].copy(),
                        caps[:, 3:6].copy(), x[self.cub0:self.cub0 + 2].copy(), self.yaw,
                        x[self.cub0 + 2:self.brd0].copy(), deltas)

    # ------------------------------------------------------------------ residuals
    def project(self, x: np.ndarray, jacobian: bool = False) -> np.ndarray | tuple[np.ndarray, coo_matrix]:
        """(N, 2) predicted pixel of every observation; with ``jacobian`` also d(pixels)/d(unknowns)."""
        o = self.obs
        n = len(o)
        cams = x[:self.cap0].reshape(self.n_cameras, N_CAM)
        caps = self._caps(x)
        # world_from_beam per capture: Rz(encoder + offset) @ wobble; X_b = W^T (Rz^T X_w - s)
        theta = self.encoder_rad + caps[:, 0]
        wob = Rotation.from_rotvec(np.c_[caps[:, 1:3], np.zeros(self.n_captures)]).as_matrix()
        cz, sz = np.cos(theta), np.sin(theta)
        rz = np.zeros((self.n_captures, 3, 3))
        rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1], rz[:, 2, 2] = cz, -sz, sz, cz, 1.0
        r_cam = Rotation.from_rotvec(cams[:, :3]).as_matrix()
        t_cam = cams[:, 3:6]
        local, world_from_board, cuboid = self._board_frames(x)
        xw = np.einsum("nij,nj->ni", world_from_board[self.face, :3, :3], local) + world_from_board[self.face, :3, 3]
        k = o.capture
        y = np.einsum("nji,nj->ni", rz[k], xw)  # Rz^T X_w
        xb = np.einsum("nji,nj->ni", wob[k], y - caps[k, 3:6])
        rc = r_cam[o.camera]
        xc = np.einsum("nji,nj->ni", rc, xb - t_cam[o.camera])
        q = cams[o.camera, 6:]
        z = np.where(np.abs(xc[:, 2]) < 1e-6, 1e-6, xc[:, 2])
        a, b = xc[:, 0] / z, xc[:, 1] / z
        r2 = a * a + b * b
        k1, k2, p1, p2 = q[:, 4], q[:, 5], q[:, 6], q[:, 7]
        radial = 1.0 + k1 * r2 + k2 * r2 * r2
        ud = a * radial + 2 * p1 * a * b + p2 * (r2 + 2 * a * a)
        vd = b * radial + p1 * (r2 + 2 * b * b) + 2 * p2 * a * b
        px = np.c_[q[:, 0] * ud + q[:, 2], q[:, 1] * vd + q[:, 3]]
        if not jacobian:
            return px
        # d pixel / d X_c: focal . distortion . perspective
        dr = 2 * (k1 + 2 * k2 * r2)
        jd = np.empty((n, 2, 2))
        jd[:, 0, 0] = radial + a * dr * a + 2 * p1 * b + 6 * p2 * a
        jd[:, 0, 1] = a * dr * b + 2 * p1 * a + 2 * p2 * b
        jd[:, 1, 0] = b * dr * a + 2 * p1 * a + 2 * p2 * b
        jd[:, 1, 1] = radial + b * dr * b + 6 * p1 * b + 2 * p2 * a
        jd[:, 0] *= q[:, 0:1]
        jd[:, 1] *= q[:, 1:2]
        jp = np.zeros((n, 2, 3))
        jp[:, 0, 0] = jp[:, 1, 1] = 1.0 / z
        jp[:, 0, 2], jp[:, 1, 2] = -a / z, -b / z
        j_xc = jd @ jp  # (n, 2, 3)
        blocks = []
        # camera: rotation (right perturbation), translation, lens
        jr = _right_jacobian(cams[:, :3])[o.camera]
        blocks.append(j_xc @ _skew(xc) @ jr)
        blocks.append(-j_xc @ np.transpose(rc, (0, 2, 1)))
        lens = np.zeros((n, 2, 8))
        lens[:, 0, 0], lens[:, 1, 1], lens[:, 0, 2], lens[:, 1, 3] = ud, vd, 1.0, 1.0
        lens[:, 0, 4], lens[:, 1, 4] = q[:, 0] * a * r2, q[:, 1] * b * r2
        lens[:, 0, 5], lens[:, 1, 5] = q[:, 0] * a * r2 * r2, q[:, 1] * b * r2 * r2
        lens[:, 0, 6], lens[:, 1, 6] = q[:, 0] * 2 * a * b, q[:, 1] * (r2 + 2 * b * b)
        lens[:, 0, 7], lens[:, 1, 7] = q[:, 0] * (r2 + 2 * a * a), q[:, 1] * 2 * a * b
        blocks.append(lens)
        j_xb = j_xc @ np.transpose(rc, (0, 2, 1))  # d pixel / d X_b
        # capture: angle, wobble tilt (right perturbation of W, x and y only), shift
        wt = np.transpose(wob[k], (0, 2, 1))
        ez_cross_y = np.c_[-y[:, 1], y[:, 0], np.zeros(n)]
        blocks.append(j_xb @ (-np.einsum("nij,nj->ni", wt, ez_cross_y))[:, :, None])
        jw = _right_jacobian(np.c_[caps[:, 1:3], np.zeros(self.n_captures)])[k]
        blocks.append((j_xb @ _skew(xb) @ jw)[:, :, :2])
        blocks.append(-j_xb @ wt)
        j_xw = j_xb @ np.transpose((rz @ wob)[k], (0, 2, 1))  # d pixel / d X_w = j_xb W^T Rz^T
        # cuboid: tilt (x, y), offset (x, y) with the floor constraint on z
        blocks.append(j_xw @ self._cuboid_derivative(x, xw, cuboid))
        cam_cols = (o.camera * N_CAM)[:, None] + np.arange(N_CAM)
        held = self.cap_pos[k] < 0
        cap_cols = (self.cap0 + np.maximum(self.cap_pos[k], 0) * N_CAP)[:, None] + np.arange(N_CAP)
        cub_cols = np.broadcast_to(self.cub0 + np.arange(N_CUBOID), (n, N_CUBOID))
        cols = [cam_cols, cap_cols, cub_cols]
        values = np.concatenate(blocks, axis=2)  # (n, 2, 14 + 6 + 4)
        values[held, :, N_CAM:N_CAM + N_CAP] = 0.0  # the reference capture's pose is held
        all_cols = np.concatenate(cols, axis=1)
        rows = np.repeat(np.arange(2 * n).reshape(n, 2, 1), all_cols.shape[1], axis=2)
        data, r_idx, c_idx = [values.ravel()], [rows.ravel()], [np.repeat(all_cols[:, None, :], 2, axis=1).ravel()]
        for j, f in enumerate(self.free_boards):
            sel = np.flatnonzero(self.face == f)
            if not len(sel):
                continue
            m = world_from_board[f, :3, :3]
            p = x[self.brd0 + j * N_BOARD:self.brd0 + (j + 1) * N_BOARD]
            jb = np.concatenate([-(j_xw[sel] @ m) @ _skew(local[sel]) @ _right_jacobian(p[None, :3])[0],
                                 j_xw[sel] @ (cuboid[:3, :3] @ self.nominal_boards[f][:3, :3])], axis=2)
            data.append(jb.ravel())
            r_idx.append(np.repeat(np.c_[2 * sel, 2 * sel + 1][:, :, None], N_BOARD, axis=2).ravel())
            c_idx.append(np.broadcast_to(self.brd0 + j * N_BOARD + np.arange(N_BOARD), (len(sel), 2, N_BOARD)).ravel())
        jac = coo_matrix((np.concatenate(data), (np.concatenate(r_idx), np.concatenate(c_idx))),
                         shape=(2 * n, self.n_params))
        return px, jac

    def _board_frames(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(N, 3) board-frame corner of each observation, (F, 4, 4) world_from_board, (4, 4) world_from_cuboid."""
        cuboid = cuboid_pose(x[self.cub0:self.cub0 + 2], self.yaw, x[self.cub0 + 2:self.brd0])
        frames = np.empty((self.n_faces, 4, 4))
        for f in range(self.n_faces):
            m = self.nominal_boards[f]
            if f in self.free_boards:
                j = self.free_boards.index(f)
                p = x[self.brd0 + j * N_BOARD:self.brd0 + (j + 1) * N_BOARD]
                m = m @ from_rotvec(p[:3], p[3:])
            frames[f] = cuboid @ m
        return self.board_corners[self.local, :3], frames, cuboid

    def _cuboid_derivative(self, x: np.ndarray, xw: np.ndarray, cuboid: np.ndarray) -> np.ndarray:
        """(N, 3, 4) d X_w / d (tilt x, tilt y, offset x, offset y), including the floor constraint on z."""
        n = len(xw)
        tilt, offset = x[self.cub0:self.cub0 + 2], x[self.cub0 + 2:self.brd0]
        w = np.array([tilt[0], tilt[1], 0.0])
        rw = Rotation.from_rotvec(w).as_matrix()
        jr = _right_jacobian(w[None])[0]
        p_cuboid = xw - cuboid[:3, 3]  # R_C p, p the corner in the cuboid frame
        # R_C p = Rw (Rz p): a right perturbation of Rw moves it by -Rw [Rz p]x Jr dw
        rz_p = p_cuboid @ rw  # Rw^T R_C p = Rz p
        d_rot = -np.einsum("ij,njk->nik", rw, _skew(rz_p)) @ jr[:, :2]
        nz = cuboid[:3, 2]
        dn = -rw @ _skew(np.array([0.0, 0.0, 1.0])[None])[0] @ jr[:, :2]  # (3, 2) d normal / d tilt
        dz_dn = np.array([-offset[0] / nz[2], -offset[1] / nz[2], (nz[0] * offset[0] + nz[1] * offset[1]) / nz[2] ** 2])
        out = np.zeros((n, 3, 4))
        out[:, :, :2] = d_rot
        out[:, 2, :2] += dz_dn @ dn
        out[:, 0, 2], out[:, 1, 3] = 1.0, 1.0
        out[:, 2, 2], out[:, 2, 3] = -nz[0] / nz[2], -nz[1] / nz[2]
        return out

    def _prior_weights(self) -> np.ndarray:
        """(6,) 1/sigma of the capture unknowns (angle, tilt x, tilt y, shift x, y, z)."""
        s = self.settings
        return np.array([1 / math.radians(s.angle_sigma_deg)] + [1 / math.radians(s.tilt_sigma_deg)] * 2
                        + [1 / s.shift_sigma_mm] * 3)

    def _caps(self, x: np.ndarray) -> np.ndarray:
        """(K, 6) every capture's angle offset, tilt and shift (the reference capture's held at 0)."""
        caps = np.zeros((self.n_captures, N_CAP))
        caps[self.free_caps] = x[self.cap0:self.cub0].reshape(-1, N_CAP)
        return caps

    def residuals(self, x: np.ndarray) -> np.ndarray:
        caps = x[self.cap0:self.cub0].reshape(-1, N_CAP)
        return np.r_[(self.project(x) - self.obs.px).ravel(), (caps * self._prior_weights()).ravel()]

    def jacobian(self, x: np.ndarray) -> csr_matrix:
        _, jac = self.project(x, jacobian=True)
        k = len(self.free_caps)
        prior = coo_matrix((np.tile(self._prior_weights(), k), (np.arange(6 * k), self.cap0 + np.arange(6 * k))),
                           shape=(6 * k, self.n_params))
        return (vstack([jac, prior]) @ diags(self.free)).tocsr()

    def solve(self, state: RigState, *, robust: bool = True) -> tuple[RigState, np.ndarray, int]:
        """Adjusted state, (N,) pixel error of each observation, function evaluations used.

        robust: the settings' robust loss (outliers still in); False: plain least squares."""
        from threadpoolctl import threadpool_limits

        s = self.settings
        x0 = self.pack(state)
        # The solver's vector operations are small: OpenBLAS threads cost more than they save
        # (tenfold on a busy machine).
        with threadpool_limits(limits=1, user_api="blas"):
            result = least_squares(self.residuals, x0, jac=self.jacobian, method="trf", tr_solver="lsmr",
                                   loss=s.loss if robust else "linear", f_scale=s.loss_scale_px, x_scale="jac",
                                   max_nfev=s.max_evaluations, xtol=1e-9, ftol=1e-9, gtol=1e-10)
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


def _skew(v: np.ndarray) -> np.ndarray:
    """(N, 3, 3) cross-product matrices of (N, 3) vectors."""
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return out


def _right_jacobian(rotvec: np.ndarray) -> np.ndarray:
    """(N, 3, 3) right Jacobian of SO(3) at (N, 3) rotation vectors: Exp(w + d) ~ Exp(w) Exp(Jr d)."""
    theta = np.linalg.norm(rotvec, axis=1)
    k = _skew(rotvec)
    small = theta < 1e-8
    t = np.where(small, 1.0, theta)
    a = np.where(small, 0.5, (1 - np.cos(t)) / t**2)
    b = np.where(small, 1.0 / 6.0, (t - np.sin(t)) / t**3)
    return np.eye(3)[None] - a[:, None, None] * k + b[:, None, None] * (k @ k)
