"""Trial rotations from congruent point triples (replacing Algorithm 1's grid).

Algorithm 1 of the paper rotates the source by every trial rotation of a
grid until the plane in the ``{dx, dy, dz}`` joint space becomes dense
enough for tensor voting to find it. At 90% outliers the plane is found
only when the remaining rotation is within a few degrees, so a grid needs
tens of thousands of voting passes.  Here the number of trials collapses:
a trial rotation is generated only from three source points and three
target points with the same side lengths (side lengths survive any rigid
motion).  A trial built from three true matches leaves a residual rotation
near zero, and the true pairs then form the dense pure-translation cluster
of section 3.4.  Each trial is scored by a cheap density test (how many
source points the trial motion brings onto a target point, a grid lookup),
and only the best trials go on to tensor voting, which stays the judge
that extracts the correspondences.

The number of source triples to draw follows the RANSAC bound: with an
inlier share ``w`` of the source, a triple is all-inlier with probability
``w**3``, so ``log(1 - confidence) / log(1 - w**3)`` triples find one with
the requested confidence.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from . import congruent_kernels as _k
from ..._validation import check_memory
from ..base import homogeneous
from ...stats import ball_measure, chance_support, samples_needed

__all__ = [
    "FIRST_BOX_MATCHES",
    "HALF_BOX_FROM",
    "MISS_RATE",
    "TargetGrid",
    "TargetIndex",
    "TrialMotions",
    "TrialPool",
    "accept_level",
    "chance_support",
    "expected_matches",
    "first_boxes",
    "kernel_array",
    "n_triples_needed",
    "predicted_matches",
    "rarest_side_first",
    "sample_triples",
    "sequential_boundary",
    "trial_motions",
]


def kernel_array(a, dtype=np.float64) -> np.ndarray:
    """``a`` as the kernels take every array: C-contiguous, ``dtype``, writable.

    numba compiles a kernel once per argument types, and a read-only array
    (a frozen :class:`gatv.stages.Problem`'s, a result's) is another type
    than a writable one, int32 another than int64: every caller normalising
    here compiles each kernel once (a read-only array is copied; the
    kernels' inputs are small next to their work).
    """
    return np.require(a, dtype, ["C", "W"])


def n_triples_needed(inlier_share: float, confidence: float = 0.999) -> int:
    """Source triples to draw so one is all-inlier with ``confidence`` (:func:`gatv.stats.samples_needed`)."""
    return samples_needed(inlier_share, confidence, 3)


@dataclass(frozen=True, eq=False)
class TargetGrid:
    """Target points in a dense grid over their bounding box, for nearest lookups within ``radius``
    (:func:`congruent_kernels.nearest_in_grid`): :class:`TargetIndex`'s scoring grid, and the scans
    pipeline's ICP screens' (:func:`gatv._icp_kernels.screen_icp`)."""

    target: np.ndarray
    radius: float
    #: The box's lower corner and its extent (at least 1e-12 along each axis).
    origin: np.ndarray
    extent: np.ndarray
    cell: float
    dims: np.ndarray
    #: :func:`congruent_kernels.build_grid`'s runs of each cell and the points' order.
    start: np.ndarray
    order: np.ndarray

    @classmethod
    def of(cls, target: np.ndarray, radius: float, *, cell_radii: float = 1.0, max_side: int = 128) -> "TargetGrid":
        """Cells ``cell_radii`` times ``radius`` (a lookup visits at most 3 x 3 x 3 of them at one radius, 2 x 2
        x 2 at two), coarser where the box would need more than ``max_side`` a side: a finer radius then
        visits more of a cell's points, not more cells."""
        target = np.ascontiguousarray(target, dtype=np.float64)
        lo = target.min(axis=0)
        ext = np.maximum(target.max(axis=0) - lo, 1e-12)
        cell = max(cell_radii * float(radius), float(ext.max()) / max_side)
        dims = np.maximum(np.ceil(ext / cell).astype(np.int64), 1)
        origin = lo.astype(np.float64)
        start, order = _k.build_grid(target, origin, cell, dims)
        return cls(target, float(radius), origin, ext, cell, dims, start, order)


#: Most cells a side of :class:`TargetIndex`'s occupancy grid (2 MB at most).
OCCUPANCY_CELLS = 128


class TargetIndex:
    """Pair-length table, sorted neighbour lists and a grid of the target."""

    def __init__(self, target: np.ndarray, radius: float, *, memory_budget=None):
        n = target.shape[0]
        # pair table (n²/2 × 16 bytes) + neighbour lists (n² × 12 bytes)
        check_memory(20.0 * n * n, f"the congruent-triple index of {n} target points", memory_budget)
        self.target = target = kernel_array(target)
        self.plen, self.pi, self.pj = _k.pair_table(target)
        self.plen_bounds, self.plen_step = _k.length_lookup(self.plen, 16)
        self.ndist, self.nidx = _k.sorted_neighbours(target)
        self.set_radius(radius)

    def set_radius(self, radius: float) -> None:
        """Rebuild the scoring grid for a match radius."""
        target = self.target
        # Cells twice the radius (a lookup then visits at most 2 x 2 x 2 of
        # them), at most ~64 cells a side.
        grid = TargetGrid.of(target, radius, cell_radii=2.0, max_side=64)
        ext = grid.extent
        self.radius = grid.radius
        self.origin, self.cell, self.dims = grid.origin, grid.cell, grid.dims
        self.start, self.order = grid.start, grid.order
        self.volume = float(np.prod(ext + 2 * radius))
        # Occupancy of the target's balls (sure misses in one read), over the
        # box grown by the radius, cells half the radius (at most
        # OCCUPANCY_CELLS a side): a wrong motion's points mostly miss.
        span = ext + 2.0 * float(radius)
        ocell = max(0.5 * float(radius), float(span.max()) / OCCUPANCY_CELLS)
        self.occ_origin = self.origin - float(radius)
        self.occ_cell = ocell
        self.occ_dims = np.maximum(np.ceil(span / ocell).astype(np.int64), 1)
        self.occupancy = _k.build_occupancy(target, self.occ_origin, ocell, self.occ_dims, float(radius))

    def nearest(self, points: np.ndarray, radius: float | None = None) -> np.ndarray:
        """Index of the nearest target within ``radius`` of each point, or -1."""
        r = self.radius if radius is None else float(radius)
        points = kernel_array(points)
        out = np.empty(points.shape[0], np.int64)
        for i in range(points.shape[0]):
            out[i] = _k.nearest_in_grid(points[i], self.target, self.start, self.order,
                                        self.origin, self.cell, self.dims, r)
        return out


@dataclass(frozen=True, eq=False)
class TrialMotions:
    """Trial motions ranked by support, best first."""

    rotations: np.ndarray  # (K, 3, 3)
    translations: np.ndarray  # (K, 3)
    support: np.ndarray  # (K,)
    threshold: int
    n_triples: int
    n_congruent: int
    n_listed: int = 0  # congruent matches listed (of which n_congruent were scored)
    n_visited: int = -1  # source points visited in scoring them (-1: not counted)
    n_probes: int = 0  # binary searches and candidate points of the listing (its cost)
    n_candidates: int = 0  # candidate triples of the wide draws (``wide`` a sample drawn)

    def __len__(self) -> int:
        return int(self.support.shape[0])

    @property
    def matrices(self) -> np.ndarray:
        """(K, d + 1, d + 1) homogeneous matrices of the trial motions (``rotations`` holds the
        linear parts: rotations for rigid motions, ``s R`` for similarities, ``A`` for affine maps)."""
        if len(self) == 0:
            d = self.rotations.shape[-1] if self.rotations.ndim == 3 else 3
            return np.zeros((0, d + 1, d + 1))
        return np.stack([homogeneous(R, t) for R, t in zip(self.rotations, self.translations)])


class TrialPool:
    """The best trial motions of a search, collected batch by batch.

    Each batch offers its per-sample best motions; the ``4 * keep`` best of
    those scoring at least ``min_score`` are kept.  :meth:`trials` ranks
    them and keeps ``keep`` distinct ones: a motion is a repeat when its
    linear part is within ``1e-3`` of a kept one's (Frobenius norm; relative
    to the kept one's norm with ``relative=True``, for models that scale)
    and its translation within ``radius``.
    """

    def __init__(self, keep: int, min_score: int, dim: int = 3):
        self.keep, self.min_score, self.dim = int(keep), int(min_score), int(dim)
        self.scores: list = []
        self.linear: list = []
        self.translations: list = []

    @property
    def best(self) -> int:
        """Best score so far (0 when empty)."""
        return max(self.scores) if self.scores else 0

    def add(self, scores: np.ndarray, linear: np.ndarray, translations: np.ndarray) -> None:
        good = np.flatnonzero(scores >= self.min_score)
        if good.size:
            top = good[np.argsort(-scores[good], kind="stable")[: 4 * self.keep]]
            self.scores.extend(scores[top].tolist())
            self.linear.extend(linear[top])
            self.translations.extend(translations[top])

    def trials(self, radius: float, threshold: int, n_samples: int, n_matches: int, *,
               relative: bool = False) -> TrialMotions:
        d = self.dim
        if not self.scores:
            return TrialMotions(np.zeros((0, d, d)), np.zeros((0, d)), np.zeros(0, np.int64),
                                threshold, n_samples, n_matches)
        s = np.asarray(self.scores)
        order = np.argsort(-s, kind="stable")
        As = np.asarray(self.linear)[order]
        ts = np.asarray(self.translations)[order]
        s = s[order]
        kept: list[int] = []
        for i in range(len(s)):
            if all(np.linalg.norm(As[i] - As[j]) > (1e-3 * np.linalg.norm(As[j]) if relative else 1e-3)
                   or np.linalg.norm(ts[i] - ts[j]) > radius for j in kept):
                kept.append(i)
            if len(kept) >= self.keep:
                break
        k = np.asarray(kept)
        return TrialMotions(As[k], ts[k], s[k], threshold, n_samples, n_matches)


def accept_level(accept: int | None, threshold: int) -> int:
    """The support that stops a trial search early: ``threshold`` by default, never for ``<= 0``."""
    if accept is None:
        return threshold
    if accept <= 0:
        return np.iinfo(np.int64).max
    return accept


def expected_matches(source: np.ndarray, triples: np.ndarray, index: TargetIndex, eps: float) -> np.ndarray:
    """A proxy of how many target triples each source triple matches congruently.

    The product over the triple's three sides of the number of target pairs
    whose length is within ``eps`` of the side (a binary search in the
    sorted pair-length table); the congruent matches a triple has to score
    grow with it.  Long sides, where the target's pair lengths are sparse,
    give few matches.
    """
    return np.prod(_side_widths(source, triples, index, eps), axis=1, dtype=np.float64)


def predicted_matches(source: np.ndarray, triples: np.ndarray, index: TargetIndex, eps: float) -> np.ndarray:
    """About how many target triples each source triple matches within ``eps``: ``8 w₁ w₂ w₃ / n³``.

    A random ordered target triple ``(k, l, m)`` has each side in a side's
    window with probability ``2 wᵢ / n²`` (``wᵢ`` of the ``n² / 2`` target
    pairs, :func:`expected_matches`); taken as independent, the ``n³``
    triples give this many matches.  Within a factor ~2.5 of the count on
    uniform points (the sides of a triangle are not independent).
    """
    n = float(index.target.shape[0])
    return 8.0 * expected_matches(source, triples, index, eps) / (n * n * n)


#: Matches a triple is predicted to have (:func:`predicted_matches`), in
#: units of the matches scored, from which the listing tries a smaller box
#: first (:func:`first_boxes`).
HALF_BOX_FROM = 4.0
#: Matches, in units of the matches scored, that the first box is sized to
#: hold: the scored tightest must all lie within its inscribed ball (~half
#: of it), and the prediction is good to a factor ~2.5.
FIRST_BOX_MATCHES = 4.0


def first_boxes(predicted: np.ndarray, max_matches: int) -> np.ndarray:
    """Share of ``eps`` of the box each triple's listing tries first (0: the full box at once).

    The tightest ``max_matches`` of a triple's matches lie in a box ``f``
    times as wide as the listing's that holds about ``f³`` of them: a
    triple predicted to have ``P`` matches lists the box holding
    :data:`FIRST_BOX_MATCHES` × ``max_matches`` (``f = (that / P)^(1/3)``,
    at most 1/2), at about ``f²`` of the listing's work, and doubles it
    until it answers (:func:`gatv.models.rigid.congruent_kernels.scored_matches`).
    Below :data:`HALF_BOX_FROM` × ``max_matches`` no smaller box answers
    and the full one is listed at once.
    """
    p = np.asarray(predicted, dtype=np.float64)
    box = np.minimum(0.5, np.cbrt(FIRST_BOX_MATCHES * max_matches / np.maximum(p, 1e-300)))
    return np.where(p >= HALF_BOX_FROM * max_matches, box, 0.0)


def _side_widths(points: np.ndarray, triples: np.ndarray, index: TargetIndex, eps: float) -> np.ndarray:
    """(M, 3) target pairs of ``index`` within ``eps`` of the length of each side ``(0, 1), (0, 2), (1, 2)``."""
    return _k.side_widths(kernel_array(points), kernel_array(triples, np.int64),
                          index.plen, index.plen_bounds, index.plen_step, float(eps))


def sample_triples(n: int, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` random triples of distinct indices below ``n``, (count, 3)."""
    t = np.empty((count, 3), np.int64)
    t[:, 0] = rng.integers(0, n, count)
    t[:, 1] = rng.integers(0, n - 1, count)
    t[:, 1] += t[:, 1] >= t[:, 0]
    lo = np.minimum(t[:, 0], t[:, 1])
    hi = np.maximum(t[:, 0], t[:, 1])
    c = rng.integers(0, n - 2, count)
    c += c >= lo
    c += c >= hi
    t[:, 2] = c
    return t


def trial_motions(
    source: np.ndarray,
    index: TargetIndex,
    *,
    eps: float,
    max_triples: int,
    rng: np.random.Generator,
    min_side: float = 0.0,
    batch: int = 512,
    keep: int = 8,
    max_matches: int = 64,
    accept: int | None = None,
    source_normals: np.ndarray | None = None,
    target_normals: np.ndarray | None = None,
    feature_tol: float = 0.15,
    wide: int = 1,
    max_enumerated: int = 0,
    sequential: bool = False,
    min_share: float = 0.0,
    adaptive_confidence: float | None = None,
    progress=None,
) -> TrialMotions:
    """Draw source triples, match them congruently, score the motions.

    Stops early once a trial's support reaches ``accept`` (default: the
    chance level of :func:`chance_support`), after finishing its batch.

    Parameters
    ----------
    source : (N, 3) ndarray
    index : TargetIndex
    eps : float
        Side-length tolerance of congruence (data units).
    max_triples : int
        Upper bound on source triples drawn.
    min_side : float
        Triples with a side shorter than this are redrawn (short sides make
        the rotation sensitive to noise).
    keep : int
        Number of best distinct trials returned.
    accept : int, optional
        Stop once a trial reaches this support; ``0`` never stops early
        (use for real scans, whose surfaces make the chance level of
        :func:`chance_support` meaningless).
    source_normals, target_normals : (N, 3) ndarray, optional
        Unoriented unit normals (e.g. from a tensor-voting ball pass,
        section 4.1). When given, matched sides must also agree in the
        rigid invariants ``|n_i·u|, |n_j·u|, |n_i·n_j|`` within
        ``feature_tol``, which prunes most congruent but wrong triangles
        on real surfaces.
    wide : int, default: 1
        Draw this many candidate triples for each one kept and keep the one
        with the fewest expected congruent matches
        (:func:`expected_matches`): under noise the tolerance ``eps`` lets
        a triple match many target triples, about as many as its side
        lengths have target pairs within ``eps``, and long, rare sides cut
        that work without changing which points are drawn when inliers and
        outliers are spread alike.  Only triangles at least
        :func:`_min_height` tall compete (the tallest of the ``wide`` when
        none is): the fewest matches alone favour short sides and thin
        triangles, whose noisy pose misses the gate away from the triangle.
    max_enumerated : int, default: 0
        Congruent matches listed per triple, of which the ``max_matches``
        tightest (smallest side-length discrepancy) are scored; ``0`` lists
        only ``max_matches``.
    sequential : bool, default: False
        Count a motion's support in random order and stop at the rejection
        boundary of Wald's sequential test (:func:`sequential_boundary`)
        between the chance hit rate and the hit rate of a motion at the
        ``accept`` level, missed with probability at most
        :data:`MISS_RATE`: most congruent matches of a noisy triple are
        wrong and are dropped after a few dozen points, so that many more
        of them can be scored.
    min_share : float, default: 0.0
        Smallest share of the source that the caller's number of triples is
        drawn to find (its RANSAC bound): the sequential test's alternative
        is a motion of the larger of this share and ``accept``.
    adaptive_confidence : float, optional
        Stop, after a batch, once the triples drawn are as many as the RANSAC
        bound needs (:func:`n_triples_needed` at this confidence) for the
        inlier share the best trial so far shows (its support over the
        source's points, at least ``min_share``): adaptive RANSAC
        termination (Hartley and Zisserman, *Multiple View Geometry*,
        section 4.7.1).  Where the best trial is a wrong motion the caller's
        check must catch it and search again without this stop.  Small
        ``batch`` sizes let it stop sooner.
    """
    source = kernel_array(source)
    n = source.shape[0]
    threshold = chance_support(n, index.target.shape[0], index.volume, index.radius,
                               n_tests=max_triples * max_matches)
    accept = accept_level(accept, threshold)
    no_normals = np.zeros((0, 3))
    sn = no_normals if source_normals is None else kernel_array(source_normals)
    tn = no_normals if target_normals is None else kernel_array(target_normals)
    pool = TrialPool(keep, 3)
    min_height = _min_height(source) if wide > 1 else 0.0
    drawn = 0
    n_congruent = 0
    n_listed = 0
    slope, offset = _sequential_test(n, index, accept, min_share) if sequential else (0.0, 0.0)
    n_visited = 0
    n_probes = 0
    n_candidates = 0
    while drawn < max_triples:
        m = min(batch, max_triples - drawn)
        if wide > 1:
            n_candidates += m * int(wide)
            pool_tri = sample_triples(n, m * int(wide), rng).reshape(m, int(wide), 3)
            cost = expected_matches(source, pool_tri.reshape(-1, 3), index, eps).reshape(m, int(wide))
            height = triangle_heights(source, pool_tri.reshape(-1, 3)).reshape(m, int(wide))
            best = np.argmin(np.where(height >= min_height, cost, np.inf), axis=1)
            thin = ~np.any(height >= min_height, axis=1)
            best[thin] = np.argmax(height[thin], axis=1)
            tri = pool_tri[np.arange(m), best]
        else:
            tri = sample_triples(n, m * 2 if min_side > 0 else m, rng)
        if min_side > 0:
            p = source
            s1 = np.linalg.norm(p[tri[:, 0]] - p[tri[:, 1]], axis=1)
            s2 = np.linalg.norm(p[tri[:, 0]] - p[tri[:, 2]], axis=1)
            s3 = np.linalg.norm(p[tri[:, 1]] - p[tri[:, 2]], axis=1)
            tri = tri[np.minimum(np.minimum(s1, s2), s3) >= min_side][:m]
            if tri.shape[0] == 0:
                tri = sample_triples(n, m, rng)
        drawn += tri.shape[0]
        tri = rarest_side_first(source, tri, index, eps)
        first_box = first_boxes(predicted_matches(source, tri, index, eps), max_matches)
        offsets = rng.integers(0, np.iinfo(np.int32).max, tri.shape[0])
        # A fresh visiting order a batch: the sequential test's misses of one
        # true motion are then independent between batches.
        visit = rng.permutation(n).astype(np.int64) if slope > 0 else np.zeros(0, np.int64)
        scores, R, t, nm, nl, nv, npr = _k.triple_hypotheses(
            source, index.target, kernel_array(tri, np.int64), offsets, index.plen, index.pi, index.pj,
            index.ndist, index.nidx, float(eps), index.start, index.order, index.origin, index.cell, index.dims,
            index.radius, int(max_matches), sn, tn, float(feature_tol), int(max_enumerated),
            visit, float(slope), float(offset), index.occupancy, index.occ_origin, index.occ_cell,
            index.occ_dims, kernel_array(first_box),
        )
        n_congruent += int(nm.sum())
        n_listed += int(nl.sum())
        n_visited += int(nv.sum())
        n_probes += int(npr.sum())
        pool.add(scores, R, t)
        if progress is not None:
            progress(min(1.0, drawn / max_triples), f"{drawn} triples, best support {pool.best}")
        if pool.best >= accept:
            break
        if adaptive_confidence is not None and drawn >= n_triples_needed(
                max(pool.best / n, float(min_share), 1e-6), float(adaptive_confidence)):
            break
    trials = pool.trials(index.radius, threshold, drawn, n_congruent)
    return dataclasses.replace(trials, n_listed=n_listed, n_visited=n_visited, n_probes=n_probes,
                               n_candidates=n_candidates)


def rarest_side_first(points: np.ndarray, triples: np.ndarray, index: TargetIndex, eps: float) -> np.ndarray:
    """``triples`` with each one's vertices reordered: the rarest side first, the rarer of the others second.

    The congruent listing scans the target pairs as long as the first side
    ``(0, 1)`` within ``eps`` (or, when they outnumber the target's points,
    every point's neighbours at that length), so the rarest length in the
    target's sorted pair lengths (``index.plen``) makes the shortest scan.  For
    each pair ``(k, l)`` it scanned, the listing then tries the third
    points in ``k``'s neighbours at the length of side ``(0, 2)`` (those
    ``|bc|`` from ``l`` are kept): about ``2 w / n`` of them for a side
    whose length has ``w`` target pairs, so the rarer of the other two
    sides there tries fewer.  The triangle and its matches are the same;
    only the order of the work changes.
    """
    t = np.asarray(triples)
    if t.shape[0] == 0:
        return t
    w = _side_widths(points, t, index, eps)  # sides (0, 1), (0, 2), (1, 2)
    # Each vertex order's sides (0, 1) and (0, 2), as indices into ``w``.
    perms = np.array([[0, 1, 2], [1, 0, 2], [0, 2, 1], [2, 0, 1], [1, 2, 0], [2, 1, 0]])
    first = np.array([0, 0, 1, 1, 2, 2])
    second = np.array([1, 2, 0, 2, 0, 1])
    width = w.astype(np.float64)
    key = width[:, first] * (float(w.max(initial=0)) + 1.0) + width[:, second]
    return np.take_along_axis(t, perms[np.argmin(key, axis=1)], axis=1)


def triangle_heights(points: np.ndarray, triples: np.ndarray) -> np.ndarray:
    """Smallest height of each triangle ``points[triples]``: twice its area over its longest side."""
    return _k.triangle_heights(kernel_array(points), kernel_array(triples, np.int64))


def _min_height(source: np.ndarray) -> float:
    """Smallest triangle height whose noisy pose still carries the scoring gate.

    A triple matched at tolerance ``τ`` (point noise up to ``τ``) has its
    rotation about its longest side wrong by about ``sqrt(2) τ / h`` (``h``
    the triangle's smallest height); at the source's RMS radius ``ρ`` that
    moves a point by ``sqrt(2) τ ρ / h``, which stays inside the scoring
    gate ``3.5 τ`` (:func:`gatv.stages.gate`) when ``h >= sqrt(2) ρ / 3.5``.
    """
    centred = source - source.mean(axis=0)
    rho = float(np.sqrt(np.mean(np.sum(centred**2, axis=1))))
    return np.sqrt(2.0) * rho / 3.5


#: Largest probability that :func:`trial_motions`' sequential test drops a
#: motion whose support is at the ``accept`` level (higher support: less).
MISS_RATE = 0.05


def sequential_boundary(p_chance: float, p_accept: float, miss_rate: float = MISS_RATE) -> tuple[float, float]:
    """Rejection boundary ``(slope, offset)`` of Wald's sequential test of a motion's hit rate.

    Each visited source point lands on a target with probability
    ``p_chance`` under a wrong motion and with ``p_accept`` or more under a
    motion worth counting in full.  After ``v`` points with ``h`` hits the
    log-likelihood ratio of the two is ``h D - v log((1 - p_chance) /
    (1 - p_accept))``, ``D = log(p_accept (1 - p_chance) / (p_chance (1 -
    p_accept)))``; the test rejects once it reaches ``log(miss_rate)``, that
    is once ``h < slope v + offset``.  By Wald's inequality a motion of hit
    rate ``p_accept`` or more is rejected with probability at most
    ``miss_rate``; a wrong one after about ``-log(miss_rate)`` over the
    Kullback–Leibler divergence of the two rates, a few dozen points.
    ``(0, 0)`` (never reject) unless ``0 < p_chance < p_accept < 1``.
    """
    if not (0.0 < p_chance < p_accept < 1.0) or not (0.0 < miss_rate < 1.0):
        return 0.0, 0.0
    step = float(np.log((1.0 - p_chance) / (1.0 - p_accept)))
    D = float(np.log(p_accept / p_chance)) + step
    return step / D, float(np.log(miss_rate)) / D


def _sequential_test(n: int, index: TargetIndex, accept: int, min_share: float = 0.0) -> tuple[float, float]:
    """:func:`sequential_boundary` of :func:`trial_motions`' scoring.

    A wrong motion brings each source point onto some target with the chance
    rate ``1 - exp(-n_target · ball(radius) / volume)``; one worth counting
    brings ``accept / n`` of them, or ``min_share`` if more.
    """
    if accept <= 0 or accept >= np.iinfo(np.int64).max:
        return 0.0, 0.0
    p_chance = 1.0 - np.exp(-index.target.shape[0] * ball_measure(index.radius) / index.volume)
    return sequential_boundary(p_chance, min(max(accept / n, float(min_share)), 1.0))
