"""Space carving of the TSDF surface: the free space depth frames saw through, and the surface carved from it."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.sim.depth import DepthRenderer, DepthScene, simulate_sweep
from planner.carve import FreeSpace, carve
from planner.mesh_metrics import surface_distance
from planner.tsdf import FLOOR_BAND_MM, FRAME_SPACING_DEG, fuse
from tests.depth_helpers import small_rig

MODEL = small_rig(scale=2).depth_camera_model
MARGIN_MM = 5.0
CENTRE_Z = 1000.0


def _looking_at(origin: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4, 4) camera-to-world, OpenCV axes: z towards target, y (image down) towards the floor."""
    forward = (target - origin) / np.linalg.norm(target - origin)
    right = np.cross(forward, [0.0, 0.0, -1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, down, forward, origin
    return m


def _posts(radius: float, gap: float) -> trimesh.Trimesh:
    """Two standing cylinders 300 mm tall around z = CENTRE_Z, ``gap`` mm apart along x."""
    posts = [trimesh.creation.cylinder(radius=radius, height=300.0, sections=64).apply_translation(
        [side * (radius + gap / 2), 0.0, CENTRE_Z]) for side in (-1, 1)]
    return trimesh.util.concatenate(posts)


@functools.cache
def _views(radius: float, gap: float, seed: int) -> FreeSpace:
    """Noisy depth frames of the posts (and the floor) from 12 cameras around them, 40 deg down."""
    renderer = DepthRenderer(DepthScene(_posts(radius, gap)), MODEL)
    space = FreeSpace(MODEL, MARGIN_MM)
    rng = np.random.default_rng(seed)
    for azimuth in np.radians(np.arange(0, 360, 30)):
        origin = np.array([800 * np.cos(azimuth), 800 * np.sin(azimuth), CENTRE_Z + 670.0])
        pose = _looking_at(origin, np.array([0.0, 0.0, CENTRE_Z]))
        space.add(renderer.render(pose, rng) * MODEL.depth_unit_mm, MODEL.intrinsic_matrix, pose)
    return space


def _bridge(gap: float, step: float = 2.0) -> trimesh.Trimesh:
    """A sheet across the gap (plane y = 0, |x| <= gap / 2, 100 mm tall): the webbing the TSDF leaves."""
    x = np.arange(-gap / 2, gap / 2 + 1e-9, step)
    z = CENTRE_Z + np.arange(-50.0, 50.0 + 1e-9, step)
    xx, zz = np.meshgrid(x, z)
    vertices = np.stack([xx.ravel(), np.zeros(xx.size), zz.ravel()], axis=1)
    i = np.arange(xx.size).reshape(xx.shape)[:-1, :-1].ravel()
    n = len(x)
    faces = np.concatenate([np.stack([i, i + 1, i + n + 1], 1), np.stack([i, i + n + 1, i + n], 1)])
    return trimesh.Trimesh(vertices, faces, process=False)


posts = dict(radius=st.sampled_from([50.0, 90.0]), gap=st.sampled_from([20.0, 32.0]), seed=st.integers(0, 3))


@settings(max_examples=8, deadline=None)
@given(**posts, offset=st.floats(-2.5, 2.5), sample_seed=st.integers(0, 100))
def test_the_skin_is_never_free_space(radius: float, gap: float, seed: int, offset: float, sample_seed: int) -> None:
    """Points on the posts, off by up to half a voxel along the normal, are never carved: at the
    silhouettes, at grazing angles and facing each other across the gap."""
    mesh = _posts(radius, gap)
    points, faces = trimesh.sample.sample_surface(mesh, 20_000, seed=sample_seed)
    points = points + offset * mesh.face_normals[faces]
    assert not _views(radius, gap, seed).free(points).any()


@settings(max_examples=8, deadline=None)
@given(**posts)
def test_the_gap_between_the_posts_is_free_space(radius: float, gap: float, seed: int) -> None:
    """The middle of the gap, where the cameras looking along it saw the floor, is free."""
    z = CENTRE_Z + np.linspace(-100.0, 100.0, 21)
    y = np.linspace(-radius / 2, radius / 2, 11)
    yy, zz = np.meshgrid(y, z)
    middle = np.stack([np.zeros(yy.size), yy.ravel(), zz.ravel()], axis=1)
    assert _views(radius, gap, seed).free(middle).all()


@settings(max_examples=8, deadline=None)
@given(**posts)
def test_the_bridge_is_carved_and_the_posts_kept(radius: float, gap: float, seed: int) -> None:
    solid = _posts(radius, gap)
    mesh = trimesh.util.concatenate([solid, _bridge(gap)])
    vertices, faces = carve(mesh.vertices, mesh.faces, _views(radius, gap, seed))
    kept = trimesh.Trimesh(vertices, faces, process=False)
    # every face of the posts is kept (in order), of the bridge only a fringe at the posts
    assert np.array_equal(vertices[faces[:len(solid.faces)]], solid.triangles)
    assert np.abs(kept.triangles_center[len(solid.faces):, 0]).min() > gap / 2 - 8.0


def test_a_small_piece_cut_off_by_the_carving_goes_with_it() -> None:
    """A bit of surface left floating in the gap once the bridge around it is carved is dropped."""
    radius, gap = 90.0, 32.0
    solid, bridge = _posts(radius, gap), _bridge(gap)
    speck = trimesh.creation.icosphere(subdivisions=0, radius=0.5).apply_translation([0.0, 0.0, CENTRE_Z + 200.0])
    mesh = trimesh.util.concatenate([solid, bridge, speck])
    vertices, faces = carve(mesh.vertices, mesh.faces, _views(radius, gap, 0))
    assert np.abs(vertices[faces][..., 2] - (CENTRE_Z + 200.0)).min() > 1.0


def test_without_frames_nothing_is_carved() -> None:
    mesh = _posts(50.0, 20.0)
    vertices, faces = carve(mesh.vertices, mesh.faces, FreeSpace(MODEL, MARGIN_MM))
    assert vertices is mesh.vertices and faces is mesh.faces


def _webbing_cm2(mesh: trimesh.Trimesh, body: trimesh.Trimesh, floor_mm: float) -> float:
    """Area (cm^2) more than 10 mm off the body, above the feet's floor closure."""
    centres = mesh.triangles_center
    off = (surface_distance(centres, body) > 10.0) & (centres[:, 2] > floor_mm)
    return float(mesh.area_faces[off].sum() / 100)


@pytest.mark.slow
def test_the_webbing_of_a_simulated_body_is_carved_and_its_skin_kept(monkeypatch: pytest.MonkeyPatch) -> None:
    """The TSDF of a simulated adult: uncarved, about 160 cm^2 of its surface lies more than 10 mm
    off the skin, bridging arms and torso and hands and thighs; carving takes most of it away
    (about 37 cm^2 left), and every vertex the TSDF put on the skin (within 1 mm) is still there."""
    import planner.tsdf
    from sim.body import make_body

    rig = small_rig(scale=2)
    body = make_body(seed=0)
    frames = simulate_sweep(body, rig, seed=0, noise=True, frame_spacing_deg=FRAME_SPACING_DEG).frames
    floor_mm = FLOOR_BAND_MM + rig.tsdf.floor_clearance_mm
    carved = fuse(frames, rig).mesh
    with monkeypatch.context() as patch:
        patch.setattr(planner.tsdf, "carve", lambda vertices, faces, _space: (vertices, faces))
        uncarved = fuse(frames, rig).mesh
    webbing = _webbing_cm2(uncarved, body, floor_mm)
    assert webbing > 100.0
    assert _webbing_cm2(carved, body, floor_mm) < 0.35 * webbing

    skin = uncarved.vertices[surface_distance(uncarved.vertices, body) < 1.0]
    kept = {tuple(v) for v in carved.vertices}
    assert all(tuple(v) in kept for v in skin)


def test_a_frame_of_the_wrong_shape_is_refused_naming_the_shapes() -> None:
    with pytest.raises(ValueError, match=r"\(3, 3\) intrinsics.*got \(4, 5\), \(3, 4\)"):
        FreeSpace(MODEL, MARGIN_MM).add(np.zeros((4, 5)), np.zeros((3, 4)), np.eye(4))
