"""The verdict: the last stage of every pipeline.

"No motion" is an answer.  A motion is reported only when its support (the
points it brings within its gate of the other set) beats what wrong but
plausible motions collect on the same data, at a family-wise level that
accounts for how many motions the search tried.  Two null models give that
level:

* ``"poisson"`` — the exact pipeline's (:mod:`gatv.stats`): under a wrong
  motion a moved point lands within the gate of a target point with the
  probability the target's density gives, so the count is Poisson; the
  level is its ``1 - alpha / n_tested`` quantile (Bonferroni over the
  motions tried), plus the sample's own points.
* ``"wrong motions"`` — for surfaces (scans, the catadioptric sphere), where
  points are not scattered uniformly: wrong motions that lay one surface
  tangentially onto the other and are polished as the search's are
  (:func:`gatv.motions.scans.chance_support`) collect what crossing and
  sliding surfaces give; the level is the best of many such draws, with a
  tail fitted to them to extrapolate to the motions tried.

Every result carries the figures as ``info["verdict"]``
(:meth:`Verdict.to_dict`): ``support``, ``chance`` (the level), ``n_tested``
(the motions tried), ``p_value`` (family-wise, an estimate for the
``"wrong motions"`` null), ``margin`` (support over level), ``passed`` and
``method``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.stats import poisson

from .stats import ALPHA

__all__ = ["Verdict", "chance_verdict", "poisson_verdict", "wrong_motion_verdict"]


@dataclass(frozen=True)
class Verdict:
    """Whether a motion beats the wrong motions on the same data, and by how much.

    Attributes
    ----------
    support : int
        The motion's support.
    chance : float
        The level a wrong motion reaches (family-wise over ``n_tested``);
        the motion passes when its support exceeds it.
    n_tested : float
        Motions the search tried (the family the level accounts for).
    p_value : float
        Family-wise probability that a wrong motion reaches ``support``
        (NaN when the null model gives none).
    method : str
        ``"poisson"`` or ``"wrong motions"`` (the module docstring).
    """

    support: int
    chance: float
    n_tested: float
    p_value: float
    method: str

    @property
    def passed(self) -> bool:
        return bool(self.support > self.chance)

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
                "method": self.method}


def chance_verdict(support: int, chance: float, n_tested: float, *, method: str,
                   p_value: float = math.nan) -> Verdict:
    """A verdict from a level a pipeline has already computed."""
    return Verdict(int(support), float(chance), max(1.0, float(n_tested)), float(p_value), str(method))


def poisson_verdict(support: int, expected: float, n_tested: float, *, sample_size: int = 3,
                    alpha: float = ALPHA) -> Verdict:
    """The exact pipeline's null: Poisson(``expected``) chance pairs plus the sample's own points.

    The level is the ``1 - alpha / n_tested`` quantile (as
    :func:`gatv.stats.chance_support`); the p-value is Bonferroni,
    ``n_tested · P(count ≥ support − sample_size)``, capped at 1.
    """
    n = max(1.0, float(n_tested))
    level = float(poisson.isf(alpha / n, expected)) + sample_size
    k = int(support) - int(sample_size)
    p = 1.0 if k <= 0 else min(1.0, n * float(poisson.sf(k - 1, expected)))
    return Verdict(int(support), level, n, p, "poisson")


#: Share of the wrong-motion draws whose excesses over the rest fit the tail of
#: :func:`wrong_motion_verdict`.
TAIL_SHARE = 0.25


def wrong_motion_verdict(support: int, draws, n_tested: float) -> Verdict:
    """The surfaces' null: supports ``draws`` of polished wrong motions on the same data.

    The level is the best draw.  The p-value extrapolates the draws' upper
    tail: the excesses of the top :data:`TAIL_SHARE` over the next draw are
    fitted by an exponential (the peaks-over-threshold model of a
    light-tailed count), which gives ``P(a wrong motion ≥ support)``;
    Bonferroni over ``n_tested`` motions, capped at 1.
    """
    d = np.sort(np.asarray(draws, dtype=np.float64))[::-1]
    n = max(1.0, float(n_tested))
    if d.size == 0:
        return Verdict(int(support), 0.0, n, math.nan, "wrong motions")
    best = float(d[0])
    k = max(2, int(math.ceil(TAIL_SHARE * d.size)))
    if d.size <= k:
        return Verdict(int(support), best, n, math.nan, "wrong motions")
    u = float(d[k])
    scale = max(float(np.mean(d[:k] - u)), 1.0)
    tail = (k / d.size) * math.exp(-(float(support) - u) / scale) if support > u else 1.0
    return Verdict(int(support), best, n, min(1.0, n * tail), "wrong motions")
