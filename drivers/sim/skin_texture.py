"""Skin with something to see: freckles and naevi fixed to the simulated subject's skin.

A camera on a real rig sees pigment spots, pores and hair; a skin of one flat colour leaves
nothing in a picture that tells one patch of skin from the next. The spots here are a solid
texture in the subject's own skin coordinates (each skin point's position in the unswayed body,
carried through sway and a new stance), so the same freckle sits on the same skin in every
visit of one person.

Spots are hashed per cell of a cubic lattice: a cell holds at most one spot, placed so that it
never crosses the cell's faces, so a point looks only at its own cell (cheap enough for every
pixel of every picture). Two layers: small dark freckles and larger faint patches.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SpotLayer:
    """Spots of one lattice: cell side (mm), share of cells with a spot, radius and darkness ranges."""

    cell_mm: float
    share: float
    radius_mm: tuple[float, float]
    darkness: tuple[float, float]
    salt: int


LAYERS = (
    SpotLayer(cell_mm=8.0, share=0.55, radius_mm=(1.0, 2.6), darkness=(0.25, 0.55), salt=0x9E3779B97F4A7C15),
    SpotLayer(cell_mm=22.0, share=0.5, radius_mm=(3.5, 7.5), darkness=(0.06, 0.16), salt=0xC2B2AE3D27D4EB4F),
)
PIGMENT_TINT = np.array([0.62, 0.78, 0.85], dtype=np.float32)
"""How much a spot of darkness 1 takes from red, green and blue (melanin absorbs blue most)."""
EDGE_MM = 0.35
"""Half-width of a spot's soft edge."""


def _mix(values: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser: (N,) uint64 -> well-mixed uint64."""
    z = values.copy()
    z ^= z >> np.uint64(30)
    z *= np.uint64(0xBF58476D1CE4E5B9)
    z ^= z >> np.uint64(27)
    z *= np.uint64(0x94D049BB133111EB)
    z ^= z >> np.uint64(31)
    return z


def _uniforms(cells: np.ndarray, salt: int) -> np.ndarray:
    """(N, 8) uniform numbers in [0, 1) (16 bits each) drawn from the integer cells (N, 3)."""
    key = cells.astype(np.int64).view(np.uint64)
    with np.errstate(over="ignore"):
        h = _mix(key[:, 0] * np.uint64(0x8CB92BA72F3D8DD7) ^ key[:, 1] * np.uint64(0xD6E8FEB86659FD93)
                 ^ key[:, 2] * np.uint64(0xA0761D6478BD642F) ^ np.uint64(salt))
        words = np.stack([h, _mix(h + np.uint64(0x9E3779B97F4A7C15))], axis=1)
    return words.view(np.uint16).reshape(len(cells), 8).astype(np.float32) / np.float32(65536.0)


def layer_spots(cells: np.ndarray, layer: SpotLayer, seed: int = 0) -> tuple[np.ndarray, ...]:
    """The spots of lattice cells (N, 3) int of one layer: which cells hold one (K,) index into
    cells, their centres (K, 3) mm and radii (K,) mm (a ball in skin coordinates) and darkness (K,)."""
    u = _uniforms(cells, layer.salt ^ (int(seed) * 0x632BE59BD9B4E019 & 0xFFFFFFFFFFFFFFFF))
    spotted = np.flatnonzero(u[:, 0] < layer.share)
    u, cells = u[spotted], cells[spotted]
    radius = layer.radius_mm[0] + u[:, 1] * (layer.radius_mm[1] - layer.radius_mm[0])
    span = layer.cell_mm - 2 * radius  # the spot stays inside its cell
    centre = cells.astype(np.float32) * layer.cell_mm + radius[:, None] + u[:, 2:5] * span[:, None]
    depth = layer.darkness[0] + u[:, 5] * (layer.darkness[1] - layer.darkness[0])
    return spotted, centre, radius, depth


def pigment(skin_mm: np.ndarray, seed: int = 0) -> np.ndarray:
    """(N,) darkness in [0, 1) at skin points (N, 3) given in skin coordinates, mm."""
    points = np.asarray(skin_mm, dtype=np.float32).reshape(-1, 3)
    light = np.ones(len(points), dtype=np.float32)
    for layer in LAYERS:
        cells = np.floor(points / np.float32(layer.cell_mm)).astype(np.int64)
        spotted, centre, radius, depth = layer_spots(cells, layer, seed)
        distance = np.linalg.norm(points[spotted] - centre, axis=1)
        edge = np.clip((radius - distance) / (2 * EDGE_MM) + 0.5, 0.0, 1.0)
        light[spotted] *= 1.0 - depth * edge
    return 1.0 - light


def pigmented(albedo_rgb: np.ndarray, darkness: np.ndarray) -> np.ndarray:
    """(N, 3) albedo with the spots' pigment taken out."""
    result: np.ndarray = albedo_rgb * (1.0 - darkness[:, None].astype(np.float32) * PIGMENT_TINT)
    return result
