"""A texture atlas for a scan's mesh: charts of similarly facing triangles, projected flat and
packed into one image, and every texel's point on the surface.

Each triangle joins the chart direction (one of 26: the cube's faces, edges and corners) closest
to its normal averaged over a few rings of neighbours (a TSDF surface's normals are noisy); the
edge-connected triangles of one direction form a chart, projected orthographically along it, and
charts too small to be worth their gutter join a neighbour their triangles face within 70 deg.
A texel spans 1 / cos(angle to the chart's direction) texel sizes on the skin. Charts are
packed by their footprints (the PACK_BLOCK-texel blocks their texels and gutters reach), tallest
first, each dropped into the skyline of those placed where it rests highest, so charts interlock
instead of each taking its bounding box. The gutter texels next to a chart hold the skin that
continues over its edge, taken from the chart beyond, and the rest the colour of the nearest
texel (:func:`seam_gutters`), so filtering at a chart's edge never reads an unrelated chart and
a spot cut by a seam is whole on both sides. Open3D's
UVAtlas would cut fewer seams but needs a manifold mesh and is an order of magnitude slower on
a TSDF body.

Atlas coordinates: texel (row, column) of an (H, W) image; UV (glTF) u = (column + 0.5) / W,
v = (row + 0.5) / H, origin at the image's top-left.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph
from trimesh.triangles import points_to_barycentric

from planner.cores import each

#: Texels of border round every chart (the skin over the chart's edge is continued into it).
GUTTER = 2
#: Texels between a chart's box and its texels (a texel within GUTTER of its triangles stays in the box).
MARGIN = GUTTER + 1
#: Side of the blocks charts are packed in, texels (a chart's footprint is its blocks with skin or gutter).
PACK_BLOCK = 8
#: Atlas widths tried, as multiples of the footprints' area under the square root.
PACK_WIDTHS = (1.0, 1.15, 1.3)
#: Side of the texel blocks whose mean colour fills the atlas beyond the gutters.
BACKGROUND_BLOCK = 8
#: The 26 chart directions: every non-zero (x, y, z) in {-1, 0, 1}^3, unit length.
DIRECTIONS = np.array([d for d in itertools.product((-1, 0, 1), repeat=3) if any(d)], dtype=float)
DIRECTIONS /= np.linalg.norm(DIRECTIONS, axis=1, keepdims=True)
#: Rings of neighbouring triangles a triangle's normal is averaged over to choose its direction.
SMOOTH_RINGS = 6
#: Charts of fewer triangles join a neighbour ...
MIN_CHART = 40
#: ... if their triangles are within 70 deg of its direction (cos 70 deg).
MERGE_COS = 0.342
MERGE_PASSES = 6
#: Texel tests per block of the rasterisation (bounds its temporary arrays: about 200 bytes a test).
RASTER_BLOCK = 1 << 21


class AtlasError(ValueError):
    """The mesh cannot be laid out in an atlas of the allowed size."""


@dataclass(frozen=True)
class Atlas:
    """The unwrapped mesh and its texels.

    vertices: (V', 3) float mm, a mesh vertex once per chart it belongs to; faces: (F, 3) into
    them, in the source mesh's triangle order; source_vertex: (V',) index of each in the source
    mesh; uv: (V', 2) glTF texture coordinates; texel_mm: texel side on the chart plane;
    shape: (H, W); charts: number of charts; texel_rc: (T, 2) int row, column of every texel a
    triangle covers; texel_face: (T,) its triangle; texel_point: (T, 3) float its point, mm.
    """

    vertices: np.ndarray
    faces: np.ndarray
    source_vertex: np.ndarray
    uv: np.ndarray
    texel_mm: float
    shape: tuple[int, int]
    charts: int
    texel_rc: np.ndarray
    texel_face: np.ndarray
    texel_point: np.ndarray


def chart_labels(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F,) chart of every triangle, 0..C-1, and (F,) the chart's direction (into DIRECTIONS).

    Directions come from normals smoothed over a few rings of neighbours (a TSDF surface's
    normals are noisy); charts are the edge-connected triangles of one direction, and charts of
    fewer than MIN_CHART triangles join a neighbouring chart whose direction their own normals
    are within 70 deg of."""
    corners = vertices[faces]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    pairs = _face_adjacency(faces)
    n = len(faces)
    ring = sparse.coo_matrix((np.ones(2 * len(pairs)), (np.r_[pairs[:, 0], pairs[:, 1]], np.r_[pairs[:, 1], pairs[:, 0]])),
                             shape=(n, n)).tocsr() + sparse.identity(n, format="csr")
    smooth = normals
    for _ in range(SMOOTH_RINGS):
        smooth = ring @ smooth
    direction = np.argmax(smooth @ DIRECTIONS.T, axis=1)
    labels = _components(pairs, direction, n)
    for _ in range(MERGE_PASSES):
        size = np.bincount(labels)
        small = size[labels] < MIN_CHART
        if not small.any():
            break
        both = np.r_[pairs, pairs[:, ::-1]]
        a, b = both[:, 0], both[:, 1]
        fits = np.einsum("ij,ij->i", normals[a], DIRECTIONS[direction[b]]) > MERGE_COS
        take = small[a] & ~small[b] & fits
        if not take.any():
            break
        a, b = a[take], b[take]
        # each small chart joins the chart its triangles share the most edges with
        key = labels[a] * (labels.max() + 1) + labels[b]
        keys, votes = np.unique(key, return_counts=True)
        order = np.lexsort((-votes, keys // (labels.max() + 1)))
        keys = keys[order]
        first = np.r_[True, keys[1:] // (labels.max() + 1) != keys[:-1] // (labels.max() + 1)]
        target = np.arange(labels.max() + 1)
        target[keys[first] // (labels.max() + 1)] = keys[first] % (labels.max() + 1)
        chart_direction = np.zeros(labels.max() + 1, dtype=np.int64)
        chart_direction[labels] = direction
        labels = target[labels]
        direction = chart_direction[labels]
        _, labels = np.unique(labels, return_inverse=True)
    return labels.astype(np.int64), direction


def _components(pairs: np.ndarray, direction: np.ndarray, n: int) -> np.ndarray:
    """(n,) labels of the edge-connected triangles of one direction."""
    kept = pairs[direction[pairs[:, 0]] == direction[pairs[:, 1]]]
    graph = sparse.coo_matrix((np.ones(len(kept)), (kept[:, 0], kept[:, 1])), shape=(n, n))
    return csgraph.connected_components(graph, directed=False)[1]


def _face_adjacency(faces: np.ndarray) -> np.ndarray:
    """(E, 2) pairs of triangles sharing an edge (every pair, also at non-manifold edges)."""
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    owner = np.repeat(np.arange(len(faces)), 3)
    order = np.lexsort((edges[:, 1], edges[:, 0]))
    edges, owner = edges[order], owner[order]
    same = np.all(edges[1:] == edges[:-1], axis=1)
    return np.stack([owner[:-1][same], owner[1:][same]], axis=1)


def _plane_axes(direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit axes spanning the plane perpendicular to ``direction`` (3,)."""
    helper = np.array([0.0, 0.0, 1.0]) if abs(direction[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(helper, direction)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(direction, e1)


def unwrap(vertices: np.ndarray, faces: np.ndarray, texel_mm: float, *, max_side: int = 8192) -> Atlas:
    """Charts, flattening and packing of a triangle mesh (V, 3) mm, (F, 3), at ``texel_mm``;
    the texel grows (by 15 % steps) until the atlas fits ``max_side`` on both sides."""
    vertices = np.asarray(vertices, dtype=float)
    faces = np.asarray(faces, dtype=np.int64)
    if not len(faces):
        raise AtlasError("the mesh has no triangles")
    labels, direction = chart_labels(vertices, faces)
    n_charts = int(labels.max()) + 1
    # a vertex once per chart it belongs to
    keys = labels[:, None] * len(vertices) + faces  # (F, 3)
    unique, inverse = np.unique(keys.ravel(), return_inverse=True)
    source_vertex = unique % len(vertices)
    chart_of_vertex = unique // len(vertices)
    new_faces = inverse.reshape(-1, 3)
    chart_direction = np.zeros(n_charts, dtype=np.int64)
    chart_direction[labels] = direction
    flat = np.zeros((len(unique), 2))
    for d in np.unique(chart_direction):
        e1, e2 = _plane_axes(DIRECTIONS[d])
        mine = chart_direction[chart_of_vertex] == d
        points = vertices[source_vertex[mine]]
        flat[mine] = np.stack([points @ e1, -(points @ e2)], axis=1)  # column, row (mm)
    low = np.full((n_charts, 2), np.inf)
    high = np.full((n_charts, 2), -np.inf)
    np.minimum.at(low, chart_of_vertex, flat)
    np.maximum.at(high, chart_of_vertex, flat)
    while True:
        local = (flat - low[chart_of_vertex]) / texel_mm + MARGIN  # (column, row) texels in the chart's box
        sizes = np.ceil((high - low) / texel_mm).astype(np.int64) + 1 + 2 * MARGIN  # (C, 2) columns, rows
        placed = _pack(_footprints(local[new_faces], labels, sizes), max_side)
        if placed is not None:
            break
        texel_mm *= 1.15
    offsets, shape = placed
    texel = local + offsets[chart_of_vertex]  # (column, row), texels
    uv = np.stack([texel[:, 0] / shape[1], texel[:, 1] / shape[0]], axis=1)
    rc, face, point = _rasterise(texel, new_faces, vertices[source_vertex], RASTER_BLOCK)
    return Atlas(vertices[source_vertex], new_faces, source_vertex, uv, float(texel_mm), shape, n_charts, rc, face, point)


def _footprints(corners: np.ndarray, labels: np.ndarray, sizes: np.ndarray) -> list[np.ndarray]:
    """Each chart's footprint on the packing grid: (rows, columns) bool of PACK_BLOCK-texel blocks,
    set where a texel within GUTTER of a texel one of its triangles covers may lie (each
    triangle's bounding box, GUTTER + 1 texels wider). corners: (F, 3, 2) column, row of every triangle's corners in
    its chart's box (labels (F,)); sizes (C, 2): the boxes' columns, rows."""
    b = PACK_BLOCK
    lo = (np.floor(corners.min(axis=1) - 0.5).astype(np.int64) - GUTTER - 1) // b  # (F, 2) column, row
    hi = (np.ceil(corners.max(axis=1) - 0.5).astype(np.int64) + GUTTER + 1) // b
    blocks = -(-sizes // b)  # (C, 2)
    lo = np.clip(lo, 0, blocks[labels] - 1)
    hi = np.clip(hi, 0, blocks[labels] - 1)
    # each box added to its chart's difference array (one more row and column), then summed up
    rows, cols = blocks[:, 1] + 1, blocks[:, 0] + 1
    start = np.concatenate([[0], np.cumsum(rows * cols)])
    diff = np.zeros(int(start[-1]), dtype=np.int32)
    base, width = start[labels], cols[labels]
    for r, c, sign in ((lo[:, 1], lo[:, 0], 1), (lo[:, 1], hi[:, 0] + 1, -1),
                       (hi[:, 1] + 1, lo[:, 0], -1), (hi[:, 1] + 1, hi[:, 0] + 1, 1)):
        np.add.at(diff, base + r * width + c, sign)
    return [diff[start[k]:start[k + 1]].reshape(rows[k], cols[k]).cumsum(0).cumsum(1)[:-1, :-1] > 0
            for k in range(len(sizes))]


def _pack(footprints: list[np.ndarray], max_side: int) -> tuple[np.ndarray, tuple[int, int]] | None:
    """The charts' footprints (rows, columns of PACK_BLOCK-texel blocks) packed into one image:
    offsets (C, 2) texels (column, row) and the atlas (H, W), both multiples of 64 texels; None if
    no width tried fits max_side on both sides. Each width tried is near the square root of the
    footprints' area (PACK_WIDTHS); the smallest atlas wins."""
    b = PACK_BLOCK
    step = 64 // b
    area = sum(int(f.sum()) for f in footprints)
    widest = max(f.shape[1] for f in footprints)
    best: tuple[np.ndarray, tuple[int, int]] | None = None
    for factor in PACK_WIDTHS:
        width = -(-max(int(np.ceil(np.sqrt(area * factor))), widest) // step) * step
        if width * b > max_side:
            continue
        offsets, height = _skyline(footprints, width)
        shape = (-(-height // step) * step * b, width * b)
        if shape[0] <= max_side and (best is None or shape[0] * shape[1] < best[1][0] * best[1][1]):
            best = offsets * b, shape
    return best


def _skyline(footprints: list[np.ndarray], width: int) -> tuple[np.ndarray, int]:
    """Skyline packing of footprints into ``width`` columns of blocks, tallest first: each drops
    from the top at the column where it comes to rest highest (then leaves the least space above
    it); a column's skyline is the first row below every block placed in it. Block offsets (C, 2)
    column, row, and the rows used."""
    sky = np.zeros(width, dtype=np.int64)
    offsets = np.zeros((len(footprints), 2), dtype=np.int64)
    for k in sorted(range(len(footprints)), key=lambda k: (-footprints[k].shape[0], -int(footprints[k].sum()), k)):
        f = footprints[k]
        h, w = f.shape
        used = f.any(axis=0)
        top = np.where(used, f.argmax(axis=0), 0)
        bottom = np.where(used, h - f[::-1].argmax(axis=0), 0)  # one past the last block
        window = np.lib.stride_tricks.sliding_window_view(sky, w)  # (width - w + 1, w)
        rest = np.where(used, window - top, 0).max(axis=1).clip(min=0)  # the row it comes to rest at
        gap = np.where(used, rest[:, None] + top - window, 0).sum(axis=1)
        x = int(np.lexsort((gap, rest))[0])
        offsets[k] = (x, rest[x])
        sky[x:x + w] = np.where(used, np.maximum(sky[x:x + w], rest[x] + bottom), sky[x:x + w])
    return offsets, int(sky.max())


def _rasterise(texel: np.ndarray, faces: np.ndarray, points: np.ndarray,
               block: int = RASTER_BLOCK) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Texel centres inside each triangle: (T, 2) row, column; (T,) triangle; (T, 3) point mm.
    texel: (V', 2) column, row of every vertex in texels (a texel's centre is at +0.5).

    Each row of a triangle's bounding box is tested only over the columns its edges bound there
    (one texel wider each side, against rounding), not over the whole box; triangles in blocks
    of about ``block`` tests, two blocks at once where a core is spare."""
    corners = texel[faces]  # (F, 3, 2)
    lo = np.floor(corners.min(axis=1) - 0.5).astype(np.int64)
    hi = np.ceil(corners.max(axis=1) - 0.5).astype(np.int64)
    a = corners[:, 0]
    v0, v1 = corners[:, 1] - a, corners[:, 2] - a
    den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
    rows_of = np.where(den != 0, hi[:, 1] - lo[:, 1] + 1, 0)
    starts = np.concatenate([[0], np.cumsum(rows_of * (hi[:, 0] - lo[:, 0] + 1))])
    bounds = [0]
    while bounds[-1] < len(faces):
        f0 = bounds[-1]
        bounds.append(max(int(np.searchsorted(starts, starts[f0] + block, side="right")) - 1, f0 + 1))

    def texels_of(f0: int, f1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # every (triangle, row) of the boxes, and the columns the three edges bound on it
        f = np.repeat(np.arange(f0, f1), rows_of[f0:f1])
        row = lo[f, 1] + np.arange(len(f)) - np.repeat(np.cumsum(rows_of[f0:f1]) - rows_of[f0:f1], rows_of[f0:f1])
        first, last = _row_span(row + 0.5, a[f], v0[f], v1[f], den[f])
        first = np.maximum(first, lo[f, 0])
        last = np.minimum(last, hi[f, 0])
        count = np.maximum(last - first + 1, 0)
        f, row, first = np.repeat(f, count), np.repeat(row, count), np.repeat(first, count)
        col = first + np.arange(len(f)) - np.repeat(np.cumsum(count) - count, count)
        centre = np.stack([col + 0.5, row + 0.5], axis=1)
        v2 = centre - a[f]
        d = den[f]
        with np.errstate(divide="ignore", invalid="ignore"):
            w1 = (v2[:, 0] * v1[f, 1] - v1[f, 0] * v2[:, 1]) / d
            w2 = (v0[f, 0] * v2[:, 1] - v2[:, 0] * v0[f, 1]) / d
            w0 = 1.0 - w1 - w2
        inside = (w0 >= -1e-9) & (w1 >= -1e-9) & (w2 >= -1e-9)
        f, w0, w1, w2 = f[inside], w0[inside], w1[inside], w2[inside]
        tri = points[faces[f]]
        return (np.stack([row[inside], col[inside]], axis=1), f,
                w0[:, None] * tri[:, 0] + w1[:, None] * tri[:, 1] + w2[:, None] * tri[:, 2])

    parts = each(lambda span: texels_of(*span), zip(bounds[:-1], bounds[1:]), name="rasterise")
    rc, face, point = (np.concatenate(column) for column in zip(*parts))
    # a texel on an edge shared by two triangles of a chart: kept once
    _, first_seen = np.unique(rc[:, 0] * (1 << 32) + rc[:, 1], return_index=True)
    return rc[first_seen], face[first_seen], point[first_seen]


def _row_span(y: np.ndarray, a: np.ndarray, v0: np.ndarray, v1: np.ndarray,
              den: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First and last column (K,) int whose centre may lie in a triangle on the row of centre
    height y (K,): each barycentric weight is linear along the row, w = p x + q, and w >= 0
    bounds x on one side (a weight constant along the row bounds nothing; the exact test after
    decides). Triangles: corner a (K, 2), edges v0, v1 (K, 2) from it, den (K,) non-zero."""
    dy = y - a[:, 1]
    low = np.full(len(y), -np.inf)
    high = np.full(len(y), np.inf)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # slivers: huge or undefined bounds
        # w1 = ((x - ax) v1y - v1x dy) / den, w2 = (v0x dy - (x - ax) v0y) / den, w0 = 1 - w1 - w2
        p1, q1 = v1[:, 1] / den, (-a[:, 0] * v1[:, 1] - v1[:, 0] * dy) / den
        p2, q2 = -v0[:, 1] / den, (v0[:, 0] * dy + a[:, 0] * v0[:, 1]) / den
        p0, q0 = -p1 - p2, 1.0 - q1 - q2
        for p, q in ((p0, q0), (p1, q1), (p2, q2)):
            bound = -q / p
            low = np.where(p > 0, np.maximum(low, bound), low)
            high = np.where(p < 0, np.minimum(high, bound), high)
    big = float(1 << 40)
    first = np.floor(np.clip(low, -big, big) - 0.5).astype(np.int64) - 1
    last = np.ceil(np.clip(high, -big, big) - 0.5).astype(np.int64) + 1
    return first, last


def seam_gutters(atlas: Atlas, image: np.ndarray, filled: np.ndarray,
                 closest_faces: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
                 width: int = GUTTER) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The gutter texels within ``width`` of a chart given the skin that continues over the
    chart's edge: each such texel's place on its nearest chart texel's triangle plane, extended
    past the edge, is moved to the closest point of the mesh (``closest_faces``: (Q, 3) points
    -> closest points (Q, 3), triangles (Q,)), and where that point lies in another chart (or
    far across this one) the texel takes that chart's texel there, so a spot cut by a seam is
    whole on both sides and filtering at the edge reads the skin beyond it.

    image: (H, W, C) with the charts' texels filled (filled (H, W) bool); returns the image with
    the gutter texels within ``width`` of a chart given the colour of their nearest filled texel
    where no seam texel's skin replaces it, every other unfilled texel the mean colour of the
    nearest block of BACKGROUND_BLOCK x BACKGROUND_BLOCK texels holding skin (shown only by the
    texture's smaller mipmaps), and the seam texels' (G, 2) row, column and (G, 3) mm surface
    points."""
    if not filled.any():
        return image, np.zeros((0, 2), dtype=np.int64), np.zeros((0, 3))
    reach = ndimage.maximum_filter(filled.view(np.uint8), size=2 * width + 1).view(bool) & ~filled
    g_rows, g_cols = np.nonzero(reach)
    del reach
    near_r, near_c = _nearest_filled(filled, g_rows, g_cols, width)
    result = _background(image, filled)
    result[g_rows, g_cols] = image[near_r, near_c]
    # the nearest filled texel's index among the atlas' texels (sorted by row, then column)
    keys = atlas.texel_rc[:, 0] * atlas.shape[1] + atlas.texel_rc[:, 1]
    near = near_r * atlas.shape[1] + near_c
    source = np.minimum(np.searchsorted(keys, near), len(keys) - 1)
    keep = keys[source] == near
    g_rows, g_cols, source = g_rows[keep], g_cols[keep], source[keep]
    size = np.array([atlas.shape[1], atlas.shape[0]], dtype=float)
    # the nearest texel's triangle, affine from texel (column, row) to the surface, extended
    corners = atlas.faces[atlas.texel_face[source]]
    tex = atlas.uv[corners] * size  # (G, 3, 2) column, row
    weights = points_to_barycentric(tex, np.stack([g_cols + 0.5, g_rows + 0.5], axis=1))
    planar = np.einsum("gk,gkj->gj", weights, atlas.vertices[corners])
    point, face = closest_faces(planar)
    # the closest point's place in the atlas: its triangle's texel coordinates (none on a
    # triangle of no area)
    there = atlas.uv[atlas.faces[face]] * size
    with np.errstate(divide="ignore", invalid="ignore"):
        at = np.einsum("gk,gkj->gj", points_to_barycentric(atlas.vertices[atlas.faces[face]], point), there)
    placed = np.isfinite(at).all(axis=1)
    at = np.where(placed[:, None], at, 0.0)  # column, row
    r = np.clip(np.floor(at[:, 1]).astype(np.int64), 0, atlas.shape[0] - 1)
    c = np.clip(np.floor(at[:, 0]).astype(np.int64), 0, atlas.shape[1] - 1)
    elsewhere = placed & filled[r, c] & (np.hypot(r - g_rows, c - g_cols) > width + 1.5)
    g_rows, g_cols, r, c, point = g_rows[elsewhere], g_cols[elsewhere], r[elsewhere], c[elsewhere], point[elsewhere]
    result[g_rows, g_cols] = image[r, c]
    return result, np.stack([g_rows, g_cols], axis=1), point


def _nearest_filled(filled: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                    width: int) -> tuple[np.ndarray, np.ndarray]:
    """A nearest filled texel (Euclidean) of each texel (rows, cols) (K,) that has one within
    ``width`` on both axes: neighbours tried nearest first (lowest row, then column, on ties),
    out to the distance beyond which no texel can be nearer than the one the square holds."""
    reach = int(np.ceil(width * np.sqrt(2.0)))
    steps = np.arange(-reach, reach + 1)
    dr, dc = (a.ravel() for a in np.meshgrid(steps, steps, indexing="ij"))
    order = np.lexsort((dc, dr, dr * dr + dc * dc))[1:]  # (0, 0) first: not filled
    height, breadth = filled.shape
    near_r, near_c = rows.copy(), cols.copy()
    open_ = np.arange(len(rows))
    for k in order:
        r, c = rows[open_] + dr[k], cols[open_] + dc[k]
        inside = (r >= 0) & (r < height) & (c >= 0) & (c < breadth)
        hit = np.zeros(len(open_), dtype=bool)
        hit[inside] = filled[r[inside], c[inside]]
        near_r[open_[hit]], near_c[open_[hit]] = r[hit], c[hit]
        open_ = open_[~hit]
        if not len(open_):
            break
    return near_r, near_c


def _background(image: np.ndarray, filled: np.ndarray) -> np.ndarray:
    """The image (H, W, C) with every unfilled texel given the mean colour of the filled texels
    of its BACKGROUND_BLOCK-square block, or of the nearest block holding one: a background
    only the texture's smaller mipmaps show, at a 64th of the cost of each texel's own nearest."""
    b = BACKGROUND_BLOCK
    height, breadth = filled.shape
    grid = (-(-height // b), -(-breadth // b))
    rows, cols = np.nonzero(filled)
    cell = (rows // b) * grid[1] + cols // b
    count = np.bincount(cell, minlength=grid[0] * grid[1]).reshape(grid)
    mean = np.stack([np.bincount(cell, image[rows, cols, k].astype(np.float64), minlength=count.size)
                     for k in range(image.shape[2])], axis=1).reshape(*grid, -1)
    mean /= np.maximum(count, 1)[..., None]
    near = ndimage.distance_transform_edt(count == 0, return_distances=False, return_indices=True)
    colour = mean[near[0], near[1]]  # (grid, C): each block's fill
    if np.issubdtype(image.dtype, np.integer):
        colour = np.rint(colour)
    result = np.repeat(np.repeat(colour.astype(image.dtype), b, axis=0), b, axis=1)[:height, :breadth]
    np.copyto(result, image, where=filled[..., None])
    return result
