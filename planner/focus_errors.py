"""Errors of the focus planner: bad meshes, nothing to image, malformed focus plans."""

from __future__ import annotations

from planner.picklable import PicklableError


class FocusPlanError(PicklableError, ValueError):
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


class SubjectOutsideRing(FocusPlanError):
    """A mesh vertex is not finite or lies beyond the camera ring: not a subject inside this rig
    (a stray vertex, or a mesh in other units than mm)."""

    def __init__(self, mesh: str, vertex: int, position_mm: tuple[float, float, float], ring_radius_mm: float) -> None:
        self.mesh = mesh
        self.vertex = vertex
        self.position_mm = position_mm
        self.ring_radius_mm = ring_radius_mm
        where = ", ".join(f"{v:.6g}" for v in position_mm)
        super().__init__(
            f"mesh {mesh}: vertex {vertex} at ({where}) mm lies outside the camera ring (radius "
            f"{ring_radius_mm:g} mm around the rotation axis); the subject must stand inside the ring, in mm"
        )


class PlanTooLarge(FocusPlanError):
    """Planning this many samples for this many poses would need more memory than the budget."""

    def __init__(self, points: int, poses: int, need_bytes: int, budget_bytes: int) -> None:
        self.points = points
        self.poses = poses
        self.need_bytes = need_bytes
        self.budget_bytes = budget_bytes
        super().__init__(
            f"{points} samples x {poses} poses need about {need_bytes / 1024**3:.1f} GiB to plan, more than "
            f"the {budget_bytes / 1024**3:g} GiB budget"
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
