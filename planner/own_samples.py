"""The compiled per-group step of the group moves (``planner/group_moves.py``): a group's own
samples and their focus intervals.

A group's own samples are those seen by one of its poses that no pose outside the group holds
sharp. At 100,000 samples a group's poses see 30,000 pairs, and finding the few hundred own
samples among them with NumPy (gathers, a mark array, bincounts over every pair) took 0.8 s of
the plan over the 1,100 groups visited; here it is a few passes over the group's pairs (0.2 s).
"""

from __future__ import annotations

import numpy as np

from planner.jit import jit


@jit
def own_samples(members, pose_ptr, point, lo, hi, focus, held, count, column):  # type: ignore[no-untyped-def]
    """(own (n,) int64 ascending, lo (k, n), hi (k, n)): the samples seen by one of the k poses in
    ``members`` that only they hold sharp (``held``: (N,) sharp views per sample under ``focus``),
    and each member's focus interval of each of them (nan where it does not see one).

    ``count`` (N,) int64 zeros and ``column`` (N,) int64 of -1: scratch, returned as found."""
    k = len(members)
    seen = 0
    for r in range(k):
        c = members[r]
        seen += pose_ptr[c + 1] - pose_ptr[c]
        s = focus[c]
        for i in range(pose_ptr[c], pose_ptr[c + 1]):
            if lo[i] <= s and s <= hi[i]:
                count[point[i]] += 1
    candidates = np.empty(seen, dtype=np.int64)
    n = 0
    for r in range(k):
        c = members[r]
        for i in range(pose_ptr[c], pose_ptr[c + 1]):
            p = point[i]
            if column[p] == -1:
                column[p] = -2  # looked at
                if held[p] == count[p]:
                    candidates[n] = p
                    n += 1
    own = np.sort(candidates[:n])
    for j in range(n):
        column[own[j]] = j
    own_lo = np.full((k, n), np.nan)
    own_hi = np.full((k, n), np.nan)
    for r in range(k):
        c = members[r]
        for i in range(pose_ptr[c], pose_ptr[c + 1]):
            p = point[i]
            count[p] = 0
            j = column[p]
            if j >= 0:
                own_lo[r, j] = lo[i]
                own_hi[r, j] = hi[i]
    for r in range(k):
        c = members[r]
        for i in range(pose_ptr[c], pose_ptr[c + 1]):
            column[point[i]] = -1
    return own, own_lo, own_hi
