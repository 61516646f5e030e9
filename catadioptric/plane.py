"""A plane moved rigidly, seen on the sphere: the plane-induced mapping of the rays.

The rays of the points of a plane ``n·X = d`` (view 1's frame) that moves
rigidly, ``X' = R X + t``, are related by a homography of the sphere:
``y ∝ H x`` with ``H = R + t nᵀ / d`` (8 degrees of freedom, fixed by 4
pairs). This is the second motion of the real catadioptric pairs (a
hand-held checkerboard in front of a static corridor), found on the rays
that the dominant motion leaves unexplained: the peeling of section 5 of
Reyes, Medioni & Bayro (IJCV 2007), on the sphere.

Stages (:func:`plane_stage`):

1. **Trial mappings.** Local quadruples (a ray and three of its nearest
   neighbours, oriented counter-clockwise) are matched between the views
   by their affine signature (the coordinates of the fourth ray in the
   frame of the first three, on the tangent plane; a homography is locally
   affine). Each match fixes a homography (:func:`homography_from_rays`).
2. **Local score, then growth.** Each trial is scored on the rays around
   its quadruple; the best are grown over ever larger neighbourhoods with
   the homography refitted on its gated one-to-one pairs (like the
   rotation's ICP), then scored on all rays.
3. **Repeated structure** (:func:`resolve_pattern`). A regular pattern
   matches itself shifted by one period; the true mapping explains every
   visible corner of the pattern, a shifted one leaves a row or a column
   unmatched (and moves the pattern's border onto empty sphere). The
   winner is compared with every distinct rival (the other grown trials
   and the winner's matches shifted by one neighbour step) by a one-sided
   sign test on the rays that one explains and the other does not. A
   mapping that leaves significantly more rays unexplained than another
   loses; among the rest the best fit (:func:`mapping_score`) wins. A
   rival that nothing distinguishes (a pattern symmetric under a half-turn
   matches itself turned, with every corner explained) is reported in
   ``info["tie"]``.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import binom, norm

from catadioptric.constants import (
    GATE_SIGMAS,
    PATTERN_ALPHA,
    PLANE_GROWTH,
    PLANE_LOCAL,
    PLANE_MATCHES,
    PLANE_NEIGHBOURS,
    PLANE_SIGNATURE_TOL,
    PLANE_TRIALS,
    PLANE_TRIALS_GROWN,
    SHIFTED_MAPPINGS,
)
from catadioptric.rotation import gated_pairs

__all__ = [
    "apply_homography",
    "decompose_homography",
    "fit_homography",
    "homography_from_rays",
    "mapping_score",
    "plane_stage",
    "resolve_pattern",
    "sign_test",
]


# --------------------------------------------------------------- the mapping
def apply_homography(H, rays):
    """Unit rays ``H x / |H x|`` of view 1's ``rays`` (rows with ``H x = 0`` are inf)."""
    z = np.asarray(rays, dtype=np.float64) @ np.asarray(H, dtype=np.float64).T
    n = np.linalg.norm(z, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = z / n
    out[~np.isfinite(out).all(axis=-1)] = np.inf
    return out


def _dlt_rows(x, y):
    """The two rows of ``y × (H x) = 0`` per pair, for the 9 entries of ``H`` (row-major)."""
    z = np.zeros_like(x)
    u, v, w = y[..., 0:1], y[..., 1:2], y[..., 2:3]
    r1 = np.concatenate([z, -w * x, v * x], axis=-1)
    r2 = np.concatenate([w * x, z, -u * x], axis=-1)
    return np.concatenate([r1, r2], axis=-2)


def homography_from_rays(x, y):
    """Homographies of stacks of 4 (or more) ray pairs: ``y ∝ H x``.

    Parameters
    ----------
    x, y : (T, K, 3) ndarray of float
        ``K >= 4`` pairs of unit rays per trial.

    Returns
    -------
    (T, 3, 3) ndarray
        Unit Frobenius norm, signed so that ``(H x) · y > 0`` on the pairs
        (the plane lies in front of both views).
    """
    A = _dlt_rows(x, y)
    # The null vector only: no 2K x 2K U (full V while 2K < 9, where the reduced one would lack it).
    _, _, vt = np.linalg.svd(A, full_matrices=A.shape[-2] < A.shape[-1])
    H = vt[:, -1, :].reshape(-1, 3, 3)
    s = np.einsum("tij,tkj,tki->t", H, x, y)
    return H * np.where(s < 0, -1.0, 1.0)[:, None, None]


def _frame(rays):
    """A 3x3 map of rays to normalised gnomonic coordinates about their mean (Hartley's scaling)."""
    m = rays.mean(axis=0)
    m /= np.linalg.norm(m)
    a = np.array([1.0, 0.0, 0.0]) if abs(m[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(m, a)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(m, e1)
    Q = np.vstack([e1, e2, m])
    g = rays @ Q.T
    p = g[:, :2] / np.maximum(g[:, 2:3], 1e-6)
    c = p.mean(axis=0)
    s = math.sqrt(2.0) / max(float(np.mean(np.linalg.norm(p - c, axis=1))), 1e-12)
    return np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]]) @ Q


def fit_homography(x, y):
    """Least-squares homography ``y ∝ H x`` of ``K >= 4`` ray pairs (normalised DLT).

    Both sets are mapped to gnomonic coordinates about their mean ray and
    scaled to a mean distance ``sqrt(2)`` (Hartley) before the DLT, which
    conditions the fit on a small patch of the sphere.
    """
    T1, T2 = _frame(x), _frame(y)
    xn, yn = x @ T1.T, y @ T2.T
    Hn = homography_from_rays(xn[None], yn[None])[0]
    H = np.linalg.solve(T2, Hn @ T1)
    H /= np.linalg.norm(H)
    if float(np.sum((x @ H.T) * y)) < 0:
        H = -H
    return H


def decompose_homography(H):
    """The motions ``(R, t, n)`` with ``H ∝ R + t nᵀ`` (Faugeras' SVD decomposition).

    ``t`` is the translation over the plane's distance ``d`` (view 1's
    frame) and ``n`` the plane's unit normal. Of the up to eight algebraic
    solutions, those that put the plane in front of view 1 (``n`` pointing
    towards the mean ray's side, ``n₃``-sign chosen so) are returned, at
    most four; two of them are physically valid when the matched rays are
    known (:func:`plane_stage` keeps those with every matched ray in front
    of both views). A pure rotation (``t = 0``) gives ``R`` alone.
    """
    U, d, Vt = np.linalg.svd(H)
    H = H / d[1]
    d = d / d[1]
    s = np.linalg.det(U) * np.linalg.det(Vt)
    d1, d2, d3 = d
    out = []
    if d1 - d3 < 1e-9:
        R = s * U @ Vt
        return [(R, np.zeros(3), np.array([0.0, 0.0, 1.0]))]
    x1 = math.sqrt(max(0.0, (d1 * d1 - d2 * d2) / (d1 * d1 - d3 * d3)))
    x3 = math.sqrt(max(0.0, (d2 * d2 - d3 * d3) / (d1 * d1 - d3 * d3)))
    for e1, e3 in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        # d' = +d2 (the solutions with d' = -d2 reverse the orientation)
        st = (d1 - d3) * e1 * x1 * e3 * x3 / d2
        ct = (d1 * d3 + d2 * d2) / ((d1 + d3) * d2)
        Rp = np.array([[ct, 0.0, -st], [0.0, 1.0, 0.0], [st, 0.0, ct]])
        tp = (d1 - d3) * np.array([e1 * x1, 0.0, -e3 * x3])
        np_ = np.array([e1 * x1, 0.0, e3 * x3])
        R = s * U @ Rp @ Vt
        t = U @ tp
        n = Vt.T @ np_
        out.append((R, t * s, n))
    return out


# --------------------------------------------------------------- trial mappings
def _tangent(rays, anchor):
    """Gnomonic coordinates of ``rays`` (..., 3) on the tangent planes at ``anchor`` (..., 3)."""
    a = anchor
    ref = np.where(np.abs(a[..., :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = np.cross(a, ref)
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    e2 = np.cross(a, e1)
    dot = np.sum(rays * a, axis=-1)
    p = rays / np.maximum(dot, 1e-6)[..., None] - a
    return np.stack([np.sum(p * e1, axis=-1), np.sum(p * e2, axis=-1)], axis=-1)


def _quads(rays, k):
    """Oriented local quadruples ``(a, b, c, d)`` and their affine signatures.

    ``b, c, d`` are among the ``k`` nearest rays of ``a``; ``(a, b, c)``
    turns counter-clockwise seen from outside the sphere; the signature is
    ``(α, β)`` with ``d − a = α (b − a) + β (c − a)`` on the tangent plane
    at ``a`` (an affine invariant). Nearly degenerate frames (``b``, ``c``
    almost collinear with ``a``) and far fourth rays are dropped.
    """
    n = rays.shape[0]
    k = min(k, n - 1)
    if k < 3:
        return np.empty((0, 4), np.int64), np.empty((0, 2))
    _, nb = cKDTree(rays).query(rays, k=k + 1)
    nb = nb[:, 1:]
    P = _tangent(rays[nb], rays[:, None, :])  # (n, k, 2)
    combos = [(p, q, r) for p in range(k) for q in range(k) for r in range(k) if len({p, q, r}) == 3]
    p, q, r = (np.array(c) for c in zip(*combos, strict=True))
    B, C, D = P[:, p], P[:, q], P[:, r]  # (n, m, 2)
    det = B[..., 0] * C[..., 1] - B[..., 1] * C[..., 0]
    lb, lc = np.linalg.norm(B, axis=-1), np.linalg.norm(C, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        alpha = (D[..., 0] * C[..., 1] - D[..., 1] * C[..., 0]) / det
        beta = (B[..., 0] * D[..., 1] - B[..., 1] * D[..., 0]) / det
        sin = det / (lb * lc)
    ok = (sin > 0.3) & (np.abs(alpha) <= 2.5) & (np.abs(beta) <= 2.5)
    ii, mm = np.nonzero(ok)
    quads = np.column_stack([ii, nb[ii, p[mm]], nb[ii, q[mm]], nb[ii, r[mm]]]).astype(np.int64)
    return quads, np.column_stack([alpha[ii, mm], beta[ii, mm]])


def trial_homographies(r1, r2, rng, *, tol=PLANE_SIGNATURE_TOL, matches=PLANE_MATCHES,
                       trials=PLANE_TRIALS):
    """Homographies of view-1 quadruples onto view-2 quadruples of the same affine signature.

    Returns ``(H (T, 3, 3), anchors (T,) view-1 rays)``; at most ``trials``
    of them (a seeded random subset beyond).
    """
    q1, g1 = _quads(r1, PLANE_NEIGHBOURS)
    q2, g2 = _quads(r2, PLANE_NEIGHBOURS)
    if q1.shape[0] == 0 or q2.shape[0] == 0:
        return np.empty((0, 3, 3)), np.empty(0, np.int64)
    k = min(matches, q2.shape[0])
    dist, j = cKDTree(g2).query(g1, k=k, distance_upper_bound=tol)
    dist, j = dist.reshape(len(g1), -1), j.reshape(len(g1), -1)
    ii, kk = np.nonzero(np.isfinite(dist))
    if ii.size > trials:
        pick = np.sort(rng.choice(ii.size, trials, replace=False))
        ii, kk = ii[pick], kk[pick]
    a, b = q1[ii], q2[j[ii, kk]]
    H = homography_from_rays(r1[a], r2[b])
    ok = np.all(np.isfinite(H), axis=(1, 2))
    return H[ok], a[ok, 0]


# --------------------------------------------------------------- growth
def grow_homography(H, r1, r2, tree2, s1, s2, anchor, order1=None):
    """Grow a trial homography from its anchor outwards; returns ``(H, pairs)``.

    The homography is refitted on its gated one-to-one pairs among the
    ``PLANE_GROWTH`` nearest rays of the anchor, then the ever larger sets,
    then all rays, with the gate narrowing from 2 noise gates to 1 at the
    end (a homography from four neighbouring rays extrapolates poorly, so
    the pairs are taken near it first).
    """
    n1 = r1.shape[0]
    if order1 is None:
        order1 = np.argsort(np.linalg.norm(r1 - r1[anchor], axis=1), kind="stable")
    pairs = np.empty((0, 2), np.int64)
    sizes = [m for m in PLANE_GROWTH if m < n1] + [n1]
    for m in sizes:
        rows = order1[:m]
        for _ in range(3):
            moved = np.full((n1, 3), np.inf)
            moved[rows] = apply_homography(H, r1[rows])
            new = gated_pairs(moved, r2, tree2, s1, s2, 2.0)
            if new.shape[0] < 5:
                return H, np.empty((0, 2), np.int64)
            H = fit_homography(r1[new[:, 0]], r2[new[:, 1]])
            if new.shape == pairs.shape and np.array_equal(new, pairs):
                break
            pairs = new
    for _ in range(3):
        new = gated_pairs(apply_homography(H, r1), r2, tree2, s1, s2, 1.0)
        if new.shape[0] < 5:
            return H, np.empty((0, 2), np.int64)
        if new.shape == pairs.shape and np.array_equal(new, pairs):
            break
        pairs = new
        H = fit_homography(r1[pairs[:, 0]], r2[pairs[:, 1]])
    return H, pairs


# --------------------------------------------------------------- repeated structure
def sign_test(a: int, b: int) -> float:
    """One-sided sign test: ``P(Binomial(a + b, 1/2) >= a)``.

    ``a``: rays one mapping explains and the other does not; ``b``: the
    converse. Under "both mappings are equally good" each such ray is
    either's with probability 1/2.
    """
    if a + b == 0:
        return 1.0
    return float(binom.sf(a - 1, a + b, 0.5))


def _explained(pairs, n1):
    m = np.zeros(n1, bool)
    m[pairs[:, 0]] = True
    return m


def _shift_rivals(H, pairs, r1, r2, tree2, s1, s2):
    """The winner's pairs with every partner moved by one neighbour step or turned, grown again.

    For the matched view-2 ray nearest the matches' centre and each of its
    ``PLANE_NEIGHBOURS`` neighbours, every partner ``y_j`` is moved by the
    step between them (one period of a regular pattern) onto the nearest
    ray of view 2; the homography of these shifted pairs is grown like a
    trial. The last rival turns every partner by a half-turn about the
    matches' centre.
    """
    ys = r2[pairs[:, 1]]
    c = ys.mean(axis=0)
    centre = int(np.argmin(np.linalg.norm(ys - c, axis=1)))
    # the matches nearest the centre: on a small patch one step is one vector
    _, near = cKDTree(ys).query(ys[centre], k=min(PLANE_GROWTH[0], ys.shape[0]))
    near = np.atleast_1d(near)
    seeds, yn = pairs[near], ys[near]
    j0 = pairs[centre, 1]
    k = min(PLANE_NEIGHBOURS + 1, r2.shape[0])
    _, nbj = tree2.query(r2[j0], k=k)
    moved = []
    for jn in np.atleast_1d(nbj)[1:]:
        moved.append(tree2.query(yn + (r2[jn] - r2[j0]))[1])
    # the half-turn: every partner reflected through the matches' centroid
    # on the tangent plane there (a pattern symmetric under a half-turn)
    cu = c / np.linalg.norm(c)
    a = np.array([1.0, 0.0, 0.0]) if abs(cu[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(cu, a)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(cu, e1)
    P = _tangent(yn, np.broadcast_to(cu, yn.shape))
    back = cu - P[:, :1] * e1 - P[:, 1:] * e2
    moved.append(tree2.query(back / np.linalg.norm(back, axis=1, keepdims=True))[1])
    out = []
    for jj in moved:
        if np.unique(jj).size < 5:
            continue
        Hs = fit_homography(r1[seeds[:, 0]], r2[jj])
        out.append(grow_homography(Hs, r1, r2, tree2, s1, s2, int(pairs[centre, 0])))
    return out


def resolve_pattern(candidates, r1, r2, tree2, s1, s2, *, alpha=PATTERN_ALPHA, max_rounds=4):
    """The grown mapping that explains the most rays, rivals compared by :func:`sign_test`.

    Parameters
    ----------
    candidates : list of (H, pairs)
        Grown mappings (distinct or not).

    Returns
    -------
    (H, pairs, info) or None
        ``info`` holds ``rivals_tested``, ``rival_support`` (the best
        rival with other partners), ``rival_p`` (its sign-test p-value)
        and, when a rival explains as many rays and nothing tells them
        apart (neither the sign test nor the likelihood gap beyond the
        scores' own noise), ``tie``: the better fit is kept and the tie
        reported.
    """
    cands = [(H, p) for H, p in candidates if p.shape[0] >= 5]
    if not cands:
        return None
    n1 = r1.shape[0]
    seen = {}
    for H, p in cands:
        seen.setdefault(p.tobytes(), (H, p))
    pool = list(seen.values())

    scores = {}

    def rank(c):
        key = c[1].tobytes()
        if key not in scores:
            scores[key] = mapping_score(c[0], c[1], r1, r2, s1, s2)
        return (scores[key], -_displacement(c[1], r1, r2))

    def beaten(w):
        """The rivals that explain significantly more of view 1's rays than ``w`` (sign test)."""
        return [c for c in pool if c[1].shape[0] > w[1].shape[0] and _compare(c[1], w[1], n1) < alpha]

    def choose():
        # whole-pattern support first: a mapping that leaves significantly
        # more rays unexplained than another loses, however tight its fit;
        # among the rest the best fit wins
        standing = [c for c in pool if not beaten(c)]
        return max(standing or pool, key=rank)

    win = choose()
    tested = set()
    for _ in range(max_rounds):
        # shift the winner and the best supported mappings: a regular pattern
        # is reached from a shifted match one period at a time
        top = sorted(pool, key=lambda c: -c[1].shape[0])[:SHIFTED_MAPPINGS]
        fresh = [c for c in [win, *top] if c[1].tobytes() not in tested]
        if not fresh:
            break
        for c in fresh:
            tested.add(c[1].tobytes())
            for H, p in _shift_rivals(c[0], c[1], r1, r2, tree2, s1, s2):
                if p.shape[0] >= 5:
                    pool.append((H, p))
        win = choose()
    # rivals with other partners: the strongest, and whether the sign test tells it apart
    info = {"rivals_tested": len(pool)}
    own = set(map(tuple, win[1].tolist()))
    best_rival, best_p = None, 1.0
    for H, p in pool:
        shared = sum(tuple(q) in own for q in p.tolist())
        if shared > 0.5 * min(p.shape[0], win[1].shape[0]):
            continue
        pv = _compare(win[1], p, n1)
        if best_rival is None or pv > best_p:
            best_rival, best_p = (H, p), pv
    if best_rival is not None:
        gap = rank(win)[0] - rank(best_rival)[0]
        info.update(rival_support=int(best_rival[1].shape[0]), rival_p=best_p, rival_score_gap=gap,
                    score=rank(win)[0])
        # the scores' own noise: each fits its scale c from its n residuals
        # (sd of log c² about 1/sqrt(n)), so a gap is within noise below
        # the alpha-quantile of a normal with sd sqrt(2 n)
        noise_gap = float(norm.isf(alpha)) * math.sqrt(2.0 * win[1].shape[0])
        if best_p >= alpha and gap < max(noise_gap, math.log(1.0 / alpha)):
            info["tie"] = (
                f"a rival with other partners explains {best_rival[1].shape[0]} rays against "
                f"{win[1].shape[0]} (sign test p = {best_p:.2f}, log-likelihood gap {gap:.1f}, within the "
                f"scores' noise {noise_gap:.1f}): nothing in the geometry tells them apart (a pattern "
                f"symmetric under a half-turn matches itself turned); the better fit is kept")
    return win[0], win[1], info


def mapping_score(H, pairs, r1, r2, s1, s2):
    """Log-likelihood ratio of a mapping's pairs against chance, with the mapping's own noise scale.

    Each pair's residual ``e`` (in per-pair noise units) is Gaussian with
    the scale ``c`` fitted to the mapping's residuals (``mean(e²) = 2 c²``
    on the sphere's tangent plane, ``c`` at least 0.25), against a chance
    partner spread over the gate: ``Σ (g²/2 − e²/(2c²) − 2 log c)`` with
    ``g`` the gate in noise units (``GATE_SIGMAS``), which is
    ``n (g²/2 − 1 − 2 log c)``. A pair at the gate under the assumed noise
    scores 0 (MSAC's truncated quadratic for ``c = 1``); a mapping whose
    residuals are tighter scores more per pair: the true mapping of a
    pattern fits its corners better than a mapping that bends to take
    clutter.
    """
    if pairs.shape[0] == 0:
        return 0.0
    sig = np.sqrt(s1[pairs[:, 0]] ** 2 + s2[pairs[:, 1]] ** 2)
    e2 = np.sum((apply_homography(H, r1[pairs[:, 0]]) - r2[pairs[:, 1]]) ** 2, axis=1) / sig**2
    c2 = max(float(np.mean(e2)) / 2.0, 0.0625)
    return float(np.sum(0.5 * GATE_SIGMAS**2 - 0.5 * e2 / c2 - math.log(c2)))


def _compare(p_win, p_rival, n1):
    """Sign-test p-value that ``p_win`` explains more of view 1's rays than ``p_rival``."""
    a_m, b_m = _explained(p_win, n1), _explained(p_rival, n1)
    return sign_test(int(np.count_nonzero(a_m & ~b_m)), int(np.count_nonzero(b_m & ~a_m)))


def _displacement(pairs, r1, r2):
    """Median angle between the paired rays (radians)."""
    if pairs.shape[0] == 0:
        return math.inf
    c = np.clip(np.sum(r1[pairs[:, 0]] * r2[pairs[:, 1]], axis=1), -1.0, 1.0)
    return float(np.median(np.arccos(c)))


# --------------------------------------------------------------- the stage
def plane_stage(r1, r2, s1, s2, rng, info, *, tree2=None):
    """The plane-induced mapping that explains the most rays, with its repeated-structure check.

    Parameters
    ----------
    r1, r2 : (N1, 3), (N2, 3) ndarray
        Unit rays of the views (those no earlier motion explains).
    s1, s2 : (N1,), (N2,) ndarray
        Their sphere noise.
    rng : numpy.random.Generator
        Draws the subset of trials when there are more than ``PLANE_TRIALS``.
    info : dict
        Receives the stage's diagnostics.

    Returns
    -------
    (H, pairs) or None
        ``pairs`` (K, 2) rows of ``r1, r2``.
    """
    if r1.shape[0] < 5 or r2.shape[0] < 5:
        info["plane_reason"] = "fewer than 5 rays"
        return None
    tree2 = cKDTree(r2) if tree2 is None else tree2
    Hs, anchors = trial_homographies(r1, r2, rng)
    info["plane_trials"] = int(Hs.shape[0])
    if Hs.shape[0] == 0:
        info["plane_reason"] = "no local quadruples of the same shape"
        return None
    # local score: gated hits among the anchor's nearest rays
    k = min(PLANE_LOCAL, r1.shape[0])
    _, nb = cKDTree(r1).query(r1, k=k)
    nb = nb.reshape(r1.shape[0], k)
    rows = nb[anchors]  # (T, k)
    moved = np.einsum("tij,tkj->tki", Hs, r1[rows])
    moved /= np.linalg.norm(moved, axis=-1, keepdims=True)
    gmax = 2.0 * GATE_SIGMAS * math.sqrt(float(s1.max()) ** 2 + float(s2.max()) ** 2)
    flat = moved.reshape(-1, 3)
    d, j = tree2.query(flat, distance_upper_bound=gmax)
    ii = rows.reshape(-1)
    hit = np.isfinite(d)
    jj = np.where(hit, j, 0)
    hit &= d <= 2.0 * GATE_SIGMAS * np.sqrt(s1[ii] ** 2 + s2[jj] ** 2)
    score = hit.reshape(rows.shape).sum(axis=1)
    # equal local scores in random order: the grown trials then spread over
    # the rays (on a regular pattern every lattice-consistent trial scores
    # the same locally, and growth tells them apart)
    shuffle = rng.permutation(score.size)
    order = shuffle[np.argsort(-score[shuffle], kind="stable")]
    grown = []
    used_anchor = {}
    for t in order:
        if len(grown) >= PLANE_TRIALS_GROWN or score[t] < 5:
            break
        a = int(anchors[t])
        # one trial per anchor: the others are mostly the same mapping
        if used_anchor.get(a, 0) >= 1:
            continue
        used_anchor[a] = used_anchor.get(a, 0) + 1
        grown.append(grow_homography(Hs[t], r1, r2, tree2, s1, s2, a))
    info["plane_grown"] = len(grown)
    res = resolve_pattern(grown, r1, r2, tree2, s1, s2)
    if res is None:
        info["plane_reason"] = "no trial mapping grew"
        return None
    H, pairs, pinfo = res
    info.update({f"plane_{k}": v for k, v in pinfo.items()})
    return H, pairs
