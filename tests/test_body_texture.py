"""The photographic body: the atlas, the choice of images per texel, exposure matching, body.glb."""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage
from scipy.spatial import cKDTree

from analysis.atlas import (
    BACKGROUND_BLOCK,
    GUTTER,
    MARGIN,
    PACK_BLOCK,
    _background,
    _footprints,
    _nearest_filled,
    _pack,
    _rasterise,
    seam_gutters,
    unwrap,
)
from analysis.body_texture import (
    choose_views,
    report_and_body,
    smooth_face_normals,
    stored_image_size,
    texture_scan,
    write_body,
)
from analysis.exposure import FALLOFF_KNOTS, fit_exposure
from analysis.navigate import Navigator
from analysis.pixels import bicubic
from analysis.scan_views import open_scan
from analysis.texel_views import texel_views
from cli import main
from tests.test_web import folder_of

#: The capsule scan's texel here (its images would give 0.9 mm: 2 M texels, 40 s a texture).
TEST_TEXEL_MM = 3.0


def _body_like() -> trimesh.Trimesh:
    """A capsule with a bent arm-like bump: charts of every direction, some concavity."""
    body = trimesh.creation.capsule(height=600.0, radius=120.0, count=[32, 32])
    arm = trimesh.creation.capsule(height=300.0, radius=40.0, count=[16, 16])
    arm.apply_transform(trimesh.transformations.rotation_matrix(np.radians(60), [1, 0, 0]))
    arm.apply_translation([0.0, 170.0, 100.0])
    return trimesh.util.concatenate([body, arm])


@settings(max_examples=8, deadline=None)
@given(st.floats(1.5, 6.0))
def test_the_atlas_covers_every_triangle_once_with_texels_on_their_triangle(texel_mm):
    mesh = _body_like()
    atlas = unwrap(mesh.vertices, mesh.faces, texel_mm)
    # the unwrapped mesh is the same surface: its vertices are source vertices, its triangles the same
    assert np.allclose(atlas.vertices, mesh.vertices[atlas.source_vertex])
    assert np.array_equal(atlas.source_vertex[atlas.faces], mesh.faces)
    assert np.all((atlas.uv > 0) & (atlas.uv < 1))
    # texels: each once, on its own triangle, covering the projected surface
    keys = atlas.texel_rc[:, 0] * atlas.shape[1] + atlas.texel_rc[:, 1]
    assert len(np.unique(keys)) == len(keys)
    tri = mesh.triangles[atlas.texel_face]
    normal = mesh.face_normals[atlas.texel_face]
    assert np.max(np.abs(np.einsum("ij,ij->i", atlas.texel_point - tri[:, 0], normal))) < 1e-6
    bary = trimesh.triangles.points_to_barycentric(tri, atlas.texel_point)
    assert bary.min() > -1e-6
    covered = len(atlas.texel_rc) * atlas.texel_mm**2
    assert 0.8 * mesh.area < covered < 1.05 * mesh.area  # flattened along each chart's direction: a little smaller
    # no two triangles overlap in the atlas: the texels each claims sum to the total
    uv = atlas.uv[atlas.faces] * np.array(atlas.shape[::-1])
    e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    flat_area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum()
    assert len(atlas.texel_rc) == pytest.approx(flat_area, rel=0.03)
    # every chart keeps its gutter free: texels stay GUTTER inside the atlas' edges, and a texel of
    # another chart is further than two gutters away (charts are edge-connected: one component each)
    assert atlas.texel_rc.min() >= GUTTER and np.all(atlas.texel_rc.max(axis=0) < np.array(atlas.shape) - GUTTER)
    chart = trimesh.graph.connected_component_labels(trimesh.graph.face_adjacency(atlas.faces), len(atlas.faces))
    assert chart.max() + 1 == atlas.charts
    pairs = cKDTree(atlas.texel_rc).query_pairs(2 * GUTTER, p=np.inf, output_type="ndarray")
    label = chart[atlas.texel_face]
    assert np.array_equal(label[pairs[:, 0]], label[pairs[:, 1]])


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.integers(1, 30), st.integers(1, 30), st.floats(0.2, 1.0), st.integers(0, 2**16)),
                min_size=1, max_size=25))
def test_packed_footprints_never_overlap_and_stay_inside_the_atlas(charts) -> None:
    footprints = []
    for rows, cols, share, seed in charts:
        f = np.random.default_rng(seed).random((rows, cols)) < share
        f[seed % rows, seed % cols] = True  # at least one block
        footprints.append(f)
    placed = _pack(footprints, max_side=1 << 20)
    assert placed is not None
    offsets, (height, width) = placed
    assert height % 64 == 0 and width % 64 == 0 and np.all(offsets % PACK_BLOCK == 0)
    grid = np.zeros((height // PACK_BLOCK, width // PACK_BLOCK), dtype=np.int64)
    for f, (x, y) in zip(footprints, offsets // PACK_BLOCK):
        rows, cols = np.nonzero(f)  # a footprint's empty rows may reach past the atlas' end
        assert x >= 0 and y >= 0 and np.all(x + cols < grid.shape[1]) and np.all(y + rows < grid.shape[0])
        grid[y + rows, x + cols] += 1
    assert grid.max() == 1
    assert _pack(footprints, max_side=32) is None  # narrower than any atlas (64 texels)


@settings(max_examples=80, deadline=None)
@given(st.integers(0, 2**16), st.floats(2.0, 40.0), st.integers(1, 4))
def test_a_charts_footprint_holds_its_texels_and_their_gutters(seed, scale, triangles) -> None:
    rng = np.random.default_rng(seed)
    corners = rng.uniform(0.0, scale, (triangles, 3, 2)) + MARGIN  # (F, 3, 2) column, row in the chart's box
    sizes = np.ceil(corners.max(axis=(0, 1))).astype(np.int64)[None] + 1 + MARGIN
    footprint = _footprints(corners, np.zeros(len(corners), dtype=np.int64), sizes)[0]
    texels = np.zeros((footprint.shape[0] * PACK_BLOCK, footprint.shape[1] * PACK_BLOCK), dtype=bool)
    rc, _, _ = _rasterise(corners.reshape(-1, 2), np.arange(len(corners) * 3).reshape(-1, 3), np.zeros((len(corners) * 3, 3)))
    texels[rc[:, 0], rc[:, 1]] = True
    reach = ndimage.maximum_filter(texels.view(np.uint8), size=2 * GUTTER + 1).view(bool)
    blocks = reach.reshape(footprint.shape[0], PACK_BLOCK, footprint.shape[1], PACK_BLOCK).any(axis=(1, 3))
    assert not (blocks & ~footprint).any()


def _fold(spacing_mm: float = 2.0) -> trimesh.Trimesh:
    """Two 30 x 30 mm squares meeting at a right-angled edge along y (x = z = 0): two charts."""
    s, y = np.meshgrid(np.arange(-30.0, 30.1, spacing_mm), np.arange(0.0, 30.1, spacing_mm), indexing="ij")
    s, y = s.ravel(), y.ravel()
    vertices = np.stack([np.minimum(s, 0.0), y, -np.maximum(s, 0.0)], axis=1)
    n_s, n_y = len(np.unique(s)), len(np.unique(y))
    i, j = np.meshgrid(np.arange(n_s - 1), np.arange(n_y - 1), indexing="ij")
    a = (i * n_y + j).ravel()
    faces = np.concatenate([np.stack([a, a + n_y, a + 1], axis=1), np.stack([a + 1, a + n_y, a + n_y + 1], axis=1)])
    return trimesh.Trimesh(vertices, faces, process=False)


def test_the_gutters_at_a_seam_hold_the_skin_that_continues_over_it_so_a_cut_spot_is_whole():
    from planner.visibility import RayScene

    mesh = _fold()
    atlas = unwrap(mesh.vertices, mesh.faces, 0.5)
    assert atlas.charts == 2

    def skin(points: np.ndarray) -> np.ndarray:  # a dark spot of 3 mm sigma on the seam
        geodesic = np.stack([points[:, 0] - points[:, 2], points[:, 1]], axis=1)  # the fold flattened
        return 200.0 - 150.0 * np.exp(-np.sum((geodesic - [0.0, 15.0]) ** 2, axis=1) / 18.0)

    image = np.zeros((*atlas.shape, 1), dtype=np.float64)
    filled = np.zeros(atlas.shape, dtype=bool)
    image[atlas.texel_rc[:, 0], atlas.texel_rc[:, 1], 0] = skin(atlas.texel_point)
    filled[atlas.texel_rc[:, 0], atlas.texel_rc[:, 1]] = True
    scene = RayScene(mesh)
    continued, rc, point = seam_gutters(atlas, image, filled, scene.closest_faces)
    # the gutter texels along the seam (both charts' sides, GUTTER deep) and only unfilled ones
    seam_length = 30.0 / atlas.texel_mm
    assert 2 * GUTTER * seam_length * 0.8 < len(rc) < 2 * GUTTER * seam_length * 1.3
    assert not filled[rc[:, 0], rc[:, 1]].any()
    # each holds the skin at its point, which lies on the other square, past the seam by less than GUTTER + 1 texels
    assert np.linalg.norm(scene.closest_faces(point)[0] - point, axis=1).max() < 1e-3
    past = np.abs(point[:, 0] - point[:, 2])
    assert past.max() < (GUTTER + 1) * atlas.texel_mm * 1.5
    assert np.all((point[:, 0] > -1e-6) & (point[:, 2] > -1e-6) | (point[:, 0] < 1e-6) & (point[:, 2] < 1e-6))
    got = continued[rc[:, 0], rc[:, 1], 0]
    assert np.abs(got - skin(point)).max() < 150.0 * atlas.texel_mm / 3.0
    # the spot is whole: at the seam the gutter continues darker towards its centre, where the
    # chart's own colour spread into the gutter would stay as dark as the edge
    near_centre = np.abs(point[:, 1] - 15.0) < 1.0
    rows, cols = ndimage.distance_transform_edt(~filled, return_distances=False, return_indices=True)
    spread = image[rows, cols][rc[:, 0], rc[:, 1], 0]  # the nearest chart texel's colour
    assert np.abs(got - skin(point))[near_centre].mean() < 0.3 * np.abs(spread - skin(point))[near_centre].mean()


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 4), st.floats(0.02, 0.6))
def test_a_gutter_texel_takes_a_nearest_filled_texel_and_the_rest_a_block_s_colour(seed, width, share):
    rng = np.random.default_rng(seed)
    filled = rng.random((37, 53)) < share
    filled[rng.integers(37), rng.integers(53)] = True
    image = np.where(filled[..., None], rng.integers(0, 256, (37, 53, 3)), 0).astype(np.uint8)
    reach = ndimage.maximum_filter(filled.view(np.uint8), size=2 * width + 1).view(bool) & ~filled
    rows, cols = np.nonzero(reach)
    near_r, near_c = _nearest_filled(filled, rows, cols, width)
    assert filled[near_r, near_c].all()
    distance = ndimage.distance_transform_edt(~filled)[rows, cols]  # to the nearest filled texel
    assert np.allclose(np.hypot(near_r - rows, near_c - cols), distance)
    background = _background(image, filled)
    assert np.array_equal(background[filled], image[filled])
    # an unfilled texel's colour is the mean of the filled texels of some block: within their range
    block = BACKGROUND_BLOCK
    lo, hi = image[filled].min(axis=0), image[filled].max(axis=0)
    assert ((background[~filled] >= lo) & (background[~filled] <= hi)).all()
    r, c = np.nonzero(filled)
    cell = (r[0] // block, c[0] // block)  # a block that holds skin: its unfilled texels take its mean
    mine = (r // block == cell[0]) & (c // block == cell[1])
    inside = ~filled[cell[0] * block:(cell[0] + 1) * block, cell[1] * block:(cell[1] + 1) * block]
    if inside.any():
        got = background[cell[0] * block:(cell[0] + 1) * block, cell[1] * block:(cell[1] + 1) * block][inside]
        assert np.abs(got.astype(float) - image[r[mine], c[mine]].mean(axis=0)).max() <= 0.5 + 1e-9


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(0, 40), st.floats(0, 40)), min_size=3, max_size=30), st.booleans())
def test_rasterising_row_spans_finds_the_texels_of_testing_every_texel_of_the_box(corners, snap):
    """The rasteriser tests each row only over the columns the edges bound: the same texels as
    the barycentric test over the triangle's whole bounding box (thin, flat and snapped ones too)."""
    texel = np.array(corners[: len(corners) // 3 * 3], dtype=float)
    if snap:
        texel = np.round(texel * 2) / 2  # corners on texel centres and edges
    faces = np.arange(len(texel)).reshape(-1, 3)
    points = np.c_[texel, np.zeros(len(texel))]
    rc, face, point = _rasterise(texel, faces, points)
    want = set()
    for tri in texel[faces].tolist():
        tri = np.array(tri)
        (ax, ay), (bx, by), (cx, cy) = tri
        den = (bx - ax) * (cy - ay) - (cx - ax) * (by - ay)
        if den == 0:
            continue
        for row in range(int(np.floor(tri[:, 1].min() - 0.5)), int(np.ceil(tri[:, 1].max() - 0.5)) + 1):
            for col in range(int(np.floor(tri[:, 0].min() - 0.5)), int(np.ceil(tri[:, 0].max() - 0.5)) + 1):
                px, py = col + 0.5 - ax, row + 0.5 - ay
                with np.errstate(over="ignore"):
                    w1 = np.float64(px * (cy - ay) - (cx - ax) * py) / den
                    w2 = np.float64((bx - ax) * py - px * (by - ay)) / den
                if min(1.0 - w1 - w2, w1, w2) >= -1e-9:
                    want.add((row, col))
    assert set(map(tuple, rc.tolist())) == want
    assert np.allclose(point[:, :2], rc[:, ::-1] + 0.5)


@settings(max_examples=50, deadline=None)
@given(st.floats(-3, 3), st.floats(-3, 3), st.floats(-0.2, 0.2), st.floats(0, 100),
       st.lists(st.floats(1.5, 11.5), min_size=4, max_size=4), st.lists(st.floats(1.5, 15.5), min_size=4, max_size=4))
def test_bicubic_is_exact_on_a_quadratic_image_inside_its_edges(a, b, q, c, us, vs):
    """Keys' cubic reproduces linear and quadratic images; on a quadratic the value is then
    clamped to the two nearest pixel centres' values (it passes them only where the curve turns
    between them)."""
    rows, cols = np.mgrid[0:17, 0:13]
    image = (a * (cols + 0.5) + b * (rows + 0.5) + c)[:, :, None]
    u, v = np.array(us), np.array(vs)
    assert bicubic(image, u, v)[:, 0] == pytest.approx(a * u + b * v + c, abs=1e-9)
    curved = (q * (cols + 0.5) ** 2 + a * (cols + 0.5) + c)[:, :, None]
    got = bicubic(curved, u, v)[:, 0]
    x0 = np.floor(u - 0.5) + 0.5
    ends = np.stack([q * x0**2 + a * x0 + c, q * (x0 + 1) ** 2 + a * (x0 + 1) + c])
    want = np.clip(q * u**2 + a * u + c, ends.min(axis=0), ends.max(axis=0))
    assert got == pytest.approx(want, abs=1e-9)


@settings(max_examples=50, deadline=None)
@given(st.floats(0.5, 12.5), st.floats(0.5, 16.5), st.integers(0, 2**31 - 1))
def test_bicubic_stays_within_the_nearest_pixels_values(u, v, seed):
    image = np.random.default_rng(seed).uniform(0, 255, (17, 13, 3)).astype(np.float32)
    got = bicubic(image, np.array([u]), np.array([v]))[0]
    x0, y0 = min(int(u - 0.5), 11), min(int(v - 0.5), 15)
    x0, y0 = max(x0, 0), max(y0, 0)
    x1, y1 = min(x0 + 1, 12), min(y0 + 1, 16)
    near = image[[y0, y0, y1, y1], [x0, x1, x0, x1]]
    assert np.all(got >= near.min(axis=0) - 1e-4) and np.all(got <= near.max(axis=0) + 1e-4)


def test_bicubic_keeps_more_of_a_one_pixel_spot_than_the_average_of_its_neighbours():
    """A dark pixel on bright skin read half a pixel off its centre: bilinear interpolation would
    give the mean of the spot and its neighbour (half the contrast); the cubic keeps more."""
    image = np.full((9, 9, 1), 200.0)
    image[4, 4] = 100.0
    got = bicubic(image, np.array([5.0]), np.array([4.5]))[0, 0]  # half a pixel right of the spot's centre
    assert got < 150.0 - 5.0
    assert bicubic(image, np.array([4.5]), np.array([4.5]))[0, 0] == pytest.approx(100.0)  # exact at the centre


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_exposure_recovers_the_gains_and_the_light_falloff_of_synthetic_images(seed):
    rng = np.random.default_rng(seed)
    poses, texels = 12, 4000
    true_gain = np.exp(rng.uniform(-0.3, 0.3, (poses, 3)))
    true_gain /= np.exp(np.log(true_gain).mean(axis=0))  # the fit holds the log gains' mean at zero
    albedo = rng.uniform(60, 200, (texels, 3))
    texel = np.repeat(np.arange(texels), 3)
    pose = np.concatenate([rng.choice(poses, 3, replace=False) for _ in range(texels)])
    incidence = rng.uniform(0.2, 1.0, len(texel))
    colour = albedo[texel] * true_gain[pose] * (0.25 + 0.75 * incidence)[:, None]
    weight = rng.uniform(0.2, 1.0, len(texel))
    fitted = fit_exposure(texel, pose, incidence, colour, weight, poses)
    assert fitted.gains == pytest.approx(true_gain, rel=0.05)  # the weak pull towards 1 shrinks them a little
    knots = FALLOFF_KNOTS >= 0.25
    assert np.exp(fitted.falloff[knots]) == pytest.approx(0.25 + 0.75 * FALLOFF_KNOTS[knots], abs=0.03)


@pytest.fixture(scope="module")
def textured(web_store, tmp_path_factory) -> Path:
    """A copy of the web tests' simulated scan, with its textured body."""
    root = tmp_path_factory.mktemp("textured")
    name = folder_of(web_store)
    shutil.copytree(web_store / name, root / name)
    write_body(root / name, texel_mm=TEST_TEXEL_MM)
    return root / name


@pytest.fixture(scope="module")
def body(textured):
    """The textured scan's body with its per-texel records (the texture is deterministic: the
    same as body.glb's)."""
    return texture_scan(open_scan(textured), texel_mm=TEST_TEXEL_MM)


def test_body_glb_is_listed_in_the_manifest_and_loads_back_textured(textured):
    manifest = json.loads((textured / "manifest.json").read_text())
    assert manifest["files"]["body"] == "body.glb"
    scan = open_scan(textured)
    assert scan.folder.check() == []
    scene = trimesh.load(textured / "body.glb", file_type="glb")
    mesh = next(iter(scene.geometry.values()))
    texture = mesh.visual.material.baseColorTexture
    assert texture.size[0] >= 128 and texture.size[1] >= 128
    assert mesh.visual.uv.shape == (len(mesh.vertices), 2)
    # the scan's own surface, in metres
    source = scan.mesh()
    assert mesh.area * 1e6 == pytest.approx(source.area, rel=1e-3)
    assert np.allclose(mesh.bounds * 1000.0, source.bounds, atol=0.01)
    # skin-coloured where the texture has skin: the simulated skin is reddish
    pixels = np.asarray(texture.convert("RGB"), dtype=float).reshape(-1, 3)
    lit = pixels[pixels.sum(axis=1) > 150]
    assert len(lit) > 0.5 * len(pixels) and np.median(lit[:, 0]) > np.median(lit[:, 2])


def test_every_texel_takes_the_image_navigation_ranks_best(textured):
    """The texture's choice of image is the navigator's: sharp first, at the lowest plan cost."""
    scan = open_scan(textured)
    nav = Navigator(scan)
    mesh = nav.mesh
    rng = np.random.default_rng(3)
    faces = rng.choice(len(mesh.faces), 60, replace=False)
    points = np.asarray(mesh.triangles_center)[faces]
    normals = -np.asarray(mesh.face_normals)[faces]
    found = choose_views(nav, points, normals, stored_image_size(scan))
    for k, point in enumerate(points):
        views = nav.query(point=point, count=None)["views"]
        if not views:
            assert found.best_pose[k] == -1
            continue
        assert found.best_pose[k] == views[0]["pose"]
        assert found.best_sharp[k] == views[0]["in_focus"]
        assert found.best_sharp[k] == any(v["in_focus"] for v in views)  # a sharp image wins when there is one


def _unwrapped(scan_dir: Path, texel_mm: float) -> tuple[Navigator, tuple[int, int], np.ndarray, np.ndarray, Any]:
    """A scan's navigator, stored image size, inward and smoothed triangle normals and atlas."""
    scan = open_scan(scan_dir)
    nav = Navigator(scan)
    vertices, faces = np.asarray(nav.mesh.vertices, dtype=float), np.asarray(nav.mesh.faces)
    normals, smooth = -np.asarray(nav.scene.face_normals), smooth_face_normals(vertices, faces)
    return nav, stored_image_size(scan), normals, smooth, unwrap(vertices, faces, texel_mm)


def test_the_texels_take_the_images_the_planners_visibility_and_cost_give(textured):
    """texel_views costs each texel's pairs itself (frustum, facing, occlusion, cost terms) and
    casts rays only where a pair can matter: with every pose a candidate it picks what
    choose_views picks through planner.navigation.view_costs, in texel order, heaviest first."""
    from scipy import sparse

    nav, size, normals, smooth, atlas = _unwrapped(textured, 6.0)
    every = sparse.csr_matrix(np.ones((len(nav.mesh.faces), nav.scan.rig.n_poses)))
    got = texel_views(nav, atlas, normals, smooth, every, size)
    face = atlas.texel_face
    want = choose_views(nav, atlas.texel_point, normals[face], size, smooth_normals=smooth[face])
    assert (got.best_pose >= 0).mean() > 0.9
    assert np.mean(got.best_pose == want.best_pose) > 0.999 and np.mean(got.best_sharp == want.best_sharp) > 0.999
    key_got = got.texel.astype(np.int64) * 1000 + got.pose
    key_want = want.texel.astype(np.int64) * 1000 + want.pose
    assert len(np.setxor1d(key_got, key_want)) < 1e-3 * len(key_want)
    _, i, j = np.intersect1d(key_got, key_want, return_indices=True)
    assert got.weight[i] == pytest.approx(want.weight[j], abs=1e-4)
    assert np.hypot(got.u[i] - want.u[j], got.v[i] - want.v[j]).max() < 1e-3
    assert np.all(np.diff(got.texel) >= 0)
    same = np.diff(got.texel) == 0
    assert np.all(got.weight[1:][same] <= got.weight[:-1][same])


def test_images_seeing_the_skin_squarely_lead_the_blend():
    from analysis.texel_views import squarely

    weight = np.array([1.0, 1.0, 0.5, 0.0], dtype=np.float32)
    incidence = np.array([1.0, 0.5, 1.0, 1.0], dtype=np.float32)
    got = squarely(weight, incidence)
    assert got[0] == 1.0 and got[1] < 0.1 and got[2] == 0.5 and got[3] == 0.0
    assert squarely(np.ones(1, np.float32), np.zeros(1, np.float32))[0] > 0


def test_the_texture_is_blended_from_the_best_images_and_sharp_where_they_are(body):
    samples = body.samples
    seen = samples.best_pose >= 0
    assert seen.mean() > 0.9
    # a texel's heaviest sample is its best image, except near that image's border, where its
    # weight falls towards zero
    order = np.lexsort((-samples.weight, samples.texel))
    first = order[np.r_[True, samples.texel[order][1:] != samples.texel[order][:-1]]]
    heaviest = np.full(len(seen), -1)
    heaviest[samples.texel[first]] = samples.pose[first]
    assert np.mean(heaviest[seen] == samples.best_pose[seen]) > 0.9
    assert np.all(samples.weight > 0) and np.all(samples.weight <= 1)


def test_tbp_texture_writes_the_body_and_names_what_is_wrong(textured, tmp_path, capsys):
    copy = tmp_path / textured.name
    shutil.copytree(textured, copy)
    (copy / "body.glb").unlink()
    assert main(["texture", str(copy), "--texel-mm", str(TEST_TEXEL_MM)]) == 0
    out, err = capsys.readouterr()
    assert out.strip() == str(copy / "body.glb") and "atlas" in err
    steps = next(line for line in err.splitlines() if "steps: " in line)  # where the time went, step by step
    assert all(f"{name} " in steps for name in ("atlas", "views", "sample", "exposure", "blend", "gutters"))
    assert trimesh.load(io.BytesIO((copy / "body.glb").read_bytes()), file_type="glb").geometry
    assert main(["texture", str(tmp_path / "nothing")]) == 2
    assert "nothing" in capsys.readouterr().err
    assert main(["texture", str(copy), "--texel-mm", "0"]) == 2
    assert "--texel-mm 0" in capsys.readouterr().err


@pytest.mark.parametrize("damage", ["cut short", "not a picture"])
def test_tbp_texture_names_an_image_that_no_longer_decodes_and_leaves_the_folder_as_it_was(textured, tmp_path,
                                                                                          capsys, damage):
    copy = tmp_path / textured.name
    shutil.copytree(textured, copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    verified = [i for i in manifest["images"] if i["status"] == "verified"]
    if damage == "cut short":  # its header reads: the column's middle phone half way round, which
        middle = max(i["angle_index"] for i in verified) // 2  # holds the torso every texture samples
        name = next(i["file"] for i in verified if i["camera_index"] == 3 and i["angle_index"] == middle)
    else:  # the first image: the texture reads its header for the images' size
        name = verified[0]["file"]
    picture = copy / name
    picture.write_bytes(picture.read_bytes()[:2000] if damage == "cut short" else b"bit rot")
    before = {p: p.read_bytes() for p in copy.rglob("*") if p.is_file()}
    assert main(["texture", str(copy), "--texel-mm", str(TEST_TEXEL_MM)]) == 2
    err = capsys.readouterr().err
    assert f"{picture}: the image does not decode" in err and "tbp scans --check" in err
    assert "Traceback" not in err
    assert {p: p.read_bytes() for p in copy.rglob("*") if p.is_file()} == before


def test_the_texel_grows_until_the_skin_holds_no_more_than_the_texel_budget(textured, monkeypatch):
    import analysis.body_texture as body_texture

    scan = open_scan(textured)
    area = float(trimesh.load(textured / "mesh.ply", process=False).area)
    budget = int(area / (2.0 * TEST_TEXEL_MM) ** 2)  # a quarter of what the test's texel needs
    monkeypatch.setattr(body_texture, "MAX_TEXELS", budget)
    said: list[str] = []
    capped = texture_scan(scan, texel_mm=TEST_TEXEL_MM, progress=said.append)
    assert capped.atlas.texel_mm >= 2.0 * TEST_TEXEL_MM * 0.999
    assert len(capped.atlas.texel_rc) <= 1.05 * budget
    assert any(f"more than {budget / 1e6:g} M texels" in line for line in said)


def test_two_threads_texture_the_same_body_as_one_in_many_blocks(textured, body, monkeypatch):
    """With a spare core the atlas, the view choice and the image sampling run two blocks or
    images at once (planner.cores.each); the body is the one a single thread makes."""
    import analysis.atlas as atlas_module
    import analysis.body_texture as body_texture_module
    import analysis.texel_views as texel_views_module
    from planner import cores

    assert not cores.spare_core()  # the suite's processes run one numeric thread: `body` was made on one
    monkeypatch.setattr(cores, "spare_core", lambda: True)
    monkeypatch.setattr(atlas_module, "RASTER_BLOCK", 5_000)
    monkeypatch.setattr(texel_views_module, "TEXEL_BLOCK", 3_000)
    monkeypatch.setattr(body_texture_module, "SAMPLE_BLOCK", 4_000)
    threaded: list[str] = []
    real_each = cores.each

    def counted(work, items, *, name="each"):
        threaded.append(name)
        return real_each(work, items, name=name)

    for module in ("analysis.atlas", "analysis.texel_views", "analysis.body_texture"):
        monkeypatch.setattr(f"{module}.each", counted)
    twin = texture_scan(open_scan(textured), texel_mm=TEST_TEXEL_MM)
    assert {"rasterise", "texel-views", "sample", "blend"} <= set(threaded)
    assert len(twin.atlas.texel_rc) > 10 * 3_000
    assert np.array_equal(twin.atlas.texel_rc, body.atlas.texel_rc)
    assert np.array_equal(twin.atlas.texel_point, body.atlas.texel_point)
    for name in ("texel", "pose", "u", "v", "weight", "incidence", "best_pose"):
        assert np.array_equal(getattr(twin.samples, name), getattr(body.samples, name)), name
    assert np.array_equal(twin.texture, body.texture)


def test_after_a_scan_the_report_is_written_and_the_body_only_where_there_is_a_mesh(textured, tmp_path):
    copy = tmp_path / textured.name
    shutil.copytree(textured, copy)
    (copy / "body.glb").unlink()
    scan = open_scan(copy)
    scan.folder.manifest.files.pop("body")
    scan.folder.manifest.files.pop("mesh")  # as a scan stopped before its depth sweep
    scan.folder.save()
    (copy / "mesh.ply").unlink()
    page = report_and_body(copy)
    assert page.is_file() and not (copy / "body.glb").exists()
    assert "body" not in json.loads((copy / "manifest.json").read_text())["files"]
    assert open_scan(copy).folder.check() == []


def _glb_accessor(data: bytes, index: int) -> np.ndarray:
    """An accessor of a glTF binary (float32 VEC2/VEC3 or uint32 scalars), read by hand."""
    import struct

    length = struct.unpack_from("<I", data, 12)[0]
    gltf = json.loads(data[20:20 + length])
    binary = data[20 + length + 8:]
    accessor = gltf["accessors"][index]
    view = gltf["bufferViews"][accessor["bufferView"]]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3}[accessor["type"]]
    kind = {5126: "<f4", 5125: "<u4"}[accessor["componentType"]]
    start = view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
    return np.frombuffer(binary, kind, accessor["count"] * width, start).reshape(accessor["count"], width)


def test_the_glb_carries_the_atlas_texture_coordinates_as_gltf_reads_them(textured, body):
    """glTF's UV origin is the image's top-left corner: a texel's colour in the file's image at
    its triangle's UV is the colour the atlas gave it."""
    from PIL import Image

    data = (textured / "body.glb").read_bytes()
    length = int.from_bytes(data[12:16], "little")
    gltf = json.loads(data[20:20 + length])
    primitive = gltf["meshes"][0]["primitives"][0]
    uv = _glb_accessor(data, primitive["attributes"]["TEXCOORD_0"]).astype(float)
    faces = _glb_accessor(data, primitive["indices"]).reshape(-1, 3)
    image_view = gltf["bufferViews"][gltf["images"][0]["bufferView"]]
    binary = data[20 + length + 8:]
    start = image_view.get("byteOffset", 0)
    picture = np.asarray(Image.open(io.BytesIO(binary[start:start + image_view["byteLength"]])).convert("RGB"), dtype=float)
    assert np.array_equal(faces, body.atlas.faces)
    assert uv == pytest.approx(body.atlas.uv, abs=1e-6)
    centres = uv[faces].mean(axis=1)  # inside the triangle: its own chart's colour
    rows = np.minimum((centres[:, 1] * picture.shape[0]).astype(int), picture.shape[0] - 1)
    cols = np.minimum((centres[:, 0] * picture.shape[1]).astype(int), picture.shape[1] - 1)
    expected = body.texture[rows, cols].astype(float)
    assert np.median(np.abs(picture[rows, cols] - expected)) < 4.0  # JPEG
