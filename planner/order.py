"""A stable sort order at the speed of NumPy's vectorised quicksort.

NumPy sorts floats and 32/64-bit integers with SIMD quicksort (x86-simd-sort, highway) when
``kind`` is left at its default, about three times as fast as ``kind="stable"`` (a timsort for
these types). The planner needs stable orders (interval starts before ends at equal
coordinates, reproducible plans), but exact ties are rare in its data: sorting with the fast
kind and then putting each run of equal values back in index order gives the stable order
itself, whatever order the quicksort left the ties in.
"""

from __future__ import annotations

import numpy as np


def stable_argsort(values: np.ndarray) -> np.ndarray:
    """(n,) int64: exactly ``np.argsort(values, kind="stable")`` for a 1-D array without NaN."""
    values = np.asarray(values)
    order = np.argsort(values)
    if len(order) < 2:
        return order
    ranked = values[order]
    tied = ranked[1:] == ranked[:-1]
    if not tied.any():
        return order
    # Positions inside runs of equal values; each run gets its index order back.
    in_run = np.zeros(len(order), dtype=bool)
    in_run[1:] |= tied
    in_run[:-1] |= tied
    where = np.flatnonzero(in_run)
    run = np.cumsum(np.r_[True, ~tied])[where]
    original = order[where]
    order[where] = original[np.lexsort((original, run))]
    return order
