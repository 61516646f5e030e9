"""The chance level: what support a wrong motion collects at random.

Every search in gatv keeps a motion only when its support beats what a
random motion would collect (Table 2's outliers are uniform in the
inliers' box).  Under a wrong motion a moved source point lands within
``radius`` of one of ``n_target`` points spread over a region of measure
``measure`` (a volume in 3D, an area in 2D or on the sphere) with
probability ``p = min(1, n_target · ball(radius) / measure)``; the count
over ``n_source`` points is about Poisson(``n_source · p``).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import gammaln, pdtrc

from .errors import InputError

__all__ = ["ALPHA", "ball_measure", "chance_alpha", "chance_count", "chance_mean", "chance_support",
           "likelihood_level", "pair_scores", "peak_ratios", "poisson_isf", "samples_needed", "score_cumulants",
           "support_alpha", "support_level"]

#: Family-wise level of the chance tests: a wrong motion beats the chance
#: level with at most this probability over all the tests counted.
ALPHA = 1e-6


def ball_measure(radius: float, dim: int = 3) -> float:
    """Measure of a ball of ``radius``: ``π r²`` in 2D, ``4/3 π r³`` in 3D."""
    if dim == 2:
        return math.pi * radius * radius
    if dim == 3:
        return 4.0 / 3.0 * math.pi * radius**3
    return math.pi ** (dim / 2.0) / math.gamma(dim / 2.0 + 1.0) * radius**dim


def poisson_isf(q: float, mu: float) -> int:
    """Smallest ``k`` (at least −1) with ``P(X > k) ≤ q`` for ``X`` ~ Poisson(``mu``).

    The level of every chance test is this quantile at ``alpha / n_tests``,
    which a search scoring 10⁷–10⁹ matches puts at 10⁻¹³–10⁻¹⁶.  SciPy's
    ``poisson.isf`` goes through ``1 − q`` there: below about 10⁻¹³ it can
    return a count one too low (a level a wrong motion reaches more often
    than ``q``) and below about 10⁻¹⁶ NaN.  Here the upper tail itself
    (``scipy.special.pdtrc``, accurate to the smallest floats) is searched:
    doubling, then bisection, about 2 log₂ k evaluations.

    Examples
    --------
    >>> poisson_isf(0.05, 3.0)
    6
    >>> poisson_isf(1e-20, 3.0)
    30
    """
    q, mu = float(q), float(mu)
    if not q > 0.0:
        raise InputError(f"q must be a positive probability (alpha / n_tests of a chance level), got {q!r}; "
                         "pass alpha > 0")
    if not (mu >= 0.0 and math.isfinite(mu)):
        raise InputError(f"mu must be a finite mean of at least 0, got {mu!r}; check the counts and the measure")
    if q >= 1.0:
        return -1
    lo, hi = -1, max(0, int(math.ceil(mu)))  # P(X > -1) = 1 > q
    while pdtrc(hi, mu) > q:
        lo, hi = hi, 2 * hi + 1
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if pdtrc(mid, mu) > q:
            lo = mid
        else:
            hi = mid
    return hi


def chance_mean(n_source: float, n_target: float, measure: float, radius: float, *, dim: int = 3) -> float:
    """Expected chance count of a wrong motion: ``n_source · min(1, n_target · ball(radius) / measure)``."""
    if dim == 3:
        expected = n_target * (4.0 / 3.0) * math.pi * radius**3
    elif dim == 2:
        expected = n_target * math.pi * radius * radius
    else:
        expected = n_target * ball_measure(radius, dim)
    return n_source * min(1.0, expected / max(measure, 1e-300))


def chance_count(n_source: float, n_target: float, measure: float, radius: float, *,
                 dim: int = 3, alpha: float = ALPHA, n_tests: float = 1.0) -> int:
    """Smallest count a random motion exceeds with probability below ``alpha / n_tests``."""
    return poisson_isf(alpha / max(n_tests, 1.0), chance_mean(n_source, n_target, measure, radius, dim=dim))


def chance_support(n_source: int, n_target: int, measure: float, radius: float,
                   n_tests: float = 1.0, alpha: float = ALPHA, *, dim: int = 3,
                   sample_size: int = 3) -> int:
    """Support a wrong motion reaches by chance only with probability ``alpha`` (family-wise).

    One more than :func:`chance_count` (the count a wrong motion exceeds
    with probability below ``alpha / n_tests``, so reaching it is not
    enough), plus the ``sample_size`` points that generated the trial
    motion, which always match: a motion supported by its own sample alone
    never reaches it.

    Examples
    --------
    >>> chance_support(100, 100, 1000.0, 1e-3)
    4
    >>> chance_support(100, 100, 1000.0, 1.0) > chance_support(100, 100, 1000.0, 0.5)
    True
    """
    return support_level(chance_mean(n_source, n_target, measure, radius, dim=dim), n_tests, alpha,
                         sample_size=sample_size)


def chance_alpha(support: int, n_source: int, n_target: int, measure: float, radius: float,
                 n_tests: float = 1.0, *, dim: int = 3, sample_size: int = 3) -> float:
    """The smallest family-wise level at which ``support`` reaches :func:`chance_support`.

    :func:`support_alpha` at the chance count's mean (:func:`chance_mean`):
    ``chance_support(..., alpha=a) <= support`` exactly when ``a`` is at
    least this.  Above 1 it is the Bonferroni bound on how many of the
    ``n_tests`` wrong motions reach ``support`` (what a benchmark reports
    for a motion no level at :data:`ALPHA` can keep).

    Examples
    --------
    >>> chance_alpha(4, 100, 100, 1000.0, 1e-3) <= ALPHA
    True
    >>> chance_alpha(2, 100, 100, 1000.0, 1e-3)
    inf
    """
    return support_alpha(support, chance_mean(n_source, n_target, measure, radius, dim=dim), n_tests,
                         sample_size=sample_size)


def support_level(expected: float, n_tests: float = 1.0, alpha: float = ALPHA, *, sample_size: int = 3) -> int:
    """Support a wrong motion with Poisson(``expected``) chance pairs reaches only with probability ``alpha``.

    Family-wise over ``n_tests``: one above the Poisson quantile at
    ``alpha / n_tests`` (:func:`poisson_isf`; reaching the quantile is not
    enough), plus the ``sample_size`` points that generated the trial
    motion, which always match.
    """
    return poisson_isf(alpha / max(float(n_tests), 1.0), expected) + 1 + int(sample_size)


def support_alpha(support: int, expected: float, n_tests: float = 1.0, *, sample_size: int = 3) -> float:
    """The smallest family-wise level at which ``support`` reaches :func:`support_level`.

    ``n_tests · P(X ≥ support − sample_size)`` for ``X`` ~ Poisson(``expected``),
    the Bonferroni p-value, not capped at 1; ``inf`` when ``support`` does
    not even hold the sample.
    """
    k = int(support) - 1 - int(sample_size)
    if k < -1:
        return math.inf
    tail = 1.0 if k == -1 else float(pdtrc(k, expected))
    return max(float(n_tests), 1.0) * tail


def samples_needed(inlier_share: float, confidence: float = 0.999, sample_points: int = 3) -> int:
    """Samples to draw so that one is all-inlier with ``confidence`` (the RANSAC bound).

    With an inlier share ``w``, a sample of ``k`` points is all-inlier with
    probability ``w**k``, so ``log(1 - confidence) / log(1 - w**k)`` samples
    find one.

    Examples
    --------
    >>> samples_needed(1.0, 0.999, 4)
    1
    >>> samples_needed(0.5, 0.99, 3)
    35
    """
    w = float(inlier_share) ** sample_points
    if w >= 1.0:
        return 1
    return int(math.ceil(math.log1p(-confidence) / math.log1p(-w)))


# ------------------------------------------------------- likelihood ratio
def peak_ratios(sigma: float, density, odds: float, dim: int = 3) -> np.ndarray:
    """``odds · φ_σ(0) / ρ``: a pair's likelihood ratio at residual 0 (:func:`pair_scores`).

    ``φ_σ`` is the density of a true pair's residual ``x' − T(x)``, an
    isotropic Gaussian of per-axis variance ``2 σ²`` (both points noisy),
    ``φ_σ(0) = (4 π σ²)^{−d/2}``; ``ρ`` (``density``, per point) the target
    points per unit measure where the motion puts the source point.
    """
    rho = np.asarray(density, dtype=np.float64)
    return float(odds) / (np.maximum(rho, 1e-300) * (4.0 * np.pi * float(sigma) ** 2) ** (dim / 2.0))


def pair_scores(residuals, sigma: float, density, odds: float, dim: int = 3) -> np.ndarray:
    """Each pair's log likelihood ratio ``log(1 + odds · φ_σ(r) / ρ)`` (``r`` its residual norm).

    The ratio of a point's likelihood when it is an inlier with prior odds
    ``odds`` (its partner's residual Gaussian at the noise ``σ``,
    :func:`peak_ratios`) or a chance neighbour (the target's local density
    ``ρ``) to its likelihood as a chance neighbour alone: the mixture
    likelihood of the rigid EM (:func:`gatv.stages.weighted_pose`) against
    the uniform null, per point.  Never negative, and near 0 beyond a few
    ``σ``: summed over a motion's pairs it weighs each by how tight it is,
    where a count within one gate weighs the tight and the loose alike.
    """
    r = np.asarray(residuals, dtype=np.float64)
    a = peak_ratios(sigma, density, odds, dim)
    return np.log1p(a * np.exp(-(r * r) / (4.0 * float(sigma) ** 2)))


#: Gauss–Legendre nodes of :func:`score_cumulants`' integral over ``t = sqrt(u)``.
_NODES = 128


def _score_grid(ratios, weights, odds: float, dim: int):
    """The scores ``g`` on :func:`score_cumulants`' nodes, the nodes' weights and each ratio's factor."""
    a = np.asarray(ratios, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    t_max = np.sqrt(np.log(max(float(a.max()), 1.0)) + 40.0)
    x, q = np.polynomial.legendre.leggauss(_NODES)
    t = 0.5 * t_max * (x + 1.0)
    u = t * t
    q = q * 0.5 * t_max * 2.0 * t ** (dim - 1)  # u^{d/2-1} du = 2 t^{d-1} dt
    g = np.log1p(a[:, None] * np.exp(-u)[None, :])
    pre = w * float(odds) / (a * np.exp(gammaln(dim / 2.0)))
    return g, q, pre


def _cumulants(theta: float, g, q, pre) -> tuple[float, float, float]:
    e = np.exp(theta * g)
    k0 = float(pre @ ((e - 1.0) @ q))
    eg = e * g
    return k0, float(pre @ (eg @ q)), float(pre @ ((eg * g) @ q))


def score_cumulants(theta: float, ratios, weights, odds: float, dim: int = 3) -> tuple[float, float, float]:
    """``K(θ), K'(θ), K''(θ)``: the cumulant generating function of a wrong motion's summed scores.

    Under a wrong motion the target points around a moved source point
    whose local density is ``ρ`` form a Poisson process of intensity ``ρ``
    (the null of :func:`chance_count`, point by point).  Summing
    :func:`pair_scores` over *every* target point around every source
    point, not only its one-to-one partner, gives a compound Poisson sum,
    never smaller than the one-to-one sum (the scores are not negative),
    whose generating function is, with ``a`` the point's
    :func:`peak_ratios` and ``u = r² / (4 σ²)``::

        K(θ) = Σ_points (odds / (a Γ(d/2))) ∫₀^∞ ((1 + a e^{−u})^θ − 1) u^{d/2 − 1} du

    (``K(1) = odds`` a point: the ratio's mean is 1).  ``ratios`` are the
    distinct ``a`` and ``weights`` the points that have each.  The
    integral is taken over ``t = sqrt(u)`` by Gauss–Legendre up to where
    ``a e^{−u}`` is below ``e^{−40}``.
    """
    return _cumulants(float(theta), *_score_grid(ratios, weights, odds, dim))


def likelihood_level(ratios, odds: float, n_tests: float = 1.0, alpha: float = ALPHA, *,
                     dim: int = 3) -> float:
    """The summed :func:`pair_scores` a wrong motion reaches with probability ``alpha / n_tests``.

    ``ratios``: every source point's :func:`peak_ratios` under the motion
    (its local target density).  The tail of the compound Poisson sum of
    :func:`score_cumulants` at the saddle point ``θ`` (``K'(θ) = s``),
    Bahadur–Rao: ``P(S ≥ s) ≈ exp(K(θ) − θ s) / (θ sqrt(2 π K''(θ)))``,
    the prefactor taken as 1 where it would exceed it (Chernoff's bound,
    which holds for any ``θ``).  The level solves ``P = alpha / n_tests``
    (Newton's method on ``θ``, bracketed): the count test's Poisson
    quantile (:func:`chance_count`) for a weighted count.  Ratios are
    grouped to 2% before the integral.
    """
    a = np.asarray(ratios, dtype=np.float64).ravel()
    a = a[np.isfinite(a) & (a > 0)]
    if a.size == 0:
        return 0.0
    keys, weights = np.unique(np.round(np.log(a) * 50.0), return_counts=True)
    grid = _score_grid(np.exp(keys / 50.0), weights, odds, dim)
    target = np.log(max(float(n_tests), 1.0) / float(alpha))

    def excess(theta):
        k0, k1, k2 = _cumulants(theta, *grid)
        prefactor = max(0.0, np.log(theta * np.sqrt(2.0 * np.pi * max(k2, 1e-300))))
        return theta * k1 - k0 + prefactor - target, k1, k2

    lo, hi, theta = 0.0, np.inf, 1.0
    for _ in range(100):
        h, k1, k2 = excess(theta)
        if abs(h) <= 1e-6 * target:
            break
        if h < 0.0:
            lo = theta
        else:
            hi = theta
        step = theta - h / max(theta * k2, 1e-300)  # h'(θ) ≈ θ K''(θ)
        if not lo < step < hi:
            step = 2.0 * theta if hi == np.inf else 0.5 * (lo + hi)
        theta = step
    return float(k1)
