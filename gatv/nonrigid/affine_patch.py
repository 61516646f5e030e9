"""Affine patch hypothesis of the *local* windows: a small surface patch under local strain.

The local hypothesis (:func:`gatv.nonrigid.stages.local_hypothesis`) registers small source
patches rigidly.  A smooth warp with a large local strain (the bcpd bunny: a patch of 40 rows
shrinks by 45% along one direction after the global similarity) leaves no rigid fit within the
rigid search's gate, while the best *affine* fit of the same patch stays within a tenth of a
spacing.  This module searches such a patch's affine map among the targets of a placed window.

Affine-invariant base (4PCS, Aiger, Mitra & Cohen-Or 2008): four roughly coplanar points
``a, b, c, d`` of the patch whose segments ``ab`` and ``cd`` cross at ``e = a + r1 (b − a) =
c + r2 (d − c)``.  An affine map keeps ``r1`` and ``r2``: the partners ``p, q, s, t`` satisfy
``p + r1 (q − p) ≈ s + r2 (t − s)``.  Target pairs whose lengths are within the allowed stretch
of ``|ab|`` (and of ``|cd|``) give the two sets of intersection points; the ones that meet give
the candidate quadruples, each an affine map of the patch's plane (9 parameters from 4 points:
3 residual degrees of freedom check it).

Each candidate is scored on the patch's nearest rows (how many land within the gate of a
target), the best ones are grown over the whole patch by refitting a 3D affine map (the patch's
height left out while it spans less than the gate: a patch is nearly flat) and re-matching
one-to-one.  A candidate
is kept only when its grown support is at least ``AFFINE_CHANCE_RATIO`` times the median grown
support of the other best-scored candidates: those are wrong affine maps on the same data, so
their support is the chance level of the search, affine freedom and number of trials included.
The kept patch is then grown over the window and verified against chance by the caller, as a
rigid patch is.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np
from scipy.spatial import cKDTree

from ..candidates import one_to_one

__all__ = [
    "AFFINE_BASE_POINTS",
    "AFFINE_BLOCK",
    "AFFINE_CHANCE_RATIO",
    "AFFINE_CHECK_POINTS",
    "AFFINE_GROWN",
    "AffinePatch",
    "affine_patch",
    "crossing_base",
    "crossing_points",
    "stretch_band",
]

#: The base's four points are chosen among the patch's this many rows nearest its centre: a base
#: of a few spacings keeps the number of target pairs in its length band small.
AFFINE_BASE_POINTS = 8
#: Rows nearest the patch's centre on which each candidate quadruple is scored.
AFFINE_CHECK_POINTS = 20
#: Best-scored candidates grown over the whole patch; the others among them give the chance level.
AFFINE_GROWN = 20
#: Crossing points of the second base pair looked up at a time (bounds the memory of the search).
AFFINE_BLOCK = 4096
#: A grown candidate is kept when its support is at least this many times the median support of
#: the other grown candidates (wrong affine maps on the same data).
AFFINE_CHANCE_RATIO = 2.0


def stretch_band(strain: float) -> tuple[float, float]:
    """Allowed ratio of a patch length in the target to the same length in the (placed) source.

    The local strain ``ε`` bounds the length change between neighbours under the warp; the
    placement's own scale is a global estimate, off locally by up to as much: ``[(1 − ε)²,
    (1 + ε)²]`` (``ε`` capped below 1).
    """
    e = min(float(strain), 0.9)
    return (1.0 - e) ** 2, (1.0 + e) ** 2


def crossing_points(a, b, c, d):
    """Parameters ``r1, r2`` of the closest points of lines ``ab`` and ``cd`` and their gap.

    ``a + r1 (b − a)`` and ``c + r2 (d − c)`` are the closest points; for coplanar points whose
    segments cross they coincide (gap 0).  Works on (..., 3) arrays; parallel lines give nan.
    """
    u, v, w = b - a, d - c, a - c
    uu, uv, vv = np.sum(u * u, -1), np.sum(u * v, -1), np.sum(v * v, -1)
    uw, vw = np.sum(u * w, -1), np.sum(v * w, -1)
    det = uu * vv - uv * uv
    with np.errstate(invalid="ignore", divide="ignore"):
        r1 = (uv * vw - vv * uw) / det
        r2 = (uu * vw - uv * uw) / det
    gap = np.linalg.norm(a + r1[..., None] * u - c - r2[..., None] * v, axis=-1)
    return r1, r2, gap


def crossing_base(P, max_gap: float = np.inf):
    """Four rows of ``P`` whose segments cross well inside (``0.2 ≤ r1, r2 ≤ 0.8``), widest first.

    Over every 4 rows and each of their 3 pairings whose lines pass within ``max_gap`` of each
    other (nearly coplanar: the partners' crossing points are looked up within about that gap,
    so a wide gap on a curved patch multiplies the candidates), the base maximises
    ``min(|ab|, |cd|) · sin(angle)`` (a wide, well-conditioned quadrilateral; a thin one leaves
    the affine map ill-determined).  Returns ``(rows, r1, r2, gap)`` with rows ordered ``a, b,
    c, d``, or ``None`` when no 4 rows qualify (fewer than 4, collinear, too curved).
    """
    P = np.asarray(P, dtype=float)
    if P.shape[0] < 4:
        return None
    quads = np.array(list(combinations(range(P.shape[0]), 4)), np.int64)
    orders = np.concatenate([quads[:, [0, 1, 2, 3]], quads[:, [0, 2, 1, 3]], quads[:, [0, 3, 1, 2]]])
    a, b, c, d = (P[orders[:, k]] for k in range(4))
    r1, r2, gaps = crossing_points(a, b, c, d)
    u, v = b - a, d - c
    lu, lv = np.linalg.norm(u, axis=1), np.linalg.norm(v, axis=1)
    sin = np.linalg.norm(np.cross(u, v), axis=1) / np.maximum(lu * lv, 1e-300)
    with np.errstate(invalid="ignore"):
        ok = (np.isfinite(r1) & np.isfinite(r2) & (r1 >= 0.2) & (r1 <= 0.8) & (r2 >= 0.2) & (r2 <= 0.8)
              & (gaps <= max_gap))
    if not ok.any():
        return None
    score = np.where(ok, np.minimum(lu, lv) * sin, -np.inf)
    k = int(np.argmax(score))
    rr1, rr2, gap = crossing_points(a[k], b[k], c[k], d[k])
    return orders[k], float(rr1), float(rr2), float(gap)


def _band_pairs(T, tree_t, length: float, lo: float, hi: float) -> np.ndarray:
    """Ordered target pairs (both orders) whose length is within ``[lo, hi] · length``."""
    pr = tree_t.query_pairs(hi * length, output_type="ndarray")
    if pr.shape[0] == 0:
        return np.empty((0, 2), np.int64)
    ln = np.linalg.norm(T[pr[:, 1]] - T[pr[:, 0]], axis=1)
    pr = pr[ln >= lo * length].astype(np.int64)
    return np.vstack([pr, pr[:, ::-1]])


def _frame(P):
    """Centre and orthonormal frame (rows: the two in-plane axes, then the normal) of ``P``."""
    centre = P.mean(axis=0)
    return centre, np.linalg.svd(P - centre)[2]


@dataclass(frozen=True, eq=False)
class AffinePatch:
    """Result of :func:`affine_patch`: the kept matches (patch row, target row) and the search's figures.

    ``pairs`` is empty when no candidate beats the chance level.  ``support`` is the kept
    candidate's grown support, ``chance`` the median grown support of the other candidates,
    ``trials`` the candidate quadruples scored.
    """

    pairs: np.ndarray
    support: int
    chance: float
    trials: int


def _grow(F, T, tree_t, src, tgt, gate: float, rounds: int = 4):
    """Refit the patch's affine map on the matches and re-match every row one-to-one within ``gate``.

    ``F`` holds the patch rows in their own frame (two in-plane coordinates and the height).  The
    map is ``y = t + A (u1, u2, h)``, fitted by least squares; while the matched rows' heights
    span less than the gate it is the plane's map ``y = t + A (u1, u2)``: heights that small (a
    base's 4 points, a flat patch) do not determine the map of the normal.
    """
    D_all = np.column_stack([np.ones(F.shape[0]), F])
    for _ in range(rounds):
        cols = 4 if np.ptp(F[src, 2]) > gate else 3
        coef = np.linalg.lstsq(D_all[src, :cols], T[tgt], rcond=None)[0]
        dist, j = tree_t.query(D_all[:, :cols] @ coef, k=1, distance_upper_bound=gate)
        ok = np.flatnonzero(np.isfinite(dist))
        if ok.size < 4:
            break
        cand = np.column_stack([ok, j[ok]]).astype(np.int64)
        kept = cand[one_to_one(cand, dist[ok])]
        if kept.shape[0] == src.size and np.array_equal(kept[:, 0], src) and np.array_equal(kept[:, 1], tgt):
            break
        order = np.argsort(kept[:, 0], kind="stable")
        src, tgt = kept[order, 0], kept[order, 1]
    return src, tgt


def affine_patch(Xp, T, gate: float, strain: float, tree_t=None) -> AffinePatch:
    """Search the affine map of the surface patch ``Xp`` (rows ordered by distance from its centre)
    among the targets ``T`` (see the module's description).

    Parameters
    ----------
    Xp : (k, 3) ndarray
        The patch's source rows, placed (the targets' scale), nearest its centre first.
    T : (m, 3) ndarray
        The targets that may hold the patch's partners.
    gate : float
        Match gate of a predicted row (the verification gate).
    strain : float
        Local strain; the lengths' band is :func:`stretch_band`.

    Returns
    -------
    AffinePatch
    """
    Xp, T = np.asarray(Xp, dtype=float), np.asarray(T, dtype=float)
    none = AffinePatch(np.empty((0, 2), np.int64), 0, 0.0, 0)
    k = Xp.shape[0]
    if k < 6 or T.shape[0] < 4:
        return none
    base = crossing_base(Xp[:min(AFFINE_BASE_POINTS, k)], max_gap=gate)
    if base is None:
        return none
    rows, r1, r2, gap = base
    tree_t = tree_t if tree_t is not None else cKDTree(T)
    lo, hi = stretch_band(strain)
    B = Xp[rows]
    p1 = _band_pairs(T, tree_t, float(np.linalg.norm(B[1] - B[0])), lo, hi)
    p2 = _band_pairs(T, tree_t, float(np.linalg.norm(B[3] - B[2])), lo, hi)
    if p1.shape[0] == 0 or p2.shape[0] == 0:
        return none
    e1 = T[p1[:, 0]] + r1 * (T[p1[:, 1]] - T[p1[:, 0]])
    e2 = T[p2[:, 0]] + r2 * (T[p2[:, 1]] - T[p2[:, 0]])
    # the crossing points of the partners meet up to the base's gap (stretched) and the gate; the
    # quadruples are scored a block of crossing points at a time (bounded memory at 100k points)
    reach = hi * gap + 2.0 * gate
    tree_e1 = cKDTree(e1)
    check = np.setdiff1d(np.arange(min(AFFINE_CHECK_POINTS, k)), rows)
    if check.size == 0:
        return none
    centre, frame = _frame(Xp[:min(AFFINE_CHECK_POINTS, k)])
    M = np.column_stack([np.ones(4), (B - centre) @ frame[:2].T])
    pinv = np.linalg.pinv(M)
    U = np.column_stack([np.ones(check.size), (Xp[check] - centre) @ frame[:2].T])
    kept_q, kept_hits, trials = [], [], 0
    for start in range(0, e2.shape[0], AFFINE_BLOCK):
        near = tree_e1.query_ball_point(e2[start:start + AFFINE_BLOCK], reach)
        n_near = np.fromiter((len(v) for v in near), np.int64, len(near))
        if n_near.sum() == 0:
            continue
        i = np.fromiter((x for v in near for x in v), np.int64, int(n_near.sum()))
        j = np.repeat(np.arange(start, start + len(near)), n_near)
        Q = np.column_stack([p1[i], p2[j]])
        Q = Q[(Q[:, 0] != Q[:, 2]) & (Q[:, 0] != Q[:, 3]) & (Q[:, 1] != Q[:, 2]) & (Q[:, 1] != Q[:, 3])]
        if Q.shape[0] == 0:
            continue
        # the plane map of each quadruple: least squares on the base's in-plane coordinates
        coef = np.einsum("ij,njk->nik", pinv, T[Q])  # (n, 3, 3): t, then A's two rows
        res = np.linalg.norm(np.einsum("ij,njk->nik", M, coef) - T[Q], axis=2).max(axis=1)
        sv = np.linalg.svd(coef[:, 1:, :], compute_uv=False)
        keep = (res <= gate + gap) & (sv[:, 0] <= hi) & (sv[:, 1] >= lo)
        if not keep.any():
            continue
        Q, coef = Q[keep], coef[keep]
        trials += Q.shape[0]
        pred = np.einsum("ij,njk->nik", U, coef)
        dist = tree_t.query(pred.reshape(-1, 3), k=1, distance_upper_bound=gate)[0].reshape(pred.shape[:2])
        hits = np.isfinite(dist).sum(axis=1)
        best = np.argsort(-hits, kind="stable")[:AFFINE_GROWN]
        kept_q.append(Q[best])
        kept_hits.append(hits[best])
    if trials == 0:
        return none
    Q, hits = np.vstack(kept_q), np.concatenate(kept_hits)
    top = np.argsort(-hits, kind="stable")[:AFFINE_GROWN]
    # grow each of the best over the whole patch (in its own frame)
    pc, pf = _frame(Xp)
    F = (Xp - pc) @ pf.T
    grown = [_grow(F, T, tree_t, np.asarray(rows, np.int64), Q[q].astype(np.int64), gate) for q in top]
    support = np.array([g[0].size for g in grown])
    best = int(np.argmax(support))
    others = np.delete(support, best)
    chance = float(np.median(others)) if others.size else 0.0
    if others.size == 0 or support[best] < AFFINE_CHANCE_RATIO * max(chance, 1.0):
        return AffinePatch(none.pairs, int(support[best]), chance, trials)
    src, tgt = grown[best]
    return AffinePatch(np.column_stack([src, tgt]), int(support[best]), chance, trials)
