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

from .. import stages
from .._validation import as_rng, check_int
from ..candidates import one_to_one
from ..fitting import fit_rigid, kabsch
from ..models.base import homogeneous
from ..stages import NOISE_SCHEDULE
from .result import Segmentation

__all__ = ["ransac_segment"]


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
    P = stages.prepare(source, target, "rigid")
    X, Y = P.source, P.target
    max_motions = check_int(max_motions, "max_motions", 1, allow_none=True)
    min_support = check_int(min_support, "min_support", 3, allow_none=True)
    tol = float(noise) if noise is not None else NOISE_SCHEDULE[0] * P.spacing
    gate = stages.gate(tol)
    rng = as_rng(seed)
    n1, n2 = X.shape[0], Y.shape[0]
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
            R, t = kabsch(X[si], Y[tj])
            # cheap pre-test: the three sample pairs themselves must fit
            r3 = np.linalg.norm(np.einsum("sij,snj->sni", R, X[si]) + t[:, None] - Y[tj], axis=2)
            good = np.flatnonzero(r3.max(axis=1) <= gate)
            for g in good:
                moved = X[fs] @ R[g].T + t[g]
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
            moved = X[fs] @ R.T + t
            lists = P.tree.query_ball_point(moved, gate)
            pairs = np.array([(fs[a], b) for a, l in enumerate(lists) for b in l if free_t[b]],
                             np.int64).reshape(-1, 2)
            if pairs.shape[0] < 3:
                break
            res = np.linalg.norm(Y[pairs[:, 1]] - (X[pairs[:, 0]] @ R.T + t), axis=1)
            pairs = pairs[one_to_one(pairs, res)]
            R, t = fit_rigid(X[pairs[:, 0]], Y[pairs[:, 1]])
        if pairs.shape[0] < threshold:
            break
        k = len(motions)
        motions.append(stages.make_result(P, stages.Fit(homogeneous(R, t), pairs), {}))
        src_lab[pairs[:, 0]] = k
        tgt_lab[pairs[:, 1]] = k
        free_s[pairs[:, 0]] = False
        free_t[pairs[:, 1]] = False
    return Segmentation(tuple(motions), src_lab, tgt_lab, np.empty((0, 2), np.int64), np.empty(0, np.int64),
                        {"method": "sequential-ransac", "iterations": iterations, "support_threshold": threshold})
