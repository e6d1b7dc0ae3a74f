"""Numba compilation for the planner's inner loops, imported only by processes that plan (numba's
import alone takes most of a second; the daemon's own process never needs it)."""

from __future__ import annotations

import numba
import structlog

log = structlog.get_logger(__name__)


def jit(func):  # type: ignore[no-untyped-def]
    """Compiled, cached where numba finds a writable cache directory (NUMBA_CACHE_DIR, the
    package's ``__pycache__`` or the user's cache), compiled in memory where it finds none."""
    try:
        return numba.njit(cache=True, nogil=True)(func)
    except RuntimeError as exc:  # "cannot cache function ...: no locator available"
        log.info("planner.no_compile_cache", reason=str(exc))
        return numba.njit(nogil=True)(func)
