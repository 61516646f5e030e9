"""The verdict: the last stage of every pipeline.

"No motion" is an answer.  A motion is reported only when its support (the
points it brings within its gate of the other set) beats what wrong but
plausible motions collect on the same data, at a family-wise level that
accounts for how many motions the search tried.  Three null models give that
level:

* ``"poisson"`` — the exact pipeline's (:mod:`gatv.stats`): under a wrong
  motion a moved point lands within the gate of a target point with the
  probability the target's density gives, so the count is Poisson; the
  level is its ``1 - alpha / n_tested`` quantile (Bonferroni over the
  motions tried), plus the sample's own points.
* ``"wrong motions"`` — for surfaces (scans), where
  points are not scattered uniformly: wrong motions that lay one surface
  tangentially onto the other and are polished as the search's are
  (:func:`gatv.scans.surface_verdict`) collect what crossing and sliding
  surfaces give; the level is the best of such draws times the gain a
  search's selection among far more motions buys (:data:`SEARCH_GAIN`).
* ``"local consistency"`` — the non-rigid pipelines' (:mod:`gatv.nonrigid`):
  the matches that pass the local eq. 41 against the level the hypothesis
  choice applies to the hypotheses scored.

Every result carries the figures as ``info["verdict"]``
(:meth:`Verdict.to_dict`): ``support``, ``chance`` (the level), ``n_tested``
(the motions tried), ``p_value`` (family-wise; an estimate for the
``"wrong motions"`` null; NaN where the pipeline keeps only its level, as the
exact search does), ``margin`` (support over level), ``passed`` and
``method``.  The catadioptric matcher records its sphere's Poisson level.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .stats import ALPHA, support_alpha, support_level

__all__ = ["Verdict", "chance_verdict", "poisson_verdict", "wrong_motion_verdict"]


@dataclass(frozen=True)
class Verdict:
    """Whether a motion beats the wrong motions on the same data, and by how much.

    Attributes
    ----------
    support : int
        The motion's support.
    chance : float
        The level a wrong motion reaches only with probability ``alpha``
        (family-wise over ``n_tested``); the motion passes when its support
        reaches it.
    n_tested : float
        Motions the search tried (the family the level accounts for).
    p_value : float
        Family-wise probability that a wrong motion reaches ``support``
        (NaN when the null model gives none).
    method : str
        ``"poisson"``, ``"wrong motions"`` or ``"local consistency"`` (the
        module docstring).
    alpha : float
        The family-wise level the chance level is set at (NaN where the
        level is not a quantile: the ``"wrong motions"`` null).
    """

    support: int
    chance: float
    n_tested: float
    p_value: float
    method: str
    alpha: float = ALPHA

    @property
    def passed(self) -> bool:
        """Support at or above the level (the count a wrong motion reaches with probability at most ``alpha``)."""
        return bool(self.support >= self.chance)

    @property
    def margin(self) -> float:
        """``support / chance`` (inf for a level of 0)."""
        return float(self.support) / self.chance if self.chance > 0 else math.inf

    def __bool__(self) -> bool:
        return self.passed

    def reason(self) -> str:
        """A sentence for a failed result's ``info["reason"]``."""
        return (f"no motion beats the wrong motions on these data: the best supports {self.support} points "
                f"against a chance level of {self.chance:.0f} ({self.method}, {self.n_tested:.3g} motions tried)")

    def to_dict(self) -> dict:
        """JSON-ready figures (``info["verdict"]``)."""
        return {"support": int(self.support), "chance": float(self.chance), "n_tested": float(self.n_tested),
                "p_value": float(self.p_value), "margin": float(self.margin), "passed": self.passed,
                "method": self.method, "alpha": float(self.alpha)}


def chance_verdict(support: int, chance: float, n_tested: float, *, method: str,
                   p_value: float = math.nan) -> Verdict:
    """A verdict from a level a pipeline has already computed."""
    return Verdict(int(support), float(chance), max(1.0, float(n_tested)), float(p_value), str(method))


def poisson_verdict(support: int, expected: float, n_tested: float, *, sample_size: int = 3,
                    alpha: float = ALPHA) -> Verdict:
    """The exact pipeline's null: Poisson(``expected``) chance pairs plus the sample's own points.

    The level is one above the ``1 - alpha / n_tested`` quantile, plus the
    sample (as :func:`gatv.stats.chance_support`): reached by chance with
    probability at most ``alpha / n_tested``; the p-value is Bonferroni,
    ``n_tested · P(count ≥ support − sample_size)``, capped at 1.
    """
    n = max(1.0, float(n_tested))
    level = float(support_level(expected, n, alpha, sample_size=sample_size))
    p = min(1.0, support_alpha(support, expected, n, sample_size=sample_size))
    return Verdict(int(support), level, n, p, "poisson", alpha)


#: How far a search's best wrong motion outdoes the best of the polished wrong
#: draws of :func:`wrong_motion_verdict`: the search selects among far more
#: (tens of thousands of) trial motions than the draws, so its best wrong one
#: can beat the draws' best by about this factor.  Measured on the supports of
#: :func:`gatv.scans.surface_verdict` (docs/design-notes.md, "The verdict"):
#: seventeen pairs with no true motion (unrelated real scans, clean and noisy,
#: a mirrored scan, disjoint halves, random clouds) reach at most 0.75 of the
#: level this gain sets; the right motions of 63 real scan pairs (clean, 2%
#: and 4% noise, with and without clutter) at least 1.11 of it.
SEARCH_GAIN = 1.6


def wrong_motion_verdict(support: int, draws, n_tested: float, *, n_points: int | None = None,
                         gain: float = SEARCH_GAIN, n_looks: int = 1, n_drawn: int | None = None) -> Verdict:
    """The surfaces' null: supports ``draws`` of polished wrong motions on the same data.

    The level is the best draw ``b`` made ``gain`` times likelier
    (:data:`SEARCH_GAIN`): on the odds of a point's support among the
    ``n_points`` counted, ``o = gain · b / (n_points - b)`` and the level is
    ``n_points · o / (1 + o)`` — ``gain · b`` while wrong motions hold few
    of the points, and short of ``n_points`` where they hold most (a
    self-similar object polished onto itself).  Without ``n_points``, ``gain
    · b``.  The p-value is an estimate from the draws' upper tail, fitted by
    an exponential whose mean ``β`` is the draws' median excess over their
    lowest over ``ln 2`` (robust to one draw that finds a large partial
    overlap): ``n_looks · exp(-(support - b) / β)``, ``n_looks`` the gates
    looked at; it measures how far the motion stands out, it is not held
    to a level.

    ``n_drawn``: the wrong motions the draws were drawn from (the verdict
    polishes the best screened of them), when the search's best among its
    ``n_tested`` motions is judged against them alone.  The level is then
    also at least the draws' best raised by the excess the best of
    ``n_tested`` motions has over the best of ``n_drawn`` from one
    exponential tail, ``β · ln(n_tested / n_drawn)`` (extreme values: the
    maximum of ``m`` exponential deviates grows as ``β ln m``), capped at
    ``n_points``: a search that selects among many motions more than the
    draws have is held to more (:data:`SEARCH_GAIN` alone was passed by a
    wrong motion selected among 577, design notes, section 6).
    """
    d = np.sort(np.asarray(draws, dtype=np.float64))[::-1]
    n = max(1.0, float(n_tested))
    if d.size == 0:
        return Verdict(int(support), 0.0, n, math.nan, "wrong motions", math.nan)
    best = float(d[0])
    if n_points is None:
        level = gain * best
    else:
        odds = gain * best / max(float(n_points) - best, 1e-300)
        level = float(n_points) * odds / (1.0 + odds)
    p = math.nan
    if d.size >= 3:
        beta = max(float(np.median(d[:-1] - d[-1])) / math.log(2.0), 1.0)
        p = 1.0 if support <= best else min(1.0, n_looks * math.exp(-(float(support) - best) / beta))
        if n_drawn is not None and n > n_drawn:
            extreme = best + beta * math.log(n / float(n_drawn))
            level = max(level, extreme if n_points is None else min(extreme, float(n_points)))
    return Verdict(int(support), level, n, p, "wrong motions", math.nan)
