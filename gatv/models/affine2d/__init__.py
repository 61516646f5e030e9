"""Kang et al.'s 2D affine model: ``x' = A x + t``, ``A`` any 2x2 (paper, section 1.2).

Eq. 1 rewritten as eqs. 3–4 splits into two joint spaces, ``(x, y, x')``
and ``(x, y, y')``: the pairs of one affine motion lie on the plane
``(a, b, -1, tx)`` in the first and ``(c, d, -1, ty)`` in the second.

How the pieces fit the stages of :mod:`gatv.stages`
---------------------------------------------------
* **Trial motions from area ratios** (:meth:`Affine2D.trial_motions`).  An
  affine map keeps ratios of areas, so the barycentric coordinates of a
  fourth point with respect to a triangle are invariant.  The target is
  indexed by the signatures of its *local* quadruples — an anchor and three
  of its ``knn`` nearest neighbours (affine maps of moderate distortion keep
  neighbourhoods roughly) — bucketed on a grid of the signature plane
  (:class:`AffineIndex`, ``O(M knn³)`` entries instead of ``O(M³)``
  triangles).  A source sample is an anchor and three of its
  ``sample_knn`` nearest neighbours; in each of its 6 orders it looks up
  target quadruples of the same signature, the base triangles' affine map
  must bring the fourth point onto the target's, and a density test scores
  the map (:mod:`gatv.models.affine2d.kernels`, numba, with a numpy reference).
* **Tokens** are Kang's first joint space ``(x, y, x')`` with ``x`` the
  source moved by the trial's linear part (the stages' convention);
  :meth:`Affine2D.joint_spaces` gives both spaces, and
  :func:`gatv.stages.vote_tokens` votes in each and keeps a token salient only
  when it is salient in both (geometric mean of the two ball-pass
  saliencies).
* **The constraint** (:meth:`Affine2D.consistent`), the analogue of eq. 41:
  two tokens of one affine motion satisfy ``Δx' = A Δx``.  In the trial
  frame ``A ≈ I``, so the tokens whose displacement ``x' - x`` equals the
  reference's within ``tau`` come first; the two joint-space planes (the
  rows of ``A``) are then fitted on them by least squares, trimmed once,
  and every token with ``|Δx' - A Δx| <= tau`` against the reference is
  kept (twice, so the planes grow from the reference's neighbourhood).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from math import comb

import numpy as np
from scipy.spatial import cKDTree

from . import kernels as _k
from ..._validation import as_points, check_memory
from ..rigid.congruent import TrialPool, accept_level
from ...errors import InputError
from ...stats import chance_alpha, chance_support
from ..base import Motion, SearchPolicy, freeze_fields, homogeneous, matrix_residuals
from ..rigid import check_dimension, check_spread

__all__ = ["Affine2D", "Affine2DMotion", "AffineIndex", "MODEL", "fit_affine", "Affine2DTrials"]

#: Bytes per entry of the quadruple table (signature, 4 indices, scale, bucket order).
BYTES_PER_QUAD = 48


def fit_affine(source, target, weights=None) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least-squares ``(A, t)`` with ``target ≈ source @ A.T + t`` (numpy ``lstsq``)."""
    X = np.asarray(source, dtype=np.float64)
    Y = np.asarray(target, dtype=np.float64)
    H = np.hstack([X, np.ones((X.shape[0], 1))])
    if weights is not None:
        w = np.sqrt(np.asarray(weights, dtype=np.float64).reshape(-1, 1))
        H, Y = H * w, Y * w
    M = np.linalg.lstsq(H, Y, rcond=None)[0]  # (3, 2): rows a-col, b-col, t
    return M[:2].T.copy(), M[2].copy()


# ------------------------------------------------------------------ result
@dataclass(frozen=True, eq=False)
class Affine2DMotion(Motion):
    """A 2D affine motion ``target ≈ source @ linear.T + translation`` and its correspondences.

    A failed search is a falsy ``Affine2DMotion`` (``support == 0``) whose
    ``info["reason"]`` says why.
    """

    model = "affine2d"

    linear: np.ndarray
    translation: np.ndarray
    correspondences: np.ndarray = field(default_factory=lambda: np.empty((0, 2), np.int64))
    score: float = 0.0
    rms: float = float("nan")
    info: dict = field(default_factory=dict)

    def __post_init__(self):
        freeze_fields(self, linear=(2, 2), translation=(2,))

    @classmethod
    def from_matrix(cls, matrix, correspondences=None, *, score: float = 0.0,
                    rms: float = float("nan"), info: dict | None = None) -> Affine2DMotion:
        """From a 3×3 homogeneous matrix ``[[A, t], [0, 0, 1]]``."""
        T = np.asarray(matrix, dtype=np.float64)
        if T.shape != (3, 3):
            raise InputError(f"Expected `matrix` to have shape (3, 3), got {T.shape}.")
        pairs = np.empty((0, 2), np.int64) if correspondences is None else correspondences
        return cls(T[:2, :2], T[:2, 2], pairs, score, rms, {} if info is None else info)

    @property
    def matrix(self) -> np.ndarray:
        """3×3 homogeneous matrix, ``p_target = T @ [p_source, 1]``."""
        return homogeneous(self.linear, self.translation)

    @property
    def determinant(self) -> float:
        """``det A``: the area ratio (negative for a reflection)."""
        return float(np.linalg.det(self.linear))

    def inverse(self) -> Affine2DMotion:
        """The motion from target to source, with swapped correspondences.

        Raises
        ------
        InputError
            When ``A`` is singular (no inverse map).
        """
        A = self.linear
        s = np.linalg.svd(A, compute_uv=False)
        if s[1] <= 1e-12 * max(s[0], 1e-300):
            raise InputError(f"The affine map is singular (singular values {s.tolist()}); it has no inverse.")
        Ai = np.linalg.inv(A)
        return Affine2DMotion(Ai, -Ai @ self.translation, self.correspondences[:, ::-1], self.score,
                              self.rms, dict(self.info))

    def to_dict(self) -> dict:
        """JSON-friendly dictionary: the base keys plus ``linear`` and ``translation``."""
        return {**super().to_dict(), "linear": self.linear.tolist(),
                "translation": self.translation.tolist()}

    def __repr__(self) -> str:
        A = np.array2string(self.linear, precision=4, separator=", ").replace("\n", "")
        t = np.array2string(self.translation, precision=4, separator=", ")
        return f"Affine2DMotion(linear={A}, translation={t}, support={self.support}, rms={self.rms:.3g})"


# ------------------------------------------------------------------- index
class AffineIndex:
    """The target's local-quadruple signature table (bucketed) and its scoring grid.

    Parameters
    ----------
    target : (M, 2) ndarray
    radius : float
        Match radius of the density test.
    knn : int
        Neighbours of each anchor whose triples are indexed: ``M C(knn, 3)`` entries.
    max_cond : float
        Largest condition number of an indexed base triangle and of a trial map.
    """

    #: Side of the signature-plane grid of ``[-LMAX, LMAX]^2``.
    GRID = 128

    def __init__(self, target: np.ndarray, radius: float, *, knn: int = 10, max_cond: float = 10.0,
                 memory_budget=None):
        m = target.shape[0]
        k = int(min(knn, m - 1))
        check_memory(BYTES_PER_QUAD * m * comb(max(k, 0), 3),
                     f"the affine quadruple index of {m} target points", memory_budget)
        self.target = np.ascontiguousarray(target, dtype=np.float64)
        self.knn = k
        self.max_cond = float(max_cond)
        if k >= 3:
            nbr = cKDTree(self.target).query(self.target, k=k + 1)[1][:, 1:].astype(np.int64)
            self.sig, self.quad, self.scale = _k.quad_table(self.target, np.ascontiguousarray(nbr),
                                                            self.max_cond)
        else:
            self.sig, self.quad, self.scale = np.zeros((0, 2)), np.zeros((0, 4), np.int32), np.zeros(0)
        # The tenth of the entries most sensitive to noise (tiny or thin
        # triangles, 4th point far out) is dropped: it would widen every lookup.
        self.s_cap = float(np.quantile(self.scale, 0.9)) if self.scale.size else 0.0
        keep = self.scale <= self.s_cap
        self.sig, self.quad, self.scale = (np.ascontiguousarray(self.sig[keep]),
                                           np.ascontiguousarray(self.quad[keep]),
                                           np.ascontiguousarray(self.scale[keep]))
        self.bstart, self.border = _k.bucket(self.sig, self.GRID)
        self.set_radius(radius)

    def __len__(self) -> int:
        return int(self.sig.shape[0])

    def set_radius(self, radius: float) -> None:
        """Rebuild the scoring grid for a match radius."""
        target = self.target
        lo, hi = target.min(axis=0), target.max(axis=0)
        ext = np.maximum(hi - lo, 1e-12)
        cell = max(float(radius), float(ext.max()) / 256.0)
        self.dims = np.maximum(np.ceil(ext / cell).astype(np.int64), 1)
        self.origin = lo.astype(np.float64)
        self.cell = cell
        self.radius = float(radius)
        self.gstart, self.gorder = _k.build_grid(target, self.origin, cell, self.dims)
        self.volume = float(np.prod(ext + 2.0 * radius))


@dataclass(frozen=True)
class Affine2DTrials:
    """Options of the affine trial search (:meth:`Affine2D.trial_motions`)."""

    sample_knn: int = 6
    batch: int = 512


def _sample_quads(source: np.ndarray, knn: int, count: int, rng) -> np.ndarray:
    """``count`` samples ``(anchor, n1, n2, n3)``: a random anchor and 3 of its ``knn`` neighbours."""
    n = source.shape[0]
    k = int(min(knn, n - 1))
    nbr = cKDTree(source).query(source, k=k + 1)[1][:, 1:]
    combos = np.array([(a, b, c) for a in range(k) for b in range(a + 1, k) for c in range(b + 1, k)],
                      np.int64)
    anchor = rng.integers(0, n, count)
    pick = combos[rng.integers(0, combos.shape[0], count)]
    return np.ascontiguousarray(np.column_stack([anchor, nbr[anchor[:, None], pick]]), np.int64)


# ------------------------------------------------------------------- model
class Affine2D:
    """Kang's six-parameter 2D affine motion: 3-point fits, 4-point invariant samples."""

    name = "affine2d"
    dim = 2
    sample_size = 3
    n_params = 6
    #: Points of a trial sample (a triangle and the 4th point that verifies it).
    trial_sample_size = 4

    def __init__(self, *, knn: int = 10, sample_knn: int = 6, max_cond: float = 10.0):
        self.knn = int(knn)
        self.sample_knn = int(sample_knn)
        self.max_cond = float(max_cond)

    def __repr__(self) -> str:
        return f"Affine2D(knn={self.knn}, sample_knn={self.sample_knn}, max_cond={self.max_cond:g})"

    # ------------------------------------------------------------ input
    def check_points(self, points, name: str) -> np.ndarray:
        """(N, 2) float64 points, at least 3, not all identical or collinear."""
        check_dimension(points, name, self.dim, self.name)
        p = as_points(points, name, min_points=self.sample_size, dim=2)
        check_spread(p, name, "an affine motion needs 3 non-collinear points")
        return p

    # -------------------------------------------------------------- fit
    def fit(self, source: np.ndarray, target: np.ndarray, weights=None) -> np.ndarray:
        """Weighted least-squares affine map (:func:`fit_affine`), as a 3×3 matrix."""
        A, t = fit_affine(source, target, weights)
        return homogeneous(A, t)

    def residuals(self, matrix: np.ndarray, source: np.ndarray, target: np.ndarray) -> np.ndarray:
        return matrix_residuals(matrix, source, target)

    # ----------------------------------------------------------- trials
    def sample_space(self, n: int) -> int:
        """Distinct trial samples of ``n`` source points (anchor × neighbour triples)."""
        return int(n * comb(int(min(self.sample_knn, max(n - 1, 0))), 3))

    def index(self, target: np.ndarray, radius: float, *, memory_budget=None) -> AffineIndex:
        return AffineIndex(target, radius, knn=self.knn, max_cond=self.max_cond,
                           memory_budget=memory_budget)

    def trial_motions(self, source: np.ndarray, index: AffineIndex, *, eps: float, max_triples: int,
                      rng: np.random.Generator, keep: int = 8, max_matches: int = 64,
                      accept: int | None = None, batch: int = 512, progress=None, **_ignored):
        """Trial affine maps from area-ratio invariant samples, best first.

        ``max_triples`` samples (anchor + 3 of its ``sample_knn`` nearest
        neighbours) are drawn; each looks up target quadruples of the same
        barycentric signature (``eps``: point tolerance), verifies the 4th
        point and scores the map.  Stops early once a trial reaches
        ``accept`` (default the chance level; ``<= 0`` never stops early).
        Returns :class:`gatv.models.rigid.congruent.TrialMotions` with ``rotations`` the
        (K, 2, 2) linear parts and ``translations`` the (K, 2) vectors.
        """
        n = source.shape[0]
        m = index.target.shape[0]
        threshold = self.chance(n, m, index.volume, index.radius, max_triples * max_matches)
        accept = accept_level(accept, threshold)
        pool = TrialPool(keep, 4, dim=2)
        if n < 4 or len(index) == 0:
            return pool.trials(index.radius, threshold, 0, 0)
        src = np.ascontiguousarray(source, dtype=np.float64)
        drawn = n_match = 0
        while drawn < max_triples:
            cnt = int(min(batch, max_triples - drawn))
            samples = _sample_quads(src, self.sample_knn, cnt, rng)
            drawn += cnt
            sc, A, t, nm = _k.quad_hypotheses(
                src, samples, index.target, index.sig, index.quad, index.scale, index.s_cap,
                index.bstart, index.border, index.GRID, float(eps), index.gstart, index.gorder,
                index.origin, index.cell, index.dims, index.radius, int(max_matches), self.max_cond)
            n_match += int(nm.sum())
            pool.add(sc, A, t)
            if progress is not None:
                progress(min(1.0, drawn / max_triples), f"{drawn} samples")
            if pool.best >= accept:
                break
        return pool.trials(index.radius, threshold, drawn, n_match)

    # ----------------------------------------------------------- tokens
    def joint_spaces(self, source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Kang's two joint spaces (eqs. 3–4): ``(x, y, x')`` and ``(x, y, y')``."""
        return (np.column_stack([source, target[:, 0]]), np.column_stack([source, target[:, 1]]))

    def tokens(self, source: np.ndarray, target: np.ndarray) -> np.ndarray:
        """``(x, y, x')`` of eq. 3 (``x`` already moved by the trial's linear part).

        The second space, ``(x, y, y')`` of eq. 4, is :meth:`joint_spaces`'s
        second array; :meth:`consistent` checks both planes.
        """
        return self.joint_spaces(source, target)[0]

    def consistent(self, tokens, ref: int, tau: float) -> np.ndarray:
        """Tokens with ``|Δx' - A Δx| <= tau`` against token ``ref`` (the analogue of eq. 41).

        ``A`` starts as the identity (the trial frame) and is then the
        least-squares fit of the two joint-space planes (eqs. 3–4) on the
        tokens kept, trimmed once at ``tau``; two rounds.  A token that reuses
        the reference's source or target point (a double match) is dropped.
        """
        xs, ys, pairs = tokens.source_points, tokens.target_points, tokens.pairs
        dx, dy = xs - xs[ref], ys - ys[ref]
        same = (pairs[:, 0] == pairs[ref, 0]) ^ (pairs[:, 1] == pairs[ref, 1])
        cons = np.union1d(np.flatnonzero((np.linalg.norm(dy - dx, axis=1) <= tau) & ~same), [ref])
        for _ in range(2):
            if cons.size < 3 or np.linalg.matrix_rank(dx[cons], tol=1e-9 * (1 + np.abs(dx).max())) < 2:
                return cons
            A, t = fit_affine(xs[cons], ys[cons])
            near = np.linalg.norm(ys[cons] - (xs[cons] @ A.T + t), axis=1) <= tau
            if 3 <= near.sum() < cons.size:
                A, _ = fit_affine(xs[cons[near]], ys[cons[near]])
            r = np.linalg.norm(dy - dx @ A.T, axis=1)
            new = np.union1d(np.flatnonzero((r <= tau) & ~same), [ref])
            if np.array_equal(new, cons):
                break
            cons = new
        return cons

    def chance(self, n_source: int, n_target: int, measure: float, gate: float,
               n_tests: float = 1.0) -> int:
        return chance_support(n_source, n_target, measure, gate, n_tests=n_tests, dim=2,
                              sample_size=self.trial_sample_size)

    def chance_alpha(self, support: int, n_source: int, n_target: int, measure: float, gate: float,
                     n_tests: float = 1.0) -> float:
        """The smallest family-wise level at which ``support`` reaches :meth:`chance`."""
        return chance_alpha(support, n_source, n_target, measure, gate, n_tests, dim=2,
                            sample_size=self.trial_sample_size)

    # ----------------------------------------------------------- result
    def result(self, matrix: np.ndarray, correspondences: np.ndarray, *, score: float,
               rms: float, info: dict) -> Motion:
        return Affine2DMotion(matrix[:2, :2], matrix[:2, 2], correspondences, score, rms, info)

    def search_policy(self) -> SearchPolicy:
        """:data:`POLICY`."""
        return POLICY


#: The 2D affine search: the defaults (:data:`gatv.models.base.NOISE_SCHEDULE`, motions peeled one at
#: a time), each motion held against its turned and shifted copies.
POLICY = SearchPolicy(turned_copies=True)

MODEL = Affine2D()
