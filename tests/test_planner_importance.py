"""Importance samples: the skin few poses see is sampled finer at lower weight, the samples'
visibility is exactly theirs, and the plan reports shares of the skin, not of the samples."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from planner.importance import Importance, refine_samples, region_faces
from planner.plan import plan_focus
from planner.poses import rgb_poses
from planner.rig import load_rig
from planner.sampling import Triangles, sample_surface
from planner.visibility import RayScene, visible_pairs
from tests.planner_standin import standin_body
from tests.test_planner_optimise import RIG

_BODY = standin_body()


@pytest.fixture(scope="module")
def body():
    return _BODY


class _Uniform:
    """Area-uniform samples of a body with their visibility from the rig's poses, and a call
    that refines them."""

    def __init__(self, body, count: int, seed: int) -> None:
        self.body, self.seed, self.poses = body, seed, rgb_poses(RIG)
        self.triangles = Triangles.of(body)
        self.samples = sample_surface(body, count, seed=seed, triangles=self.triangles)
        self.scene = RayScene(body)
        self.vis = visible_pairs(self.scene, self.poses, self.samples, RIG.optics)

    def refine(self, importance: Importance, max_samples: int | None = None):
        return refine_samples(self.body, self.triangles, self.samples, self.vis, self.scene, self.poses,
                              RIG.optics, importance, self.seed, max_samples=max_samples)


@pytest.mark.parametrize("density", [2.0, 4.0])
def test_importance_samples_are_the_skin_few_poses_see_finer_and_their_visibility_is_exact(body, density) -> None:
    u = _Uniform(body, 3000, seed=2)
    uniform, vis, triangles, scene, poses = u.samples, u.vis, u.triangles, u.scene, u.poses
    samples, merged = u.refine(Importance(few_views=6, radius_mm=20.0, density=density))

    fine = samples.weight < 1.0
    assert np.allclose(samples.weight[fine], 1.0 / density, rtol=0.01) and np.all(samples.weight[~fine] == 1.0)
    assert fine.sum() > 0 and len(samples) > len(uniform)
    assert np.all(np.diff(samples.points[:, 2]) >= 0)  # ordered by height, as sample_surface gives them
    # The region: triangles within 20 mm of a sample 1 to 6 poses see. The fine samples lie on
    # it, the uniform samples kept lie off it.
    views = np.bincount(vis.point, minlength=len(uniform))
    region = region_faces(triangles, uniform.points[(views >= 1) & (views <= 6)], 20.0)
    assert region[samples.face_index[fine]].all()
    assert not region[samples.face_index[~fine]].any()
    assert (~fine).sum() == (~region[uniform.face_index]).sum()
    # The region is where few poses see the skin: its uniform samples were seen by fewer poses.
    in_region = region[uniform.face_index]
    assert np.median(views[in_region]) < np.median(views[~in_region])
    # The weights stand for the same skin: the region's share of the area, near enough.
    doubled = triangles.doubled_areas
    share = doubled[region].sum() / doubled.sum()
    assert samples.weight[fine].sum() == pytest.approx(share * len(uniform), rel=1e-9)
    # Merged visibility: exactly the pairs a fresh ray cast of the merged samples finds.
    fresh = visible_pairs(scene, poses, samples, RIG.optics)
    key = lambda v: np.lexsort((v.point, v.pose))  # noqa: E731
    a, b = key(merged), key(fresh)
    assert np.array_equal(merged.pose[a], fresh.pose[b]) and np.array_equal(merged.point[a], fresh.point[b])
    assert np.allclose(merged.depth[a], fresh.depth[b]) and np.allclose(merged.facing[a], fresh.facing[b])
    assert np.array_equal(merged.pose_ptr, fresh.pose_ptr)


def test_the_memory_budget_caps_the_importance_samples(body) -> None:
    u = _Uniform(body, 3000, seed=2)
    importance = Importance(few_views=6, radius_mm=20.0, density=4.0)
    full, _ = u.refine(importance)
    capped, capped_vis = u.refine(importance, max_samples=len(full) - 100)
    assert len(capped) == len(full) - 100 and capped_vis.n_points == len(capped)
    # Fewer, heavier fine samples: the region still weighs what its skin does.
    assert capped.weight.sum() == pytest.approx(full.weight.sum(), rel=1e-9)
    # No room to sample the region finer than the uniform samples: left as it was.
    same, same_vis = u.refine(importance, max_samples=len(u.samples))
    assert same is u.samples and same_vis is u.vis


def test_importance_off_leaves_the_uniform_samples(body) -> None:
    u = _Uniform(body, 1000, seed=1)
    samples, vis = u.refine(Importance(6, 20.0, 1.0))
    assert samples is u.samples and vis is u.vis


def test_the_plan_uses_the_rig_files_importance_and_reports_shares_of_the_skin(body) -> None:
    rig = load_rig()
    on = dataclasses.replace(rig, planner=dataclasses.replace(rig.planner, importance_density=4.0))
    off = dataclasses.replace(rig, planner=dataclasses.replace(rig.planner, importance_density=1.0))
    plan_on = plan_focus(body, on, points=2000, seed=3, methods=("robust",))
    plan_off = plan_focus(body, off, points=2000, seed=3, methods=("robust",))
    assert len(plan_off.samples) == 2000 and plan_off.samples.weight is None
    assert len(plan_on.samples) > 2000
    assert plan_on.to_json()["points"] == 2000 and plan_on.to_json()["samples"] == len(plan_on.samples)
    assert plan_on.table.total_weight == pytest.approx(2000, rel=0.02)
    # Shares of the skin, not of the samples: the visible share of one body stays put.
    assert plan_on.visible_fraction == pytest.approx(plan_off.visible_fraction, abs=0.02)
    assert 0.0 < plan_on.methods["robust"].in_focus_fraction <= plan_on.visible_fraction
    # Given samples are planned on as they are.
    given_samples = sample_surface(body, 1500, seed=4)
    assert len(plan_focus(body, on, points=given_samples, methods=("robust",)).samples) == 1500


@pytest.mark.parametrize("key, value", [("importance_density", 0.5), ("importance_views", 0),
                                        ("importance_radius_mm", -1.0)])
def test_importance_settings_are_checked(tmp_path, key: str, value: float) -> None:
    import yaml

    from planner.rig import DEFAULT_RIG_PATH, RigConfigError

    raw = yaml.safe_load(DEFAULT_RIG_PATH.read_text())
    raw["planner"][key] = value
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(raw))
    with pytest.raises(RigConfigError) as info:
        load_rig(path)
    assert info.value.key == f"planner.{key}"


@given(seed=st.integers(0, 10_000), count=st.integers(0, 12), radius=st.floats(5.0, 200.0))
@settings(max_examples=30, deadline=None)
def test_the_region_is_every_triangle_whose_centre_is_near_a_point(seed: int, count: int, radius: float) -> None:
    triangles = Triangles.of(_BODY)
    points = np.random.default_rng(seed).uniform(-300.0, 300.0, (count, 3)) + [0.0, 0.0, 900.0]
    centres = triangles.a + (triangles.ab + triangles.ac) / 3.0
    if count:
        near = (np.linalg.norm(centres[:, None, :] - points[None, :, :], axis=2) < radius).any(axis=1)
    else:
        near = np.zeros(len(centres), dtype=bool)
    assert np.array_equal(region_faces(triangles, points, radius), near)
