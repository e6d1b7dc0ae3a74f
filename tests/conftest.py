"""Shared test set-up."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import structlog


@pytest.fixture(autouse=True)
def _structlog_defaults() -> Iterator[None]:
    """A CLI run in-process binds structlog to pytest's captured stdout, which closes after the
    test; put the defaults back so later tests never log into a closed stream."""
    yield
    structlog.reset_defaults()
