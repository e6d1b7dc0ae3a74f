"""A coarse body region for a point on a standing patient's scanned body: the lesion list's groups.

The body frame is the mesh's own: its height from the lowest to the highest vertex (z up, the feet
on the platform) and its vertical axis, the median (x, y) of the vertices between 55 and 75 % of the
height (the trunk, with the arms on either side). The patient faces +x and their left is +y (the
rig frame, as the simulated subject stands). A point's region then follows from its height
fraction ``h`` and its offset from the axis:

- ``head and neck``: h >= 0.84 (above the shoulders: the shoulder line is at about 0.82 of a
  standing adult's height, the chin at about 0.87);
- ``left leg`` / ``right leg``: h < 0.47 (below the crotch, at about 0.47), by the side of the axis;
- ``left arm`` / ``right arm``: in between, farther than 0.12 of the height from the axis sideways
  (the trunk's half width is at most about 0.11 of the height at the shoulders);
- ``trunk, front`` / ``trunk, back``: the rest, in front of the axis or behind it.

The fractions are an adult's proportions, not a segmentation of this body: a hand held against
the thigh counts as leg and a raised arm's hand as head; they group a lesion list, nothing more.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

REGIONS = ("head and neck", "trunk, front", "trunk, back", "left arm", "right arm", "left leg", "right leg")
"""In the order the lesion list shows them."""
HEAD_FROM = 0.84
LEGS_BELOW = 0.47
ARM_BEYOND = 0.12
TRUNK_BAND = (0.55, 0.75)


@dataclass(frozen=True)
class BodyFrame:
    """A standing body's vertical axis and height. centre_xy: (2,) mm; z_min_mm, z_max_mm: the feet
    and the top of the head."""

    centre_xy: tuple[float, float]
    z_min_mm: float
    z_max_mm: float

    @classmethod
    def of_vertices(cls, vertices: np.ndarray) -> BodyFrame:
        """The frame of a body mesh's (V, 3) vertices, mm."""
        v = np.asarray(vertices, dtype=float).reshape(-1, 3)
        if len(v) == 0:
            raise ValueError("a body frame needs at least one vertex")
        z0, z1 = float(v[:, 2].min()), float(v[:, 2].max())
        h = (v[:, 2] - z0) / max(z1 - z0, 1e-9)
        band = v[(h >= TRUNK_BAND[0]) & (h <= TRUNK_BAND[1])]
        centre = np.median(band if len(band) else v, axis=0)
        return cls((float(centre[0]), float(centre[1])), z0, z1)

    def as_dict(self) -> dict[str, object]:
        return {"centre_xy": list(self.centre_xy), "z_min_mm": self.z_min_mm, "z_max_mm": self.z_max_mm}

    def regions(self, points: np.ndarray) -> list[str]:
        """The region (one of :data:`REGIONS`) of each of (N, 3) points, mm."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        height = max(self.z_max_mm - self.z_min_mm, 1e-9)
        h = (p[:, 2] - self.z_min_mm) / height
        dx = p[:, 0] - self.centre_xy[0]
        dy = p[:, 1] - self.centre_xy[1]
        left = dy >= 0.0
        region = np.select(
            [h >= HEAD_FROM, (h < LEGS_BELOW) & left, h < LEGS_BELOW,
             (np.abs(dy) > ARM_BEYOND * height) & left, np.abs(dy) > ARM_BEYOND * height, dx >= 0.0],
            ["head and neck", "left leg", "right leg", "left arm", "right arm", "trunk, front"], "trunk, back")
        return [str(r) for r in region]
