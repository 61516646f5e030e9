"""Epipolar stage: a camera motion (R, t) and matches along its epipolar arcs.

With a camera translation, true pairs satisfy ``y · (t × R x) = 0``: ``y``
lies on the great-circle arc from ``R x`` (infinite depth) towards the
epipole ``t`` (zero depth). :func:`epipolar_stage`:

1. **Motion.** An essential matrix is found by 8-point RANSAC on the
   sphere, each sample three matched local triangles (nine pairs, all
   right far more often than eight independent pairs; the ``EPI_MATCHES``
   most similar target triangles of each source triangle, as parallax
   reorders their shapes) from a cluster of triangle rotations as wide as
   the parallax, scored on those pairs and the earlier stages' pairs. A
   minimal sample's essential matrix is rough, so the samples are ranked
   with a wider gate, and the best ``EPI_LO`` are refitted on all their
   pairs and polished by least squares on the epipolar angles before they
   compete (LO-RANSAC).
2. **Growth along the arcs.** The inverse depth ``rho = |t| / d`` of a
   plane is linear in the ray, ``rho = w · u``, so the plane that most of a
   ray's matched neighbours agree with (the best of their triples,
   refitted) predicts where on its arc the ray lands; candidates within
   the noise gate (along the arc widened by the prediction's own standard
   error, from the plane fit's covariance) are matched one-to-one, closest
   first, growing until the matches repeat, with (R, t) refitted on them.
   In the last round a ray is also predicted by every other plane that
   ``EPI_SHARE`` of its neighbours agree with (both sides of a crease),
   and a match is kept only when its posterior
   (:func:`catadioptric.acceptance.posterior`) reaches ``MIN_POSTERIOR``.
3. **Parallax check.** Without parallax (a pure rotation, ``t``
   undefined) the stage stands aside for the rigid one.

Motion convention: ``y ∝ R X + t`` with ``X = d x`` the scene point in
view 1's frame (:func:`catadioptric.synthetic_views`).
"""

from __future__ import annotations

import math
from itertools import combinations

import numpy as np
from scipy.spatial import cKDTree

from catadioptric.acceptance import likelihood, posterior, rival_likelihood
from catadioptric.constants import (
    EPI_CLUSTER_DEG,
    EPI_FINAL,
    EPI_HYPOTHESES,
    EPI_LO,
    EPI_LO_GATE,
    EPI_MATCHES,
    EPI_MIN_PARALLAX,
    EPI_OUTER,
    EPI_RANSAC,
    EPI_RIVAL,
    EPI_SHAPE_TOL,
    EPI_SHARE,
    GATE_SIGMAS,
    MIN_ESSENTIAL_PAIRS,
    MIN_POSTERIOR,
    REACH_SPACINGS,
)
from catadioptric.rotation import dominant_rotation
from gatv.validation import check_memory
from gatv.candidates import one_to_one

__all__ = ["epipolar_stage", "essential_from_motion"]

# Bytes per entry of the stage's large tables, for the memory checks: the
# RANSAC table (sample x candidate pair: both epipolar lines, the distances
# and the masks), the candidates within ``max_parallax`` (rows, arc
# coordinates and their temporaries) and the last round's candidate x plane
# table (predictions, variances, distances).
_BYTES_PER_SAMPLE_PAIR = 96
_BYTES_PER_CANDIDATE = 160
_BYTES_PER_CANDIDATE_PLANE = 48


def essential_from_motion(R, t):
    """Essential matrix ``E = [t]x R`` of the motion (R, t): ``y^T E x = 0`` for true pairs."""
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    return tx @ R


def _epipolar_distance(E, x, y):
    """Angular distance of ``y`` from the epipolar great circle of ``x`` and vice versa (the larger)."""
    ex = x @ E.T
    ey = y @ E
    num = np.abs(np.einsum("ij,ij->i", y, ex))
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.maximum(num / np.linalg.norm(ex, axis=1), num / np.linalg.norm(ey, axis=1))
    return np.nan_to_num(d, nan=np.inf)


def _batched_essentials(X, Y):
    """Essential matrices of stacks of 8 ray pairs (K, 8, 3) by the linear 8-point method."""
    A = np.einsum("kni,knj->knij", Y, X).reshape(X.shape[0], X.shape[1], 9)
    if A.shape[1] < 9:
        A = np.concatenate([A, np.zeros((A.shape[0], 9 - A.shape[1], 9))], axis=1)
    _, _, Vt = np.linalg.svd(A)
    E = Vt[:, -1, :].reshape(-1, 3, 3)
    U, _, Vt = np.linalg.svd(E)
    return U @ np.diag([1.0, 1.0, 0.0]) @ Vt


def _motions(E):
    """The four (R, t) of an essential matrix."""
    U, _, Vt = np.linalg.svd(E)
    if np.linalg.det(U) < 0:
        U = -U
    if np.linalg.det(Vt) < 0:
        Vt = -Vt
    W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    out = []
    for Rm in (U @ W @ Vt, U @ W.T @ Vt):
        for s in (1.0, -1.0):
            out.append((Rm, s * U[:, 2]))
    return out


def _arc_coordinates(Rx, t, y):
    """Epipolar coordinates of ``y`` against the rays ``Rx`` for the translation direction ``t``.

    Returns ``(phi, alpha, across)``: ``phi`` the angle from ``Rx`` to the
    projection of ``y`` on the epipolar great circle, positive towards
    ``t``; ``alpha`` the angle from ``Rx`` to ``t``; ``across`` the signed
    angular distance of ``y`` from the circle.
    """
    c = Rx @ t
    e2 = t[None, :] - c[:, None] * Rx
    s = np.linalg.norm(e2, axis=1)
    e2 = e2 / np.maximum(s, 1e-12)[:, None]
    nrm = np.cross(Rx, e2)
    a, b = np.einsum("ij,ij->i", y, Rx), np.einsum("ij,ij->i", y, e2)
    phi = np.arctan2(b, a)
    alpha = np.arctan2(s, c)
    across = np.arcsin(np.clip(np.einsum("ij,ij->i", y, nrm), -1.0, 1.0))
    return phi, alpha, across


def _inverse_depth(phi, alpha):
    """Inverse depth ``|t| / d`` of the arc angle ``phi`` (``alpha``: angle to the epipole)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.sin(phi) / np.sin(alpha - phi)


def _arc_angle(rho, alpha):
    """Arc angle of the inverse depth ``rho`` (inverse of :func:`_inverse_depth`)."""
    return np.arctan2(rho * np.sin(alpha), 1.0 + rho * np.cos(alpha))


def _cheirality(R, t, x, y):
    """Pairs in front of both cameras (inverse depth above a small negative bound)."""
    phi, alpha, _ = _arc_coordinates(x @ R.T, t, y)
    return (phi > -0.02) & (phi < alpha)


def _refine_motion(R, t, x, y, sig):
    """Least squares (R, t) on the sphere: signed epipolar distances, 5 parameters."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    def unpack(p):
        Rm = Rotation.from_rotvec(p[:3]).as_matrix() @ R
        # t on the sphere: tangent coordinates about the current t
        b1 = np.cross(t, [1.0, 0.0, 0.0] if abs(t[0]) < 0.9 else [0.0, 1.0, 0.0])
        b1 /= np.linalg.norm(b1)
        b2 = np.cross(t, b1)
        tv = t + p[3] * b1 + p[4] * b2
        return Rm, tv / np.linalg.norm(tv)

    def res(p):
        Rm, tv = unpack(p)
        n = np.cross(tv[None, :], x @ Rm.T)
        nn = np.linalg.norm(n, axis=1)
        return np.einsum("ij,ij->i", y, n) / np.maximum(nn, 1e-9) / sig

    sol = least_squares(res, np.zeros(5), loss="soft_l1", f_scale=GATE_SIGMAS)
    return unpack(sol.x)


def _estimate_motions(x, y, sig, rng, groups=None, iterations=None, hypotheses=None, memory_budget=None):
    """Robust motions (R, t) from candidate pairs: 8-point RANSAC on the sphere, then least squares.

    ``groups`` (G, 3) rows of ``x, y``: the vertex pairs of matched local
    triangles; a sample is then three triangles (nine pairs), all right
    far more often than eight independent pairs. ``rng``: the
    :class:`numpy.random.Generator` of the samples. Returns up to
    ``hypotheses`` distinct ``(R, t, inlier mask)``, best supported first
    (the caller keeps the one that explains most rays). Raises
    :class:`~gatv.errors.InputError` when the table of the samples'
    distances to every pair would not fit in ``memory_budget`` bytes.
    """
    iterations = EPI_RANSAC if iterations is None else iterations
    hypotheses = EPI_HYPOTHESES if hypotheses is None else hypotheses
    k = x.shape[0]
    if k < MIN_ESSENTIAL_PAIRS:
        return []
    check_memory(_BYTES_PER_SAMPLE_PAIR * iterations * k,
                 f"{iterations:,} RANSAC samples x {k:,} candidate pairs", memory_budget)
    if groups is not None and groups.shape[0] >= 3:
        pick = np.argsort(rng.random((iterations, groups.shape[0])), axis=1)[:, :3]
        samples = groups[pick].reshape(iterations, 9)
    else:
        samples = np.argsort(rng.random((iterations, k)), axis=1)[:, :8]
    Es = _batched_essentials(x[samples], y[samples])
    gate = GATE_SIGMAS * sig
    ex = np.einsum("kij,nj->kni", Es, x)
    ey = np.einsum("kij,ni->knj", Es, y)
    num = np.abs(np.einsum("ni,kni->kn", y, ex))
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.maximum(num / np.linalg.norm(ex, axis=2), num / np.linalg.norm(ey, axis=2))
    # a minimal sample's E is rough (the problem is ill-conditioned at small
    # parallax): samples are ranked with a wider gate, and the best are
    # polished on all their pairs before they compete (LO-RANSAC)
    inl_wide = np.nan_to_num(d, nan=np.inf) <= EPI_LO_GATE * gate
    whole = groups is not None and groups.shape[0] >= 3

    def score_of(inl):
        # whole triangles consistent with the motion: a wrong E gathers
        # single near-miss pairs along its epipolar circles more easily
        s = np.count_nonzero(inl, axis=-1)
        return np.all(inl[..., groups], axis=-1).sum(axis=-1) * (k + 1) + s if whole else s

    score = score_of(inl_wide)
    polished = []
    for h in np.argsort(-score, kind="stable")[:EPI_LO]:
        inl = inl_wide[h]
        if np.count_nonzero(inl) < 8:
            continue
        E = _batched_essentials(x[inl][None], y[inl][None])[0]
        cands = [(int(np.count_nonzero(_cheirality(Rm, tv, x[inl], y[inl]))), i, Rm, tv)
                 for i, (Rm, tv) in enumerate(_motions(E))]
        _, _, R, t = max(cands, key=lambda c: (c[0], -c[1]))
        ok = True
        for _ in range(3):
            R, t = _refine_motion(R, t, x[inl], y[inl], sig[inl])
            E = essential_from_motion(R, t)
            inl = (_epipolar_distance(E, x, y) <= gate) & _cheirality(R, t, x, y)
            if np.count_nonzero(inl) < 8:
                ok = False
                break
        if ok:
            polished.append((R, t, inl, score_of(inl)))
    out = []
    for R, t, inl, sc in sorted(polished, key=lambda o: -o[3]):
        if out and (len(out) >= hypotheses or sc < EPI_RIVAL * out[0][3]):
            break
        if any(np.count_nonzero(inl & o[2]) > 0.5 * np.count_nonzero(inl) for o in out):
            continue
        out.append((R, t, inl, sc))
    return [o[:3] for o in out]


def _epipolar_candidates(r1, r2, tree2, s1, s2, R, t, max_parallax, memory_budget=None):
    """Candidate pairs near the epipolar arcs of the motion (R, t).

    Returns ``(i, j, phi, across, sigma, alpha)``: per candidate the rows,
    the arc angle and the distance from the arc (:func:`_arc_coordinates`)
    and the pair's noise; ``alpha`` per ray of view 1 (angle to the epipole).
    A candidate lies within the noise gate of the arc from ``R x`` to the
    epipole and within ``max_parallax`` (chord) of ``R x``. Raises
    :class:`~gatv.errors.InputError` when the pairs within ``max_parallax``
    would not fit in ``memory_budget`` bytes.
    """
    Rx = r1 @ R.T
    lists = tree2.query_ball_point(Rx, max_parallax)
    lens = np.fromiter((len(a) for a in lists), np.int64, len(lists))
    n_near = int(lens.sum())
    check_memory(_BYTES_PER_CANDIDATE * n_near,
                 f"{n_near:,} pairs within max_parallax={max_parallax:g}", memory_budget)
    ii = np.repeat(np.arange(r1.shape[0]), lens)
    jj = np.fromiter((j for a in lists for j in a), np.int64, int(lens.sum()))
    if ii.size == 0:
        e = np.empty(0)
        return ii, jj, e, e, e, np.arctan2(np.linalg.norm(np.cross(Rx, t), axis=1), Rx @ t)
    phi, alpha, across = _arc_coordinates(Rx[ii], t, r2[jj])
    sig = np.sqrt(s1[ii] ** 2 + s2[jj] ** 2)
    gate = GATE_SIGMAS * sig
    ok = (np.abs(across) <= gate) & (phi >= -gate) & (phi <= alpha + gate)
    alpha_all = np.arctan2(np.linalg.norm(np.cross(Rx, t), axis=1), Rx @ t)
    return ii[ok], jj[ok], phi[ok], across[ok], sig[ok], alpha_all


def _triple_planes(A, rn, wts, keep, support_gate):
    """The exact plane through each triple of a ray's neighbours, and who agrees with it.

    ``A, rn, wts, keep`` as in :func:`_local_planes` (k >= 3 neighbours).
    Returns ``usable (n, T)`` (three usable, independent neighbours),
    ``res (n, T, k)`` the neighbours' residuals from each triple's plane in
    noise units, and ``inl (n, T, k)`` those within ``support_gate``; the
    T triples in :func:`itertools.combinations` order.
    """
    k = A.shape[1]
    trip = np.array(list(combinations(range(k), 3)), dtype=np.int64)
    a0, a1, a2 = A[:, trip[:, 0]], A[:, trip[:, 1]], A[:, trip[:, 2]]   # (n, T, 3)
    c0, c1, c2 = np.cross(a1, a2), np.cross(a2, a0), np.cross(a0, a1)
    det = np.einsum("nti,nti->nt", a0, c0)
    usable = np.all(keep[:, trip], axis=2) & (np.abs(det) > 1e-12)
    bt = rn[:, trip]                                  # (n, T, 3)
    # Cramer's rule: the plane through the three neighbours' (ray, rho)
    wt = (bt[..., 0:1] * c0 + bt[..., 1:2] * c1 + bt[..., 2:3] * c2) / np.where(usable, det, 1.0)[..., None]
    res = (rn[:, None, :] - np.einsum("nki,nti->ntk", A, wt)) * np.sqrt(wts)[:, None, :]
    inl = (np.abs(res) <= support_gate) & keep[:, None, :]
    return usable, res, inl


def _local_planes(A, rn, wts, keep, ridge, support_gate=GATE_SIGMAS):
    """Inverse-depth planes ``rho = w . u`` of each ray's neighbours, robust to a second plane.

    Every triple of a ray's neighbours gives an exact plane; the plane that
    the most neighbours agree with (within ``support_gate`` noise units of
    arc angle) is refitted by weighted least squares on those neighbours,
    so a ray near a crease of the scene is predicted by one side of it
    rather than by a blend of both.

    ``A``: (n, k, 3) neighbour rays; ``rn``: (n, k) their inverse depths;
    ``wts``: (n, k) weights (arc-angle sensitivity over noise, squared);
    ``keep``: (n, k) bool mask of usable neighbours. Returns the planes
    (n, 3) and the normal matrices ``M`` (n, 3, 3) of their weighted least
    squares: the weights are inverse variances of the neighbours' inverse
    depths, so ``M^-1`` is the covariance of ``w`` and ``u . M^-1 u`` the
    variance of the plane's inverse depth at the ray ``u``.
    """
    n, k, _ = A.shape
    if k >= 3:
        usable, res, inl = _triple_planes(A, rn, wts, keep, support_gate)
        score = inl.sum(axis=2) - np.minimum(np.where(inl, res * res, 0.0).sum(axis=2) / (support_gate ** 2 * k), 0.99)
        score = np.where(usable, score, -1.0)
        best = np.argmax(score, axis=1)
        w = wts * inl[np.arange(n), best]
        w = np.where(np.any(usable, axis=1)[:, None], w, wts * keep)
    else:
        w = wts * keep
    AtW = A * w[..., None]
    Mt = np.einsum("nki,nkj->nij", AtW, A) + ridge * (wts * keep).sum(axis=1)[:, None, None] * np.eye(3)
    b = np.einsum("nki,nk->ni", AtW, rn)
    return _solve3(Mt, b), Mt


def _supported_planes(A, rn, wts, keep, ridge, share, support_gate=GATE_SIGMAS):
    """Every well-supported inverse-depth plane of each ray's neighbours (a crease has two).

    Each triple of usable neighbours gives an exact plane; those that at
    least ``share`` of the ray's usable neighbours agree with (within
    ``support_gate`` noise units, as in :func:`_local_planes`) are refitted
    by weighted least squares on their agreeing neighbours. Returns the
    planes ``(n, T, 3)``, their normal matrices ``(n, T, 3, 3)`` and the
    mask ``(n, T)`` of the well-supported ones (T triples).
    """
    n, k, _ = A.shape
    if k < 3:
        return np.zeros((n, 0, 3)), np.zeros((n, 0, 3, 3)), np.zeros((n, 0), bool)
    usable, _, inl = _triple_planes(A, rn, wts, keep, support_gate)
    ok = usable & (inl.sum(axis=2) >= share * keep.sum(axis=1)[:, None] - 1e-9)
    w = wts[:, None, :] * inl
    Mt = (np.einsum("ntk,nki,nkj->ntij", w, A, A)
          + ridge * (wts * keep).sum(axis=1)[:, None, None, None] * np.eye(3))
    b = np.einsum("ntk,nki,nk->nti", w, A, rn)
    T = inl.shape[1]
    wv = _solve3(Mt.reshape(n * T, 3, 3), b.reshape(n * T, 3)).reshape(n, T, 3)
    return wv, Mt, ok


def _solve3(M, b):
    """Solutions of stacks of 3x3 systems ``M w = b`` by Cramer's rule."""
    m0, m1, m2 = M[:, :, 0], M[:, :, 1], M[:, :, 2]
    c0, c1, c2 = np.cross(m1, m2), np.cross(m2, m0), np.cross(m0, m1)
    det = np.einsum("ni,ni->n", m0, c0)
    det = np.where(np.abs(det) > 1e-300, det, 1e-300)
    return np.column_stack([np.einsum("ni,ni->n", b, c0), np.einsum("ni,ni->n", b, c1),
                            np.einsum("ni,ni->n", b, c2)]) / det[:, None]



def _grow_epipolar(r1, cand, n2, seeds, neighbours=6, scale=2.0, rounds=15, final_scale=EPI_FINAL, ridge=1e-3,
                   tree2=None, memory_budget=None):
    """Match along the epipolar arcs, each ray at the inverse depth of its matched neighbours.

    The inverse depth of a plane is linear in the ray, ``rho(u) = w . u``:
    ``w`` is fitted (weighted least squares in arc angle) on the
    ``neighbours`` matched rays nearest to each ray, and predicts where on
    its epipolar arc the ray lands; candidates within ``scale`` noise gates
    of the prediction are matched one-to-one, closest first, until the
    matches repeat; the last round uses ``final_scale``. A ray farther than
    ``REACH_SPACINGS`` match spacings from every match is not predicted.

    In the last round the distance along the arc is measured against the
    pair's noise plus the prediction's own variance (the fitted plane's
    covariance carried to the ray, :func:`_local_planes`, times the squared
    arc-angle sensitivity ``d phi / d rho = sin alpha / (1 + 2 rho cos alpha
    + rho^2)``): a ray predicted by few or one-sided neighbours gets a
    longer window along its arc, one inside many neighbours a tight one.
    Across the arc the test stays the pair's noise. The wider window keeps
    true pairs that the plain noise gate loses; the growth rounds keep the
    plain distance, since their wider gates with the longer windows let a
    growth drift onto chance pairs. The last round also measures each
    candidate against every plane that ``EPI_SHARE`` of the ray's
    neighbours agree with (:func:`_supported_planes`), keeping the nearest
    prediction, and, given the tree ``tree2`` of view 2's rays, keeps the
    matches whose posterior (:func:`catadioptric.acceptance.posterior`)
    reaches ``MIN_POSTERIOR``: the other candidates of either ray inside
    the gate are its rivals. This replaces a ratio test, which dropped true
    pairs for rivals well beyond them and kept fewer true pairs at equal
    precision; see docs/design-notes.md (catadioptric).

    ``cand``: :func:`_epipolar_candidates`; ``n2``: the number of view 2's
    rays; ``memory_budget``: bytes the last round's table of candidates x
    predicting planes may take (else :class:`~gatv.errors.InputError`).
    """
    ii, jj, phi, across, sig, alpha = cand
    n1 = r1.shape[0]
    # each candidate's inverse depth
    rho_c = _inverse_depth(np.minimum(phi, alpha[ii] - 1e-6), alpha[ii])
    order = np.lexsort((jj, ii))
    ii, jj, phi, across, sig, rho_c = ii[order], jj[order], phi[order], across[order], sig[order], rho_c[order]
    # the seeds that are candidates, and their rows among the candidates
    pair_id = ii * n2 + jj
    pid = seeds[:, 0] * n2 + seeds[:, 1]
    pos = np.minimum(np.searchsorted(pair_id, pid), max(pair_id.size - 1, 0))
    ok = (pair_id[pos] == pid) if pair_id.size else np.zeros(len(pid), bool)
    pairs = seeds[ok]
    k_of = pos[ok]
    sa = np.sin(alpha)
    for r in range(rounds + 1):
        last = r == rounds
        m = pairs.shape[0]
        if m < 4:
            return np.empty((0, 2), np.int64)
        xs = r1[pairs[:, 0]]
        rho_m = rho_c[k_of]
        D = 1.0 + 2.0 * rho_m * np.cos(alpha[pairs[:, 0]]) + rho_m ** 2
        wts = (sa[pairs[:, 0]] / D) ** 2 / sig[k_of] ** 2
        k = min(neighbours + 1, m)
        tree = cKDTree(xs)
        dist, nb = tree.query(r1, k=k)
        dist, nb = dist.reshape(n1, k), nb.reshape(n1, k)
        # leave the ray itself out of its own prediction
        self_hit = pairs[nb, 0] == np.arange(n1)[:, None]
        keep = ~self_hit
        keep &= np.cumsum(keep, axis=1) <= k - 1
        A = xs[nb]                                        # (n1, k, 3)
        wv, Mt = _local_planes(A, rho_m[nb], wts[nb], keep, ridge)
        spacing = float(np.median(tree.query(xs, k=2)[0][:, 1])) if m > 1 else 1.0
        reach = np.where(keep, dist, np.inf).min(axis=1)
        valid = reach <= REACH_SPACINGS * spacing
        s = final_scale if last else scale
        if last:
            # along the arc the prediction's own error adds to the pair's
            # noise (a Mahalanobis distance in units of the pair's noise):
            # the plane's covariance (its weights are inverse variances)
            # carried to the ray, times (d phi / d rho)^2; every
            # well-supported plane predicts too, the nearest counts
            wv, Mt, okp = wv[:, None], Mt[:, None], np.ones((n1, 1), bool)
            if EPI_SHARE < 1.0:
                wvt, Mtt, okt = _supported_planes(A, rho_m[nb], wts[nb], keep, ridge, EPI_SHARE)
                wv, Mt, okp = np.concatenate([wv, wvt], 1), np.concatenate([Mt, Mtt], 1), np.hstack([okp, okt])
            P = wv.shape[1]
            check_memory(_BYTES_PER_CANDIDATE_PLANE * ii.size * P,
                         f"{ii.size:,} epipolar candidates x {P} planes", memory_budget)
            rho_pred = np.einsum("npi,ni->np", wv, r1)
            phi_pred = _arc_angle(rho_pred, alpha[:, None])
            rr = np.broadcast_to(r1[:, None, :], (n1, P, 3)).reshape(-1, 3)
            var_rho = np.maximum(np.einsum("ni,ni->n", rr, _solve3(Mt.reshape(-1, 3, 3), rr)).reshape(n1, P), 0.0)
            dpred = sa[:, None] / (1.0 + 2.0 * rho_pred * np.cos(alpha)[:, None] + rho_pred ** 2)
            var_pred = np.nan_to_num(var_rho * dpred ** 2, nan=np.inf)
            st = np.sqrt(sig[:, None] ** 2 + var_pred[ii])
            dt = np.hypot((phi[:, None] - phi_pred[ii]) * sig[:, None] / st, across[:, None])
            near = np.argmin(np.where(okp[ii], dt, np.inf), axis=1)[:, None]
            dd = np.take_along_axis(dt, near, axis=1)[:, 0]
            s_along = np.take_along_axis(st, near, axis=1)[:, 0]
        else:
            phi_pred = _arc_angle(np.einsum("ni,ni->n", wv, r1), alpha)
            dd = np.hypot(phi - phi_pred[ii], across)
        okc = valid[ii] & (dd <= s * GATE_SIGMAS * sig)
        cp = np.column_stack([ii[okc], jj[okc]])
        if cp.shape[0] == 0:
            return cp
        sel = one_to_one(cp, dd[okc])
        new = cp[sel]
        new_k = np.flatnonzero(okc)[sel]
        o = np.argsort(new[:, 0], kind="stable")
        new, new_k = new[o], new_k[o]
        if last:
            if tree2 is not None and MIN_POSTERIOR > 0.0 and new.shape[0]:
                # every candidate inside the gate is a possible partner
                like = likelihood(dd / sig, sig, s_along)
                rivals = rival_likelihood(new, like[new_k], cp, like[okc], n1, n2)
                post = posterior(new, like[new_k], tree2, np.count_nonzero(valid), rivals)
                new = new[post >= MIN_POSTERIOR]
            return new
        if new.shape == pairs.shape and np.array_equal(new, pairs):
            rounds = r + 1
        pairs, k_of = new, new_k
    return pairs


def epipolar_stage(r1, r2, tree2, s1, s2, seeds, noise, max_parallax, rng, info, memory_budget=None):
    """Motion (R, t) and the pairs matched along its epipolar arcs, or None (``info["epipolar_reason"]``).

    The RANSAC pool: local-triangle matches whose rotation lies within the
    parallax spread of the densest cluster (three pairs each, sampled as
    a unit), plus the pairs ``seeds`` of the earlier stages.

    Parameters
    ----------
    r1, r2 : (N1, 3), (N2, 3) ndarray
        Unit rays; ``tree2`` the :class:`~scipy.spatial.cKDTree` of ``r2``.
    s1, s2 : (N1,), (N2,) ndarray
        Per-ray sphere noise; ``noise`` their median.
    seeds : (K, 2) ndarray of int
        Pairs of the rotation or locally rigid stage.
    max_parallax : float
        Largest chord from ``R x`` to a candidate partner.
    rng : numpy.random.Generator
        Draws the RANSAC samples.
    info : dict
        Receives the stage's diagnostics (``epipolar_*`` keys).
    memory_budget : float, optional
        Bytes a table of the stage may take.

    Returns
    -------
    tuple or None
        ``(R, t, pairs)``: the motion (``t`` a unit vector) and the
        matched pairs (rows of ``r1, r2``).
    """
    Rd, _, _, tri = dominant_rotation(r1, r2, EPI_SHAPE_TOL, EPI_CLUSTER_DEG, EPI_MATCHES, memory_budget)
    sets = [tri]
    # the deeper retrieval brings more true triangles but also more chance
    # ones, which can form a denser wrong cluster: when the densest cluster
    # of the 8 most similar triangles (the rotation search's retrieval)
    # lies elsewhere, its triangles give hypotheses too, and growth decides
    R8, _, _, tri8 = dominant_rotation(r1, r2, EPI_SHAPE_TOL, EPI_CLUSTER_DEG, memory_budget=memory_budget)
    if Rd is not None and R8 is not None and tri8.shape[0]:
        c = (float(np.trace(Rd.T @ R8)) - 1.0) / 2.0
        if math.degrees(math.acos(min(1.0, max(-1.0, c)))) > EPI_CLUSTER_DEG:
            sets.append(tri8)
    info["epipolar_clusters"] = len(sets)
    pool = np.vstack([seeds.reshape(-1, 2)] + [t.reshape(-1, 2) for t in sets])
    pool, inverse = np.unique(pool, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    group_sets, start = [], seeds.shape[0]
    for t in sets:
        n = t.shape[0] * 3
        group_sets.append(inverse[start:start + n].reshape(-1, 3) if n else None)
        start += n
    info["epipolar_pool"] = int(pool.shape[0])
    seeds = pool
    if seeds.shape[0] < MIN_ESSENTIAL_PAIRS:
        info["epipolar_reason"] = f"fewer than {MIN_ESSENTIAL_PAIRS} candidate pairs for the essential matrix"
        return None
    x, y = r1[seeds[:, 0]], r2[seeds[:, 1]]
    sig = np.sqrt(s1[seeds[:, 0]] ** 2 + s2[seeds[:, 1]] ** 2)
    ests = [e for groups in group_sets
            for e in _estimate_motions(x, y, sig, rng, groups, memory_budget=memory_budget)]
    if not ests:
        info["epipolar_reason"] = "no essential matrix with 8 or more supporting pairs"
        return None
    best = None
    for R, t, inl in ests:
        pairs, grown = seeds[inl], np.empty((0, 2), np.int64)
        for it in range(EPI_OUTER):
            cand = _epipolar_candidates(r1, r2, tree2, s1, s2, R, t, max_parallax, memory_budget)
            new = _grow_epipolar(r1, cand, r2.shape[0], pairs, tree2=tree2, memory_budget=memory_budget)
            if new.shape[0] < MIN_ESSENTIAL_PAIRS:
                break
            converged = it > 0 and np.array_equal(new, grown)
            grown = pairs = new
            if converged or it + 1 == EPI_OUTER:
                break
            sig_p = np.sqrt(s1[pairs[:, 0]] ** 2 + s2[pairs[:, 1]] ** 2)
            R, t = _refine_motion(R, t, r1[pairs[:, 0]], r2[pairs[:, 1]], sig_p)
        info.setdefault("epipolar_hypotheses", []).append((int(np.count_nonzero(inl)), int(grown.shape[0])))
        if grown.shape[0] and (best is None or grown.shape[0] > best[2].shape[0]):
            best = (R, t, grown)
    if best is None:
        info["epipolar_reason"] = f"growth along the epipolar arcs found fewer than {MIN_ESSENTIAL_PAIRS} pairs"
        return None
    R, t, pairs = best
    sig_p = np.sqrt(s1[pairs[:, 0]] ** 2 + s2[pairs[:, 1]] ** 2)
    R, t = _refine_motion(R, t, r1[pairs[:, 0]], r2[pairs[:, 1]], sig_p)
    # growth cannot jump gaps wider than its reach: grow once more from the
    # matches and every pool pair consistent with the final motion
    consistent = (_epipolar_distance(essential_from_motion(R, t), x, y) <= GATE_SIGMAS * sig) & _cheirality(R, t, x, y)
    cand = _epipolar_candidates(r1, r2, tree2, s1, s2, R, t, max_parallax, memory_budget)
    again = _grow_epipolar(r1, cand, r2.shape[0], np.unique(np.vstack([pairs, seeds[consistent]]), axis=0),
                           tree2=tree2, memory_budget=memory_budget)
    info["epipolar_regrown"] = int(again.shape[0])
    if again.shape[0] > pairs.shape[0]:
        pairs = again
    # no parallax: a pure rotation, whose t is arbitrary (the rigid stage's case)
    phi, _, _ = _arc_coordinates(r1[pairs[:, 0]] @ R.T, t, r2[pairs[:, 1]]) if pairs.size else (np.zeros(1),) * 3
    info["epipolar_median_parallax"] = float(np.median(phi))
    if not np.median(phi) > EPI_MIN_PARALLAX * noise:
        info["epipolar_reason"] = "no parallax: the views differ by a rotation only"
        return None
    return R, t, pairs

