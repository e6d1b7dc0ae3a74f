"""Pictures of the ChArUco calibration cuboid for the simulated phones and depth cameras' infrared stream.

Each pixel's ray leaves the camera through the true lens (pinhole + Brown-Conrady distortion,
inverted once per camera), meets the nearest board face of the cuboid (the cuboid is convex, so
the nearest front-facing hit is the visible one) and reads the printed board there (the real
board image, bilinear). Then what a camera adds: shading by incidence and a seeded light
falloff, the optics' point spread, the defocus of the phone's lens (thin-lens circle of
confusion, as in phone_render.py), sensor noise.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter

from drivers.sim.phone_render import PhoneRenderer, circle_of_confusion_mm
from planner.calibration.geometry import invert
from planner.calibration.model import Intrinsics
from planner.calibration.target import CuboidTarget
from planner.rig import Optics

FLOOR_GREY = 70.0
BACKGROUND_GREY = 28.0
SIDE_GREY = 150.0  # the cuboid's unprinted top


class CuboidScene:
    """The target as it stands in the world: the board images and each board's pose.

    world_from_cuboid: (4, 4); cuboid_from_boards: one (4, 4) per face (as glued, mm).
    texture_px_per_mm: resolution of the board images the cameras read.
    """

    def __init__(self, target: CuboidTarget, world_from_cuboid: np.ndarray,
                 cuboid_from_boards: list[np.ndarray] | tuple[np.ndarray, ...], texture_px_per_mm: float = 4.0) -> None:
        self.target = target
        self.px_per_mm = float(texture_px_per_mm)
        self.board_w = target.squares[0] * target.square_mm
        self.board_h = target.squares[1] * target.square_mm
        self.world_from_board = [world_from_cuboid @ m for m in cuboid_from_boards]
        self.board_from_world = [invert(m) for m in self.world_from_board]
        # printed boards: black 0 / white 255 become ink 20 / paper 235
        self.textures = [(20.0 + target.board_image(f.index, self.px_per_mm).astype(np.float32) * (215.0 / 255.0))
                         for f in target.faces]
        top = world_from_cuboid @ np.array([0.0, 0.0, target.size_mm[2], 1.0])
        self.top_centre = top[:3]
        self.top_normal = world_from_cuboid[:3, 2]
        self.half_size = np.array(target.size_mm[:2]) / 2
        self.world_from_cuboid = world_from_cuboid
        self.cuboid_from_world = invert(world_from_cuboid)

    def radiance(self, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For rays from origin (3,) along (N, 3) float32 directions: grey value (N,), hit parameter t (N,)
        and |cos incidence| (N,), float32. A face whose plane the camera is behind is skipped (the
        cuboid is convex: none of its rays can meet it)."""
        n = len(directions)
        best_t = np.full(n, np.inf, dtype=np.float32)
        grey = np.full(n, BACKGROUND_GREY, dtype=np.float32)
        cos_i = np.ones(n, dtype=np.float32)
        for face, b2w in enumerate(self.board_from_world):
            # the print faces out of the cuboid: rays meet it from the board's z < 0 side
            meeting = _plane_hits(b2w, origin, directions, 0.0, from_below=True)
            if meeting is None:
                continue
            front, t, x, y, dz = meeting
            hit = (t < best_t[front]) & (x >= 0) & (x <= self.board_w) & (y >= 0) & (y <= self.board_h)
            if not hit.any():
                continue
            idx, t, x, y = front[hit], t[hit], x[hit], y[hit]
            # remap takes 2-D maps under 32767 px a side: lay the hits out in rows of 4096
            rows = -(-len(idx) // 4096)
            mx = np.zeros(rows * 4096, dtype=np.float32)
            my = np.zeros(rows * 4096, dtype=np.float32)
            mx[: len(idx)] = x * np.float32(self.px_per_mm) - np.float32(0.5)
            my[: len(idx)] = y * np.float32(self.px_per_mm) - np.float32(0.5)
            value = cv2.remap(self.textures[face], mx.reshape(rows, 4096), my.reshape(rows, 4096),
                              cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            grey[idx] = value.ravel()[: len(idx)]
            best_t[idx] = t
            hits = directions[idx]
            cos_i[idx] = dz[idx] / np.sqrt(np.einsum("ij,ij->i", hits, hits))
        # the unprinted top face, seen only from above it, and the floor
        meeting = _plane_hits(self.cuboid_from_world, origin, directions, self.target.size_mm[2], from_below=False)
        if meeting is not None:
            down, t, x, y, _dz = meeting
            top = (t < best_t[down]) & (np.abs(x) <= self.half_size[0]) & (np.abs(y) <= self.half_size[1])
            grey[down[top]], best_t[down[top]] = SIDE_GREY, t[top]
        if origin[2] > 0.0:
            down = np.flatnonzero(directions[:, 2] < 0)
            t = np.float32(-origin[2]) / directions[down, 2]
            floor = t < best_t[down]
            grey[down[floor]], best_t[down[floor]] = FLOOR_GREY, t[floor]
        return grey, best_t, cos_i


def _plane_hits(local_from_world: np.ndarray, origin: np.ndarray, directions: np.ndarray, height: float, *,
                from_below: bool) -> tuple[np.ndarray, ...] | None:
    """The rays from ``origin`` (3,) along ``directions`` (N, 3) float32 that meet the plane
    z = ``height`` of a local frame from below it (``from_below``) or from above: their indices,
    hit parameters t and local x, y, and every ray's local z component (N,); None when the origin
    is on the other side (no ray can meet the plane from this one)."""
    o = (local_from_world[:3, :3] @ origin + local_from_world[:3, 3]).astype(np.float32)
    if (o[2] >= height) if from_below else (o[2] <= height):
        return None
    rotation = local_from_world[:3, :3].astype(np.float32)
    dz = directions @ rotation[2]
    rays = np.flatnonzero(dz > 1e-9 if from_below else dz < 0)
    along = (directions if len(rays) == len(directions) else directions[rays]) @ rotation[:2].T
    t = (np.float32(height) - o[2]) / dz[rays]
    return rays, t, o[0] + t * along[:, 0], o[1] + t * along[:, 1], dz


def pixel_rays(intrinsics: Intrinsics) -> np.ndarray:
    """(H * W, 3) float camera-frame ray directions (z = 1) through every pixel centre of a distorted lens."""
    u, v = np.meshgrid(np.arange(intrinsics.width_px, dtype=np.float64), np.arange(intrinsics.height_px, dtype=np.float64))
    pts = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    # cv2's stub has no None (noArray) for R and P; None gives normalized coordinates
    und = cv2.undistortPointsIter(pts, intrinsics.matrix, intrinsics.dist, None, None,  # type: ignore[call-overload]
                                  (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)).reshape(-1, 2)
    result: np.ndarray = np.c_[und, np.ones(len(und))]
    return result


class CuboidCamera:
    """One simulated camera's pictures of the cuboid.

    intrinsics: the true lens of this camera at the rendered resolution. optics: the phone's
    optics for the defocus blur (None: a fixed-focus camera, e.g. a depth camera's IR imager).
    psf_sigma_px: the optics' and sensor's blur; noise_sigma: grey levels of sensor noise.
    """

    def __init__(self, scene: CuboidScene, intrinsics: Intrinsics, *, optics: Optics | None = None,
                 psf_sigma_px: float = 0.6, noise_sigma: float = 2.0, light_falloff: float = 0.25) -> None:
        self.scene = scene
        self.intrinsics = intrinsics
        self.optics = optics
        self.psf_sigma_px = psf_sigma_px
        self.noise_sigma = noise_sigma
        self.light_falloff = light_falloff
        self._rays = pixel_rays(intrinsics).astype(np.float32)
        u = np.linspace(-0.5, 0.5, intrinsics.width_px, dtype=np.float32)
        v = np.linspace(-0.5, 0.5, intrinsics.height_px, dtype=np.float32)
        self._u, self._v = u[None, :], v[:, None]
        if optics is not None:
            # sensor pixel pitch (mm) of the rendered pixels: the sensor's focal length over fx
            self.pixel_mm = optics.focal_length_mm / intrinsics.fx

    def render(self, camera_to_world: np.ndarray, rng: np.random.Generator, focus_mm: float | None = None,
               extra_blur_px: float = 0.0) -> np.ndarray:
        """(H, W) uint8 grey picture from a (4, 4) camera-to-world pose; focus_mm for a phone's lens."""
        k = self.intrinsics
        directions = self._rays @ camera_to_world[:3, :3].T.astype(np.float32)
        grey, t, cos_i = self.scene.radiance(camera_to_world[:3, 3], directions)
        shade = np.float32(0.55) + np.float32(0.45) * cos_i
        # light falloff across the image: a seeded direction, as from the studio lights
        slope = rng.normal(0.0, self.light_falloff, 2).astype(np.float32)
        image = (grey * shade).reshape(k.height_px, k.width_px) * (1.0 + slope[0] * self._u + slope[1] * self._v)
        image = gaussian_filter(image, self.psf_sigma_px + extra_blur_px, truncate=3.0)
        if self.optics is not None and focus_mm is not None:
            z = np.where(np.isfinite(t), t, 1e6).reshape(image.shape)  # rays have camera z = 1: t is depth
            coc = circle_of_confusion_mm(z, focus_mm, self.optics) / self.pixel_mm
            image = PhoneRenderer._defocus(np.repeat(image[..., None], 1, axis=2), coc)[..., 0].astype(np.float32)
        image = image + rng.standard_normal(image.shape, dtype=np.float32) * np.float32(self.noise_sigma)
        result: np.ndarray = np.clip(np.rint(image), 0, 255).astype(np.uint8)
        return result
