"""Exposure matching between a scan's images: a gain per image and a light falloff curve over
the angle of incidence, fitted where images overlap on the skin.

A pixel's value is the skin's colour times its image's gain times the light's falloff with the
incidence c = cos(angle between the camera's ray and the skin's normal): the rig lights the skin
from beside the cameras, so skin seen obliquely is darker in every image. Both are fitted by
weighted least squares on log values, each texel's samples against its highest-weight sample:
log v_a - log v_b = g[pose a] - g[pose b] + f(c_a) - f(c_b), with f piecewise linear over
FALLOFF_KNOTS incidences, f(1) = 0 (head-on skin shows its colour), the log gains' mean at zero,
a weak pull of every gain towards 1 and of the curve towards a straight line. Equations whose
residual is more than ROBUST_MADS median absolute deviations out (a sample at an occluding edge
mixing in what lies behind) are dropped and the fit repeated once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse

#: Incidences (cos) at which the falloff curve is a free value (linear in between).
FALLOFF_KNOTS = np.linspace(0.0, 1.0, 9)
#: Pixel values outside this range (background, clipped highlights) are not fitted.
VALUE_RANGE = (12.0, 245.0)
#: Pull of every log gain towards zero and of the curve's second differences towards zero,
#: relative to the mean weight of an unknown's equations.
PRIOR = 0.1
ROBUST_MADS = 4.0
#: Skin seen more obliquely is corrected as if seen at this incidence (cos): a grazing view's
#: few photons are not multiplied into a glare.
LOWEST_INCIDENCE = 0.25
#: Equations fitted at most (a random subset of the overlaps, fixed seed).
MAX_EQUATIONS = 300_000


@dataclass(frozen=True)
class Exposure:
    """gains (P, C) per pose and channel; falloff (S,) log factor at FALLOFF_KNOTS (0 at 1)."""

    gains: np.ndarray
    falloff: np.ndarray

    def factor(self, pose: np.ndarray, incidence: np.ndarray) -> np.ndarray:
        """(K, C) what each sample's value is its skin's colour times (incidences below
        LOWEST_INCIDENCE taken as that)."""
        curve = np.exp(np.interp(np.clip(incidence, LOWEST_INCIDENCE, 1.0), FALLOFF_KNOTS, self.falloff))
        return self.gains[pose] * curve[:, None]


def _knot_weights(incidence: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hat-function weights of incidences (K,) on the knots: (K,) lower knot, (K,) upper, (K,) upper's weight."""
    c = np.clip(incidence, 0.0, 1.0) * (len(FALLOFF_KNOTS) - 1)
    low = np.minimum(np.floor(c).astype(np.int64), len(FALLOFF_KNOTS) - 2)
    return low, low + 1, c - low


def fit_exposure(texel: np.ndarray, pose: np.ndarray, incidence: np.ndarray, colour: np.ndarray,
                 weight: np.ndarray, n_poses: int) -> Exposure:
    """The gains and falloff (see the module docstring) from samples: texel (K,), pose (K,),
    incidence (K,) cos, colour (K, C) 0..255, weight (K,) blend weight."""
    channels = colour.shape[1]
    knots = len(FALLOFF_KNOTS)
    usable = np.all((colour > VALUE_RANGE[0]) & (colour < VALUE_RANGE[1]), axis=1) & (weight > 0)
    idx = np.flatnonzero(usable)
    order = idx if _grouped_heaviest_first(texel[idx], weight[idx]) else idx[np.lexsort((-weight[idx], texel[idx]))]
    t = texel[order]
    head = np.r_[True, t[1:] != t[:-1]]
    anchor = order[np.maximum.accumulate(np.where(head, np.arange(len(order)), 0))]
    a, b = order[~head], anchor[~head]
    if len(a) > MAX_EQUATIONS:  # plenty for P + S unknowns; the fit's time stays bounded
        pick = np.sort(np.random.default_rng(0).choice(len(a), MAX_EQUATIONS, replace=False))
        a, b = a[pick], b[pick]
    if not len(a):
        return Exposure(np.ones((n_poses, channels)), np.zeros(knots))
    # oblique samples say least (noisy normals, the falloff steepest there)
    w = np.minimum(weight[a], weight[b]) * np.clip(np.minimum(incidence[a], incidence[b]), 0.05, 1.0) ** 2
    n = n_poses + knots
    eq = np.arange(len(a))
    la, ua, fa = _knot_weights(incidence[a])
    lb, ub, fb = _knot_weights(incidence[b])
    rows = np.concatenate([eq, eq, eq, eq, eq, eq])
    cols = np.concatenate([pose[a], pose[b], n_poses + la, n_poses + ua, n_poses + lb, n_poses + ub])
    vals = np.concatenate([np.ones(len(a)), -np.ones(len(a)), 1 - fa, fa, -(1 - fb), -fb])
    design = sparse.csr_matrix((vals, (rows, cols)), shape=(len(a), n))
    diff = np.log(colour[a].astype(float)) - np.log(colour[b].astype(float))  # (E, C)
    keep = np.ones(len(a), dtype=bool)
    for _ in range(2):
        solution = _solve(design[keep], w[keep], diff[keep], n_poses, knots)
        residual = (design @ solution - diff).mean(axis=1)
        spread = np.median(np.abs(residual - np.median(residual))) + 1e-9
        keep = np.abs(residual - np.median(residual)) <= ROBUST_MADS * spread
    return Exposure(np.exp(solution[:n_poses]), solution[n_poses:].mean(axis=1))


def _grouped_heaviest_first(texel: np.ndarray, weight: np.ndarray) -> bool:
    """Samples (K,) already in texel order, heaviest first within a texel (as
    analysis.texel_views gives them): sorting them again would change nothing."""
    rises = texel[1:] > texel[:-1]
    return bool(np.all(rises | ((texel[1:] == texel[:-1]) & (weight[1:] <= weight[:-1]))))


def _solve(design: sparse.csr_matrix, w: np.ndarray, diff: np.ndarray, n_poses: int, knots: int) -> np.ndarray:
    """(P + S, C) least-squares unknowns with the priors and constraints of the module docstring."""
    n = n_poses + knots
    normal = (design.T @ sparse.diags(w) @ design).toarray()
    rhs = design.T @ (w[:, None] * diff)
    scale = max(float(np.trace(normal)) / n, 1e-9)
    normal[:n_poses, :n_poses] += PRIOR * scale * np.eye(n_poses) + scale * np.ones((n_poses, n_poses)) / n_poses
    second = np.zeros((knots - 2, n))
    for k in range(knots - 2):
        second[k, n_poses + k:n_poses + k + 3] = (1.0, -2.0, 1.0)
    normal += PRIOR * scale * second.T @ second
    head_on = np.zeros(n)
    head_on[n - 1] = 1.0  # f(1) = 0
    normal += scale * np.outer(head_on, head_on)
    return np.linalg.solve(normal, rhs)
