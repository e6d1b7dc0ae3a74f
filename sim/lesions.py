"""The lesion changes of a simulated follow-up visit on one subject's skin: the truth a test or a
benchmark compares with.

``drivers/sim/skin_texture.py`` decides the changes cell by cell over all of skin space; a body
shows those whose spot meets its skin. Here that is every changed spot of a cell the skin
passes through whose ball (its radius after the change) reaches the skin surface.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from drivers.sim.skin_texture import NAEVI, ChangedSpots, LesionChanges, changed_spots

SAMPLE_MM = 2.0
"""Spacing of the skin samples that find the cells the skin passes through (under a cell's side,
so the samples' cells and their neighbours hold every such cell)."""


def skin_surface(subject: Any) -> tuple[np.ndarray, np.ndarray]:
    """The subject's skin as a surface in skin coordinates: vertices (V, 3) mm and faces (F, 3)."""
    skin = getattr(subject, "vertex_attributes", {}).get("skin_mm")
    vertices = np.asarray(subject.vertices if skin is None else skin, dtype=np.float32)
    return vertices, np.asarray(subject.faces, dtype=np.int64)


def changed_lesions(subject: Any, changes: LesionChanges, seed: int = 0) -> ChangedSpots:
    """The spots ``changes`` grows or makes appear on the skin of ``subject`` (a mesh, with
    ``vertex_attributes["skin_mm"]`` when it has skin coordinates)."""
    import open3d as o3d  # seconds to import: only where the truth is asked for

    vertices, faces = skin_surface(subject)
    corners = vertices[faces]  # (F, 3, 3)
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    rng = np.random.default_rng(0)
    count = np.ceil(area / SAMPLE_MM**2).astype(np.int64) + 1
    which = np.repeat(np.arange(len(faces)), count)
    ab = rng.random((len(which), 2))
    ab = np.where(ab.sum(axis=1, keepdims=True) > 1.0, 1.0 - ab, ab)
    c = corners[which]
    samples = c[:, 0] + ab[:, :1] * (c[:, 1] - c[:, 0]) + ab[:, 1:] * (c[:, 2] - c[:, 0])
    cells = np.unique(np.floor(np.concatenate([samples, vertices]) / NAEVI.cell_mm).astype(np.int64), axis=0)
    around = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    cells = np.unique((cells[:, None, :] + around[None]).reshape(-1, 3), axis=0)
    _, spots = changed_spots(cells, changes, seed)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices), o3d.core.Tensor(faces.astype(np.uint32)))
    distance = scene.compute_distance(o3d.core.Tensor(spots.centre_mm.astype(np.float32))).numpy()
    return spots.rows(distance < spots.radius_after_mm)
