"""The compiled loop of the exact block-coordinate descent (``planner/refine.py`` explains it).

One pose's step is a few dozen operations per visible pair; as NumPy calls, each step paid
twenty-odd calls' overhead on arrays of a thousand pairs, and the descent (about 700 steps on a
body) took 0.15 s of the 1 s between the depth sweep and the capture. Numba compiles the loop
once per process (cached on disk where the cache directory is writable; the daemon's worker
compiles or loads it at start-up, before the first scan).

Arrays are grouped by pose (``vis.pose_ptr``) unless named otherwise; every update is made in
place on the state arrays the caller passes.
"""

from __future__ import annotations

import numpy as np

from planner.cost import INVISIBLE_COST
from planner.jit import jit


@jit
def _refresh_point(p, order, point_ptr, pair_cost, best, second, best_pair, invisible):  # type: ignore[no-untyped-def]
    """Point p's best and second-best pair cost (capped at ``invisible``) and its best pair (the
    first lowest in point order) from pair_cost; True when any of the three changed."""
    lowest = np.inf
    lowest_pair = -1
    for j in range(point_ptr[p], point_ptr[p + 1]):
        cost = pair_cost[order[j]]
        if cost < lowest:
            lowest = cost
            lowest_pair = order[j]
    runner_up = np.inf
    for j in range(point_ptr[p], point_ptr[p + 1]):
        pair = order[j]
        if pair != lowest_pair and pair_cost[pair] < runner_up:
            runner_up = pair_cost[pair]
    return _store(p, min(lowest, invisible), min(runner_up, invisible), lowest_pair, best, second, best_pair)


@jit
def _store(p, b, s, bp, best, second, best_pair):  # type: ignore[no-untyped-def]
    """Set point p's best and second-best cost and best pair; True when any of them changed."""
    changed = b != best[p] or s != second[p] or bp != best_pair[p]
    best[p] = b
    second[p] = s
    best_pair[p] = bp
    return changed


@jit
def lowest_pairs(seen_points, point_ptr, order, pose, base, lo, hi, focus, w_focus):  # type: ignore[no-untyped-def]
    """Each of ``seen_points``' lowest pair cost under ``focus`` and that pair (the first lowest
    in point order, as ``CostTable.assignment``); pose, base, lo, hi in point order
    (``CostTable.by_point``). EM's assignment step: at 100,000 samples NumPy's gathers and
    reductions over 3 million pairs took 0.1 s a step."""
    n = len(seen_points)
    best_pair = np.empty(n, dtype=np.int64)
    lowest = np.empty(n)
    for i in range(n):
        p = seen_points[i]
        low = np.inf
        pair = -1
        for j in range(point_ptr[p], point_ptr[p + 1]):
            s = focus[pose[j]]
            cost = base[j] if lo[j] <= s and s <= hi[j] else base[j] + w_focus
            if cost < low:
                low = cost
                pair = order[j]
        best_pair[i] = pair
        lowest[i] = low
    return best_pair, lowest


@jit
def init_point_best(order, point_ptr, pair_cost, best, second, best_pair, invisible):  # type: ignore[no-untyped-def]
    """Every seen point's best and second-best cost and best pair, from scratch."""
    for p in range(len(point_ptr) - 1):
        if point_ptr[p + 1] > point_ptr[p]:
            _refresh_point(p, order, point_ptr, pair_cost, best, second, best_pair, invisible)


@jit
def _pair_changed(i, p, old, order, point_ptr, pair_cost, best, second, best_pair, invisible):  # type: ignore[no-untyped-def]
    """Pair i (of point p) changed cost from ``old`` to pair_cost[i]: update p's best and second
    in O(1) where that is exact (a cost fell, or a pair that was neither best nor second rose),
    else refresh p. True when p's best, second or best pair changed."""
    new = min(pair_cost[i], invisible)
    old = min(old, invisible)
    b, s, bp = best[p], second[p], best_pair[p]
    is_best = bp == i
    fell = new < old
    rose = new > old
    if rose and ((new > s) if is_best else (old <= s)):
        return _refresh_point(p, order, point_ptr, pair_cost, best, second, best_pair, invisible)
    if is_best:
        nb, ns, nbp = (new if (fell or rose) else b), s, bp
    elif fell and new < b:
        nb, ns, nbp = new, b, i
    elif fell:
        nb, ns, nbp = b, min(s, new), bp
    else:
        nb, ns, nbp = b, s, bp
    return _store(p, nb, ns, nbp, best, second, best_pair)


@jit
def _best_cell(c, gain, end_ptr, end, pose_ptr, lo, hi, running):  # type: ignore[no-untyped-def]
    """(s, score) of pose c's best cell under per-pair ``gain`` (the pose's pairs in order), as
    ``PresortedIntervals.sweep``: the first maximum of the running sum, widened over the cells
    of equal score that follow it, at the diopter midpoint. ``end``: the pose's sorted ends, a
    lower end as its pair's index in the pose, an upper end as ~index."""
    e0, e1 = end_ptr[c], end_ptr[c + 1]
    total = 0.0
    top = -np.inf
    k = 0
    for j in range(e0, e1 - 1):  # the last end closes every interval: no cell starts there
        e = end[j]
        if e >= 0:
            total += gain[e]
        else:
            total -= gain[~e]
        running[j - e0] = total
        if total > top:
            top = total
            k = j - e0
    n = e1 - e0 - 1
    tolerance = 1e-12 * max(1.0, abs(top))
    j = k
    while j < n and not running[j] < top - tolerance:
        j += 1
    a = pose_ptr[c]
    e, f = end[e0 + k], end[e0 + j]
    left = lo[a + e] if e >= 0 else hi[a + ~e]
    right = lo[a + f] if f >= 0 else hi[a + ~f]
    if np.isinf(right):
        return 2.0 * left, top
    s = 2.0 * left * right / (left + right) if left + right > 0 else left
    return min(max(s, left), right), top


@jit
def descend(pose_ptr, point, base, lo, hi, w_focus, order, point_ptr,  # type: ignore[no-untyped-def]
            end_ptr, end, focus, sharp_pair, pair_cost,
            best, second, best_pair, sharp_views, extra, redundancy, weight, max_sweeps, min_gain):
    """Visit every pose one of whose points changed since its last look, in pose order, pass
    after pass, moving its focus to the exact best cell when K (plus the redundancy term) drops by
    more than ``min_gain``; each point's gains count with its ``weight``. Returns (passes,
    accepted moves)."""
    invisible = INVISIBLE_COST
    n_poses = len(pose_ptr) - 1
    widest = 0
    for c in range(n_poses):
        widest = max(widest, pose_ptr[c + 1] - pose_ptr[c])
    gain = np.empty(widest)
    running = np.empty(2 * widest)
    changed_at = np.zeros(len(point_ptr) - 1, dtype=np.int64)
    looked_at = np.full(n_poses, -1, dtype=np.int64)
    dirty = np.zeros(n_poses, dtype=np.bool_)
    step = 0
    sweeps = 0
    updates = 0
    while sweeps < max_sweeps:
        any_dirty = False
        for c in range(n_poses):
            latest = -1
            for i in range(pose_ptr[c], pose_ptr[c + 1]):
                latest = max(latest, changed_at[point[i]])
            dirty[c] = pose_ptr[c + 1] > pose_ptr[c] and latest > looked_at[c]
            any_dirty = any_dirty or dirty[c]
        if not any_dirty:
            break
        sweeps += 1
        changed_any = False
        for c in range(n_poses):
            if not dirty[c]:
                continue
            step += 1
            looked_at[c] = step
            a, b = pose_ptr[c], pose_ptr[c + 1]
            possible = 0.0
            current = 0.0
            for i in range(a, b):
                p = point[i]
                other = second[p] if best_pair[p] == i else best[p]
                g = max(min(other, base[i] + w_focus) - base[i], 0.0)
                if redundancy:
                    g += extra[sharp_views[p] - sharp_pair[i]]
                g *= weight[p]
                gain[i - a] = g
                possible += g
                if sharp_pair[i]:
                    current += g
            if not possible - current > min_gain:
                continue  # everything this pose could gain is already in focus
            s, score = _best_cell(c, gain, end_ptr, end, pose_ptr, lo, hi, running)
            if score <= current + min_gain:
                continue
            focus[c] = s
            updates += 1
            changed_any = True
            for i in range(a, b):
                now = lo[i] <= s <= hi[i]
                if now == sharp_pair[i]:
                    continue
                p = point[i]
                sharp_pair[i] = now
                sharp_views[p] += 1 if now else -1
                old = pair_cost[i]
                pair_cost[i] = base[i] if now else base[i] + w_focus
                # this pose's own changes are not newer than its look
                if _pair_changed(i, p, old, order, point_ptr, pair_cost, best, second, best_pair, invisible) \
                        or redundancy:
                    changed_at[p] = step
        if not changed_any:
            break
    return sweeps, updates

