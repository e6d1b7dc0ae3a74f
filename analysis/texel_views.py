"""Which images texture each texel of the photographic body, and with what weight.

Every texel takes its colour from the images that show its skin point best, ranked as image
navigation ranks them (planner.navigation.view_costs: the plan's cost, in which an image that
holds the point outside its depth of field pays the focus term, so a sharp image always wins over
a blurred one). Images within ``BLEND_MARGIN`` of the best cost are blended, with weights falling
to zero at that margin and towards each image's border, so the texture has no seams where the
best image changes.

An atlas has millions of texels; each triangle's texels test only the few poses worth testing
(:func:`candidate_poses`), and :func:`texel_views` costs those pairs directly from the cost's
own terms (planner.cost area_term, axis_term and the focus interval) in one compiled pass
(planner/candidate_costs.py), texels in bounded blocks, two blocks at once where a core is
spare (planner/cores.py).
Samples are stored compactly (32-bit floats: plenty for pixel positions and 8-bit colour).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Any

import numpy as np

from planner.cores import each

if TYPE_CHECKING:
    from analysis.atlas import Atlas
    from analysis.navigate import Navigator

#: Images whose cost is within this of a texel's best image are blended into it (the cost's
#: off-axis term grows by about this much across a fifth of an image).
BLEND_MARGIN = 0.05
#: The blend weight of an image rises from 0 at its border to 1 this share of its width inside.
EDGE_SHARE = 0.08
#: Poses this much above a corner's blend margin are tested at the triangle's texels too (the
#: cost changes across a triangle; a depth-of-field limit may cross it).
CANDIDATE_SLACK = 0.05
#: Images blended into a texel at most (the heaviest).
MAX_BLEND = 4
#: Images more than MAX_BLEND a triangle's corners offer its texels.
CANDIDATE_EXTRA = 2
#: Where a texel's images are combined each weighs its blend weight times its incidence (cos of
#: the angle between its ray and the skin's normal) to this power: where the surface is off the
#: skin by d an image puts a spot d tan(angle) from its place, and an oblique image holds the skin
#: foreshortened, so the image that sees the skin most squarely leads.
SQUARE_POWER = 4
#: Texels per pass of the view choice (bounds its temporary arrays).
TEXEL_BLOCK = 150_000


@dataclass(frozen=True)
class Samples:
    """The images that texture each texel: per blended pair the texel index (K,) int32, pose
    (K,) int16, pixel (K,) u and v (in the stored image's pixels), blend weight (K,), incidence
    (K,) (cos of the angle between the camera's ray and the skin's normal), float32, grouped by
    texel in ascending order and heaviest first within one; per texel the best pose (T,) int32
    (-1: no image sees it), whether that image holds it sharp (T,) and its mm/px (T,) float32."""

    texel: np.ndarray
    pose: np.ndarray
    u: np.ndarray
    v: np.ndarray
    weight: np.ndarray
    incidence: np.ndarray
    best_pose: np.ndarray
    best_sharp: np.ndarray
    best_mm_px: np.ndarray


@dataclass(frozen=True)
class _Pairs:
    """Visible (point, pose) pairs of a block, grouped by point in ascending order with poses
    ascending within a point: each pair's cost, whether it is sharp, depth (mm) and pixel
    (u, v, in the optics' full-size pixels). All (M,)."""

    point: np.ndarray
    pose: np.ndarray
    cost: np.ndarray
    sharp: np.ndarray
    depth: np.ndarray
    u: np.ndarray
    v: np.ndarray

    def take(self, index: np.ndarray) -> _Pairs:
        """The pairs at ``index`` (grouped as they were)."""
        return _Pairs(*(getattr(self, f.name)[index] for f in fields(self)))


def choose_views(nav: Navigator, points: np.ndarray, normals: np.ndarray, image_size: tuple[int, int], *,
                 margin: float = BLEND_MARGIN, most: int = MAX_BLEND,
                 smooth_normals: np.ndarray | None = None) -> Samples:
    """The blended images of points (T, 3) mm with inward normals (T, 3), every pose considered:
    see :class:`Samples`. Ranked by the navigator's cost under the focus actually captured;
    images within ``margin`` of a point's best are kept, at most ``most`` of them.
    smooth_normals: (T, 3) inward normals the incidence is measured against (default ``normals``)."""
    smooth_normals = normals if smooth_normals is None else smooth_normals
    picked = _Picked(nav, len(points), image_size)
    for start in range(0, len(points), TEXEL_BLOCK):
        chunk = slice(start, start + TEXEL_BLOCK)
        pairs = _visible_pairs(nav, points[chunk], normals[chunk])
        picked.add(start, pairs, points[chunk], smooth_normals[chunk], margin, most)
    return picked.samples()


def texel_views(nav: Navigator, atlas: Atlas, normals: np.ndarray, smooth_normals: np.ndarray, candidates: Any,
                image_size: tuple[int, int]) -> Samples:
    """:func:`choose_views` of every texel of the atlas, testing only its triangle's candidate
    poses. normals: (F, 3) inward unit normals of the triangles (texels of a zero-area one stay
    unseen); smooth_normals: (F, 3) those the incidence is measured against; candidates: (F, P)
    sparse CSR whose non-zeros are each triangle's candidate poses (:func:`candidate_poses`)."""
    if not candidates.has_sorted_indices:
        candidates = candidates.sorted_indices()
    picked = _Picked(nav, len(atlas.texel_point), image_size)
    facing = np.linalg.norm(normals, axis=1) > 0

    def block(start: int) -> None:
        face = atlas.texel_face[start:start + TEXEL_BLOCK]
        on = np.flatnonzero(facing[face])
        points = atlas.texel_point[start:start + TEXEL_BLOCK][on]
        pairs = _candidate_pairs(nav, points, normals[face[on]], candidates, face[on], BLEND_MARGIN)
        picked.add(start, pairs, points, smooth_normals[face[on]], BLEND_MARGIN, MAX_BLEND, on)

    each(block, range(0, len(atlas.texel_point), TEXEL_BLOCK), name="texel-views")
    return picked.samples()


def squarely(weight: np.ndarray, incidence: np.ndarray) -> np.ndarray:
    """(K,) float64: samples' weights (K,) times their incidence (K,) to SQUARE_POWER (at least
    1e-3, so a texel its images see edge-on keeps a colour)."""
    combined: np.ndarray = weight * np.maximum(np.abs(incidence), 1e-3).astype(np.float64) ** SQUARE_POWER
    return combined


def candidate_poses(nav: Navigator, vertices: np.ndarray, faces: np.ndarray, image_size: tuple[int, int]) -> Any:
    """(F, P) sparse CSR, sorted indices: the poses worth testing for the texels of each
    triangle, the best MAX_BLEND + CANDIDATE_EXTRA within BLEND_MARGIN + CANDIDATE_SLACK of the
    best image at any of its corners (testing every pose at every texel costs ten times more and
    finds the same images)."""
    from scipy import sparse

    normals = np.zeros_like(vertices)
    corners = vertices[faces]
    area_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    for k in range(3):
        np.add.at(normals, faces[:, k], -area_normals)  # inward, weighted by area
    ok = np.flatnonzero(np.linalg.norm(normals, axis=1) > 0)
    found = choose_views(nav, vertices[ok], normals[ok], image_size, margin=BLEND_MARGIN + CANDIDATE_SLACK,
                         most=MAX_BLEND + CANDIDATE_EXTRA)
    n_poses = nav.scan.rig.n_poses
    at_vertex = sparse.csr_matrix((np.ones(len(found.texel)), (ok[found.texel], found.pose)),
                                  shape=(len(vertices), n_poses))
    incidence = sparse.csr_matrix((np.ones(faces.size), (np.repeat(np.arange(len(faces)), 3), faces.ravel())),
                                  shape=(len(faces), len(vertices)))
    per_face = (incidence @ at_vertex).tocsr()
    per_face.data[:] = 1.0
    per_face.sort_indices()
    return per_face


def runs(key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The runs of equal values of a grouped key (M,): each run's first index and length."""
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]]) if len(key) else np.zeros(0, dtype=np.int64)
    return starts, np.diff(np.r_[starts, len(key)])


def cheapest(point: np.ndarray, cost: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pairs grouped by point (M,) with their cost (M,): each pair's point's lowest cost (M,) and
    the index of each point's cheapest pair (the first on ties)."""
    starts, counts = runs(point)
    lowest = np.repeat(np.minimum.reduceat(cost, starts), counts)
    hits = np.flatnonzero(cost == lowest)
    return lowest, hits[np.r_[True, point[hits][1:] != point[hits][:-1]]]


class _Picked:
    """The samples of :func:`choose_views`, gathered block by block."""

    def __init__(self, nav: Navigator, n: int, image_size: tuple[int, int]) -> None:
        self.nav = nav
        self.optics = nav.scan.rig.optics
        self.scale = image_size[0] / self.optics.image_width_px
        self.pose_type = np.int16 if nav.scan.rig.n_poses < 2**15 else np.int32
        self.best_pose = np.full(n, -1, dtype=np.int32)
        self.best_sharp = np.zeros(n, dtype=bool)
        self.best_mm_px = np.full(n, np.nan, dtype=np.float32)
        self.parts: dict[int, tuple[np.ndarray, ...]] = {}

    def add(self, start: int, pairs: _Pairs, points: np.ndarray, smooth_normals: np.ndarray, margin: float,
            most: int, index: np.ndarray | None = None) -> None:
        """Pick among the block's pairs; point i of the block is texel start + index[i]
        (index None: start + i). Blocks may be added in any order, from any thread (each writes
        its own texels): the samples are gathered in the order of their blocks' starts."""
        from planner.optics import resolution_mm_per_px

        point, pose, cost = pairs.point, pairs.pose, pairs.cost
        if not len(point):
            return
        # each point's best image: its lowest cost, the lowest pose on ties (as navigation orders them)
        lowest, first = cheapest(point, cost)
        texel = start + (np.arange(pairs.point[-1] + 1) if index is None else index)  # of the block's points
        best = texel[point[first]]
        self.best_pose[best] = pose[first]
        self.best_sharp[best] = pairs.sharp[first]
        self.best_mm_px[best] = resolution_mm_per_px(pairs.depth[first], self.optics) / self.scale
        near = np.flatnonzero(cost - lowest < margin)
        point, pose, u, v = point[near], pose[near], pairs.u[near], pairs.v[near]
        width, height = self.optics.image_width_px, self.optics.image_height_px
        border = np.minimum.reduce([u, width - u, v, height - v])
        edge = np.clip(border / (EDGE_SHARE * width), 1e-3, 1.0)
        weight = np.clip(1.0 - (cost[near] - lowest[near]) / margin, 0.0, 1.0) * edge
        top = _heaviest(point, weight, cost[near], most)
        point, pose, u, v, weight = point[top], pose[top], u[top], v[top], weight[top]
        ray = points[point] - self.nav.poses.centres[pose]
        towards = smooth_normals[point]
        incidence = np.einsum("ij,ij->i", ray, towards) / np.maximum(
            np.sqrt(np.einsum("ij,ij->i", ray, ray) * np.einsum("ij,ij->i", towards, towards)), 1e-12)
        f32 = np.float32
        self.parts[start] = ((texel[point].astype(np.int32), pose.astype(self.pose_type), (u * self.scale).astype(f32),
                           (v * self.scale).astype(f32), weight.astype(f32), incidence.astype(f32)))

    def samples(self) -> Samples:
        if self.parts:
            columns = [np.concatenate(c) for c in zip(*(self.parts[k] for k in sorted(self.parts)))]
            self.parts.clear()
        else:
            columns = [np.zeros(0, np.int32), np.zeros(0, self.pose_type), *(np.zeros(0, np.float32),) * 4]
        return Samples(*columns, self.best_pose, self.best_sharp, self.best_mm_px)


def _heaviest(point: np.ndarray, weight: np.ndarray, cost: np.ndarray, most: int) -> np.ndarray:
    """Indices of each point's ``most`` heaviest pairs (lowest cost, then first, on ties),
    heaviest first; pairs grouped by point (M,). Each point's few pairs are sorted along a row of
    a (points, widest) table: far cheaper than sorting the block's pairs as one."""
    if not len(point):
        return np.zeros(0, dtype=np.int64)
    starts, counts = runs(point)
    row = np.repeat(np.arange(len(starts)), counts)
    column = np.arange(len(point)) - starts[row]
    keys = np.full((2, len(starts), counts.max()), np.inf)  # empty cells sort last
    keys[0, row, column] = cost
    keys[1, row, column] = -weight
    order = np.lexsort(keys, axis=-1)[:, :most]  # stable: the first pair on ties
    kept = np.arange(order.shape[1]) < counts[:, None]
    picked: np.ndarray = (starts[:, None] + order)[kept]
    return picked


def _visible_pairs(nav: Navigator, points: np.ndarray, normals: np.ndarray) -> _Pairs:
    """Every available pose's visible pairs with points (Q, 3) mm, inward normals (Q, 3)
    (planner.navigation.view_costs)."""
    from planner.navigation import pixel_of, view_costs

    rig = nav.scan.rig
    focus = np.nan_to_num(nav.focus_mm, nan=-1.0)
    table, cost, sharp = view_costs(nav.scene, rig, nav.poses, focus, points, normals)
    order = table.order[np.isfinite(nav.focus_mm)[table.vis.pose[table.order]]]  # by point, poses ascending
    point, pose = table.vis.point[order], table.vis.pose[order]
    u, v = pixel_of(nav.poses, pose, points[point], rig)
    return _Pairs(point, pose, cost[order], sharp[order], table.vis.depth[order], u, v)


def _candidate_pairs(nav: Navigator, points: np.ndarray, normals: np.ndarray, candidates: Any,
                     face: np.ndarray, margin: float) -> _Pairs:
    """The visible pairs of points (Q, 3) mm, inward normals (Q, 3), with the available
    candidate poses of their triangles face (Q,) (candidates: (F, P) CSR, sorted indices) that
    cost less than ``margin`` above the point's best: the
    frustum, facing and occlusion tests of planner.visibility and the cost of planner.cost, pair
    by pair. Occlusion rays go first to
    each point's cheapest pair; where that one is seen, pairs ``margin`` or more above it cannot
    be blended and cast none."""
    from planner.candidate_costs import candidate_costs
    from planner.visibility import SURFACE_EPSILON_MM

    optics = nav.scan.rig.optics
    point, pose, total, sharp, x, y, z = candidate_costs(nav.scan.rig, nav.poses, nav.focus_mm, points, normals,
                                                         candidates, face)
    seen = _unoccluded(nav, points, point, pose, total, margin, SURFACE_EPSILON_MM)
    point, pose, total, sharp, x, y, z = (a[seen] for a in (point, pose, total, sharp, x, y, z))
    f = optics.focal_length_px
    return _Pairs(point, pose, total, sharp, z, f * x / z + optics.image_width_px / 2.0,
                  f * y / z + optics.image_height_px / 2.0)


def _unoccluded(nav: Navigator, points: np.ndarray, point: np.ndarray, pose: np.ndarray, cost: np.ndarray,
                margin: float, epsilon_mm: float) -> np.ndarray:
    """Indices of the pairs (M,) (grouped by point) that nothing hides and that cost less than
    ``margin`` above their point's cheapest seen pair, the only ones a
    texel can use; the cheapest pair of each point is tested first, the rest only where needed."""
    if not len(point):
        return np.zeros(0, dtype=np.int64)
    lowest, first = cheapest(point, cost)
    seen = np.zeros(len(point), dtype=bool)
    seen[first] = ~nav.scene.occluded(nav.poses.centres[pose[first]], points[point[first]], epsilon_mm)
    resolved = np.zeros(point[-1] + 1, dtype=bool)
    resolved[point[first]] = seen[first]
    rest = np.ones(len(point), dtype=bool)
    rest[first] = False
    rest &= ~resolved[point] | (cost - lowest < margin)
    test = np.flatnonzero(rest)
    seen[test] = ~nav.scene.occluded(nav.poses.centres[pose[test]], points[point[test]], epsilon_mm)
    return np.flatnonzero(seen)
