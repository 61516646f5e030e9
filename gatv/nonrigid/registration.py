"""Non-rigid registration, the local-constraint mode of section 5.1.

A motion that is rigid only locally (a twist, a bend, an elastic warp) no
longer puts the true pairs on one plane of the ``{dx, dy, dz}`` joint space
(eq. 30) but on a *curved* surface — or, for motions whose displacement
varies along one direction only (a plane rolled around a cylinder), on a
3D *curve* (the paper's conclusions).  Tensor voting finds both; eq. 41 is
then enforced only locally, between each token and its closest active
neighbour (Fig. 14).

How it works
------------
1. **Candidate pairs.** All pairs for small sets (the paper's scheme,
   section 3.4); with ``max_displacement`` only the target points within that
   distance of each source point, and for large sets at most
   ``max_candidates`` nearest ones per source point.
2. **Tensor voting** on the tokens ``d = target[j] − source[i]``: a sparse
   ball pass, then stick passes with growing σ (section 3.3,
   :func:`gatv.voting.extract_surfaces`); no plane is fitted, curved
   surfaces are kept.  When the most salient tokens are curve-like
   (λ2 − λ3 > λ1 − λ2 after the ball pass) the structure is a curve and
   repeated ball passes thresholded on curveness λ2 − λ3 extract it.
3. **Local eq. 41.** Each surviving token is checked against its closest
   active neighbour in the joint space (another surviving token using
   neither of its points): ``|V × (A × Vs)| / |Vs|`` with ``A`` the token's
   surface normal (the local rotation axis); for curves, whose normal is not
   the axis, its length half ``|V · Vs| / |Vs|``.  The tolerance is relaxed
   to ``strain · |Δx| + gate``: a locally rigid motion keeps lengths up to
   the local strain (a twist of ``α`` rad per unit shears a neighbourhood at
   distance ``r`` from its axis by ``α r``), and ``gate`` covers noise.
4. **One-to-one** selection by saliency gives the seeds.  A seed whose
   displacement disagrees with the local affine trend of its neighbouring
   seeds is dropped.
5. **Warp and growth.** Ring by ring, an unmatched source point next to
   the matched region is moved by the local affine map of its matched
   neighbours and takes the nearest free target within the gate; then a
   thin-plate warp through the matches is refitted and re-matched until
   the matches repeat (the non-rigid analogue of the rigid mode's ICP
   polish).  This gives the *voting* hypothesis.
6. **Coarse-to-fine hypotheses.** Many real pairs (the face expressions of
   the benchmark) are a dominant rigid or near-identity motion plus a local
   deformation of about the point spacing, and piecewise-rigid motions (a
   hinge) put two separate surfaces in the joint space: there the voted
   tokens are mostly wrong.  The *coarse* hypothesis starts from the
   identity, the *rigid* one from the dominant rigid motion of
   :func:`gatv.register`; each matches every source point to its nearest
   target under a thin-plate warp whose gate (3 → 0.5 target spacings) and
   smoothing (10⁻¹ → 10⁻⁵ extent²) shrink level by level, fitting each
   level only on matches that agree with the local affine trend of their
   neighbours.
   The *anneal* hypothesis is a deterministic-annealing soft matching with
   an outlier class (TPS-RPM / coherent point drift with the variance
   annealed from ``(extent / 4)²`` to ``(spacing / 2)²``, :func:`_anneal`):
   it starts from displacements of several spacings among many outliers,
   where the hard nearest-target matching of the coarse levels locks on to
   wrong targets.  Its matches are the nearest targets of the annealed warp
   within half a spacing; it replaces another verified hypothesis only when
   it explains ``ANNEAL_PREFERENCE`` times as many matches (it blurs creases).
7. **Verification against chance.** Every hypothesis is scored by its
   matches whose displacement lies within ``0.2`` target spacings of the
   affine trend of their neighbouring matches (leave-one-out).  A wrong
   match passes by chance when a target happens to lie that close to the
   prediction (``≈ n (gate / 2 spacings)²`` with ``n`` targets within two
   spacings); a hypothesis counts only when its estimated chance passes are
   at most a quarter of its support and it explains at least a tenth of
   the smaller set.  The best one is grown (step 5) and only its verified
   matches are reported — fewer, correct matches rather than many wrong
   ones; when none counts the result is empty with ``info["reason"]``.
   The rigid hypothesis is tried with ``prealign=True``, or by default
   (``"auto"``) only when no other hypothesis counts or the annealed one
   wins, with a bounded rigid search (``AUTO_RIGID_TRIPLES`` source
   triples).
8. Each correspondence gets the rigid motion fitted on its nearest matched
   neighbours; the warp's smoothing is chosen by 5-fold cross-validation of
   the matched displacements unless given.

Measured choices (``benchmarks/nonrigid.py``, a 400-point 10 × 10 plane
twisted by 90°, 50% outliers, all 640 000 pairs): tensor voting alone keeps
~280 tokens of which ~64% are true (~78% at 30°), which is enough to seed
steps 4–5; pruning candidates first by neighbour distance preservation
(counting neighbours ``i'`` of ``i`` with a neighbour ``j'`` of ``j`` at
the same distance, ±30% for the twist's strain) kept only 28 of the 400
true pairs among the 16 best candidates per point and was dropped.  On the
600-point face pairs the voted seeds are 13–28% correct (the joint space of
a near-identity motion is one dense blob) while the coarse hypothesis is
95–99% correct before verification; on the hinge the voting hypothesis
finds at most one part and the coarse one both.  Voting alone fails when a
large rigid motion is added on top of a twist (the true surface is then as
sparse as the false tokens); the rigid hypothesis recovers it (a 200-point
plane twisted by 60° then turned by 70°: 198 of 200 pairs, all correct).
Large elastic warps (6 bumps of amplitude 1 and 2, i.e. 2–4 spacings, on
the 10 × 10 plane) with 50% outliers, where the source outliers lie in the
plane among the inliers: no voted or coarse hypothesis beats chance (coarse
support 10–40 of 800), while the annealed one has 146–398 supported
matches, 96–99% correct after growth (2 trials each, ~1–2 s for 800 × 800).
"""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree

from .._validation import as_points, check_positive
from ..candidates import all_pairs, median_spacing, one_to_one
from ..errors import InputError
from .motion import Diagnostics, NonRigidMotion, ThinPlateWarp

__all__ = ["register"]

#: Relative smoothing values tried by the cross-validation (times extent²).
SMOOTHING_GRID = (0.0, 1e-5, 1e-4, 1e-3, 1e-2, 1e-1)


# ------------------------------------------------------------ validation
def _check_points(points, name: str) -> np.ndarray:
    p = as_points(points, name, min_points=4)
    c = p - p.mean(axis=0)
    s = np.linalg.svd(c, compute_uv=False)
    if s[0] <= 1e-12 * max(1.0, float(np.abs(p).max())):
        raise InputError(f"All points of `{name}` are identical; a non-rigid motion needs spread points.")
    if s[1] <= 1e-9 * s[0]:
        raise InputError(f"All points of `{name}` are collinear; a non-rigid motion needs a surface or a volume.")
    return p


def _check_int(value, name: str, minimum: int, allow_none: bool = False):
    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        msg = f"Expected `{name}` to be an integer >= {minimum}, got {value!r}."
        raise InputError(msg)
    return int(value)


def _check_fraction(value, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not np.isfinite(value) or value < 0:
        msg = f"Expected `{name}` to be a finite number >= 0, got {value!r}."
        raise InputError(msg)
    return float(value)


# ------------------------------------------------------------ stage 1
def _candidates(X, Y, tree_y, max_displacement, max_candidates, max_pairs, memory_budget):
    n1, n2 = X.shape[0], Y.shape[0]
    if max_displacement is None and max_candidates is None and n1 * n2 <= max_pairs:
        return all_pairs(n1, n2, memory_budget=memory_budget), "all"
    k = min(n2, max_candidates if max_candidates is not None else max(1, max_pairs // n1))
    bound = np.inf if max_displacement is None else max_displacement
    dist, j = tree_y.query(X, k=k, distance_upper_bound=bound)
    dist, j = dist.reshape(n1, -1), j.reshape(n1, -1)
    ii, kk = np.nonzero(np.isfinite(dist))
    return np.stack([ii, j[ii, kk]], axis=1).astype(np.int64), "bounded"


# ------------------------------------------------------------ stage 2
def _extract_curves(tokens, sigma, n_passes, growth=1.5, threshold=0.1):
    """Curve analogue of section 3.3: ball passes thresholded on λ2 − λ3."""
    from ..voting import vote

    idx = np.arange(tokens.shape[0])
    s = sigma
    votes = vote(tokens, s)
    for p in range(n_passes):
        vals = votes.eigenvalues
        c = vals[:, 1] - vals[:, 2]
        if c.size == 0 or c.max() <= 0:
            return idx[:0], np.empty((0, 3)), np.empty(0), s
        star = int(np.argmax(c))
        keep = (vals[:, 0] >= threshold * vals[star, 0]) & (c >= threshold * c[star])
        idx = idx[keep]
        if p + 1 == n_passes or idx.size < 2:
            return idx, votes.normals[keep], c[keep], s
        s *= growth
        votes = vote(tokens[idx], s)
    return idx, votes.normals, votes.eigenvalues[:, 1] - votes.eigenvalues[:, 2], s


def _detect(tokens, sigma, structure, n_passes, n_expected):
    from ..voting import extract_surfaces

    surf = extract_surfaces(tokens, sigma, n_stick_passes=n_passes)
    ball = surf.ball
    if structure == "auto":
        top = np.argsort(-ball.eigenvalues[:, 0], kind="stable")[:max(3, n_expected)]
        curve = float(np.median(ball.curveness[top])) > float(np.median(ball.surfaceness[top]))
        structure = "curve" if curve else "surface"
    if structure == "surface":
        return np.asarray(surf.indices), np.asarray(surf.normals), np.asarray(surf.surfaceness), "surface"
    idx, normals, sal, _ = _extract_curves(tokens, sigma, n_passes)
    order = np.argsort(idx, kind="stable")
    return idx[order], normals[order], sal[order], "curve"


# ------------------------------------------------------------ stage 3
def _local_eq41(X, Y, pairs, tokens, normals, structure, strain, gate, k=12):
    """Check each token against its closest active neighbour (Fig. 14)."""
    m = pairs.shape[0]
    partner = np.full(m, -1, np.int64)
    ratio = np.full(m, np.inf)
    if m < 2:
        return partner, ratio
    kk = min(k + 1, m)
    _, nb = cKDTree(tokens).query(tokens, k=kk)
    nb = nb.reshape(m, -1)
    i, j = pairs[:, 0], pairs[:, 1]
    active = (i[nb] != i[:, None]) & (j[nb] != j[:, None])
    first = np.argmax(active, axis=1)
    has = active[np.arange(m), first]
    partner[has] = nb[np.arange(m), first][has]
    a = np.flatnonzero(has)
    b = partner[a]
    xi, xj = X[i[a]], X[i[b]]
    yi, yj = Y[j[a]], Y[j[b]]
    V = (yi - xi) - (yj - xj)
    Vs = (yi + xi) - (yj + xj)
    nvs = np.linalg.norm(Vs, axis=1)
    nvs = np.where(nvs > 0, nvs, 1.0)
    if structure == "surface":
        A = normals[a]
        r = np.linalg.norm(np.cross(V, np.cross(A, Vs)), axis=1) / nvs
    else:
        r = np.abs(np.einsum("ij,ij->i", V, Vs)) / nvs
    tol = strain * np.linalg.norm(xi - xj, axis=1) + gate
    ratio[a] = r / tol
    return partner, ratio


# ------------------------------------------------------------ stage 4
def _affine_residuals(Xs, D, k=8):
    """Distance of each seed's displacement from the affine trend of its neighbours."""
    n = Xs.shape[0]
    if n <= 4:
        return np.zeros(n)
    kk = min(k + 1, n)
    _, nb = cKDTree(Xs).query(Xs, k=kk)
    res = np.empty(n)
    for a in range(n):
        others = nb[a, 1:]
        dx = Xs[others] - Xs[a]
        M = np.column_stack([np.ones(len(others)), dx])
        coef, *_ = np.linalg.lstsq(M, D[others], rcond=None)
        res[a] = np.linalg.norm(coef[0] - D[a])
    return res


# ------------------------------------------------------------ stage 5
def _grow_rigid(X, Y, tree_y, seeds, gate, neighbours, max_rounds=200):
    """Grow the matches ring by ring with the local rigid motions.

    An unmatched source point next to the matched region (nearest matched
    source point within 3 matched spacings) is moved by the rigid motion
    fitted on that neighbour's matched neighbourhood; the target point
    nearest to the prediction, within ``gate``, is its candidate.  Each ring
    is made one-to-one (closest first, unused targets only).
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
        pred = _local_affine_predict(xs, ys, tree_s, near, X[free], neighbours)
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


def _local_affine_predict(xs, ys, tree_s, near, query, neighbours):
    """Move ``query[r]`` by the affine map fitted on the matches nearest ``xs[near[r]]``."""
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


def _grow(X, Y, tree_y, seeds, gate, max_iter=30):
    """ICP-like polish with the thin-plate warp: re-match, refit, until stable."""
    pairs = seeds
    for _ in range(max_iter):
        warp = ThinPlateWarp(X[pairs[:, 0]], Y[pairs[:, 1]] - X[pairs[:, 0]])
        new, n_within = _match(warp(X), tree_y, gate)
        if n_within < 4:
            break
        if new.shape == pairs.shape and np.array_equal(new, pairs):
            break
        pairs = new
    return pairs


# ------------------------------------------------------------ coarse-to-fine
#: Gate (times the target scale) and relative smoothing (times extent²) of
#: the coarse-to-fine levels of :func:`_coarse_to_fine`.
COARSE_TO_FINE = ((3.0, 1e-1), (2.0, 3e-2), (1.5, 1e-2), (1.0, 3e-3), (0.7, 1e-3), (0.5, 1e-4),
                  (0.5, 1e-5))


#: Verification gate of a match, times the target scale (:func:`_target_scale`).
VERIFY_GATE = 0.2
#: A hypothesis is kept when its chance passes are at most this share of its support.
CHANCE_SHARE = 0.25
#: ... and when its support is at least this share of the smaller set.
MIN_SHARE = 0.1
#: Source triples of the bounded rigid search of ``prealign="auto"``.
AUTO_RIGID_TRIPLES = 300


def _target_scale(Y, tree_y):
    """Spacing of the target's structure: the 30th percentile of nearest-neighbour distances
    (the median is inflated by sparse outliers)."""
    d = tree_y.query(Y, k=2)[0][:, 1]
    return float(np.percentile(d, 30))


def _match(moved, tree_y, gate):
    """Nearest target of each moved source point within ``gate``, one-to-one.

    Returns the pairs (sorted by source row) and how many source points had
    a target within the gate before the one-to-one selection.
    """
    dist, j = tree_y.query(moved, k=1, distance_upper_bound=gate)
    ok = np.flatnonzero(np.isfinite(dist))
    cand = np.stack([ok, j[ok]], axis=1).astype(np.int64)
    if ok.size == 0:
        return cand, 0
    new = cand[one_to_one(cand, dist[ok])]
    return new[np.argsort(new[:, 0], kind="stable")], int(ok.size)


def _coarse_to_fine(X, Y, tree_y, warp, scale, extent2, floor):
    """Robust smooth-warp matching from a coarse start (a rigid motion or the identity).

    At each level the moved source points are matched to their nearest
    targets within the level's gate (one-to-one), the matches off the local
    affine trend of their neighbours by more than the gate are set aside,
    and a thin-plate warp with the level's smoothing is fitted on the rest;
    gates and smoothing shrink level by level (``COARSE_TO_FINE``).
    """
    pairs = np.empty((0, 2), np.int64)
    for g, rel in COARSE_TO_FINE:
        gate = g * scale + floor
        pairs, _ = _match(warp(X), tree_y, gate)
        if pairs.shape[0] < 5:
            return np.empty((0, 2), np.int64)
        xs, ys = X[pairs[:, 0]], Y[pairs[:, 1]]
        good = _affine_residuals(xs, ys - xs) <= gate
        if good.sum() < 5:
            return np.empty((0, 2), np.int64)
        warp = ThinPlateWarp(xs[good], (ys - xs)[good], rel * extent2)
    return pairs


#: Annealed soft matching (:func:`_anneal`): at most this many points of each
#: set enter the dense soft-assignment matrix (a seeded subsample beyond).
ANNEAL_MAX_POINTS = 1500
#: ... kernel centres of its smooth displacement field (farthest-point sample).
ANNEAL_CONTROL = 200
#: Temperature ratio between levels, EM steps per level, motion-coherence weight
#: (CPD's λ), and outlier mass (times the 75th percentile of the source rows' mass).
ANNEAL_RATE, ANNEAL_STEPS, ANNEAL_LAMBDA, ANNEAL_OUTLIER = 0.8, 2, 2.0, 0.2
#: The annealed hypothesis replaces another verified one only with this many times its support.
ANNEAL_PREFERENCE = 2.0


def _farthest_points(P, k):
    """``k`` indices of ``P`` by farthest-point sampling from its first point."""
    from scipy.spatial.distance import cdist

    sel = [0]
    dmin = cdist(P, P[:1], "sqeuclidean")[:, 0]
    for _ in range(min(k, P.shape[0]) - 1):
        a = int(np.argmax(dmin))
        if dmin[a] <= 0:
            break
        sel.append(a)
        dmin = np.minimum(dmin, cdist(P, P[a:a + 1], "sqeuclidean")[:, 0])
    return np.asarray(sel, np.int64)


def _anneal(X, Y, spacing, seed):
    """Deterministic-annealing soft matching with an outlier class (the *anneal* hypothesis).

    A Gaussian mixture centred on the moved source points explains each
    target, with an extra outlier class (TPS-RPM, Chui & Rangarajan 2003;
    the coherent point drift M-step, Myronenko & Song 2010).  The variance
    ``T`` is not estimated but annealed from ``(extent / 4)²`` down to
    ``(spacing / 2)²`` (ratio ``ANNEAL_RATE``, ``ANNEAL_STEPS`` EM steps per
    level); the displacement field ``v(x) = Σ_c G(x, c) w_c`` is a Gaussian
    kernel of width ``extent / 4`` on ``ANNEAL_CONTROL`` farthest-point
    centres, regularised by ``ANNEAL_LAMBDA · T`` times its kernel norm, so
    the motion is nearly affine while ``T`` is large and gains detail as
    ``T`` shrinks.  The outlier class has mass ``ANNEAL_OUTLIER`` times the
    75th percentile of the source points' total affinity — scale-free, and
    large enough that a target far from every moved source point is left
    out of the fit.  Returns the warp (a callable on (N, 3) points).
    """
    from scipy.spatial.distance import cdist

    rng = np.random.default_rng(seed)
    Xs = X if X.shape[0] <= ANNEAL_MAX_POINTS else X[np.sort(rng.choice(X.shape[0], ANNEAL_MAX_POINTS, replace=False))]
    Ys = Y if Y.shape[0] <= ANNEAL_MAX_POINTS else Y[np.sort(rng.choice(Y.shape[0], ANNEAL_MAX_POINTS, replace=False))]
    extent = float(np.linalg.norm(np.ptp(np.vstack([Xs, Ys]), axis=0))) or 1.0
    beta2 = (0.25 * extent) ** 2
    C = Xs[_farthest_points(Xs, ANNEAL_CONTROL)]
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


def _verify(X, Y, tree_y, pairs, gate, radius):
    """Local-affine check of each match and the number expected to pass by chance.

    A match passes when its displacement is within ``gate`` of the affine
    trend of its neighbouring matches (leave-one-out).  A wrong match passes
    by chance when some target falls within ``gate`` of the predicted
    position: for a surface, with ``n`` targets within ``radius`` of it,
    about ``n (gate / radius)²``.  With ``n_w`` wrong matches among ``K``,
    ``K − passed ≈ n_w (1 − c̄)``; the chance passes are ``n_w c̄``.
    """
    if pairs.shape[0] < 5:
        return np.zeros(pairs.shape[0], bool), np.inf
    xs, ys = X[pairs[:, 0]], Y[pairs[:, 1]]
    res = _affine_residuals(xs, ys - xs)
    ok = res <= gate
    # target density around each match (its own target left out)
    n_near = np.array([len(r) - 1 for r in tree_y.query_ball_point(ys, radius)], dtype=float)
    c = float(np.clip(np.mean(n_near) * (gate / radius) ** 2, 0.0, 0.99))
    n_wrong = (pairs.shape[0] - ok.sum()) / (1.0 - c)
    return ok, n_wrong * c


# ------------------------------------------------------------ stage 6
def _choose_smoothing(Xs, D, seed, max_points=600):
    n = Xs.shape[0]
    if n < 20:
        return 0.0
    rng = np.random.default_rng(seed)
    sub = rng.choice(n, size=min(n, max_points), replace=False)
    Xs, D = Xs[sub], D[sub]
    extent2 = float(np.sum(np.ptp(Xs, axis=0) ** 2)) or 1.0
    folds = np.arange(Xs.shape[0]) % 5
    rng.shuffle(folds)
    best, best_err = 0.0, np.inf
    for rel in SMOOTHING_GRID:
        lam = rel * extent2
        err = 0.0
        for f in range(5):
            test = folds == f
            w = ThinPlateWarp(Xs[~test], D[~test], lam)
            err += float(np.sum((w(Xs[test]) - Xs[test] - D[test]) ** 2))
        if err < best_err * (1 - 1e-9):
            best, best_err = lam, err
    return best


def _batched_kabsch(P, Q):
    """Rigid fits ``Q ≈ P @ R.T + t`` for stacks ``P, Q`` of shape (K, m, 3)."""
    cp, cq = P.mean(axis=1, keepdims=True), Q.mean(axis=1, keepdims=True)
    H = np.einsum("kmi,kmj->kij", P - cp, Q - cq)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("kji,klj->kil", Vt, U)))
    d = np.where(d == 0, 1.0, d)
    D = np.zeros_like(H)
    D[:, 0, 0] = 1.0
    D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    R = np.einsum("kji,kjl,klm->kim", Vt, D, np.transpose(U, (0, 2, 1)))
    t = cq[:, 0] - np.einsum("kij,kj->ki", R, cp[:, 0])
    return R, t


def _local_motions(xs, ys, neighbours, only=None):
    """Rigid motion of each match fitted on its ``neighbours`` nearest matches.

    With ``only`` (indices), fit those rows only; the others are left as the
    identity.
    """
    k = xs.shape[0]
    R, t = np.tile(np.eye(3), (k, 1, 1)), np.zeros((k, 3))
    if k == 0:
        return R, t
    rows = np.arange(k) if only is None else np.asarray(only, dtype=np.int64)
    m = min(neighbours, k)
    _, nb = cKDTree(xs).query(xs[rows], k=m)
    nb = nb.reshape(rows.size, m)
    R[rows], t[rows] = _batched_kabsch(xs[nb], ys[nb])
    return R, t


def _failure(reason, info, diagnostics=None) -> NonRigidMotion:
    info = dict(info, reason=reason)
    z = np.empty((0, 3))
    return NonRigidMotion(np.empty((0, 2), np.int64), z, z, np.empty((0, 3, 3)), z, 0.0,
                          diagnostics, info)


# ------------------------------------------------------------ entry point
def register(
    source,
    target,
    *,
    seed: int = 0,
    max_displacement: float | None = None,
    max_candidates: int | None = None,
    max_pairs: int = 1_500_000,
    noise: float | None = None,
    sigma: float | None = None,
    n_stick_passes: int = 3,
    structure: str = "auto",
    strain: float = 0.35,
    gate: float | None = None,
    smoothing: float | None = None,
    neighbours: int = 8,
    grow: bool = True,
    prealign: bool | str = "auto",
    memory_budget: float | None = None,
) -> NonRigidMotion:
    """Register ``source`` onto ``target`` under a locally rigid, non-rigid motion.

    Parameters
    ----------
    source, target : (N, 3), (M, 3) array_like or object with ``.points``
        The two point sets (at least 4 points each, not collinear); any share
        of either may be outliers.
    seed : int, default: 0
        Seed of the scale estimate's subsample and of the smoothing
        cross-validation folds; same seed, same result.
    max_displacement : float, optional
        Bound on how far a point moves (data units): only target points that
        close to a source point are candidates.
    max_candidates : int, optional
        At most this many candidates (the nearest target points) per source
        point.  Default: all pairs while ``N·M <= max_pairs``, else
        ``max_pairs // N``.
    max_pairs : int, default: 1_500_000
        Largest number of candidate pairs voted on by default.
    noise : float, optional
        Standard deviation of the point noise (data units); widens the gates.
    sigma : float, optional
        Tensor-voting scale; default :func:`gatv.voting.default_sigma`.
    n_stick_passes : int, default: 3
        Stick passes (curve mode: ball passes) of the extraction.
    structure : {"auto", "surface", "curve"}, default: "auto"
        Structure of the true tokens in the joint space.
    strain : float, default: 0.35
        Relative length change between neighbours still called locally
        rigid in the local eq.-41 test.
    gate : float, optional
        Match radius of the warp's growth (data units). Default
        ``max(0.3 · target spacing, 3.5 · noise)``.
    smoothing : float, optional
        Thin-plate smoothing of the warp; default chosen by 5-fold
        cross-validation of the matched displacements (0 for exact data).
    neighbours : int, default: 8
        Matches in each local rigid fit.
    grow : bool, default: True
        Run the warp-and-match growth (step 5) and the coarse-to-fine
        hypotheses (step 6); without it the correspondences are the seeds
        that pass the verification (step 7).
    prealign : {"auto", True, False}, default: "auto"
        Also start the coarse-to-fine matching from the dominant rigid motion
        of :func:`gatv.register` (step 6) — for non-rigid motions on top of
        a large rigid one.  ``"auto"``: only when no other hypothesis beats
        chance, with a bounded search; ``True``: always, unbounded (slow on
        large, cluttered sets); ``False``: never.
    memory_budget : float, optional
        Bytes; inputs needing more fail at once.

    Returns
    -------
    NonRigidMotion
        One-to-one ``correspondences``, local rigid motions and
        :meth:`~NonRigidMotion.warp`; falsy with ``info["reason"]`` when
        nothing was found.

    Raises
    ------
    ValueError
        Fewer than 4 points, NaN/inf, wrong shapes, identical or collinear
        points, bad options, or more candidate pairs than the memory budget.

    References
    ----------
    Reyes, Medioni & Bayro, IJCV 75(3) 2007, eq. 41, section 5.1, Figs. 13–14.

    Examples
    --------
    >>> import numpy as np
    >>> from gatv.nonrigid import register
    >>> from gatv.nonrigid.deformations import sample_plane, twist
    >>> x = sample_plane(100, 10.0, seed=0)
    >>> y = twist(x, 45.0)
    >>> m = register(x, y[::-1])
    >>> bool(np.mean(m.correspondences[:, 1] == 99 - m.correspondences[:, 0]) > 0.95)
    True
    """
    t_start = time.perf_counter()
    X = _check_points(source, "source")
    Y = _check_points(target, "target")
    max_displacement = check_positive(max_displacement, "max_displacement", allow_none=True)
    max_candidates = _check_int(max_candidates, "max_candidates", 1, allow_none=True)
    max_pairs = _check_int(max_pairs, "max_pairs", 1)
    noise = check_positive(noise, "noise", allow_none=True)
    sigma = check_positive(sigma, "sigma", allow_none=True)
    n_stick_passes = _check_int(n_stick_passes, "n_stick_passes", 1)
    if structure not in ("auto", "surface", "curve"):
        raise InputError(f"Expected `structure` to be 'auto', 'surface' or 'curve', got {structure!r}.")
    strain = _check_fraction(strain, "strain")
    gate = check_positive(gate, "gate", allow_none=True)
    if smoothing is not None:
        smoothing = _check_fraction(smoothing, "smoothing")
    neighbours = _check_int(neighbours, "neighbours", 3)
    _check_int(seed, "seed", 0)

    tree_y = cKDTree(Y)
    spacing = median_spacing(Y)
    auto_gate = gate is None and noise is None
    if gate is None:
        gate = max(0.3 * spacing, 3.5 * noise if noise is not None else 0.0)
    info: dict = {"n_source": int(X.shape[0]), "n_target": int(Y.shape[0]), "spacing": spacing,
                  "gate": gate}

    if prealign not in (True, False, "auto"):
        raise InputError(f"Expected `prealign` to be True, False or 'auto', got {prealign!r}.")
    Xv = X

    t0 = time.perf_counter()
    pairs, scheme = _candidates(Xv, Y, tree_y, max_displacement, max_candidates, max_pairs,
                                memory_budget)
    info.update(candidates=scheme, n_candidates=int(pairs.shape[0]))
    if pairs.shape[0] < 4:
        return _failure("fewer than 4 candidate pairs", info)
    tokens = Y[pairs[:, 1]] - Xv[pairs[:, 0]]

    from ..voting import default_sigma

    sig = sigma if sigma is not None else default_sigma(tokens, seed=seed)
    n_expected = min(X.shape[0], Y.shape[0])
    idx, normals, saliency, found = _detect(tokens, sig, structure, n_stick_passes, n_expected)
    info.update(sigma=float(sig), structure=found, n_voted=int(idx.size),
                time_voting_s=time.perf_counter() - t0)
    sp, st = pairs[idx], tokens[idx]

    partner, ratio = _local_eq41(Xv, Y, sp, st, normals, found, strain, gate)
    verified = ratio <= 1.0
    ver = np.flatnonzero(verified)
    keep = ver[one_to_one(sp[ver], -saliency[ver])] if ver.size else ver
    seeds = sp[keep]
    floor = 1e-9 * spacing + (3.5 * noise if noise is not None else 0.0)
    for _ in range(2):  # drop seeds off the local affine trend of their neighbours
        res = _affine_residuals(X[seeds[:, 0]], Y[seeds[:, 1]] - X[seeds[:, 0]])
        if res.size:
            seeds = seeds[res <= 3.0 * float(np.median(res)) + floor]
    if auto_gate and seeds.shape[0] >= 5:
        # exact data: match no wider than the seeds' own departure from local affinity
        res = _affine_residuals(X[seeds[:, 0]], Y[seeds[:, 1]] - X[seeds[:, 0]])
        gate = min(gate, max(8.0 * float(np.median(res)), 1e-6 * spacing))
        info["gate"] = gate
    seeds = seeds[np.argsort(seeds[:, 0], kind="stable")]
    diag = Diagnostics(found, float(sig), int(pairs.shape[0]), sp, st, normals, saliency,
                       np.column_stack([np.arange(sp.shape[0]), partner]),
                       np.where(np.isfinite(ratio), ratio, -1.0), verified, seeds)
    info.update(n_verified=int(ver.size), n_seeds=int(seeds.shape[0]))

    # ---- hypotheses: the local mode's matches and coarse-to-fine warps
    noise_floor = 3.5 * noise if noise is not None else 0.0
    scale = _target_scale(Y, tree_y)
    extent2 = float(np.sum(np.ptp(X, axis=0) ** 2)) or 1.0
    vgate = VERIFY_GATE * scale + noise_floor
    radius = 2.0 * scale + noise_floor
    info.update(scale=scale, verify_gate=vgate)
    hypotheses: dict[str, np.ndarray] = {}
    if seeds.shape[0] >= 4:
        matched = seeds
        if grow:
            matched = _grow_rigid(X, Y, tree_y, seeds, gate, neighbours)
            matched = _grow(X, Y, tree_y, matched, gate)
            # a false seed survives the growth (the warp passes through it): drop
            # matches off the local affine trend of the grown set, and re-match
            res = _affine_residuals(X[matched[:, 0]], Y[matched[:, 1]] - X[matched[:, 0]])
            if res.size:
                kept = matched[res <= max(gate, 3.0 * float(np.median(res)) + floor)]
                if kept.shape[0] >= 4 and kept.shape[0] < matched.shape[0]:
                    matched = _grow(X, Y, tree_y, kept, gate)
        if matched.shape[0] < 4:
            matched = seeds
        hypotheses["voting"] = matched
    if grow:
        hypotheses["coarse"] = _coarse_to_fine(X, Y, tree_y, lambda p: p, scale, extent2, noise_floor)
        t0 = time.perf_counter()
        span = max(median_spacing(X), spacing)
        hypotheses["anneal"], _ = _match(_anneal(X, Y, span, seed)(X), tree_y, 0.5 * scale + noise_floor)
        info["time_anneal_s"] = time.perf_counter() - t0

    def judge(found):
        scores = {}
        for name, pairs in found.items():
            ok, chance = _verify(X, Y, tree_y, pairs, vgate, radius)
            support = int(ok.sum())
            scores[name] = (support, chance, ok)
        info["hypotheses"] = {k: {"support": v[0], "chance": round(float(v[1]), 2)}
                              for k, v in scores.items()}
        least = max(4, MIN_SHARE * min(X.shape[0], Y.shape[0]))
        good = [k for k, v in scores.items() if v[0] >= least and v[1] <= CHANCE_SHARE * v[0]]
        others = [k for k in good if k != "anneal"]
        if others and "anneal" in good:
            # the annealed field is smooth and blurs a crease: on the hinge (50% outliers)
            # it had 380 supported matches against the coarse one's 265, but 2 wrong after
            # the growth against none; it wins only when it explains far more
            top = max(others, key=lambda k: scores[k][0])
            if scores["anneal"][0] < ANNEAL_PREFERENCE * scores[top][0]:
                good = others
        return max(good, key=lambda k: scores[k][0]) if good else None, scores

    best, scores = judge(hypotheses)
    # the annealed hypothesis also recovers part of a large rigid motion (a 200-point
    # twisted plane turned by 70°: 170 matches, 99% correct, where the rigid start
    # gives 198, all correct), so "auto" still tries the rigid start when it wins
    if prealign is True or (prealign == "auto" and best in (None, "anneal") and grow):
        from ..registration import register as rigid_register

        bound = None if prealign is True else AUTO_RIGID_TRIPLES
        rigid = rigid_register(X, Y, seed=seed, noise=noise, max_triples=bound)
        info["prealign"] = {"angle_deg": rigid.angle_deg, "support": rigid.support} if rigid else None
        if rigid:
            hypotheses["rigid"] = _coarse_to_fine(X, Y, tree_y, rigid.transform, scale, extent2,
                                                  noise_floor)
            best, scores = judge(hypotheses)
    info["hypothesis"] = best
    if best is None:
        info["time_s"] = time.perf_counter() - t_start
        return _failure("no hypothesis has more locally consistent matches than chance", info, diag)
    matched = hypotheses[best][scores[best][2]]
    if grow and best != "voting":
        matched = _grow_rigid(X, Y, tree_y, matched, vgate, neighbours)
        matched = _grow(X, Y, tree_y, matched, vgate)
        ok, _ = _verify(X, Y, tree_y, matched, vgate, radius)
        if ok.sum() >= 4:
            matched = matched[ok]
    xs, ys = X[matched[:, 0]], Y[matched[:, 1]]
    lam = smoothing if smoothing is not None else _choose_smoothing(xs, ys - xs, seed)
    R, t = _local_motions(xs, ys, neighbours)
    info["time_s"] = time.perf_counter() - t_start
    return NonRigidMotion(matched, xs, ys, R, t, lam, diag, info)
