"""Skin with something to see: freckles and naevi fixed to the simulated subject's skin.

A camera on a real rig sees pigment spots, pores and hair; a skin of one flat colour leaves
nothing in a picture that tells one patch of skin from the next. The spots here are a solid
texture in the subject's own skin coordinates (each skin point's position in the unswayed body,
carried through sway and a new stance), so the same freckle sits on the same skin in every
visit of one person.

Spots are hashed per cell of a cubic lattice: a cell holds at most one spot, placed so that it
never crosses the cell's faces, so a point looks only at its own cell (cheap enough for every
pixel of every picture). Two layers: small dark freckles and naevi, and larger faint patches.

A follow-up visit can bring seeded lesion changes (``LesionChanges``): some of the larger dark
spots grow and darken, and new dark spots appear in cells that held none, each cell deciding
from its own hash again, so the same changes show in every picture of that visit and the
changed spots can be listed (``changed_spots``) as the truth a benchmark compares with.
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
NAEVI = LAYERS[0]
"""The layer whose spots change between visits: the small dark freckles and naevi."""
PIGMENT_TINT = np.array([0.62, 0.78, 0.85], dtype=np.float32)
"""How much a spot of darkness 1 takes from red, green and blue (melanin absorbs blue most)."""
EDGE_MM = 0.35
"""Half-width of a spot's soft edge."""


class LesionChangesError(ValueError):
    """A lesion change setting is not a number or outside its range."""

    def __init__(self, field: str, value: object, problem: str) -> None:
        super().__init__(f"lesion changes {field}={value!r}: {problem}")
        self.field = field
        self.value = value
        self.problem = problem


@dataclass(frozen=True)
class LesionChanges:
    """Seeded lesion changes of a follow-up visit, on the naevi layer (NAEVI).

    seed: which spots change (another seed, other spots).
    grown_share: share of the larger spots (radius >= GROW_FROM_MM) that grow: radius times
        ``growth`` as far as the spot's cell allows, and at least GROW_AT_LEAST_MM more (a spot
        without that room in its cell does not grow), darkness + ``darkening``.
    appeared_share: share of the cells without a spot where a new dark spot appears (radius
        APPEARED_RADIUS_MM, darkness APPEARED_DARKNESS).
    """

    seed: int
    grown_share: float = 0.02
    appeared_share: float = 0.005
    growth: float = 1.6
    darkening: float = 0.2

    GROW_FROM_MM = 1.6
    GROW_AT_LEAST_MM = 0.5
    APPEARED_RADIUS_MM = (1.2, 2.4)
    APPEARED_DARKNESS = (0.35, 0.6)
    MAX_DARKNESS = 0.85

    def __post_init__(self) -> None:
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise LesionChangesError("seed", self.seed, "not a whole number >= 0")
        for name, low, high in (("grown_share", 0.0, 1.0), ("appeared_share", 0.0, 1.0), ("darkening", 0.0, 1.0),
                                ("growth", 1.0, 4.0)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not low <= value <= high:  # NaN too
                raise LesionChangesError(name, value, f"not a number in [{low:g}, {high:g}]")


@dataclass(frozen=True)
class ChangedSpots:
    """Spots of NAEVI that a LesionChanges alters, one row each: ``appeared`` (K,) bool (else
    grown), centre (K, 3) mm in skin coordinates, radius and darkness before (0 for an appeared
    spot) and after (K,)."""

    appeared: np.ndarray
    centre_mm: np.ndarray
    radius_before_mm: np.ndarray
    radius_after_mm: np.ndarray
    darkness_before: np.ndarray
    darkness_after: np.ndarray

    def __len__(self) -> int:
        return len(self.appeared)

    def rows(self, which: np.ndarray) -> ChangedSpots:
        """These spots only (an index or a mask)."""
        return ChangedSpots(*(getattr(self, name)[which] for name in self.__dataclass_fields__))


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


def _layer_uniforms(cells: np.ndarray, layer: SpotLayer, seed: int) -> np.ndarray:
    return _uniforms(cells, layer.salt ^ (int(seed) * 0x632BE59BD9B4E019 & 0xFFFFFFFFFFFFFFFF))


def layer_spots(cells: np.ndarray, layer: SpotLayer, seed: int = 0) -> tuple[np.ndarray, ...]:
    """The spots of lattice cells (N, 3) int of one layer: which cells hold one (K,) index into
    cells, their centres (K, 3) mm and radii (K,) mm (a ball in skin coordinates) and darkness (K,)."""
    u = _layer_uniforms(cells, layer, seed)
    spotted = np.flatnonzero(u[:, 0] < layer.share)
    u, cells = u[spotted], cells[spotted]
    radius = layer.radius_mm[0] + u[:, 1] * (layer.radius_mm[1] - layer.radius_mm[0])
    span = layer.cell_mm - 2 * radius  # the spot stays inside its cell
    centre = cells.astype(np.float32) * layer.cell_mm + radius[:, None] + u[:, 2:5] * span[:, None]
    depth = layer.darkness[0] + u[:, 5] * (layer.darkness[1] - layer.darkness[0])
    return spotted, centre, radius, depth


def changed_spots(cells: np.ndarray, changes: LesionChanges, seed: int = 0) -> tuple[np.ndarray, ChangedSpots]:
    """The spots of NAEVI cells (N, 3) int that ``changes`` grows or makes appear (on the skin
    of person ``seed``), and each one's index (K,) into ``cells``."""
    layer = NAEVI
    cells = np.asarray(cells, dtype=np.int64).reshape(-1, 3)
    spotted, centre, radius, depth = layer_spots(cells, layer, seed)
    c = changes
    u = _uniforms(cells, 0xD1B54A32D192ED03 ^ (c.seed * 0x2545F4914F6CDD1D + int(seed) * 0x9FB21C651E98DF25
                                               & 0xFFFFFFFFFFFFFFFF))
    lo = cells[spotted].astype(np.float32) * layer.cell_mm
    room = np.minimum(centre - lo, lo + layer.cell_mm - centre).min(axis=1)  # to the cell's nearest face
    grown_radius = np.minimum(radius * c.growth, room)
    grows = ((u[spotted, 0] < c.grown_share) & (radius >= c.GROW_FROM_MM)
             & (grown_radius >= radius + c.GROW_AT_LEAST_MM))
    empty = np.ones(len(cells), dtype=bool)
    empty[spotted] = False
    new = np.flatnonzero(empty & (u[:, 1] < c.appeared_share))
    r_lo, r_hi = c.APPEARED_RADIUS_MM
    new_radius = r_lo + u[new, 2] * (r_hi - r_lo)
    new_centre = (cells[new].astype(np.float32) * layer.cell_mm + new_radius[:, None]
                  + u[new, 3:6] * (layer.cell_mm - 2 * new_radius)[:, None])
    d_lo, d_hi = c.APPEARED_DARKNESS
    g = np.flatnonzero(grows)
    return np.concatenate([spotted[g], new]), ChangedSpots(
        appeared=np.concatenate([np.zeros(len(g), dtype=bool), np.ones(len(new), dtype=bool)]),
        centre_mm=np.concatenate([centre[g], new_centre]).astype(np.float32),
        radius_before_mm=np.concatenate([radius[g], np.zeros(len(new), dtype=np.float32)]),
        radius_after_mm=np.concatenate([grown_radius[g], new_radius]).astype(np.float32),
        darkness_before=np.concatenate([depth[g], np.zeros(len(new), dtype=np.float32)]),
        darkness_after=np.concatenate([np.minimum(depth[g] + c.darkening, c.MAX_DARKNESS),
                                       d_lo + u[new, 6] * (d_hi - d_lo)]).astype(np.float32),
    )


def visit_spots(cells: np.ndarray, layer: SpotLayer, seed: int = 0,
                changes: LesionChanges | None = None) -> tuple[np.ndarray, ...]:
    """layer_spots() as seen at a visit with ``changes`` (None: none): grown spots larger and
    darker, appeared spots added (their cells once more in the index)."""
    spotted, centre, radius, depth = layer_spots(cells, layer, seed)
    if changes is None or layer is not NAEVI:
        return spotted, centre, radius, depth
    cell, changed = changed_spots(cells, changes, seed)
    grown = ~changed.appeared
    row = np.searchsorted(spotted, cell[grown])  # spotted is sorted (flatnonzero)
    radius, depth = radius.copy(), depth.copy()
    radius[row], depth[row] = changed.radius_after_mm[grown], changed.darkness_after[grown]
    new = changed.appeared
    return (np.concatenate([spotted, cell[new]]), np.concatenate([centre, changed.centre_mm[new]]),
            np.concatenate([radius, changed.radius_after_mm[new]]),
            np.concatenate([depth, changed.darkness_after[new]]))


def pigment(skin_mm: np.ndarray, seed: int = 0, changes: LesionChanges | None = None) -> np.ndarray:
    """(N,) darkness in [0, 1) at skin points (N, 3) given in skin coordinates, mm; ``changes``:
    a follow-up visit's lesion changes (None: the skin as it is)."""
    points = np.asarray(skin_mm, dtype=np.float32).reshape(-1, 3)
    light = np.ones(len(points), dtype=np.float32)
    for layer in LAYERS:
        cells = np.floor(points / np.float32(layer.cell_mm)).astype(np.int64)
        spotted, centre, radius, depth = visit_spots(cells, layer, seed, changes)
        distance = np.linalg.norm(points[spotted] - centre, axis=1)
        edge = np.clip((radius - distance) / (2 * EDGE_MM) + 0.5, 0.0, 1.0)
        light[spotted] *= 1.0 - depth * edge
    return 1.0 - light


def pigmented(albedo_rgb: np.ndarray, darkness: np.ndarray) -> np.ndarray:
    """(N, 3) albedo with the spots' pigment taken out."""
    result: np.ndarray = albedo_rgb * (1.0 - darkness[:, None].astype(np.float32) * PIGMENT_TINT)
    return result
