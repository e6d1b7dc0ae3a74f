"""Importance samples: the skin few poses see, sampled finer, each sample standing for less.

Judged on fresh samples, a plan loses most where few poses see the skin (between an arm and
the chest, the inner thighs, under the chin): there, a pose is focused for what most of its
view holds, and the two or three planning samples in the fold decide whether any pose keeps it
sharp, so the plan fits those samples rather than the skin. More samples everywhere help, at a
cost in plan time that grows with them (docs/planner.md: 40,000 uniform samples take 4x).

Method: the area-uniform samples first, with their visibility. The triangles within
``radius_mm`` of a sample that 1 to ``few_views`` poses see form the region. Its uniform samples
are replaced by ``density`` times as many area-uniform samples of the region (fewer where the
planner's memory budget says so), together weighing what the region's share of the skin is
worth in uniform samples (each about 1 / density); the others keep weight 1. Every square
millimetre of skin still counts the same in K and in the in-focus share (the weights make the
estimate unbiased); the region's samples are just finer. Only the new samples are ray cast.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from planner.poses import Poses
from planner.rig import Optics
from planner.sampling import SurfaceSamples, Triangles, sample_surface
from planner.visibility import RayScene, Visibility, group_pointers, visible_pairs


@dataclass(frozen=True)
class Importance:
    """few_views: a sample seen by 1..few_views poses marks its neighbourhood; radius_mm: that
    neighbourhood; density: how many times finer the region is sampled (1: off)."""

    few_views: int
    radius_mm: float
    density: float

    @property
    def active(self) -> bool:
        return self.density > 1.0


def region_faces(triangles: Triangles, points: np.ndarray, radius_mm: float) -> np.ndarray:
    """(F,) bool: triangles whose centre lies within ``radius_mm`` of one of ``points`` (K, 3)."""
    from scipy.spatial import cKDTree

    if not len(points):
        return np.zeros(len(triangles), dtype=bool)
    centres = triangles.a + (triangles.ab + triangles.ac) / 3.0
    distance, _ = cKDTree(np.asarray(points, dtype=float)).query(centres, k=1, distance_upper_bound=radius_mm)
    result: np.ndarray = np.isfinite(distance)
    return result


def refine_samples(
    mesh: trimesh.Trimesh,
    triangles: Triangles,
    uniform: SurfaceSamples,
    vis: Visibility,
    scene: RayScene,
    poses: Poses,
    optics: Optics,
    importance: Importance,
    seed: int,
    max_samples: int | None = None,
) -> tuple[SurfaceSamples, Visibility]:
    """The weighted sample set and its visibility (see the module docstring).

    uniform: area-uniform samples of ``mesh`` with face indices; vis: their visibility from
    ``poses``; max_samples: the most samples the result may hold (the planner's memory budget:
    the region is then sampled less finely). Returns them unchanged when importance is off or
    no skin qualifies."""
    if not importance.active:
        return uniform, vis
    views = np.bincount(vis.point, minlength=vis.n_points)
    few = (views >= 1) & (views <= importance.few_views)
    region = region_faces(triangles, uniform.points[few], importance.radius_mm)
    doubled = triangles.doubled_areas
    share = float(doubled[region].sum() / doubled.sum()) if region.any() else 0.0
    keep = ~region[uniform.face_index]
    count = int(round(importance.density * share * len(uniform)))
    if max_samples is not None:
        count = min(count, max_samples - int(keep.sum()))
    if count <= len(uniform) - int(keep.sum()):
        return uniform, vis  # no finer than the uniform samples already there
    fine = sample_surface(mesh, count, seed=seed + 7_919, triangles=triangles, faces=region)
    fine_vis = visible_pairs(scene, poses, fine, optics)

    # Both sets ordered by height, as sample_surface gives them (the planner's memory locality).
    z = np.concatenate([uniform.points[keep, 2], fine.points[:, 2]])
    order = np.argsort(z, kind="stable")
    rank = np.empty(len(order), dtype=np.int64)
    rank[order] = np.arange(len(order))
    kept = np.flatnonzero(keep)
    new_of_uniform = np.full(len(uniform), -1, dtype=np.int64)
    new_of_uniform[kept] = rank[: len(kept)]
    new_of_fine = rank[len(kept):]

    def cat(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.concatenate([a, b])[order]

    weight = cat(np.ones(len(kept)), np.full(len(fine), share * len(uniform) / count))
    samples = SurfaceSamples(
        points=cat(uniform.points[keep], fine.points),
        normals=cat(uniform.normals[keep], fine.normals),
        face_index=cat(uniform.face_index[keep], fine.face_index),
        area_mm2=uniform.area_mm2,
        weight=weight,
    )
    return samples, _merged(vis, new_of_uniform, fine_vis, new_of_fine, len(samples))


def _merged(a: Visibility, new_a: np.ndarray, b: Visibility, new_b: np.ndarray, n_points: int) -> Visibility:
    """The pairs of ``a`` whose point is kept (new_a >= 0) and all of ``b``, renumbered, sorted by
    pose then point."""
    kept = new_a[a.point] >= 0
    pose = np.concatenate([a.pose[kept], b.pose])
    point = np.concatenate([new_a[a.point[kept]], new_b[b.point]])
    # Both sets are sorted by pose then point already: on one int64 key a stable sort (timsort)
    # merges the two runs in linear time, where lexsort took 0.85 s at 100,000 samples.
    order = np.argsort(pose.astype(np.int64) * n_points + point, kind="stable")
    return Visibility(
        n_poses=a.n_poses,
        n_points=n_points,
        pose=pose[order].astype(a.pose.dtype),
        point=point[order].astype(a.point.dtype),
        depth=np.concatenate([a.depth[kept], b.depth])[order],
        off_axis=np.concatenate([a.off_axis[kept], b.off_axis])[order],
        facing=np.concatenate([a.facing[kept], b.facing])[order],
        pose_ptr=group_pointers(pose, a.n_poses),
    )
