"""Errors of the focus planner: bad meshes, nothing to image, malformed focus plans."""

from __future__ import annotations


class FocusPlanError(ValueError):
    """Base of the focus planner's errors."""


class MeshLoadError(FocusPlanError):
    """A mesh file could not be read as a triangle mesh."""

    def __init__(self, path: str, problem: str) -> None:
        self.path = path
        self.problem = problem
        super().__init__(f"mesh {path}: {problem}")


class EmptyMesh(FocusPlanError):
    """The mesh has no faces or no surface area to sample."""

    def __init__(self, mesh: str, faces: int, area_mm2: float) -> None:
        self.mesh = mesh
        self.faces = faces
        self.area_mm2 = area_mm2
        super().__init__(f"mesh {mesh} is empty: {faces} faces, surface area {area_mm2:g} mm^2")


class NothingVisible(FocusPlanError):
    """No sample of the subject is seen by any camera pose: no subject in the rig's view."""

    def __init__(self, mesh: str, points: int, poses: int, bounds_mm: list[list[float]]) -> None:
        self.mesh = mesh
        self.points = points
        self.poses = poses
        self.bounds_mm = bounds_mm
        super().__init__(
            f"mesh {mesh}: none of {points} surface samples is visible from the {poses} camera "
            f"poses (mesh bounds {bounds_mm} mm); is the subject inside the ring?"
        )


class InvertedMesh(FocusPlanError):
    """The mesh's triangles wind inward (negative volume), so no surface faces the cameras."""

    def __init__(self, mesh: str, volume_mm3: float) -> None:
        self.mesh = mesh
        self.volume_mm3 = volume_mm3
        super().__init__(
            f"mesh {mesh} is wound inside out (signed volume {volume_mm3:.4g} mm^3): its normals "
            "point into the body; flip its faces"
        )


class BadFocusPlan(FocusPlanError):
    """A focus plan has the wrong length or a non-positive or non-finite distance."""

    def __init__(self, problem: str, expected_poses: int) -> None:
        self.problem = problem
        self.expected_poses = expected_poses
        super().__init__(f"focus plan for {expected_poses} poses: {problem}")
