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

from scipy.stats import poisson

__all__ = ["ALPHA", "ball_measure", "chance_count", "chance_support", "samples_needed"]

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


def chance_count(n_source: float, n_target: float, measure: float, radius: float, *,
                 dim: int = 3, alpha: float = ALPHA, n_tests: float = 1.0) -> int:
    """Smallest count a random motion exceeds with probability below ``alpha / n_tests``."""
    if dim == 3:
        expected = n_target * (4.0 / 3.0) * math.pi * radius**3
    elif dim == 2:
        expected = n_target * math.pi * radius * radius
    else:
        expected = n_target * ball_measure(radius, dim)
    p = min(1.0, expected / max(measure, 1e-300))
    return int(poisson.isf(alpha / max(n_tests, 1.0), n_source * p))


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
    return chance_count(n_source, n_target, measure, radius, dim=dim, alpha=alpha,
                        n_tests=n_tests) + 1 + int(sample_size)


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
