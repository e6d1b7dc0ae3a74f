"""Carrying lesion marks from one scan of a person to a later one: mesh registration.

The person never stands exactly where they stood before, and sways a little. First the two
body meshes are aligned as a whole (Open3D point-to-plane ICP from the centroid offset at a
few turns about the vertical axis; the best fit wins), then every mark is refined on its own
neighbourhood (ICP on the skin within 300, 200, then 150 mm of the mark, measured along the
mesh so that the other leg is no neighbour, each fit starting from the last), so a limb that
moved a few degrees still carries its marks. Each fit's step is kept only along the directions
its patch holds the mark in (:func:`held_step`): along a limb's axis nothing does. The carried
point is snapped onto the later mesh, then, given both scans' pictures, moved along the skin to
where the skin looks the same (analysis/mark_match.py).

How far the snap moved it is kept (``surface_gap_mm``), with the local fit's rms residual: where
the later scan's surface is further from where the fit puts the skin than the two surfaces are
from each other around the mark (the residual, at least SURFACE_NOISE_MM), or further than
SURFACE_DOUBT_MM in any case, the later scan did not hold that skin as it held the skin around
(an occluded gap, between a wrist and a thigh, reconstructed inside the true skin), and the place
on its surface may not be the same skin point: the mark is in doubt and the viewer says so. It
is in doubt too where the two scans' surfaces, the earlier one moved by the mark's fit, lie
further apart than SURFACE_NOISE_MM around the mark (median over the skin within AROUND_MM of
it, ``surfaces_apart_mm``): there the skin changed shape between the visits, or one scan missed
it, and no rigid fit places the mark to the millimetre.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from analysis.mark_match import PictureMatcher


class RegistrationError(ValueError):
    """The two meshes do not overlap enough to be the same body."""


@dataclass(frozen=True)
class Registration:
    """A rigid map of the earlier scan onto the later one: transform (4, 4), points in mm."""

    transform: np.ndarray
    fitness: float
    rmse_mm: float

    def apply(self, points: np.ndarray) -> np.ndarray:
        points = np.asarray(points, dtype=float).reshape(-1, 3)
        return points @ self.transform[:3, :3].T + self.transform[:3, 3]


def _cloud(mesh: Any, voxel_mm: float) -> Any:
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(mesh.vertices, dtype=float)))
    cloud = cloud.voxel_down_sample(voxel_mm)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3 * voxel_mm, max_nn=30))
    return cloud


def _vertex_cloud(mesh: Any) -> Any:
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(mesh.vertices, dtype=float)))
    cloud.normals = o3d.utility.Vector3dVector(np.array(mesh.vertex_normals, dtype=float))
    return cloud


def _edge_graph(mesh: Any) -> Any:
    """(V, V) sparse graph of the mesh's edges weighted by length, mm."""
    from scipy.sparse import coo_matrix

    edges = np.asarray(mesh.edges_unique)
    length = np.asarray(mesh.edges_unique_length)
    n = len(mesh.vertices)
    # Coincident vertices (a seam kept unmerged) are one point of skin: join them.
    _, first = np.unique(np.round(np.asarray(mesh.vertices), 3), axis=0, return_inverse=True)
    rep = np.full(first.max() + 1, -1)
    rep[first[::-1]] = np.arange(n)[::-1]
    seam = np.flatnonzero(rep[first] != np.arange(n))
    rows = np.concatenate([edges[:, 0], seam])
    cols = np.concatenate([edges[:, 1], rep[first][seam]])
    weight = np.concatenate([length, np.full(len(seam), 1e-6)])
    return coo_matrix((weight, (rows, cols)), shape=(n, n)).tocsr()


def _yaw_about(centre: np.ndarray, yaw_deg: float, shift: np.ndarray) -> np.ndarray:
    a = np.radians(yaw_deg)
    rot = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = centre + shift - rot @ centre
    return out


def _icp(source: Any, target: Any, init: np.ndarray, distance_mm: float, iterations: int = 40) -> Any:
    import open3d as o3d

    reg = o3d.pipelines.registration
    return reg.registration_icp(source, target, distance_mm, init,
                                reg.TransformationEstimationPointToPlane(),
                                reg.ICPConvergenceCriteria(max_iteration=iterations))


def _evaluate(source: Any, target: Any, transform: np.ndarray, distance_mm: float) -> Any:
    import open3d as o3d

    return o3d.pipelines.registration.evaluate_registration(source, target, distance_mm, transform)


def held_step(before: np.ndarray, after: np.ndarray, point: np.ndarray, patch: np.ndarray, normals: np.ndarray,
              radius_mm: float, hold_share: float) -> np.ndarray:
    """(4, 4) the fit ``after`` with its step from ``before`` (both (4, 4)) kept only as far as the
    patch holds the mark along each direction: the step as a twist about the mark's place under
    ``before`` (rotation times ``radius_mm``, translation, both mm), its component along each
    eigenvector of the patch's point-to-plane normal matrix (points (N, 3) and unit normals (N, 3)
    on the earlier mesh, moved by ``before``) kept whole where the eigenvalue (the stiffness) is at
    least ``hold_share`` of the largest, scaled by the eigenvalue over that below it: a well-held step
    is kept, a step along a direction the patch cannot hold is not (degeneracy-aware
    registration, Zhang, Kaess and Singh 2016)."""
    from scipy.spatial.transform import Rotation

    rotation, shift = before[:3, :3], before[:3, 3]
    centre = rotation @ np.asarray(point, dtype=float).reshape(3) + shift
    p = patch @ rotation.T + shift
    n = normals @ rotation.T
    rows = np.hstack([np.cross(p - centre, n) / radius_mm, n])
    stiffness, axes = np.linalg.eigh(rows.T @ rows / max(len(rows), 1))
    step = after @ np.linalg.inv(before)
    twist = np.r_[Rotation.from_matrix(step[:3, :3]).as_rotvec() * radius_mm,
                  step[:3, :3] @ centre + step[:3, 3] - centre]
    keep = np.clip(stiffness / max(hold_share * float(stiffness.max()), 1e-12), 0.0, 1.0)
    twist = axes @ (keep * (axes.T @ twist))
    turn = Rotation.from_rotvec(twist[:3] / radius_mm).as_matrix()
    held = np.eye(4)
    held[:3, :3] = turn
    held[:3, 3] = centre + twist[3:] - turn @ centre
    return held @ before


class MarkCarrier:
    """Registers an earlier scan's mesh (source) onto a later one's (target) and carries points.

    voxel_mm: sampling of the whole-body fit; YAWS_DEG: the turns tried as starting points.
    """

    YAWS_DEG = (-40.0, -20.0, 0.0, 20.0, 40.0)
    MIN_FITNESS = 0.5
    SURFACE_DOUBT_MM = 3.0
    """A carried mark whose later surface is further than this from where the fit puts the skin
    is in doubt whatever the fit's residual (``./dev bench marks``, docs/web.md)."""
    SURFACE_NOISE_MM = 1.0
    """A gap under this is within any scan's surface noise: never doubt on its own. Two scans'
    surfaces further apart than this around a mark put it in doubt."""
    AROUND_MM = 30.0
    """The skin around a mark (along the skin) whose two surfaces are compared."""
    MAX_SWAY_MM = 80.0
    """A mark never moves further than this from where the whole-body fit puts it."""
    HOLD_SHARE = 0.02
    """A local fit moves the mark along a direction of its patch's point-to-plane problem only as
    far as the patch holds it there (:func:`held_step`): a direction whose stiffness is under this
    share of the stiffest keeps that fraction of the fit's step along it, a direction the patch does
    not hold at all (along a cylinder's axis) none. Without it, a fit on a nearly cylindrical patch
    can slide the mark along the axis, away from skin the later scan got wrong, to skin elsewhere,
    and the mark lands there not in doubt."""
    STAGES = ((300.0, 60.0), (200.0, 20.0), (150.0, 8.0))
    """(neighbourhood radius, correspondence distance) mm of the per-mark fits. Patches under
    about 150 mm are too flat (a back, a thigh) to hold the mark in place along the skin: on two
    simulated visits they doubled the error (web benchmark)."""

    def __init__(self, source_mesh: Any, target_mesh: Any, *, voxel_mm: float = 8.0) -> None:
        import open3d as o3d

        self.source_fine = _vertex_cloud(source_mesh)
        self._source_points = np.asarray(self.source_fine.points)
        self._source_normals = np.asarray(self.source_fine.normals)
        self.target_fine = _cloud(target_mesh, 3.0)
        self._source_tree = o3d.geometry.KDTreeFlann(self.source_fine)
        self._source_graph = _edge_graph(source_mesh)
        self._target_tree = o3d.geometry.KDTreeFlann(self.target_fine)
        legacy = o3d.t.geometry.TriangleMesh.from_legacy(o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(np.asarray(target_mesh.vertices, dtype=float)),
            o3d.utility.Vector3iVector(np.asarray(target_mesh.faces, dtype=np.int32))))
        self._target_scene = o3d.t.geometry.RaycastingScene()
        self._target_scene.add_triangles(legacy)
        self.whole = self._whole_body(_cloud(source_mesh, voxel_mm), _cloud(target_mesh, voxel_mm), voxel_mm)

    def _whole_body(self, source: Any, target: Any, voxel_mm: float) -> Registration:
        centre = np.asarray(source.get_center())
        shift = np.asarray(target.get_center()) - centre
        best = None
        for yaw in self.YAWS_DEG:
            fit = _icp(source, target, _yaw_about(centre, yaw, shift), 6 * voxel_mm)
            if best is None or (fit.fitness, -fit.inlier_rmse) > (best.fitness, -best.inlier_rmse):
                best = fit
        assert best is not None
        fine = _icp(source, target, best.transformation, 2 * voxel_mm)
        if fine.fitness < self.MIN_FITNESS:
            raise RegistrationError(
                f"the meshes overlap on {100 * fine.fitness:.0f} % of the earlier body after alignment "
                f"(needs {100 * self.MIN_FITNESS:.0f} %): not the same person, or a scan that missed most of the body")
        return Registration(np.asarray(fine.transformation), float(fine.fitness), float(fine.inlier_rmse))

    def _local(self, point: np.ndarray) -> tuple[Registration, np.ndarray]:
        """Coarse to fine on shrinking neighbourhoods of the mark, each stage from the last fit;
        and the earlier mesh's points within AROUND_MM of the mark along the skin."""
        from scipy.sparse.csgraph import dijkstra

        fit = self.whole
        _, seed, _ = self._source_tree.search_knn_vector_3d(point, 1)
        along = dijkstra(self._source_graph, directed=False, indices=int(seed[0]), limit=self.STAGES[0][0])
        for radius, distance in self.STAGES:
            near = np.flatnonzero(along <= radius)  # along the skin: the other leg is not a neighbour
            _, near_target, _ = self._target_tree.search_radius_vector_3d(fit.apply(point)[0], radius + distance)
            if len(near) < 30 or len(near_target) < 30:
                break
            source = self.source_fine.select_by_index(near.tolist())
            target = self.target_fine.select_by_index(list(near_target))
            result = _icp(source, target, fit.transform, distance)
            if result.fitness < self.MIN_FITNESS:
                break
            held = held_step(fit.transform, np.asarray(result.transformation), point, self._source_points[near],
                             self._source_normals[near], radius, self.HOLD_SHARE)
            result = _evaluate(source, target, held, distance)
            if result.fitness < self.MIN_FITNESS:
                break
            candidate = Registration(held, float(result.fitness), float(result.inlier_rmse))
            if np.linalg.norm(candidate.apply(point) - self.whole.apply(point)) > self.MAX_SWAY_MM:
                break  # slid onto another limb
            fit = candidate
        return fit, self._source_points[along <= self.AROUND_MM]

    def carry(self, points: np.ndarray, pictures: PictureMatcher | None = None) -> Carried:
        """(K, 3) points on the earlier mesh -> their places on the later mesh.

        With ``pictures`` (both scans' pictures), each carried point then moves along the skin
        to where the skin around it looks the same in both scans, when the pictures agree."""
        import open3d as o3d

        points = np.asarray(points, dtype=float).reshape(-1, 3)
        local = [self._local(point) for point in points]  # a handful of marks: one local fit each
        fits = [fit for fit, _ in local]
        moved = np.array([fit.apply(point)[0] for fit, point in zip(fits, points)]).reshape(-1, 3)
        around = [fit.apply(near) for fit, near in local]
        score = np.full(len(points), np.nan)
        apart = np.zeros(len(points))
        if len(points):
            queries = np.concatenate([moved, *around])
            closest = self._target_scene.compute_closest_points(
                o3d.core.Tensor(queries.astype(np.float32)))["points"].numpy().astype(float)
            distance = np.linalg.norm(closest - queries, axis=1)
            gap, moved = distance[:len(points)], closest[:len(points)]
            ends = np.cumsum([len(points)] + [len(near) for near in around])
            apart = np.array([np.median(distance[a:b]) if b > a else 0.0 for a, b in zip(ends[:-1], ends[1:])])
        else:
            gap = np.zeros(0)
        if pictures is not None:
            for k, (point, fit) in enumerate(zip(points, fits)):
                match = pictures.refine(point, moved[k], fit.transform[:3, :3])
                if match is not None:
                    moved[k], score[k] = match.point_mm, match.score
        return Carried(moved, np.array([fit.rmse_mm for fit in fits]), score, gap, apart)


@dataclass(frozen=True)
class Carried:
    """Points carried to the later mesh (K, 3) mm, the rmse of each one's local fit (K,) mm, the
    picture match's score (K,) where the pictures placed it (NaN: placed by the shapes), how far
    the later mesh is from where the fit put each point (K,) mm, and how far apart the two
    scans' surfaces are around it (median over AROUND_MM of skin, the earlier one moved by the
    point's fit; K,) mm."""

    points_mm: np.ndarray
    fit_rmse_mm: np.ndarray
    picture_score: np.ndarray
    surface_gap_mm: np.ndarray
    surfaces_apart_mm: np.ndarray

    @property
    def surface_departs(self) -> np.ndarray:
        """(K,) bool: the later scan's surface is further from the carried skin than the two
        surfaces are from each other around it (the local fit's rms residual, at least
        SURFACE_NOISE_MM, at most SURFACE_DOUBT_MM): it may not hold that skin."""
        limit = np.clip(self.fit_rmse_mm, MarkCarrier.SURFACE_NOISE_MM, MarkCarrier.SURFACE_DOUBT_MM)
        departs: np.ndarray = self.surface_gap_mm > limit
        return departs

    @property
    def surfaces_part(self) -> np.ndarray:
        """(K,) bool: the two surfaces around the point are further apart than SURFACE_NOISE_MM:
        the fit may not place it."""
        part: np.ndarray = self.surfaces_apart_mm > MarkCarrier.SURFACE_NOISE_MM
        return part

    @property
    def in_doubt(self) -> np.ndarray:
        """(K,) bool: either of the above."""
        doubt: np.ndarray = self.surface_departs | self.surfaces_part
        return doubt
