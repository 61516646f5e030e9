"""Hypothesis generators of the non-rigid mode (section 5.1): growth, coarse-to-fine, anneal.

Each generator turns a start (voted seeds, the identity, a rigid motion, or
nothing) into one-to-one ``(source row, target row)`` matches; the
verification of :mod:`gatv.nonrigid.stages` then decides which start, if
any, beats chance.  Everything here works on plain arrays: ``X`` the source
points, ``Y`` the target points, ``tree_y`` a :class:`scipy.spatial.cKDTree`
of ``Y``.

* :func:`grow_rings` and :func:`polish` grow voted seeds (the *voting*
  hypothesis) and the winning hypothesis: local affine prediction ring by
  ring, then a thin-plate warp refitted until the matches repeat (the
  non-rigid analogue of the rigid mode's ICP polish).
* :func:`coarse_to_fine` matches every source point under a thin-plate
  warp whose gate and smoothing shrink level by level (the *coarse* and
  *rigid* hypotheses), from the identity or a rigid motion.
* :func:`anneal` is a deterministic-annealing soft matching with an
  outlier class (the *anneal* hypothesis), for displacements of several
  spacings among many outliers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from ..candidates import one_to_one
from .motion import ThinPlateWarp

__all__ = [
    "ANNEAL_CONTROL",
    "ANNEAL_LAMBDA",
    "ANNEAL_MAX_POINTS",
    "ANNEAL_OUTLIER",
    "ANNEAL_RATE",
    "ANNEAL_STEPS",
    "COARSE_TO_FINE",
    "Matches",
    "affine_residuals",
    "anneal",
    "coarse_to_fine",
    "farthest_points",
    "grow_rings",
    "local_affine_predict",
    "match_nearest",
    "polish",
    "window_centres",
]

#: Gate (times the target scale) and relative smoothing (times extent²) of
#: the coarse-to-fine levels of :func:`coarse_to_fine`: 3 → 0.5 spacings,
#: 10⁻¹ → 10⁻⁵ extent².
COARSE_TO_FINE = ((3.0, 1e-1), (2.0, 3e-2), (1.5, 1e-2), (1.0, 3e-3), (0.7, 1e-3), (0.5, 1e-4),
                  (0.5, 1e-5))

#: Annealed soft matching (:func:`anneal`): at most this many points of each
#: set enter the dense soft-assignment matrix (a seeded subsample beyond).
ANNEAL_MAX_POINTS = 1500
#: ... kernel centres of its smooth displacement field (farthest-point sample).
ANNEAL_CONTROL = 200
#: Temperature ratio between levels, EM steps per level, motion-coherence weight
#: (CPD's λ), and outlier mass (times the 75th percentile of the source rows' mass).
ANNEAL_RATE, ANNEAL_STEPS, ANNEAL_LAMBDA, ANNEAL_OUTLIER = 0.8, 2, 2.0, 0.2

_NO_PAIRS = np.empty((0, 2), np.int64)


# ------------------------------------------------------------ local geometry
def affine_residuals(points, displacements, k: int = 8) -> np.ndarray:
    """Distance of each displacement from the affine trend of its ``k`` nearest neighbours.

    A locally rigid (or smooth) motion is locally affine: a match whose
    displacement ``D[a]`` is far from the affine map fitted (least squares,
    leave-one-out) on its neighbours' displacements is suspect.  With 4
    points or fewer there is no trend to test and every residual is 0.
    """
    n = points.shape[0]
    if n <= 4:
        return np.zeros(n)
    kk = min(k + 1, n)
    _, nb = cKDTree(points).query(points, k=kk)
    res = np.empty(n)
    for a in range(n):
        others = nb[a, 1:]
        dx = points[others] - points[a]
        M = np.column_stack([np.ones(len(others)), dx])
        coef, *_ = np.linalg.lstsq(M, displacements[others], rcond=None)
        res[a] = np.linalg.norm(coef[0] - displacements[a])
    return res


def local_affine_predict(xs, ys, tree_s, near, query, neighbours: int) -> np.ndarray:
    """Move ``query[r]`` by the affine map fitted on the ``neighbours`` matches nearest ``xs[near[r]]``."""
    out = np.empty_like(query)
    m = min(neighbours, xs.shape[0])
    for a in np.unique(near):
        rows = np.flatnonzero(near == a)
        _, nb = tree_s.query(xs[a], k=m)
        nb = np.atleast_1d(nb)
        M = np.column_stack([np.ones(nb.size), xs[nb] - xs[a]])
        coef, *_ = np.linalg.lstsq(M, ys[nb], rcond=None)
        out[rows] = coef[0] + (query[rows] - xs[a]) @ coef[1:]
    return out


@dataclass(frozen=True, eq=False)
class Matches:
    """One-to-one nearest-target matches of moved source points (:func:`match_nearest`).

    Attributes
    ----------
    pairs : (K, 2) ndarray of int
        ``(source row, target row)``, sorted by source row.
    n_within : int
        Source points that had a target within the gate before the
        one-to-one selection.
    """

    pairs: np.ndarray
    n_within: int


def match_nearest(moved, tree_y, gate: float) -> Matches:
    """Nearest target of each moved source point within ``gate``, made one-to-one (closest first)."""
    dist, j = tree_y.query(moved, k=1, distance_upper_bound=gate)
    ok = np.flatnonzero(np.isfinite(dist))
    cand = np.stack([ok, j[ok]], axis=1).astype(np.int64)
    if ok.size == 0:
        return Matches(cand, 0)
    new = cand[one_to_one(cand, dist[ok])]
    return Matches(new[np.argsort(new[:, 0], kind="stable")], int(ok.size))


# ------------------------------------------------------------ growth
def grow_rings(X, Y, tree_y, seeds, gate: float, neighbours: int, max_rounds: int = 200) -> np.ndarray:
    """Grow matches ring by ring with the local affine maps of the matched region.

    An unmatched source point next to the matched region (its nearest
    matched source point within 3 matched spacings) is moved by the affine
    map fitted on that neighbour's ``neighbours`` nearest matches; the target
    nearest to the prediction, within ``gate``, is its candidate.  Each ring
    is made one-to-one (closest first, unused targets only).  Returns the
    grown pairs sorted by source row.
    """
    pairs = seeds
    used_t = np.zeros(Y.shape[0], bool)
    used_t[pairs[:, 1]] = True
    used_s = np.zeros(X.shape[0], bool)
    used_s[pairs[:, 0]] = True
    for _ in range(max_rounds):
        xs, ys = X[pairs[:, 0]], Y[pairs[:, 1]]
        tree_s = cKDTree(xs)
        step = 3.0 * float(np.median(tree_s.query(xs, k=2)[0][:, 1]))
        free = np.flatnonzero(~used_s)
        if free.size == 0:
            break
        dist, near = tree_s.query(X[free], k=1, distance_upper_bound=step)
        ring = np.isfinite(dist)
        if not ring.any():
            break
        free, near = free[ring], near[ring]
        pred = local_affine_predict(xs, ys, tree_s, near, X[free], neighbours)
        d, j = tree_y.query(pred, k=8, distance_upper_bound=gate)
        d, j = d.reshape(len(free), -1), j.reshape(len(free), -1)
        ok = np.isfinite(d)
        ok[ok] = ~used_t[j[ok]]
        rows, cols = np.nonzero(ok)
        if rows.size == 0:
            break
        cand = np.stack([free[rows], j[rows, cols]], axis=1)
        new = cand[one_to_one(cand, d[rows, cols])]
        pairs = np.vstack([pairs, new])
        used_s[new[:, 0]] = True
        used_t[new[:, 1]] = True
    return pairs[np.argsort(pairs[:, 0], kind="stable")]


def polish(X, Y, tree_y, seeds, gate: float, max_iter: int = 30) -> np.ndarray:
    """Refit an exact thin-plate warp through the matches and re-match within ``gate`` until they repeat.

    The non-rigid analogue of the rigid mode's ICP polish; stops early when
    fewer than 4 source points find a target.
    """
    pairs = seeds
    for _ in range(max_iter):
        warp = ThinPlateWarp(X[pairs[:, 0]], Y[pairs[:, 1]] - X[pairs[:, 0]])
        found = match_nearest(warp(X), tree_y, gate)
        if found.n_within < 4:
            break
        if found.pairs.shape == pairs.shape and np.array_equal(found.pairs, pairs):
            break
        pairs = found.pairs
    return pairs


# ------------------------------------------------------------ coarse-to-fine
def coarse_to_fine(X, Y, tree_y, warp, scale: float, extent2: float, floor: float) -> np.ndarray:
    """Robust smooth-warp matching from a coarse start (a rigid motion or the identity).

    At each level of :data:`COARSE_TO_FINE` the moved source points are
    matched to their nearest targets within the level's gate (times
    ``scale``, plus the noise ``floor``; one-to-one), the matches off the
    local affine trend of their neighbours by more than the gate are set
    aside, and a thin-plate warp with the level's smoothing (times
    ``extent2``) is fitted on the rest.  ``warp`` is the start, a callable
    on (N, 3) points.  Returns the last level's matches, or no pairs when a
    level keeps fewer than 5.
    """
    pairs = _NO_PAIRS
    for g, rel in COARSE_TO_FINE:
        gate = g * scale + floor
        pairs = match_nearest(warp(X), tree_y, gate).pairs
        if pairs.shape[0] < 5:
            return _NO_PAIRS.copy()
        xs, ys = X[pairs[:, 0]], Y[pairs[:, 1]]
        good = affine_residuals(xs, ys - xs) <= gate
        if good.sum() < 5:
            return _NO_PAIRS.copy()
        warp = ThinPlateWarp(xs[good], (ys - xs)[good], rel * extent2)
    return pairs


# ------------------------------------------------------------ local windows
def window_centres(P, k: int, n: int) -> np.ndarray:
    """Up to ``n`` centres of local windows of ``k`` points, densest first, windows not overlapping.

    Points are taken in order of their window's radius (the distance to
    their ``k``-th nearest point, smallest first: a sampled surface or
    curve is denser than outliers scattered through a volume or a plane,
    and a radius over ``k`` points is a steadier density estimate than a
    nearest neighbour's); a point becomes a centre when it lies outside
    every window chosen so far (farther from each centre than that
    centre's radius).  Deterministic (stable order).

    Returns
    -------
    (n',) ndarray of int, n' <= n
    """
    m = P.shape[0]
    k = min(k, m)
    radius = cKDTree(P).query(P, k=k)[0].reshape(m, -1)[:, -1]
    free = np.ones(m, bool)
    chosen = []
    for i in np.argsort(radius, kind="stable"):
        if not free[i]:
            continue
        chosen.append(int(i))
        if len(chosen) == n:
            break
        free &= np.sum((P - P[i]) ** 2, axis=1) > radius[i] ** 2
    return np.asarray(chosen, np.int64)


# ------------------------------------------------------------ anneal
def farthest_points(P, k: int) -> np.ndarray:
    """``k`` indices of ``P`` by farthest-point sampling from its first point (fewer for duplicates)."""
    sel = [0]
    dmin = cdist(P, P[:1], "sqeuclidean")[:, 0]
    for _ in range(min(k, P.shape[0]) - 1):
        a = int(np.argmax(dmin))
        if dmin[a] <= 0:
            break
        sel.append(a)
        dmin = np.minimum(dmin, cdist(P, P[a:a + 1], "sqeuclidean")[:, 0])
    return np.asarray(sel, np.int64)


def anneal(X, Y, spacing: float, seed: int):
    """Deterministic-annealing soft matching with an outlier class; returns the warp.

    A Gaussian mixture centred on the moved source points explains each
    target, with an extra outlier class (TPS-RPM, Chui & Rangarajan 2003;
    the coherent point drift M-step, Myronenko & Song 2010).  The variance
    ``T`` is not estimated but annealed from ``(extent / 4)²`` down to
    ``(spacing / 2)²`` (ratio ``ANNEAL_RATE``, ``ANNEAL_STEPS`` EM steps per
    level): hard nearest-target matching locks on to wrong targets when the
    displacements are several spacings among many outliers, a wide soft one
    does not.  The displacement field ``v(x) = Σ_c G(x, c) w_c`` is a
    Gaussian kernel of width ``extent / 4`` on ``ANNEAL_CONTROL``
    farthest-point centres, regularised by ``ANNEAL_LAMBDA · T`` times its
    kernel norm, so the motion is nearly affine while ``T`` is large and
    gains detail as ``T`` shrinks.  The outlier class has mass
    ``ANNEAL_OUTLIER`` times the 75th percentile of the source points' total
    affinity: scale-free, and large enough that a target far from every
    moved source point is left out of the fit.  Sets larger than
    ``ANNEAL_MAX_POINTS`` are subsampled with ``seed``.

    Returns
    -------
    callable
        The warp, on (N, 3) points.
    """
    rng = np.random.default_rng(seed)
    Xs = X if X.shape[0] <= ANNEAL_MAX_POINTS else X[np.sort(rng.choice(X.shape[0], ANNEAL_MAX_POINTS, replace=False))]
    Ys = Y if Y.shape[0] <= ANNEAL_MAX_POINTS else Y[np.sort(rng.choice(Y.shape[0], ANNEAL_MAX_POINTS, replace=False))]
    extent = float(np.linalg.norm(np.ptp(np.vstack([Xs, Ys]), axis=0))) or 1.0
    beta2 = (0.25 * extent) ** 2
    C = Xs[farthest_points(Xs, ANNEAL_CONTROL)]
    G = np.exp(-cdist(Xs, C, "sqeuclidean") / (2.0 * beta2))
    Gc = np.exp(-cdist(C, C, "sqeuclidean") / (2.0 * beta2))
    ridge = 1e-10 * np.eye(C.shape[0])
    T = (0.25 * extent) ** 2
    T_end = min(T, (0.5 * spacing) ** 2)
    W = np.zeros((C.shape[0], 3))
    moved = Xs.copy()
    while True:
        for _ in range(ANNEAL_STEPS):
            d2 = cdist(moved, Ys, "sqeuclidean")
            A = np.exp(-(d2 - d2.min()) / (2.0 * T))
            xi = ANNEAL_OUTLIER * float(np.percentile(A.sum(axis=1), 75))
            P = A / (A.sum(axis=0, keepdims=True) + xi)  # posterior of each target's source
            w = P.sum(axis=1)
            rhs = G.T @ (P @ Ys - w[:, None] * Xs)
            W = np.linalg.solve(G.T @ (w[:, None] * G) + ANNEAL_LAMBDA * T * Gc + ridge, rhs)
            moved = Xs + G @ W
        if T <= T_end:
            break
        T = max(T * ANNEAL_RATE, T_end)

    def warp(points):
        return points + np.exp(-cdist(points, C, "sqeuclidean") / (2.0 * beta2)) @ W

    return warp
