"""Images for the simulated phone: the subject ray cast from the phone's pose, shaded by normal,
freckled (drivers/sim/skin_texture.py), blurred by the distance from the focal plane, encoded as JPEG.

The blur is the thin-lens circle of confusion, diameter c = A * |z - s| / z * f / (s - f) on the
sensor (A = f / N aperture, f focal length, s focus distance, z the surface depth), converted to
image pixels of the reduced-resolution render. The image is blurred at a few CoC levels and each
pixel takes the level nearest its own CoC: cheap, and enough to see focus errors.
"""

from __future__ import annotations

import io
from typing import TYPE_CHECKING, Any

import numpy as np
from PIL import Image
from scipy.ndimage import gaussian_filter

from drivers.sim.skin_texture import LesionChanges, pigment, pigmented
from planner.rig import Optics

if TYPE_CHECKING:
    import trimesh

SKIN_RGB = np.array([224.0, 178.0, 150.0])
FLOOR_RGB = np.array([90.0, 90.0, 96.0])
BACKGROUND_RGB = np.array([24.0, 26.0, 30.0])
BLUR_LEVELS_PX = (0.0, 1.0, 2.0, 4.0, 8.0, 16.0)
JPEG_QUALITY = 90


def circle_of_confusion_mm(z_mm: np.ndarray, focus_mm: float, optics: Optics) -> np.ndarray:
    """(...) blur circle diameter on the sensor (mm) for surfaces at depth z_mm, lens focused at focus_mm."""
    f = optics.focal_length_mm
    aperture = f / optics.f_number
    s = max(float(focus_mm), f * 1.001)
    z = np.maximum(np.asarray(z_mm, dtype=float), f * 1.001)
    result: np.ndarray = aperture * np.abs(z - s) / z * f / (s - f)
    return result


FLOOR_HALF_SIDE_MM = 2500.0


class SubjectScene:
    """The subject mesh (mm, world frame, feet on z = 0) on a floor square, for ray casting.

    The skin carries freckles (drivers/sim/skin_texture.py) in skin coordinates: the mesh's
    ``vertex_attributes["skin_mm"]`` when the body generator gave them (the unswayed body, so a
    swayed visit shows the same spots on the same skin), else the mesh's own vertices;
    ``lesion_changes``: a follow-up visit's grown and new spots (None: none).
    """

    def __init__(self, mesh: trimesh.Trimesh, lesion_changes: LesionChanges | None = None) -> None:
        import open3d as o3d  # seconds to import: only where a scene is ray cast

        self._o3d = o3d
        self.lesion_changes = lesion_changes
        skin = getattr(mesh, "vertex_attributes", {}).get("skin_mm")
        self.skin_mm = np.asarray(mesh.vertices if skin is None else skin, dtype=np.float32)
        self.faces = np.asarray(mesh.faces, dtype=np.int64)
        # per vertex: skin coordinates (mm) and normal, gathered together for each hit
        self._skin_and_normal = np.concatenate([self.skin_mm, np.asarray(mesh.vertex_normals, dtype=np.float32)],
                                               axis=1)
        self.scene = o3d.t.geometry.RaycastingScene()
        self._subject_id = self.scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
                                                    o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)))
        s = FLOOR_HALF_SIDE_MM
        floor = np.array([[-s, -s, 0], [s, -s, 0], [s, s, 0], [-s, s, 0]], dtype=np.float32)
        self.scene.add_triangles(o3d.core.Tensor(floor), o3d.core.Tensor(np.array([[0, 1, 2], [0, 2, 3]],
                                                                                  dtype=np.uint32)))

    def cast(self, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rays from one origin along (N, 3) directions: t_hit (N,) (inf = miss) and normals (N, 3)."""
        answer = self._cast(origin, directions)
        return answer["t_hit"].numpy(), answer["primitive_normals"].numpy()

    def cast_skin(self, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """cast(), with the skin's normals smooth across its triangles (skin is not faceted), and
        the pigment darkness (N,) where a ray meets the subject's skin (0 elsewhere)."""
        answer = self._cast(origin, directions)
        normals = answer["primitive_normals"].numpy()
        triangle = answer["primitive_ids"].numpy().astype(np.int64)
        on_skin = answer["geometry_ids"].numpy() == self._subject_id  # not the floor, not a miss
        darkness = np.zeros(len(directions))
        if on_skin.any():
            corners = self.faces[triangle[on_skin]]  # (K, 3)
            uv = answer["primitive_uvs"].numpy()[on_skin]
            weights = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
            both = np.einsum("kc,kcj->kj", weights, self._skin_and_normal[corners])
            darkness[on_skin] = pigment(both[:, :3], changes=self.lesion_changes)
            smooth = both[:, 3:]
            normals[on_skin] = smooth / np.maximum(np.linalg.norm(smooth, axis=1, keepdims=True), 1e-6)
        return answer["t_hit"].numpy(), normals, darkness

    def _cast(self, origin: np.ndarray, directions: np.ndarray) -> dict[str, Any]:
        rays = np.empty((len(directions), 6), dtype=np.float32)
        rays[:, :3] = origin
        rays[:, 3:] = directions
        result: dict[str, Any] = self.scene.cast_rays(self._o3d.core.Tensor.from_numpy(rays))
        return result


class PhoneRenderer:
    """Renders one phone's view at width x height pixels (the full sensor's field of view)."""

    def __init__(self, scene: SubjectScene, optics: Optics, width_px: int = 768, height_px: int = 1024) -> None:
        self.scene = scene
        self.optics = optics
        self.width_px, self.height_px = int(width_px), int(height_px)
        self.scale = self.width_px / optics.image_width_px
        focal = optics.focal_length_px * self.scale
        u, v = np.meshgrid(np.arange(self.width_px) + 0.5, np.arange(self.height_px) + 0.5)
        self._rays = np.stack([(u - self.width_px / 2) / focal, (v - self.height_px / 2) / focal,
                               np.ones_like(u)], axis=-1).reshape(-1, 3)
        self._inverse_length = (1.0 / np.linalg.norm(self._rays, axis=1)).astype(np.float32)
        # sensor pixel pitch (mm) of the render's pixels
        self.pixel_mm = optics.focal_length_mm / focal

    def render(self, camera_to_world: np.ndarray, focus_mm: float) -> np.ndarray:
        """(H, W, 3) uint8 image of the subject from camera_to_world (4, 4), lens focused at focus_mm."""
        rotation, origin = camera_to_world[:3, :3], camera_to_world[:3, 3]
        directions = (self._rays @ rotation.T).astype(np.float32)
        t_hit, normals, darkness = self.scene.cast_skin(origin, directions)
        hit = np.isfinite(t_hit)
        t = np.where(hit, t_hit, np.float32(1e6))  # rays have camera z = 1, so t is the z-depth
        shade = np.abs(np.einsum("ij,ij->i", normals, directions)) * self._inverse_length
        floor = hit & (np.abs(origin[2] + t * directions[:, 2]) < 0.5)
        albedo = pigmented(np.where(floor[:, None], FLOOR_RGB, SKIN_RGB).astype(np.float32),
                           np.where(floor, 0.0, darkness))
        colour = albedo * (0.25 + 0.75 * shade[:, None])
        rgb = np.where(hit[:, None], colour, BACKGROUND_RGB.astype(np.float32))
        coc_px = circle_of_confusion_mm(t, focus_mm, self.optics) / self.pixel_mm
        shape = (self.height_px, self.width_px)
        return self._defocus(rgb.reshape(*shape, 3), coc_px.reshape(shape))

    @staticmethod
    def _defocus(rgb: np.ndarray, coc_px: np.ndarray) -> np.ndarray:
        """Each pixel from the copy blurred at the level nearest its blur circle (px)."""
        levels = np.array(BLUR_LEVELS_PX)
        index = np.searchsorted((levels[1:] + levels[:-1]) / 2, coc_px)
        out = rgb.copy()
        for i in np.flatnonzero(np.bincount(index.ravel(), minlength=len(levels))):  # the levels in use
            if levels[i] == 0:
                continue
            mask = index == i
            # Blur only the box round the level's pixels, widened by the kernel's reach: the same
            # values there as blurring the whole picture (the box's edge is out of reach, or is
            # the picture's edge), at a fraction of the work.
            reach = int(np.ceil(3.0 * levels[i] / 2)) + 1
            rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
            box = np.s_[max(rows[0] - reach, 0):rows[-1] + reach + 1, max(cols[0] - reach, 0):cols[-1] + reach + 1]
            blurred = gaussian_filter(rgb[box], sigma=(levels[i] / 2, levels[i] / 2, 0), truncate=3.0)
            out[box][mask[box]] = blurred[mask[box]]
        result: np.ndarray = np.clip(out, 0, 255).astype(np.uint8)
        return result


def encode_jpeg(rgb: np.ndarray, quality: int = JPEG_QUALITY) -> bytes:
    """JPEG bytes of an (H, W, 3) uint8 image."""
    buffer = io.BytesIO()
    Image.fromarray(rgb, "RGB").save(buffer, format="JPEG", quality=quality)
    return buffer.getvalue()


def empty_rig_picture(width_px: int, height_px: int, seed: int) -> np.ndarray:
    """(H, W, 3) uint8 grey gradient with seeded noise: the picture of an empty rig (no subject)."""
    rng = np.random.default_rng(seed)
    ramp = np.linspace(40, 200, height_px)[:, None, None] * np.ones((1, width_px, 3))
    return np.clip(ramp + rng.normal(0, 4, ramp.shape), 0, 255).astype(np.uint8)
