"""Multi-resolution non-rigid registration for 10⁴–10⁵ points per set (O(N) memory).

:func:`gatv.nonrigid.register` switches to this path when the candidate
pairs of the direct solve would exceed ``max_pairs``:

1. **Subsample** (:func:`grid_subsample`): each set is reduced to about
   ``coarse_points`` points, one per occupied cell of a voxel grid (the
   point nearest the cell centre), independently for the two sets — so the
   coarse sets are *differently sampled* even when the inputs share rows.
2. **Coarse solve:** the direct mode of section 5.1 (candidate tokens,
   tensor voting, local eq. 41, hypotheses, verification against chance) on
   the coarse sets, its gates widened by the sampling gap of the coarse
   grid (a true partner is up to half a cell away).
3. **Propagate** (:func:`refine`): every source point is moved with the
   coarse warp and matched at full resolution, level by level with a
   shrinking gate: nearest target (one-to-one), matches off the local affine
   trend of their neighbours dropped (leave-one-out, :func:`loo_affine_residuals`),
   and a moving-least-squares local affine warp (:class:`LocalAffineWarp`)
   refitted on the rest.  Memory is O(N·k): only k-nearest-neighbour tables.
4. **Final local matching:** a correspondence is reported only within the
   local sampling gate (half a target spacing plus the noise floor) of the
   final warp, and only when eq. 41 holds locally between its token and its
   nearest matched neighbour's, about the axis of their local rigid motion
   (:func:`local_eq41_pairs`, Fig. 14).

No array here grows as N × M: :func:`memory_estimate` gives the bytes of
the largest allocations, linear in N + M, checked against ``memory_budget``
before any work.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..candidates import BYTES_PER_CANDIDATE_PAIR, median_spacing, one_to_one
from ..fitting import kabsch, umeyama

__all__ = [
    "GROW_AMBIGUITY",
    "GROW_NEIGHBOURS",
    "MLS_NEIGHBOURS",
    "SAMPLING_CONTRAST",
    "SURFACE_GATES",
    "REFINE_LEVELS",
    "LocalAffineWarp",
    "Refined",
    "dense_rows",
    "local_gates",
    "grid_subsample",
    "local_eq41_pairs",
    "loo_affine_residuals",
    "memory_estimate",
    "motion_parts",
    "neighbour_pairs",
    "nonuniform_spacings",
    "on_surfaces",
    "plane_distances",
    "refine",
]

#: Gates of the full-resolution levels, in coarse spacings (then down to the sampling gate).
REFINE_LEVELS = (1.0, 0.5, 0.25)
#: Matches in each moving-least-squares affine fit (the local patch).
MLS_NEIGHBOURS = 12
#: One growth ring: the nearest source points of each match of the last ring (on a uniform
#: sample, within about 2 spacings; on an anisotropic one, e.g. a strip sampled 3x closer across
#: than along, still the next row along it).
GROW_NEIGHBOURS = 12
#: A growth candidate is taken only when its nearest unused target within the gate is at most this
#: share of the distance to the second nearest: the prediction then lies well inside that target's
#: Voronoi cell.  A prediction near a cell boundary (a compressed region, an outlier beside the
#: true partner) would let a slide by one sample start and spread, locally consistent; it waits
#: for a later ring (more matched neighbours) or the final matching.
GROW_AMBIGUITY = 0.5
#: Rows per block when evaluating k-nearest-neighbour fits (bounds temporaries).
_BLOCK = 20_000
#: A local gate (:func:`local_gates`) is at least this share of the gate of the median spacing:
#: near-duplicate rows (a mesh's dense seams) do not shrink it to nothing.
LOCAL_GATE_MIN = 0.5
#: :func:`local_gates` gates by the local spacing only when its 90th percentile is more than this
#: many times its 10th (the sampling is non-uniform).
SAMPLING_CONTRAST = 4.0
#: :func:`on_surfaces` keeps a match within this many of its gates (half a local spacing each, plus
#: the matches' median height) of both local planes: the face's true matches lie within (65 of
#: 23,728 beyond one gate, 1 beyond two), outliers beside the surface mostly not (face at 50%: 220
#: wrong matches, 26).
SURFACE_GATES = 2.0


# ------------------------------------------------------------------ gates
def local_gates(Y, tree_y, gate: float, floor: float = 0.0, rows=None, k: int = 8) -> np.ndarray:
    """The sampling gate of each target row: ``gate`` where the target is sampled about
    uniformly, else half the local spacing plus the noise ``floor``, at least
    ``LOCAL_GATE_MIN`` times ``gate`` (the gate of the median spacing).

    The local spacing of row ``j`` is the median nearest-neighbour distance of its ``k`` nearest
    rows.  A mesh of a body is sampled ten times more densely at the face and hands than along
    the limbs (nearest neighbours 2–26 mm on the body, median 10 mm); one gate from the median
    spacing of the dense rows (6 mm) is a fifth of a limb's spacing, and the growth could not
    follow a limb whose warp it predicts within a third of that spacing; at the face and hands
    the same gate holds two or three samples, and the growth waits there as ambiguous.  The
    sampling is non-uniform when the 90th percentile of the local spacing over the structure's
    rows ``rows`` (default all) is more than ``SAMPLING_CONTRAST`` times the 10th: 5.1–6.5 on
    the body, 1.5–2.8 on the faces, the planes and the bunny (with or without outliers), where
    local gates cost recall (elastic plane at 50% outliers: R 0.999 → 0.993).
    """
    Y = np.asarray(Y, dtype=np.float64)
    if Y.shape[0] < k + 1:
        return np.full(Y.shape[0], float(gate))
    local = _row_spacings(Y, tree_y, k)
    if not _non_uniform(local if rows is None else local[np.asarray(rows)]):
        return np.full(Y.shape[0], float(gate))
    return np.maximum(float(gate) * LOCAL_GATE_MIN, 0.5 * local + floor)


def _row_spacings(P, tree, k: int) -> np.ndarray:
    """Each row's local spacing: the median nearest-neighbour distance of its ``k`` nearest rows."""
    d1 = tree.query(P, k=2)[0][:, 1]
    return np.median(d1[tree.query(P, k=k)[1]], axis=1)


def _non_uniform(local) -> bool:
    """Whether local spacings vary more than ``SAMPLING_CONTRAST`` (90th percentile over 10th)."""
    lo, hi = np.percentile(local, [10, 90])
    return bool(hi > SAMPLING_CONTRAST * lo)


def _within(d, j, gate) -> np.ndarray:
    """``d <= gate`` where ``d``, ``j`` are a k-d tree query's distances and rows ((Q,) or (Q, k));
    ``gate`` a float or a per-target-row array (:func:`local_gates`), then read at each query's
    *nearest* target row, so that the gate follows the place the query lands on, and a farther
    target with a wider gate (an outlier off the surface) does not pass where a nearer one fails.
    False where ``d`` is infinite."""
    ok = np.isfinite(d)
    if np.ndim(gate) == 0:
        return ok & (d <= gate)
    g = np.asarray(gate)
    first = j if d.ndim == 1 else j[:, 0]
    here = np.where(np.isfinite(d if d.ndim == 1 else d[:, 0]), g[np.minimum(first, g.size - 1)], 0.0)
    return ok & (d <= (here if d.ndim == 1 else here[:, None]))


def _bound(gate) -> float:
    return float(np.max(gate)) if np.ndim(gate) else float(gate)


# ------------------------------------------------------------------ subsampling
def grid_subsample(points, n: int, *, min_share: float = 0.0) -> np.ndarray:
    """Indices of about ``n`` points, one per occupied voxel (the point nearest its centre).

    The voxel edge is found by bisection so that the number of occupied
    cells is within 10% of ``n`` (or the closest reached in 30 steps);
    deterministic, O(N log N).  Returns all rows when ``n >= len(points)``.

    Parameters
    ----------
    points : (N, 3) ndarray of float
    n : int
    min_share : float, default: 0
        Skip voxels holding fewer than this share of the median count that a
        point sees in its voxel: a few points scattered through the volume
        (outliers) then take no share of the subsample.

    Returns
    -------
    (K,) ndarray of int
        Sorted row indices.

    Examples
    --------
    >>> import numpy as np
    >>> p = np.random.default_rng(0).uniform(size=(5000, 3)) * [1, 1, 0]
    >>> idx = grid_subsample(p, 500)
    >>> bool(450 <= idx.size <= 550) and bool(np.all(np.diff(idx) > 0))
    True
    """
    p = np.asarray(points, dtype=np.float64)
    N = p.shape[0]
    if n >= N:
        return np.arange(N)
    lo_corner = p.min(axis=0)
    ext = float(np.max(np.ptp(p, axis=0))) or 1.0
    lo, hi = ext * 1e-6, ext  # cell edges: too many cells, too few
    best = None
    for _ in range(30):
        edge = np.sqrt(lo * hi)
        inverse = _cells(p, lo_corner, edge)
        counts = np.bincount(inverse)
        full = np.ones(counts.size, bool)
        if min_share > 0:  # the median count seen by a point, not by a cell
            full = counts >= min_share * float(np.median(counts[inverse]))
        k = int(full.sum())
        if best is None or abs(k - n) < abs(best[0] - n):
            best = (k, edge, inverse, full)
        if abs(k - n) <= 0.1 * n:
            break
        if k > n:
            lo = edge
        else:
            hi = edge
    _, edge, inverse, full = best
    centre = lo_corner + (np.floor((p - lo_corner) / edge) + 0.5) * edge
    d = np.sum((p - centre) ** 2, axis=1)
    order = np.lexsort((np.arange(N), d, inverse))  # by cell, then nearest the centre
    first = np.ones(N, bool)
    first[1:] = inverse[order][1:] != inverse[order][:-1]
    chosen = order[first]
    return np.sort(chosen[full[inverse[chosen]]])


def _cells(p, corner, edge):
    ijk = np.floor((p - corner) / edge).astype(np.int64)
    _, inverse = np.unique(ijk, axis=0, return_inverse=True)
    return inverse.reshape(-1)


def dense_rows(points, k: int = 8, ratio: float = 2.5) -> np.ndarray:
    """Rows whose ``k``-th neighbour is within ``ratio`` times the 25th percentile of that distance.

    A surface sampled at spacing ``h`` has its ``k``-th neighbour at about
    ``h sqrt(k / π)``; outliers scattered through the volume are much
    farther apart.  Used to keep the coarse subsample and the window
    centres on the structure (the full-resolution matching sees every row).
    Returns all rows when fewer than ``2 k`` points.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.shape[0] < 2 * k:
        return np.arange(p.shape[0])
    d = cKDTree(p).query(p, k=k + 1)[0][:, -1]
    keep = np.flatnonzero(d <= ratio * float(np.percentile(d, 25)))
    return keep if keep.size >= 2 * k else np.arange(p.shape[0])


# ------------------------------------------------------------------ local affine fits
def _affine_fit(centres, points, values, ridge: float):
    """Least-squares affine map ``v ≈ c + L (p − centre)`` per row (constant ``c`` returned).

    ``points`` (Q, k, 3) around ``centres`` (Q, 3), ``values`` (Q, k, 3).
    A small ridge on the linear part keeps flat (planar) neighbourhoods
    solvable: the out-of-plane column gets the minimum-norm answer.
    """
    P = points - centres[:, None, :]
    A = np.concatenate([np.ones(P.shape[:2] + (1,)), P], axis=2)
    M = np.einsum("qki,qkj->qij", A, A)
    M[:, 1:, 1:] += ridge * np.eye(3)
    rhs = np.einsum("qki,qkj->qij", A, values)
    return np.linalg.solve(M, rhs)  # (Q, 4, 3)


class LocalAffineWarp:
    """Moving-least-squares warp: at each query, the affine map of its nearest matches.

    ``warp(q) = q + c(q)`` where ``c(q)`` is the constant of the
    least-squares affine fit of the displacements of the ``k`` matched
    source points nearest ``q`` (a locally rigid motion is locally affine).
    O(Q k) time and memory, evaluated in blocks; the k-d tree is of the
    control points only.

    Parameters
    ----------
    points : (K, 3) ndarray
        Matched source points (control points).
    displacements : (K, 3) ndarray
        Their displacements ``target − source``.
    k : int, default: :data:`MLS_NEIGHBOURS`
    spacing : float, optional
        Sampling spacing of the control points (scales the ridge); default their median spacing.
    """

    def __init__(self, points, displacements, k: int = MLS_NEIGHBOURS, spacing: float | None = None):
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        self.displacements = np.ascontiguousarray(displacements, dtype=np.float64)
        self.k = int(min(k, self.points.shape[0]))
        self.tree = cKDTree(self.points) if self.points.shape[0] else None
        if spacing is not None:
            h = float(spacing)
        else:
            h = median_spacing(self.points) if self.points.shape[0] >= 2 else 1.0
        self.ridge = 1e-6 * (h * h) * max(self.k, 1)

    def __call__(self, query) -> np.ndarray:
        q = np.asarray(query, dtype=np.float64).reshape(-1, 3)
        if self.tree is None:
            return q.copy()
        if self.k < 4:
            return q + self.displacements.mean(axis=0)
        out = np.empty_like(q)
        for s in range(0, q.shape[0], _BLOCK):
            qq = q[s:s + _BLOCK]
            _, nb = self.tree.query(qq, k=self.k)
            coef = _affine_fit(qq, self.points[nb], self.displacements[nb], self.ridge)
            out[s:s + _BLOCK] = qq + coef[:, 0, :]
        return out


def loo_affine_residuals(points, displacements, k: int = MLS_NEIGHBOURS) -> np.ndarray:
    """Distance of each displacement from the affine trend of its ``k`` nearest other matches.

    The vectorised, leave-one-out form of
    :func:`gatv.nonrigid.hypotheses.affine_residuals` (O(N k) memory, in
    blocks).  With 4 points or fewer every residual is 0.
    """
    x = np.asarray(points, dtype=np.float64)
    D = np.asarray(displacements, dtype=np.float64)
    n = x.shape[0]
    if n <= 4:
        return np.zeros(n)
    kk = min(k + 1, n)
    tree = cKDTree(x)
    ridge = 1e-6 * median_spacing(x) ** 2 * kk
    res = np.empty(n)
    for s in range(0, n, _BLOCK):
        _, nb = tree.query(x[s:s + _BLOCK], k=kk)
        nb = nb[:, 1:]
        coef = _affine_fit(x[s:s + _BLOCK], x[nb], D[nb], ridge)
        res[s:s + _BLOCK] = np.linalg.norm(coef[:, 0, :] - D[s:s + _BLOCK], axis=1)
    return res


def plane_distances(points, k: int = MLS_NEIGHBOURS) -> np.ndarray:
    """Distance of each point from the least-squares plane of its ``k`` nearest other points.

    On a sampled surface this is the sagitta of the local patch (a few hundredths of a
    spacing on the faces); a point off the surface (an outlier beside it) stands out by its
    height.  O(N k) memory, in blocks.  Fewer than 4 points: zeros.
    """
    p = np.asarray(points, dtype=np.float64)
    n = p.shape[0]
    if n < 4:
        return np.zeros(n)
    kk = min(k + 1, n)
    tree = cKDTree(p)
    out = np.empty(n)
    for s in range(0, n, _BLOCK):
        _, nb = tree.query(p[s:s + _BLOCK], k=kk)
        q = p[nb[:, 1:]]
        c = q.mean(axis=1)
        cov = np.einsum("nki,nkj->nij", q - c[:, None], q - c[:, None])
        normal = np.linalg.eigh(cov)[1][:, :, 0]
        out[s:s + _BLOCK] = np.abs(np.einsum("ni,ni->n", p[s:s + _BLOCK] - c, normal))
    return out


def on_surfaces(X, Y, pairs, gate) -> np.ndarray | None:
    """Matches whose source and target points both lie within ``SURFACE_GATES`` times (``gate`` +
    the matches' median height) of the local plane of the other matched points
    (:func:`plane_distances`; ``gate`` one per match, or a float).  An outlier beside a surface,
    matched to an outlier beside the other, passes the local affine trend (its displacement is
    extrapolated from its neighbours') but not this.  The median height is the surface's own
    sagitta at its sampling: a few hundredths of a spacing on the faces, 0.6 of a gate on a body
    whose limbs are sampled at a third of their radius (there two gates alone would drop 132 of
    4,099 true matches, two gates plus two median heights drop 7 and 43 of the 72 matches with an
    outlier at 30% outliers).  None with fewer than 8 matches."""
    if pairs.shape[0] < 8:
        return None
    g = np.broadcast_to(np.asarray(gate, dtype=float), (pairs.shape[0],))
    ds, dt = plane_distances(X[pairs[:, 0]]), plane_distances(Y[pairs[:, 1]])
    return (ds <= SURFACE_GATES * (g + np.median(ds))) & (dt <= SURFACE_GATES * (g + np.median(dt)))


# ------------------------------------------------------------------ memory
def memory_estimate(n_source: int, n_target: int, coarse_points: int,
                    k: int = MLS_NEIGHBOURS) -> float:
    """Bytes of the largest allocations of the multi-resolution path, linear in N + M.

    Counted: the inputs and their k-d trees, per-row k-nearest-neighbour
    tables and affine systems (in blocks of at most ``_BLOCK`` rows), the
    matches, the per-correspondence local rotations, and the coarse solve
    (``min(coarse_points, N) · min(coarse_points, M)`` candidate pairs at most, times the bytes a pair
    costs downstream).  No N × M term: a larger set costs proportionally
    more.

    Examples
    --------
    >>> a = memory_estimate(10_000, 10_000, 1000)
    >>> b = memory_estimate(20_000, 20_000, 1000)
    >>> bool(b < 2 * a)
    True
    """
    n = int(n_source) + int(n_target)
    per_row = 8 * (3 + 3 + 3 + 3 + 2 + 9 + 3 + 4)  # points, tree, warped, displacement, pair, R, t, misc
    block = min(_BLOCK, max(n_source, n_target)) * 8 * (k * (3 + 3 + 4 + 1) + 16 + 12)
    coarse = float(min(coarse_points, n_source)) * min(coarse_points, n_target) * BYTES_PER_CANDIDATE_PAIR
    return float(n * per_row + block + coarse)


# ------------------------------------------------------------------ propagation
@dataclass(frozen=True, eq=False)
class Refined:
    """The full-resolution matches and the warp they define.

    ``pairs`` (K, 2): one-to-one ``(source row, target row)`` within the
    sampling gate; ``warp`` a :class:`LocalAffineWarp` of them;
    ``levels`` the number of matches kept at each level; ``gate`` the final
    sampling gate.
    """

    pairs: np.ndarray
    warp: LocalAffineWarp
    levels: tuple
    gate: float


def _match(moved, tree, gate):
    dist, j = tree.query(moved, k=1, distance_upper_bound=_bound(gate))
    ok = np.flatnonzero(_within(dist, j, gate))
    cand = np.stack([ok, j[ok]], axis=1).astype(np.int64)
    if ok.size == 0:
        return cand
    new = cand[one_to_one(cand, dist[ok])]
    return new[np.argsort(new[:, 0], kind="stable")]


def refine(X, Y, tree_y, warp, coarse_spacing: float, spacing: float, floor: float,
           *, report=None, max_iter: int = 4, local=None) -> Refined:
    """Propagate a coarse warp to full resolution and match within the sampling gate.

    Levels: ``REFINE_LEVELS`` times ``coarse_spacing`` (plus the noise
    ``floor``), then the sampling gate ``0.5 spacing + floor`` repeated
    until the matches repeat (at most ``max_iter`` times).  At each level
    the moved source points are matched one-to-one to their nearest targets
    within the gate; matches whose displacement is off the leave-one-out
    affine trend of their neighbours by more than the gate are dropped; a
    :class:`LocalAffineWarp` is fitted on the rest and moves the source for
    the next level.  ``local``: per-target-row gates (:func:`local_gates`), used where they are
    wider than a level's gate.
    """
    gate_final = 0.5 * spacing + floor
    gates = [g * coarse_spacing + floor for g in REFINE_LEVELS]
    gates = [g for g in gates if g > gate_final] + [gate_final] * max_iter
    levels = []
    pairs = np.empty((0, 2), np.int64)
    current = warp
    for n, level in enumerate(gates):
        gate = level if local is None else np.maximum(level, local)
        new = _match(current(X), tree_y, gate)
        if new.shape[0] >= 5:
            D = Y[new[:, 1]] - X[new[:, 0]]
            res = loo_affine_residuals(X[new[:, 0]], D)
            new = new[res <= (gate if np.ndim(gate) == 0 else gate[new[:, 1]])]
        if new.shape[0] < 5:
            break
        repeat = level == gate_final and new.shape == pairs.shape and np.array_equal(new, pairs)
        pairs = new
        levels.append(int(pairs.shape[0]))
        current = LocalAffineWarp(X[pairs[:, 0]], Y[pairs[:, 1]] - X[pairs[:, 0]])
        if report is not None:
            report(n / len(gates), f"full resolution: gate {level:.3g}, {pairs.shape[0]} matches")
        if repeat:
            break
    if not levels:
        return Refined(pairs, current if isinstance(current, LocalAffineWarp)
                       else LocalAffineWarp(np.empty((0, 3)), np.empty((0, 3))), (), gate_final)
    return Refined(pairs, current, tuple(levels), gate_final)


# ------------------------------------------------------------------ local eq. 41 at full resolution
def local_eq41_pairs(X, Y, pairs, strain: float, gate, k: int = MLS_NEIGHBOURS):
    """Eq. 41 between each match's token and its nearest matched neighbour's (Fig. 14).

    The local rotation axis ``A`` of each match is that of the rigid motion
    (Kabsch/Horn) of its ``k`` nearest matches; with ``V = d_a − d_b`` and
    ``Vs = s_a − s_b`` the residual is ``|V × (A × Vs)| / |Vs|`` (as
    :func:`gatv.ga.eq41_residual`), and a match passes when it is at most
    ``strain · |x_a − x_b| + gate`` (local strain, sampling and noise; ``gate`` a float or one
    per match).  For
    a rotation of a few degrees the axis is ill-conditioned; then
    ``A × Vs`` is nearly ``Vs`` scaled and the test reduces to the length
    half (``V · Vs``), which is well defined.

    Returns
    -------
    passed : (K,) ndarray of bool
    rotations : (K, 3, 3) ndarray
    translations : (K, 3) ndarray
        The local rigid motions, ``target ≈ source @ R.T + t``.
    """
    K = pairs.shape[0]
    if K < 4:
        return np.ones(K, bool), np.tile(np.eye(3), (K, 1, 1)), np.zeros((K, 3))
    xs, ys = X[pairs[:, 0]], Y[pairs[:, 1]]
    tree = cKDTree(xs)
    m = min(k, K)
    passed = np.empty(K, bool)
    R = np.empty((K, 3, 3))
    t = np.empty((K, 3))
    for s in range(0, K, _BLOCK):
        rows = np.arange(s, min(K, s + _BLOCK))
        _, nb = tree.query(xs[rows], k=m)
        R[rows], t[rows] = kabsch(xs[nb], ys[nb])
        b = nb[:, 1]  # nearest other match
        w = R[rows] - np.transpose(R[rows], (0, 2, 1))
        axis = np.stack([w[:, 2, 1], w[:, 0, 2], w[:, 1, 0]], axis=1)
        na = np.linalg.norm(axis, axis=1, keepdims=True)
        axis = np.where(na > 1e-12, axis / np.where(na > 0, na, 1.0), 0.0)
        V = (ys[rows] - xs[rows]) - (ys[b] - xs[b])
        Vs = (ys[rows] + xs[rows]) - (ys[b] + xs[b])
        nvs = np.linalg.norm(Vs, axis=1)
        r = np.linalg.norm(np.cross(V, np.cross(axis, Vs)), axis=1) / np.where(nvs > 0, nvs, 1.0)
        length = np.abs(np.sum(V * Vs, axis=1)) / np.where(nvs > 0, nvs, 1.0)
        r = np.where(na[:, 0] > 1e-12, r, length)
        g = gate if np.ndim(gate) == 0 else np.asarray(gate)[rows]
        passed[rows] = r <= strain * np.linalg.norm(xs[rows] - xs[b], axis=1) + g
    return passed, R, t



# ------------------------------------------------------------------ growth at full resolution
def grow(X, Y, tree_y, seeds, gate, *, spacing: float | None = None, tree_x=None,
         max_rounds: int = 10_000, report=None, used_source=None, used_target=None) -> np.ndarray:
    """Grow matches ring by ring at full resolution with the local affine warp of the matched region.

    The vectorised form of :func:`gatv.nonrigid.hypotheses.grow_rings`.
    Each round takes the *next ring*: the unmatched source points among the
    ``GROW_NEIGHBOURS`` nearest of a match added in the previous round (the
    seeds at first), moves them by the :class:`LocalAffineWarp` of all
    matches, and matches them to the nearest unused target within ``gate``,
    one-to-one (closest first), when that target is unambiguous (at most
    :data:`GROW_AMBIGUITY` times as far as the second nearest unused one;
    otherwise the point waits).  Stops when a ring adds nothing; the points
    still waiting next to a match are then matched once, as leaves, by the
    same test among the targets that no other waiting point has as its
    nearest (two samples closer than twice the warp's error are each
    other's second target and would wait for ever).  Taking one
    ring at a time keeps the affine extrapolation short: a locally affine
    warp extrapolated over several spacings drifts where the warp bends,
    and a drift of one sample along a uniformly sampled surface is locally
    consistent, so nothing downstream would catch it.  O(N k) memory.

    Parameters
    ----------
    spacing : float, optional
        Source sampling spacing (the warp's ridge); default :func:`gatv.candidates.median_spacing` of ``X``.
    gate : float or (M,) ndarray
        The match gate, or one per target row (:func:`local_gates`).
    tree_x : cKDTree, optional
        Of ``X`` (built when not given).
    used_source, used_target : (N,), (M,) ndarray of bool, optional
        Rows already taken by other matches (another part's growth): never matched here, and
        not part of this growth's warp.  Returned pairs are this growth's only (seeds included).
    """
    pairs = np.asarray(seeds, np.int64).reshape(-1, 2)
    if tree_x is None:
        tree_x = cKDTree(X)
    h = float(spacing) if spacing is not None else median_spacing(X)
    kn = min(GROW_NEIGHBOURS, X.shape[0])
    used_s = np.zeros(X.shape[0], bool) if used_source is None else np.array(used_source, bool)
    used_t = np.zeros(Y.shape[0], bool) if used_target is None else np.array(used_target, bool)
    used_s[pairs[:, 0]] = True
    used_t[pairs[:, 1]] = True
    frontier = pairs[:, 0]
    for r in range(max_rounds):
        if pairs.shape[0] < 4 or frontier.size == 0:
            break
        new = _ring(X, Y, tree_x, tree_y, pairs, frontier, used_s, used_t, gate, h, kn, GROW_AMBIGUITY)
        if new.shape[0] == 0:
            break
        pairs = np.vstack([pairs, new])
        frontier = new[:, 0]
        if report is not None and r % 10 == 0:
            report(min(1.0, pairs.shape[0] / X.shape[0]), f"growth: {pairs.shape[0]} matches")
    if pairs.shape[0] >= 4:
        # Two source samples closer than twice the warp's error wait for ever, each
        # the other's second target: once growth stops, the points still waiting
        # next to a match are taken as leaves (nothing grows from them) when they
        # are unambiguous among the targets no other waiting point has as nearest.
        new = _ring(X, Y, tree_x, tree_y, pairs, pairs[:, 0], used_s, used_t, gate, h, kn, GROW_AMBIGUITY,
                    claimed=True)
        pairs = np.vstack([pairs, new])
    return pairs[np.argsort(pairs[:, 0], kind="stable")]


def _ring(X, Y, tree_x, tree_y, pairs, centres, used_s, used_t, gate, h: float, kn: int,
          ambiguity: float, *, claimed: bool = False) -> np.ndarray:
    """One ring of :func:`grow`: the unused source points among the ``kn`` nearest of ``centres``,
    moved by the local affine warp of ``pairs`` and matched one-to-one (closest first) to their
    nearest unused target within ``gate``, when at most ``ambiguity`` times as far as the second
    unused target within the query's reach (the widest gate; with ``claimed``, a target that is
    another candidate's nearest is no second).  Marks the new
    matches used; returns them, (K, 2)."""
    near = tree_x.query(X[centres], k=kn)[1]
    free = np.unique(near.reshape(-1))
    free = free[~used_s[free]]
    if free.size == 0:
        return np.empty((0, 2), np.int64)
    xs = X[pairs[:, 0]]
    warp = LocalAffineWarp(xs, Y[pairs[:, 1]] - xs, spacing=h)
    d, j = tree_y.query(warp(X[free]), k=4, distance_upper_bound=_bound(gate))
    ok = _within(d, j, gate)  # each target within its own gate
    ok[ok] = ~used_t[j[ok]]
    first = np.argmax(ok, axis=1)  # the nearest unused target's column (distances come sorted)
    # rivals: every unused target the query reached, within its own gate or not — a prediction
    # between two samples is ambiguous however narrow the nearest one's gate (a body's hand: gates
    # at their floor held one sample, and a slide by a finger's spacing grew unambiguous)
    rivals = np.isfinite(d)
    rivals[rivals] = ~used_t[j[rivals]]
    rivals[np.arange(free.size), first] = False
    if claimed:
        nearest = j[np.arange(free.size), first][ok.any(axis=1)]
        rivals &= ~np.isin(j, nearest)
    d1 = np.where(ok.any(axis=1), d[np.arange(free.size), first], np.inf)
    d2 = np.where(rivals, d, np.inf).min(axis=1)
    ok &= (d1 <= ambiguity * d2)[:, None]  # unambiguous: one unused target, or a clear nearest
    rows, cols = np.nonzero(ok)
    if rows.size == 0:
        return np.empty((0, 2), np.int64)
    cand = np.stack([free[rows], j[rows, cols]], axis=1)
    new = cand[one_to_one(cand, d[rows, cols])]
    used_s[new[:, 0]] = True
    used_t[new[:, 1]] = True
    return new


# ------------------------------------------------------------------ pre-alignment fallback
def moment_prealign(X, Y, *, iterations: int = 30, max_points: int = 3000, seed: int = 0):
    """Similarity pre-alignment from principal axes, refined by trimmed similarity ICP.

    The scale is the ratio of the RMS radii about the centroids, the
    rotation one of the four proper sign choices of the principal axes;
    each start is refined by ``iterations`` rounds of Umeyama's fit on the
    nearest-target pairs of the closest 70% of at most ``max_points``
    seeded source points, and the one with the smallest trimmed median
    distance is kept (a clustered blob of outliers biases the moments, not
    the trimmed fit).  For a
    deformation on top of a large rotation and scale change, when the
    similarity model's search on the coarse sets finds nothing (differently
    sampled sets have no exact triples).  Works for bodies whose principal
    axes are distinct; returns the 4×4 matrix ``[[s R, t], [0, 1]]``.
    """
    rng = np.random.default_rng(seed)
    xs = X if X.shape[0] <= max_points else X[rng.choice(X.shape[0], max_points, replace=False)]
    cx, cy = X.mean(axis=0), Y.mean(axis=0)
    s0 = float(np.sqrt(np.mean(np.sum((Y - cy) ** 2, axis=1)) / np.mean(np.sum((X - cx) ** 2, axis=1))))
    _, ux = np.linalg.eigh(np.cov((X - cx).T))
    _, uy = np.linalg.eigh(np.cov((Y - cy).T))
    tree = cKDTree(Y)
    best = None
    for signs in ((1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1)):
        D = np.diag(signs).astype(float)
        R = uy @ D @ ux.T
        if np.linalg.det(R) < 0:
            R = uy @ (D * np.diag([1.0, 1.0, -1.0])) @ ux.T
        fit = _trimmed_icp(xs, Y, tree, s0, R, cy - s0 * R @ cx, iterations)
        if best is None or fit[0] < best[0]:
            best = fit
    _, s, R, t = best
    A = np.eye(4)
    A[:3, :3], A[:3, 3] = s * R, t
    return A


def _trimmed_icp(xs, Y, tree, s, R, t, iterations: int, keep_share: float = 0.7):
    """Trimmed similarity ICP; returns (median distance of the kept share, s, R, t)."""
    for _ in range(iterations):
        d, j = tree.query(s * xs @ R.T + t, k=1)
        keep = d <= np.percentile(d, 100 * keep_share)
        s, R, t = umeyama(xs[keep], Y[j[keep]])
    d = tree.query(s * xs @ R.T + t, k=1)[0]
    return float(np.median(np.sort(d)[: max(1, int(keep_share * d.size))])), s, R, t


def motion_parts(source_points, target_points, strain: float, gate) -> np.ndarray:
    """Label the matches by connected part: near in the source and moving continuously.

    Matches ``a`` and ``b`` are joined when ``|x_a − x_b|`` is at most three
    median matched spacings and ``| |y_a − y_b| − |x_a − x_b| | <= strain |x_a − x_b| + gate``
    (the length half of the local eq.-41 tolerance: a locally rigid motion
    changes the distance between neighbours by at most the local strain).  Lengths, not
    displacements: a shape turned as a whole by θ changes every displacement between neighbours by
    ``2 sin(θ/2) |x_a − x_b|``, over the strain beyond about 20°, and fell into pieces.
    ``gate`` is a float or one per match (:func:`local_gates` at the matches' targets; an edge
    takes the wider of its two).  Where the matches are sampled non-uniformly (the contrast of
    :func:`local_gates`), a match is also joined to its ``GROW_NEIGHBOURS`` nearest within three
    of *its* local spacings: a body's limbs are sampled 2–3 times more sparsely than the median,
    and three median spacings there split the body into 195 parts (30% outliers: the largest
    held 2,351 of 4,314 matches).

    Returns
    -------
    (K,) ndarray of int
        Part label of each match, 0 for the largest part.
    """
    xs = np.asarray(source_points, dtype=np.float64)
    ys = np.asarray(target_points, dtype=np.float64)
    k = xs.shape[0]
    if k < 2:
        return np.zeros(k, np.int64)
    a, b = neighbour_pairs(xs, 3.0 * median_spacing(xs))
    per_match = np.ndim(gate) > 0
    if per_match:
        g = np.asarray(gate, dtype=float)
        gate = np.maximum(g[a], g[b])
    lx = np.linalg.norm(xs[a] - xs[b], axis=1)
    ok = np.abs(np.linalg.norm(ys[a] - ys[b], axis=1) - lx) <= strain * lx + gate
    graph = coo_matrix((np.ones(int(ok.sum())), (a[ok], b[ok])), shape=(k, k))
    _, labels = connected_components(graph, directed=False)
    sizes = np.bincount(labels)
    rank = np.empty_like(sizes)
    rank[np.argsort(-sizes, kind="stable")] = np.arange(sizes.size)
    return rank[labels]


def neighbour_pairs(P, radius: float, tree=None):
    """Pairs ``(a, b)`` of rows of ``P`` within ``radius`` of each other, and, where the sampling is
    non-uniform (:func:`nonuniform_spacings`), each row with its ``GROW_NEIGHBOURS`` nearest within
    three of its local spacings: the neighbours of :func:`motion_parts` and of
    :mod:`gatv.nonrigid.parts` (a body's limbs are sampled 2–3 times more sparsely than the median,
    and a radius of three median spacings leaves them in pieces)."""
    P = np.asarray(P, dtype=np.float64)
    tree = cKDTree(P) if tree is None else tree
    a, b = tree.query_pairs(radius, output_type="ndarray").T
    local = nonuniform_spacings(P, tree)
    if local is not None:
        k = P.shape[0]
        m = min(GROW_NEIGHBOURS + 1, k)
        dist, nb = tree.query(P, k=m)
        keep = (dist[:, 1:] <= 3.0 * local[:, None]) & (dist[:, 1:] > radius)
        rows = np.repeat(np.arange(k), m - 1).reshape(k, m - 1)
        a, b = np.r_[a, rows[keep]], np.r_[b, nb[:, 1:][keep]]
    return a, b


def nonuniform_spacings(P, tree, k: int = 8) -> np.ndarray | None:
    """Each row's local spacing (the median nearest-neighbour distance of its ``k`` nearest, as
    :func:`local_gates`) where the sampling is non-uniform (90th percentile over 10th above
    ``SAMPLING_CONTRAST``); None where it is about uniform or there are too few rows."""
    if P.shape[0] < k + 1:
        return None
    local = _row_spacings(P, tree, k)
    return local if _non_uniform(local) else None
