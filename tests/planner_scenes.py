"""Small analytic scenes for planner tests: single cameras and simple meshes."""

from __future__ import annotations

import numpy as np
import trimesh

from planner.poses import Poses


def looking_at(centres: np.ndarray, targets: np.ndarray) -> Poses:
    """Poses at centres (P, 3) looking at targets (P, 3), image x horizontal (world z is up)."""
    centres = np.asarray(centres, dtype=float).reshape(-1, 3)
    forward = np.asarray(targets, dtype=float).reshape(-1, 3) - centres
    forward /= np.linalg.norm(forward, axis=1, keepdims=True)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    down = np.cross(forward, right)
    n = len(centres)
    return Poses(centres, forward, right, down, np.zeros(n, dtype=int), np.arange(n))


def square(size: float, x: float, z: float = 0.0) -> trimesh.Trimesh:
    """A square in the plane at ``x``, facing +x (outward normal +x), centred at (x, 0, z)."""
    h = size / 2
    vertices = np.array([[x, -h, z - h], [x, h, z - h], [x, h, z + h], [x, -h, z + h]])
    mesh = trimesh.Trimesh(vertices, [[0, 1, 2], [0, 2, 3]], process=False)
    if mesh.face_normals[0, 0] < 0:
        mesh.invert()
    return mesh
