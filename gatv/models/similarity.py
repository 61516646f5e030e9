"""The similarity model: ``x' = s R x R̃ + t`` (rotation, uniform scale, translation).

The paper registers rigid motions; a similarity adds one degree of freedom,
a uniform scale ``s > 0``.  Everything of the rigid pipeline carries over
once the trial motion's linear part ``s R0`` has been applied to the source:

* **Trial motions** come from *similar* point triples: a similarity keeps
  a triangle's shape, so target triple ``(k, l, m)`` matches source triple
  ``(a, b, c)`` when ``|kl|/|ab| = |km|/|ac| = |lm|/|bc| = s``
  (:func:`gatv.models.rigid.congruent_kernels.similar_triple_hypotheses`, driven by
  :func:`similar_trial_motions`), with ``s`` in a scale range.
* **Tokens** are ``d = x' - s R0 x``: for true pairs the residual motion
  after the trial's scale and rotation is near rigid, and they form the
  dense pure-translation cluster of section 3.4 as for rigid motions.
* **Consistency** is eq. 41 on the trial-moved points
  (:func:`gatv.models.rigid.eq41_consistent`), after the residual scale
  ``k`` the trial left is taken out: ``k`` is the value most tokens agree
  on in the similarity analogue of eq. 41's length half,
  ``|Δx'|² - k² |Δx|² = 0`` (:func:`residual_scale`), see
  :meth:`Similarity.consistent`.
* **Scoring** of trials counts distinct target points hit
  (:func:`gatv.models.rigid.congruent_kernels.count_distinct_inliers`): unlike a
  rigid motion, a similarity can shrink the source onto a few target
  points, which a plain inlier count rewards on dense data.
* The least-squares fit is Umeyama's (:func:`gatv.fitting.umeyama`).

Units: residuals, gates and side-length tolerances are in **target** units
(the target's spacing is ``s`` times the source's).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .rigid import congruent_kernels as _k
from .._validation import as_points, check_int
from .rigid.congruent import TargetIndex, TrialPool, accept_level, kernel_array, sample_triples
from ..errors import InputError
from ..fitting import umeyama
from ..stats import chance_alpha, chance_support
from .base import Motion, Rotational, SearchPolicy, freeze_fields, homogeneous, matrix_residuals
from .rigid import check_dimension, check_spread, eq41_consistent

__all__ = ["DEFAULT_SCALE_RANGE", "MODEL", "Similarity", "SimilarityMotion", "order_triples",
           "residual_scale", "similar_trial_motions"]

#: Scales the trial search looks for by default (``s_min``, ``s_max``).
DEFAULT_SCALE_RANGE = (0.1, 10.0)


def _check_scale_range(scale_range) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in scale_range)
    except (TypeError, ValueError) as exc:
        msg = f"Expected `scale_range` to be two numbers (s_min, s_max), got {scale_range!r}."
        raise InputError(msg) from exc
    if not (np.isfinite(lo) and np.isfinite(hi) and 0.0 < lo <= hi):
        msg = f"Expected `scale_range` to satisfy 0 < s_min <= s_max < inf, got {scale_range!r}."
        raise InputError(msg)
    return lo, hi


# ------------------------------------------------------------------ result
@dataclass(frozen=True, eq=False)
class SimilarityMotion(Rotational, Motion):
    """A similarity ``target ≈ scale · source @ rotation.T + translation`` and its support.

    Attributes
    ----------
    scale : float
        Uniform scale ``s > 0``.
    rotation : (3, 3) ndarray
        Rotation matrix ``R`` (det +1).
    translation : (3,) ndarray
    correspondences : (K, 2) ndarray of int
        One-to-one ``(source index, target index)`` pairs.
    support : int
        Number of correspondences.
    score : float
        Quality of the motion (as :class:`gatv.RigidMotion`).
    rms : float
        Root-mean-square residual of the correspondences, target units.
    info : dict
        Diagnostics. Not compared.

    A failed registration is a falsy ``SimilarityMotion`` (``support == 0``)
    whose ``info["reason"]`` says why.
    """

    model = "similarity"

    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    correspondences: np.ndarray = field(default_factory=lambda: np.empty((0, 2), np.int64))
    score: float = 0.0
    rms: float = float("nan")
    info: dict = field(default_factory=dict)

    def __post_init__(self):
        try:
            s = float(self.scale)
        except (TypeError, ValueError) as exc:
            raise InputError(f"Expected `scale` to be a positive number, got {self.scale!r}.") from exc
        if not (np.isfinite(s) and s > 0):
            raise InputError(f"Expected `scale` to be a positive finite number, got {s!r}.")
        object.__setattr__(self, "scale", s)
        freeze_fields(self, rotation=(3, 3), translation=(3,))

    @classmethod
    def from_matrix(cls, matrix, correspondences=None, *, score: float = 0.0,
                    rms: float = float("nan"), info: dict | None = None) -> SimilarityMotion:
        """From a 4×4 homogeneous matrix whose upper-left block is ``s R``.

        ``s`` is the cube root of the block's determinant and ``R`` the
        rotation nearest to the block divided by ``s`` (its polar factor;
        ``R = A / s`` exactly when ``A`` is a scaled rotation).
        """
        T = np.asarray(matrix, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise InputError(f"Expected `matrix` to be a finite (4, 4) array, got shape {T.shape}.")
        A = T[:3, :3]
        det = float(np.linalg.det(A))
        if det <= 0:
            msg = (f"Expected the linear part of `matrix` to be a scaled rotation (det > 0), "
                   f"got det {det:.3g}.")
            raise InputError(msg)
        s = float(np.cbrt(det))
        U, _, Vt = np.linalg.svd(A / s)
        R = U @ Vt
        pairs = np.empty((0, 2), np.int64) if correspondences is None else correspondences
        return cls(s, R, T[:3, 3], pairs, score, rms, {} if info is None else info)

    # ------------------------------------------------------------- derived
    @property
    def matrix(self) -> np.ndarray:
        """4×4 homogeneous matrix ``[[s R, t], [0, 1]]``, ``p_target = T @ [p_source, 1]``."""
        return homogeneous(self.scale * self.rotation, self.translation)

    # ---------------------------------------------------------- operations
    def inverse(self) -> SimilarityMotion:
        """The similarity from target to source (scale ``1/s``), with swapped correspondences."""
        rot = self.rotation.T
        return SimilarityMotion(
            scale=1.0 / self.scale,
            rotation=rot,
            translation=-(rot @ self.translation) / self.scale,
            correspondences=self.correspondences[:, ::-1],
            score=self.score,
            rms=self.rms,
            info=dict(self.info),
        )

    def to_dict(self) -> dict:
        """JSON-friendly dictionary."""
        return {**super().to_dict(), "scale": self.scale, **self.rotation_dict()}

    def __repr__(self) -> str:
        t = np.array2string(self.translation, precision=4, separator=", ")
        return (
            f"SimilarityMotion(scale={self.scale:.6g}, angle={self.angle_deg:.4f} deg, "
            f"translation={t}, support={self.support}, rms={self.rms:.3g})"
        )


# ------------------------------------------------------------ trial motions
def order_triples(source: np.ndarray, triples: np.ndarray) -> np.ndarray:
    """Reorder each triple ``(a, b, c)`` so that ``ab`` is its longest side.

    The scale of a similar match is read off ``|kl| / |ab|``; the longest
    side makes it least sensitive to noise.
    """
    t = np.asarray(triples, dtype=np.int64)
    p = source
    sides = np.stack([np.linalg.norm(p[t[:, 0]] - p[t[:, 1]], axis=1),   # ab, opposite c
                      np.linalg.norm(p[t[:, 0]] - p[t[:, 2]], axis=1),   # ac, opposite b
                      np.linalg.norm(p[t[:, 1]] - p[t[:, 2]], axis=1)],  # bc, opposite a
                     axis=1)
    longest = np.argmax(sides, axis=1)
    out = t.copy()
    # longest ac: (a, c, b); longest bc: (b, c, a)
    ac = longest == 1
    out[ac] = t[ac][:, [0, 2, 1]]
    bc = longest == 2
    out[bc] = t[bc][:, [1, 2, 0]]
    return out


def _select_triples(source: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` source triples, the better conditioned half of ``2 count`` draws, ordered.

    Triples are ranked by their shortest side relative to their longest
    (near-collinear triangles fix the rotation badly and short sides the
    scale); the ranking does not look at which points are inliers.
    """
    tri = order_triples(source, sample_triples(source.shape[0], 2 * count, rng))
    p = source
    ab = np.linalg.norm(p[tri[:, 0]] - p[tri[:, 1]], axis=1)
    ac = np.linalg.norm(p[tri[:, 0]] - p[tri[:, 2]], axis=1)
    bc = np.linalg.norm(p[tri[:, 1]] - p[tri[:, 2]], axis=1)
    quality = np.minimum(ac, bc) / np.where(ab > 0, ab, 1.0) * (ab > 0)
    best = np.sort(np.argsort(-quality, kind="stable")[:count])  # keep the draw order
    return tri[best]


def similar_trial_motions(
    source: np.ndarray,
    index,
    *,
    eps: float,
    max_triples: int,
    rng: np.random.Generator,
    scale_range=DEFAULT_SCALE_RANGE,
    batch: int = 64,
    keep: int = 8,
    max_matches: int = 64,
    accept: int | None = None,
    progress=None,
):
    """Draw source triples, match them to similar target triples, score the motions.

    The similarity counterpart of :func:`gatv.models.rigid.congruent.trial_motions`:
    stops early once a trial's support reaches ``accept`` (default: the
    chance level), after finishing its batch of ``batch`` triples (small,
    as each triple scans all target pairs, ``O(M²)``).

    Parameters
    ----------
    source : (N, 3) ndarray
    index : gatv.models.rigid.congruent.TargetIndex
        Its sorted neighbour lists and scoring grid are used.
    eps : float
        Side-length tolerance, **target** units.
    max_triples : int
        Upper bound on source triples drawn.
    rng : numpy.random.Generator
    scale_range : (float, float), default: (0.1, 10)
        Scales ``s`` looked for.
    keep : int
        Number of best distinct trials returned.
    max_matches : int
        Cap on similar target triangles scored per source triple.
    accept : int, optional
        Stop once a trial reaches this support; ``0`` never stops early.

    Returns
    -------
    gatv.models.rigid.congruent.TrialMotions
        Its ``rotations`` field holds the trial's **linear part** ``s R``
        (not a rotation), so that ``.matrices`` are the trial similarities.
    """
    s_min, s_max = (float(s) for s in _check_scale_range(scale_range))
    max_triples = check_int(max_triples, "max_triples", 1)
    source = kernel_array(source)
    n = source.shape[0]
    n2 = index.target.shape[0]
    threshold = chance_support(n, n2, index.volume, index.radius, n_tests=max_triples * max_matches)
    accept = accept_level(accept, threshold)
    pool = TrialPool(keep, 3)
    drawn = 0
    n_similar = 0
    while drawn < max_triples:
        m = min(batch, max_triples - drawn)
        tri = _select_triples(source, m, rng)
        starts = rng.integers(0, n2, tri.shape[0])
        drawn += tri.shape[0]
        scores, A, t, nm = _k.similar_triple_hypotheses(
            source, index.target, kernel_array(tri, np.int64), starts, index.ndist, index.nidx, float(eps),
            s_min, s_max, index.start, index.order, index.origin, index.cell, index.dims, index.radius,
            int(max_matches),
        )
        n_similar += int(nm.sum())
        pool.add(scores, A, t)
        if progress is not None:
            progress(min(1.0, drawn / max_triples), f"{drawn} triples, best support {pool.best}")
        if pool.best >= accept:
            break
    return pool.trials(index.radius, threshold, drawn, n_similar, relative=True)


def residual_scale(xs: np.ndarray, ys: np.ndarray, ref: int, tau: float,
                   bounds=(0.8, 1.25)) -> float | None:
    """The scale ``k`` most pairs ``(xs[j], ys[j])`` agree on against pair ``ref``.

    Pair ``j`` admits ``k`` when ``| |ys[j] - ys[ref]| - k |xs[j] - xs[ref]| | <= tau``,
    an interval of ``k``; the point of ``bounds`` covered by the most
    intervals (a sweep) is returned, refined to the least-squares ``k`` of
    the pairs that admit it.  ``None`` when fewer than 3 pairs agree.
    """
    dx = np.linalg.norm(xs - xs[ref], axis=1)
    dy = np.linalg.norm(ys - ys[ref], axis=1)
    use = dx > tau
    if use.sum() < 3:
        return None
    dx, dy = dx[use], dy[use]
    r, w = dy / dx, tau / dx
    lo, hi = np.maximum(r - w, bounds[0]), np.minimum(r + w, bounds[1])
    ok = lo <= hi
    if ok.sum() < 3:
        return None
    lo, hi = lo[ok], hi[ok]
    # Max overlap of closed intervals: sweep the starts, count ends passed.
    starts, ends = np.sort(lo), np.sort(hi)
    depth = np.arange(1, starts.size + 1) - np.searchsorted(ends, starts, side="left")
    best = int(np.argmax(depth))
    if depth[best] < 3:
        return None
    k0 = starts[best]
    agree = (lo <= k0) & (hi >= k0)
    k = float(dx[ok][agree] @ dy[ok][agree]) / float(dx[ok][agree] @ dx[ok][agree])
    return k if np.isfinite(k) and k > 0 else None


# ------------------------------------------------------------------- model
class Similarity:
    """Rotation, uniform scale and translation in 3D: 3-point samples, 7 degrees of freedom.

    Parameters
    ----------
    scale_range : (float, float), default: (0.1, 10)
        Scales the trial search looks for; a narrower range is faster and
        meets fewer false similar triangles.  Pass the model object:
        ``register(x, y, model=Similarity(scale_range=(0.5, 2)))``.
    """

    name = "similarity"
    dim = 3
    sample_size = 3
    n_params = 7
    #: The motion changes units: residuals, gates and tolerances are in the
    #: target's, so the point spacing they are relative to should be the
    #: target's (not the mean of both sets', which :func:`gatv.stages.prepare`
    #: uses for rigid motions).
    changes_scale = True

    def __init__(self, scale_range=DEFAULT_SCALE_RANGE):
        self.scale_range = _check_scale_range(scale_range)

    def __repr__(self) -> str:
        if self.scale_range == DEFAULT_SCALE_RANGE:
            return "Similarity()"
        return f"Similarity(scale_range={self.scale_range!r})"

    # ------------------------------------------------------------ input
    def check_points(self, points, name: str) -> np.ndarray:
        """(N, 3) float64 points, at least 3, not all identical or collinear."""
        check_dimension(points, name, self.dim, self.name)
        p = as_points(points, name, min_points=self.sample_size)
        check_spread(p, name, "a similarity needs 3 non-collinear points")
        return p

    # -------------------------------------------------------------- fit
    def fit(self, source: np.ndarray, target: np.ndarray, weights=None) -> np.ndarray:
        """Umeyama least squares, as a 4×4 matrix ``[[s R, t], [0, 1]]``."""
        s, R, t = umeyama(source, target, weights)
        return homogeneous(s * R, t)

    def residuals(self, matrix: np.ndarray, source: np.ndarray, target: np.ndarray) -> np.ndarray:
        """``|target - (s R source + t)|``, target units."""
        return matrix_residuals(matrix, source, target)

    # ----------------------------------------------------------- trials
    def index(self, target: np.ndarray, radius: float, *, memory_budget=None):
        """The target's sorted neighbour lists and scoring grid (:class:`gatv.models.rigid.congruent.TargetIndex`)."""
        return TargetIndex(target, radius, memory_budget=memory_budget)

    def trial_motions(self, source: np.ndarray, index, **options):
        """Trial similarities from similar triples (:func:`similar_trial_motions`).

        ``scale_range`` defaults to the model's.
        """
        options.setdefault("scale_range", self.scale_range)
        return similar_trial_motions(source, index, **options)

    def triple_cost(self, n_target: int) -> float:
        """Work of one source triple's scan, in :func:`gatv.register`'s units (~µs).

        The similar-triangle scan walks every target pair, ``O(M²)`` (about
        16 ns a pair, see docs/design-notes.md), against ``O(log M)`` for the
        rigid model's length lookup; :func:`gatv.stages.search` adds this to
        its per-triple work so that its round robin sizes the chunks right.
        """
        return 1.6e-2 * float(n_target) ** 2

    # ----------------------------------------------------------- tokens
    def tokens(self, source: np.ndarray, target: np.ndarray) -> np.ndarray:
        """``{dx, dy, dz}`` of eq. 30: ``d = x' - x`` (``x`` already moved by ``s R0``)."""
        return target - source

    def consistent(self, tokens, ref: int, tau: float) -> np.ndarray:
        """Eq. 41 against token ``ref`` on the trial-moved points, residual scale removed.

        After the trial's scale and rotation, true pairs differ by a near
        rigid motion, and eq. 41 (:func:`gatv.models.rigid.eq41_consistent`)
        applies to ``x = s0 R0 x_source`` and ``x'``.  A trial from three
        noisy points leaves a small residual scale ``k`` as well, which
        breaks eq. 41's length half (``|Δx'|² - |Δx|² = 0``) on long pairs
        (by about ``|k - 1| |Δx|``).  So first the similarity analogue of
        that half, ``|Δx'| - k |Δx| = 0`` (that is ``|Δx'|² - k² |Δx|² = 0``),
        picks ``k``: the value in ``[0.8, 1.25]`` that most tokens agree
        on within ``tau`` against the reference (:func:`residual_scale`);
        then eq. 41 proper is applied to ``k x`` and ``x'``.  With ``k = 1``
        this is the rigid model's test, which is also run; the larger
        consistent set wins.
        """
        xs, ys = tokens.source_points, tokens.target_points
        pairs = tokens.pairs
        cons = eq41_consistent(ys - xs, ys + xs, pairs, ref, tau)
        k = residual_scale(xs, ys, ref, tau)
        if k is None or abs(k - 1.0) < 1e-12:
            return cons
        kx = k * xs
        again = eq41_consistent(ys - kx, ys + kx, pairs, ref, tau)
        return again if again.size > cons.size else cons

    def chance(self, n_source: int, n_target: int, measure: float, gate: float,
               n_tests: float = 1.0) -> int:
        """Support a random similarity reaches: :func:`gatv.stats.chance_support`.

        At small gates the chance count is 0, and random *similar* triangles
        are common (one free scale: about one per 600 source triples among
        500 uniform points at the exact tolerance), so a motion supported by
        its own sample alone must not pass: ``chance_support`` asks one point
        beyond the count a wrong motion exceeds only rarely, plus the sample.
        """
        return chance_support(n_source, n_target, measure, gate, n_tests=n_tests, dim=3,
                              sample_size=self.sample_size)

    def chance_alpha(self, support: int, n_source: int, n_target: int, measure: float, gate: float,
                     n_tests: float = 1.0) -> float:
        """The smallest family-wise level at which ``support`` reaches :meth:`chance`."""
        return chance_alpha(support, n_source, n_target, measure, gate, n_tests, dim=3,
                            sample_size=self.sample_size)

    # ----------------------------------------------------------- result
    def result(self, matrix: np.ndarray, correspondences: np.ndarray, *, score: float,
               rms: float, info: dict) -> Motion:
        return SimilarityMotion.from_matrix(matrix, correspondences, score=score, rms=rms,
                                            info=info)

    def search_policy(self) -> SearchPolicy:
        """:data:`POLICY`."""
        return POLICY


#: The similarity's search: the defaults (tolerances up to 5% of the
#: spacing, grown while the support grows), each motion held against its
#: turned and shifted copies, and principal axes as
#: :func:`gatv.nonrigid.register`'s fallback pre-alignment.
POLICY = SearchPolicy(turned_copies=True, moment_prealign=True)

MODEL = Similarity()
