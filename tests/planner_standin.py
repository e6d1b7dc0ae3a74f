"""A human-sized stand-in body for planner tests when the body model is not needed.

Disjoint watertight pieces (legs, torso, arms, head) about 1.72 m tall, feet on z = 0, facing
+x, centred on the z axis. Pieces do not overlap, so every triangle is outer skin.
"""

from __future__ import annotations

import numpy as np
import trimesh


def _capsule(radius: float, z0: float, z1: float, y: float = 0.0, x_scale: float = 1.0) -> trimesh.Trimesh:
    piece = trimesh.creation.capsule(height=z1 - z0 - 2 * radius, radius=radius, count=[24, 12])
    piece.apply_scale([x_scale, 1.0, 1.0])
    piece.apply_translation([0.0, y, (z0 + z1) / 2 - piece.bounds.mean(axis=0)[2]])
    return piece


def standin_body(scale: float = 1.0) -> trimesh.Trimesh:
    """(mm) A stand-in standing human: union of disjoint capsules and a sphere."""
    pieces = [
        _capsule(70.0, 0.0, 860.0, y=-95.0),
        _capsule(70.0, 0.0, 860.0, y=95.0),
        _capsule(160.0, 880.0, 1480.0, x_scale=0.65),
        _capsule(42.0, 820.0, 1440.0, y=-215.0),
        _capsule(42.0, 820.0, 1440.0, y=215.0),
    ]
    head = trimesh.creation.icosphere(subdivisions=3, radius=95.0)
    head.apply_translation([0.0, 0.0, 1625.0])
    pieces.append(head)
    body = trimesh.util.concatenate(pieces)
    body.apply_scale(scale)
    return body


def sphere(radius: float = 200.0, centre: tuple[float, float, float] = (0.0, 0.0, 960.0)) -> trimesh.Trimesh:
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=radius)
    mesh.apply_translation(np.asarray(centre))
    return mesh
