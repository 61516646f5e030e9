"""Sequential RANSAC baseline for several rigid motions.

Three-point samples drawn from *all* candidate pairs ``(i, j)`` (every
source point with every target point, the paper's matching scheme of
section 3.4), a Kabsch fit, inliers within the residual gate; the best
motion is kept, its points removed, and the search repeated until no
motion beats the chance level.  Written as the comparison for
:func:`gatv.motions.segment` in ``benchmarks/motions.py``.
"""

from __future__ import annotations

import numpy as np

from ..candidates import one_to_one
from ..motion import RigidMotion, fit_rigid
from ..registration import NOISE_SCHEDULE, _gate, _Problem
from .segmentation import Segmentation, _check_count

__all__ = ["ransac_segment"]


def _kabsch_batch(A, B):
    """Rotations and translations of many 3-pair samples, (S, 3, 3) each."""
    ca, cb = A.mean(axis=1), B.mean(axis=1)
    H = np.einsum("sni,snj->sij", A - ca[:, None], B - cb[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("sji,skj->sik", Vt, U)))
    d[d == 0] = 1.0
    D = np.zeros_like(H)
    D[:, 0, 0] = 1.0
    D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    R = np.einsum("sji,sjk,slk->sil", Vt, D, U)
    t = cb - np.einsum("sij,sj->si", R, ca)
    return R, t


def ransac_segment(source, target, *, max_motions=None, min_support=None, seed=0, noise=None,
                   iterations: int = 20000, batch: int = 2000) -> Segmentation:
    """Sequential RANSAC on all candidate pairs (baseline).

    Parameters
    ----------
    iterations : int, default: 20000
        Three-pair samples drawn per motion searched.
    noise : float, optional
        Point noise; default ``1e-6`` of the spacing (exact data).
    """
    P = _Problem(source, target)
    max_motions = _check_count(max_motions, "max_motions", 1)
    min_support = _check_count(min_support, "min_support", 3)
    tol = float(noise) if noise is not None else NOISE_SCHEDULE[0] * P.spacing
    gate = _gate(tol)
    rng = np.random.default_rng(seed)
    n1, n2 = P.X.shape[0], P.Y.shape[0]
    free_s = np.ones(n1, bool)
    free_t = np.ones(n2, bool)
    motions = []
    src_lab = np.full(n1, -1, np.int64)
    tgt_lab = np.full(n2, -1, np.int64)
    threshold = min_support if min_support is not None else max(3, P.chance(gate, n_tests=iterations))
    while max_motions is None or len(motions) < max_motions:
        fs, ft = np.flatnonzero(free_s), np.flatnonzero(free_t)
        if fs.size < 3 or ft.size < 3:
            break
        best = (0, None, None)
        for start in range(0, iterations, batch):
            m = min(batch, iterations - start)
            si = fs[rng.integers(0, fs.size, (m, 3))]
            tj = ft[rng.integers(0, ft.size, (m, 3))]
            ok = (si[:, 0] != si[:, 1]) & (si[:, 0] != si[:, 2]) & (si[:, 1] != si[:, 2]) & \
                 (tj[:, 0] != tj[:, 1]) & (tj[:, 0] != tj[:, 2]) & (tj[:, 1] != tj[:, 2])
            si, tj = si[ok], tj[ok]
            if si.shape[0] == 0:
                continue
            R, t = _kabsch_batch(P.X[si], P.Y[tj])
            # cheap pre-test: the three sample pairs themselves must fit
            r3 = np.linalg.norm(np.einsum("sij,snj->sni", R, P.X[si]) + t[:, None] - P.Y[tj], axis=2)
            good = np.flatnonzero(r3.max(axis=1) <= gate)
            for g in good:
                moved = P.X[fs] @ R[g].T + t[g]
                d, j = P.tree.query(moved, k=1, distance_upper_bound=gate)
                hit = np.isfinite(d)
                hit[hit] = free_t[j[hit]]
                c = int(hit.sum())
                if c > best[0]:
                    best = (c, R[g], t[g])
        if best[0] < threshold:
            break
        R, t = best[1], best[2]
        for _ in range(3):
            moved = P.X[fs] @ R.T + t
            lists = P.tree.query_ball_point(moved, gate)
            pairs = np.array([(fs[a], b) for a, l in enumerate(lists) for b in l if free_t[b]],
                             np.int64).reshape(-1, 2)
            if pairs.shape[0] < 3:
                break
            res = np.linalg.norm(P.Y[pairs[:, 1]] - (P.X[pairs[:, 0]] @ R.T + t), axis=1)
            pairs = pairs[one_to_one(pairs, res)]
            R, t = fit_rigid(P.X[pairs[:, 0]], P.Y[pairs[:, 1]])
        if pairs.shape[0] < threshold:
            break
        k = len(motions)
        res = np.linalg.norm(P.Y[pairs[:, 1]] - (P.X[pairs[:, 0]] @ R.T + t), axis=1)
        pairs = pairs[np.argsort(pairs[:, 0])]
        motions.append(RigidMotion(R, t, pairs, float(pairs.shape[0]), float(np.sqrt(np.mean(res**2)))))
        src_lab[pairs[:, 0]] = k
        tgt_lab[pairs[:, 1]] = k
        free_s[pairs[:, 0]] = False
        free_t[pairs[:, 1]] = False
    return Segmentation(tuple(motions), src_lab, tgt_lab, np.empty((0, 2), np.int64), np.empty(0, np.int64),
                        {"method": "sequential-ransac", "iterations": iterations, "support_threshold": threshold})
