"""Several motions of any model, peeled one at a time (paper, section 5).

"After the first plane was detected, we removed its tokens from the
voting space and the process was repeated until no more planes were
found."  :func:`peel` does this for any :class:`~gatv.models.MotionModel`
(rigid, similarity, 2D affine), as a sequence of the named stages of
:mod:`gatv.stages`:

1. **Search** (:func:`gatv.stages.search`, as :func:`gatv.register`) on
   the points no motion explains yet: the model's invariant-sample trial
   motions in round robin over the tolerance schedule, with a RANSAC
   budget for the smallest motion wanted.  A noisy peel polishes each
   chunk's best trials before the density test sees them
   (:func:`gatv.stages.polish_trials`, LO-RANSAC's local optimisation).
2. **Judge** (:func:`gatv.stages.judge`): candidate tokens within the voting reach of
   the trial, one ball pass in each of the model's joint spaces (one for
   rigid and similarity motions; Kang's two, ``(x, y, x')`` and
   ``(x, y, y')``, for 2D affine motions — a token is salient when it is
   salient in every space), the model's constraint against the most salient
   tokens, one-to-one selection by saliency, fit and residual gate.
3. **Keep** the motion when its support beats the chance level
   (``problem.chance(gate, n_tests)``), after ICP refinement and growing the
   tolerance while the support grows beyond chance; **remove** its source
   and target points; repeat.  A noisy peel (noise unknown) measures each
   motion's noise and keeps it only when its pairs within that gate still
   beat chance there (a wrong motion's residuals spread over the gate it was
   found at); one rejected from a tolerance above the finest shows that the
   density test's chance level is breached there in these data, so later
   rounds search the finer tolerances only (``info["rounds"][k]["rejected"]``).
4. **Pool**: at the end, one sensor's noise pooled over the motions kept; a
   motion whose pairs do not beat chance there is dropped
   (``info["dropped"]``).  The points a rejected or dropped motion held out
   of the later rounds (its chance pairs may be a true motion's points) go
   back to the search for one more pass (``info["returned"]``).
5. **Label**: every point to its most likely motion or to the outliers,
   jointly and one-to-one, each pose refitted on its labels, until the
   labelling repeats (:func:`joint_assignment`, ``info["joint"]``).

It stops when no trial beats chance, ``max_motions`` motions were found,
or too few points are left (``info["reason"]`` says which).  Steps 1-3 are
the search, accept and remove steps of the one peel loop,
:func:`gatv.peel_loop.peel_loop`, that every several-motion pipeline runs.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from math import gamma
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.stats import chi2

from .. import stages
from .._validation import (
    as_rng,
    check_fraction,
    check_int,
    check_positive,
    check_progress,
)
from ..errors import InputError
from ..models.base import split_matrix
from ..peel_loop import Candidate, Judgement, PeelOutcome, Stop, peel_loop
from ..stages import Fit, Problem, listed_share
from ..verdict import chance_verdict
from .result import Segmentation

__all__ = [
    "LISTING",
    "assign_pairs",
    "assignment_gain",
    "joint_assignment",
    "likelihood_gate",
    "listed_share",
    "merge_same_motions",
    "peel",
    "pool_noise",
    "search_budget",
]

#: Judged trials per round; the family-wise chance level counts them.
N_JUDGED = 4
#: Default cap on the samples drawn per tolerance level and round.
MAX_SAMPLES = 200_000
#: The listing tolerance (:func:`gatv.stages.search`'s ``listing``: standard
#: deviations of a side's length error, ``eps = 2 listing τ``) of a noisy
#: peel's rounds (see :func:`listed_share`): once the noise is measured, of
#: the points' noise; in the first round, of each level's tolerance (not the
#: search's default :data:`gatv.stages.LISTING`).
LISTING = 1.0
#: Candidate triples ranked a sample (``trial_motions``' ``wide``) in those
#: rounds.  They list 7-25 matches a sample (1-2% noise), where ranking
#: costs as much as scoring: on 1%/2% K=4 rounds 32 beat 2, 8 and 128
#: (:data:`gatv.models.rigid.WIDE`, which suits wide listings).
LISTING_WIDE = 32
#: Passes of a noisy peel, after the first, that return to the search the
#: points held out by motions rejected at their noise or dropped at the
#: pooled noise.
RETURNS = 1


def _support_weighted_noise(fits: list[Fit], noises) -> float:
    """One sensor's noise from its motions' own: ``σ² = Σ n_k σ_k² / Σ n_k`` over their supports ``n_k``."""
    n = np.array([f.support for f in fits], dtype=np.float64)
    return float(np.sqrt(np.sum(n * np.square(noises)) / np.sum(n)))


def _subproblem(P: Problem, src: np.ndarray, tgt: np.ndarray) -> Problem:
    """The points not yet explained, with the full problem's scale facts."""
    Y = P.target[tgt]
    return Problem(P.source[src], Y, P.model, cKDTree(Y), P.spacing, P.extent, P.volume)


def search_budget(problem: Problem, levels, smallest: float, confidence: float, cap: int,
                  max_matches: int, *, memory_budget: float | None = None, listed: float = 1.0,
                  index=None) -> tuple[int, float]:
    """Samples a round draws, for the smallest motion its search can find; and that motion's size.

    A motion of ``m`` of the ``n`` source points is hit by an all-inlier
    sample with ``confidence`` after :func:`gatv.stats.samples_needed`
    ``(m / n)`` draws (the RANSAC bound).  But :func:`gatv.stages.search`
    judges only trials whose support reaches its density test's chance
    level, ``model.chance(n, n2, volume, gate, budget · max_matches)`` at the
    level most lenient of ``levels``: a smaller motion is never judged,
    however many samples hit it, so drawing samples for it is wasted work.
    The smallest motion a round can find is therefore the larger of
    ``smallest`` and that level, which itself grows (slowly, as a log) with
    the budget; the budget returned is the least ``b`` (bisection) that is
    enough for the smallest motion findable with ``b`` draws, so it covers
    every motion the search could find with any budget up to ``cap``.
    ``listed`` is the share of all-inlier samples whose true match the
    search lists (:func:`listed_share`): a sample finds the motion with
    probability ``(m / n)^k · listed``.  ``index``: the model's index of
    ``problem.target`` when already built (its radius is changed).
    """
    model = problem.model
    k_pts = int(getattr(model, "trial_sample_size", model.sample_size))
    n, n2 = problem.source.shape[0], problem.target.shape[0]
    if index is None:
        index = model.index(problem.target, stages.gate(min(levels)), memory_budget=memory_budget)
    volumes = []
    for tol in levels:
        index.set_radius(stages.gate(tol))
        volumes.append((index.volume, index.radius))

    def findable(b: int) -> float:
        accept = min(model.chance(n, n2, v, r, b * max_matches) for v, r in volumes)
        return max(float(smallest), float(accept))

    def needed(m: float) -> int:
        w = min(1.0, m / n) ** k_pts * float(listed)
        return int(min(1 if w >= 1.0 else np.ceil(np.log1p(-confidence) / np.log1p(-w)), cap))

    hi = max(needed(float(smallest)), 1)
    if needed(findable(hi)) >= hi:
        return hi, findable(hi)
    lo = 1  # needed(findable(b)) is non-increasing in b: the least b with b >= needed(findable(b))
    while lo < hi:
        mid = (lo + hi) // 2
        if mid >= needed(findable(mid)):
            hi = mid
        else:
            lo = mid + 1
    return hi, findable(hi)


def likelihood_gate(sigma: float, density: float, dim: int = 3) -> float:
    """Residual radius beyond which a random target point is likelier than a true partner.

    A true pair's residual is an isotropic Gaussian of per-axis standard
    deviation ``s = sqrt(2) σ`` (both points noisy), of density
    ``(2π s²)^(-dim/2) exp(-r² / 2 s²)`` at residual ``r``; random target
    points lie at ``density`` per unit measure.  The two are equal at
    ``r² = 2 s² log((2π s²)^(-dim/2) / density)`` (0 when the target is so
    dense that a random point is always as likely).
    """
    s2 = 2.0 * float(sigma) ** 2
    ratio = (2.0 * np.pi * s2) ** (-dim / 2.0) / max(float(density), 1e-300)
    return float(np.sqrt(2.0 * s2 * np.log(ratio))) if ratio > 1.0 else 0.0


def assign_pairs(pairs: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """Rows of ``pairs`` of the one-to-one subset of largest total ``gain`` (all gains > 0 are kept candidates).

    The maximum-weight bipartite matching, exact: the candidate pairs fall
    into connected components (pairs sharing a source or a target point), and
    each component's assignment is solved on its own
    (:func:`scipy.optimize.linear_sum_assignment`, a pair left out gaining
    nothing).  With ``gain`` the log-likelihood ratio of each pair being a
    true one, this is the most likely one-to-one labelling; the greedy
    selection (cheapest first) instead drops a point whose nearest target
    went to another, even when its second nearest is free.
    """
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    gain = np.asarray(gain, np.float64)
    ok = np.flatnonzero(gain > 0)
    if ok.size == 0:
        return ok
    # the best row for each (source, target): the same pair under two motions
    order = ok[np.lexsort((-gain[ok], pairs[ok, 1], pairs[ok, 0]))]
    first = np.ones(order.size, bool)
    first[1:] = np.any(pairs[order[1:]] != pairs[order[:-1]], axis=1)
    rows = order[first]
    s_ids, s_of = np.unique(pairs[rows, 0], return_inverse=True)
    t_ids, t_of = np.unique(pairs[rows, 1], return_inverse=True)
    ns, nt = s_ids.size, t_ids.size
    graph = coo_matrix((np.ones(rows.size), (s_of, ns + t_of)), shape=(ns + nt, ns + nt))
    _, comp = connected_components(graph, directed=False)
    kept = []
    for c in np.unique(comp[s_of]):
        mine = np.flatnonzero(comp[s_of] == c)
        if mine.size == 1:
            kept.append(rows[mine])
            continue
        si, sr = np.unique(s_of[mine], return_inverse=True)
        ti, tr = np.unique(t_of[mine], return_inverse=True)
        weight = np.zeros((si.size, ti.size))
        weight[sr, tr] = gain[rows[mine]]
        a, b = linear_sum_assignment(weight, maximize=True)
        index = np.full((si.size, ti.size), -1, np.int64)
        index[sr, tr] = mine
        chosen = index[a, b]
        kept.append(rows[chosen[chosen >= 0]])
    return np.sort(np.concatenate(kept))


#: Level of :func:`merge_same_motions`' test that two found motions are one.
MERGE_LEVEL = 1e-3
#: Largest share of two motions' pairs beyond the final gate of their union's
#: fit (:data:`gatv.stages.FINAL_GATE` σ, which keeps 98% of true pairs) for
#: :func:`merge_same_motions` to test them as one: those pairs are left out of
#: the test, so that a chance pair a part took in does not keep it apart.
MERGE_OUTSIDE = 0.2


def merge_same_motions(problem: Problem, fits: list[Fit], noises: list[float], *,
                       level: float = MERGE_LEVEL) -> tuple[list[Fit], list[float], list[dict]]:
    """Join motions that are one motion found in two rounds (models whose policy has ``merge_motions``).

    A round may keep part of a motion (a trial pose a little off brings only
    some of its points within the gate) and a later round the rest.  For two
    found motions with pairs ``A`` and ``B``, the least-squares fit of ``A ∪ B``
    and the fits of each: under "one motion" the extra residual
    ``(RSS(A ∪ B) − RSS(A) − RSS(B)) / s²`` (``s² = 2 σ²`` the per-axis
    variance of a pair's residual at the pooled noise ``σ``) is a chi-square
    with the motion's 6 degrees of freedom; two different motions leave it
    orders of magnitude above.  Pairs beyond :data:`gatv.stages.FINAL_GATE`
    σ of the union's fit (at most :data:`MERGE_OUTSIDE` of them; more, and
    the two are not one motion) are left out of all three fits: a chance
    pair that a part took in would otherwise keep it apart from the rest.
    The joined motion keeps both motions' pairs (its pose is fitted without
    the far ones).
    The pair with the smallest statistic under
    its ``level`` quantile is joined (pose refitted on the union, support
    weighted noise), and the test repeats.  Returns the fits, their noises and
    a record of each join.
    """
    P = problem
    if not P.model.search_policy().merge_motions:
        return list(fits), list(noises), []
    fits, noises = list(fits), [float(x) for x in noises]
    s2 = 2.0 * _support_weighted_noise(fits, noises) ** 2
    limit = float(chi2.isf(level, P.model.n_params))
    joined = []

    def rss(pairs):
        M = P.model.fit(P.source[pairs[:, 0]], P.target[pairs[:, 1]])
        return M, float(np.sum(np.square(P.residuals(M, pairs))))

    # A true pair's residual under the union's fit stays within FINAL_GATE σ (98%);
    # the pairs beyond it (a chance pair a part took in) are left out of all three fits.
    far = stages.FINAL_GATE * np.sqrt(s2 / 2.0)
    k_min = P.model.sample_size
    while len(fits) > 1 and s2 > 0:
        best = None
        own = [rss(f.correspondences)[1] for f in fits]
        for a in range(len(fits)):
            for b in range(a + 1, len(fits)):
                pa, pb = fits[a].correspondences, fits[b].correspondences
                union = np.vstack([pa, pb])
                M, r = rss(union)
                inside = P.residuals(M, union) <= far
                if inside.mean() < 1.0 - MERGE_OUTSIDE:
                    continue  # two motions: the union's fit leaves many pairs far off
                r_a, r_b = own[a], own[b]
                if not inside.all():  # refit all three without the far pairs
                    pa, pb = pa[inside[:len(pa)]], pb[inside[len(pa):]]
                    if len(pa) < k_min or len(pb) < k_min:
                        continue
                    M, r = rss(np.vstack([pa, pb]))
                    r_a, r_b = rss(pa)[1], rss(pb)[1]
                stat = (r - r_a - r_b) / s2
                if stat <= limit and (best is None or stat < best[0]):
                    best = (stat, a, b, M, union, int(np.count_nonzero(~inside)))
        if best is None:
            break
        # The pose is the fit without the far pairs; the pairs are both motions'
        # (pool_noise re-gates every motion at the pooled noise afterwards).
        stat, a, b, M, union, left_out = best
        na, nb = fits[a].support, fits[b].support
        joined.append({"motions": (a, b), "supports": (na, nb), "statistic": stat, "limit": limit,
                       "left_out": left_out})
        noises[a] = float(np.sqrt((na * noises[a] ** 2 + nb * noises[b] ** 2) / (na + nb)))
        fits[a] = Fit(M, union[np.argsort(union[:, 0], kind="stable")])
        del fits[b], noises[b]
    return fits, noises, joined


def pool_noise(problem: Problem, fits: list[Fit], noises: list[float]) -> tuple[list[Fit], float]:
    """Every motion's correspondences re-gated at the noise of the one sensor, measured on them all.

    Each motion's noise was measured on its own few dozen residuals
    (:func:`gatv.stages.settle_noise`), an estimate good to some 10-15%; a
    gate of :data:`gatv.stages.FINAL_GATE` times an estimate that is low
    drops true pairs.  Both scans come from one sensor, so the noise is
    pooled, ``σ² = Σ n_k σ_k² / Σ n_k`` over the motions' supports ``n_k``,
    and every motion's one-to-one nearest pairs are taken again within
    ``FINAL_GATE σ``; a point two motions claim goes to the one with the
    smaller residual (one-to-one over all motions); where the target is
    sparse the gate reaches out to :func:`likelihood_gate`, where a true
    pair stops being likelier than a random target point.  A motion's wider gate
    is used only when it brings in more pairs than random points would
    collect in the added shell (their expected number).  Poses are unchanged.
    A motion left with fewer than the model's ``sample_size`` pairs keeps
    its own, less the points the others took.
    """
    P = problem
    sigma = _support_weighted_noise(fits, noises)
    g = _pooled_gate(P, sigma)
    n1, density = P.source.shape[0], P.target.shape[0] / P.volume
    ball = np.pi ** (P.dim / 2.0) / gamma(P.dim / 2.0 + 1.0)
    pairs, gain, owner = [], [], []
    for k, (fit, own) in enumerate(zip(fits, noises)):
        wider = stages.regate(P, fit, g)
        g_own = stages.FINAL_GATE * own
        # random pairs expected in the added shell, had every source point a random target there
        shell = n1 * density * ball * max(g**P.dim - g_own**P.dim, 0.0)
        g_k = g_own if g > g_own and wider.support - fit.support <= shell else g
        # Every target within the gate, not only the nearest: a point whose
        # nearest target is another's partner may take its second nearest.
        c = _gated_pairs(P, fit.matrix, g_k)
        pairs.append(c)
        # log-likelihood ratio of "true pair" over "both unexplained", times 2σ²
        gain.append(g_k**2 - np.square(P.residuals(fit.matrix, c)))
        owner.append(np.full(c.shape[0], k))
    pairs, gain, owner = np.vstack(pairs), np.concatenate(gain), np.concatenate(owner)
    keep = assign_pairs(pairs, gain)
    labelled = [_labelled(pairs, keep, owner, k) for k in range(len(fits))]
    short = [c.shape[0] < P.model.sample_size for c in labelled]
    out = [Fit(fit.matrix, c) for fit, c in zip(fits, labelled)]
    # Too few pairs at the pooled gate: the motion keeps its own pairs, less
    # the points the motions before it here took (one-to-one over all motions).
    taken = [c for c, s in zip(labelled, short) if not s]
    for k in np.flatnonzero(short):
        c = fits[k].correspondences
        if taken:
            t = np.vstack(taken)
            c = c[~(np.isin(c[:, 0], t[:, 0]) | np.isin(c[:, 1], t[:, 1]))]
        out[k] = Fit(fits[k].matrix, c)
        taken.append(c)
    return out, sigma


def _pooled_gate(P: Problem, sigma: float) -> float:
    """:func:`pool_noise`'s gate at the pooled noise ``sigma``: the larger of :data:`gatv.stages.FINAL_GATE` σ
    and :func:`likelihood_gate` at the target's mean density."""
    return max(stages.FINAL_GATE * sigma, likelihood_gate(sigma, P.target.shape[0] / P.volume, P.dim))


def _gated_pairs(P: Problem, matrix: np.ndarray, g: float) -> np.ndarray:
    """Every (source, target) pair within ``g`` under the pose ``matrix``, (K, 2)."""
    A, t = split_matrix(matrix)
    near = P.tree.query_ball_point(P.source @ A.T + t, g)
    return np.array([(i, j) for i, js in enumerate(near) for j in js], np.int64).reshape(-1, 2)


def _labelled(pairs: np.ndarray, keep: np.ndarray, owner: np.ndarray, k: int) -> np.ndarray:
    """The pairs of motion ``k`` among the kept rows ``keep`` of ``pairs`` (``owner``: each row's motion),
    by source row."""
    c = pairs[keep[owner[keep] == k]]
    return c[np.argsort(c[:, 0], kind="stable")]


#: Bound on the rounds of :func:`joint_assignment` (assign, refit); it stops
#: earlier once the labelling no longer changes.
JOINT_ROUNDS = 10


def _candidate_pairs(P: Problem, fits: list[Fit], g: float):
    """Every (source, target, motion) within ``g`` under each motion's pose, and its residual."""
    pairs, res, owner = [], [], []
    for k, fit in enumerate(fits):
        c = _gated_pairs(P, fit.matrix, g)
        pairs.append(c)
        res.append(P.residuals(fit.matrix, c))
        owner.append(np.full(c.shape[0], k))
    return np.vstack(pairs), np.concatenate(res), np.concatenate(owner)


def assignment_gain(problem: Problem, fits: list[Fit], g: float) -> float:
    """The objective :func:`joint_assignment` maximises: ``Σ (g² − r²)`` over every motion's correspondences.

    Times ``1 / 2s²`` (``s² = 2σ²``), each term is the log-likelihood ratio
    of the pair being a true pair of its motion (a Gaussian residual) over
    its two points being outliers, whose cost ``g`` is the residual where
    the two are equally likely (:func:`likelihood_gate`).
    """
    return float(sum(np.sum(g**2 - np.square(problem.residuals(f.matrix, f.correspondences))) for f in fits))


def joint_assignment(problem: Problem, fits: list[Fit], sigma: float, *, gate: float | None = None,
                     rounds: int = JOINT_ROUNDS) -> tuple[list[Fit], dict]:
    """Every point to its most likely motion or to the outliers, jointly and one-to-one; poses refitted.

    Coordinate ascent on one objective, :func:`assignment_gain`: the total
    log-likelihood ratio of the labelled pairs, each ``g² − r²`` (``g`` the
    outlier cost, by default :func:`pool_noise`'s gate at ``sigma``, the
    larger of :data:`gatv.stages.FINAL_GATE` σ and :func:`likelihood_gate`
    at the target's mean density).  With the poses fixed, the most likely
    one-to-one labelling over all motions is a maximum-weight matching
    (:func:`assign_pairs`, exact: every pair of positive gain is a
    candidate); with the labels fixed, each motion's least-squares refit on
    its pairs lowers their ``Σ r²``.  Neither step lowers the objective, so
    the rounds stop when the labelling repeats or after ``rounds``; a round
    that would leave a motion under the model's ``sample_size`` pairs, or
    lower the objective (rounding), is not taken.  Returns the fits (poses
    refitted, correspondences the labelling) and a record: the gate, the
    objective after each round (``trace``, non-decreasing; its first entry
    the input's) and the rounds run.
    """
    P = problem
    g = float(_pooled_gate(P, sigma) if gate is None else gate)
    k_min = P.model.sample_size
    fits = [Fit(f.matrix, f.correspondences) for f in fits]
    trace = [assignment_gain(P, fits, g)]
    record = {"gate": g, "trace": trace, "rounds": 0}
    if not fits or g <= 0.0:
        return fits, record
    assigned = fits  # the last labelling taken, under the poses it was made with
    for _ in range(int(rounds)):
        pairs, res, owner = _candidate_pairs(P, fits, g)
        keep = assign_pairs(pairs, g**2 - np.square(res))
        labelled = [_labelled(pairs, keep, owner, k) for k in range(len(fits))]
        if any(c.shape[0] < k_min for c in labelled):
            break
        assigned = [Fit(f.matrix, c) for f, c in zip(fits, labelled)]  # every pair within g
        value = assignment_gain(P, assigned, g)
        if value < trace[-1]:
            break
        # the labelling repeated: the poses are its least-squares fits already
        done = record["rounds"] > 0 and all(np.array_equal(a.correspondences, b.correspondences)
                                            for a, b in zip(fits, assigned))
        fits = assigned
        trace.append(value)
        record["rounds"] += 1
        if done:
            break
        refitted = []
        for fit in fits:
            c = fit.correspondences
            M = P.model.fit(P.source[c[:, 0]], P.target[c[:, 1]])
            # least squares lowers Σ r² on the fixed labels; kept only when it does (rounding)
            if np.sum(np.square(P.residuals(M, c))) > np.sum(np.square(P.residuals(fit.matrix, c))):
                M = fit.matrix
            refitted.append(Fit(M, c))
        fits = refitted  # the next round labels under these poses
    # Stopped after a refit (the rounds' bound): a pair now beyond g has a negative gain and goes.
    out = [Fit(f.matrix, f.correspondences[P.residuals(f.matrix, f.correspondences) <= g]) for f in fits]
    if fits is not assigned and all(f.support >= k_min for f in out):
        value = assignment_gain(P, out, g)
        if value >= trace[-1]:
            trace.append(value)
            return out, record
    return assigned, record


def peel(problem: Problem, *, max_motions: int | None = None, min_support: int | None = None, seed=0,
         noise: float | None = None, refine: bool = True, min_inlier_share: float = 0.03,
         confidence: float = 0.999, max_triples: int | None = None, sigma: float | None = None,
         max_candidates: int = 8, memory_budget: float | None = None, noisy: bool | None = None,
         max_work: float | None = None, schedule=None, progress=None,
         time_limit: float | None = None) -> Segmentation:
    """Find several motions of ``problem.model``, one at a time (section 5).

    Parameters
    ----------
    problem : gatv.stages.Problem
        From :func:`gatv.stages.prepare` (any model).
    max_motions : int, optional
        Stop after this many motions.
    min_support : int, optional
        Smallest support kept; default the chance level (at least the
        model's ``sample_size``).
    seed : int or numpy.random.Generator, default: 0
    noise : float, optional
        Point-noise standard deviation (data units); default the tolerance
        schedule :data:`gatv.stages.NOISE_SCHEDULE` times ``problem.spacing``.
    refine : bool, default: True
        ICP polish of each motion inside its gate.
    min_inlier_share : float, default: 0.03
        Smallest motion wanted, as a share of all source points; sets the
        samples drawn per round (with ``confidence``; the model's
        ``trial_sample_size`` points a sample, at most 3 times its
        ``sample_space``).
    confidence : float, default: 0.999
    max_triples : int, optional
        Cap on the samples per tolerance level and round (default 200,000).
    sigma : float, optional
        Voting scale; default as in :func:`gatv.stages.judge`.
    max_candidates : int, default: 8
    memory_budget : float, optional
    noisy : bool, optional
        The noise-aware search of :func:`gatv.register`, for a model whose
        :class:`~gatv.models.SearchPolicy` has ``settle_noise`` (the rigid
        model): the policy's tolerances, trial options and matches scored
        per sample (:data:`gatv.models.rigid.RIGID_TRIALS`,
        :data:`gatv.models.rigid.NOISY_MAX_MATCHES`), and each motion's
        noise measured from its residuals and its correspondences re-gated
        there (:func:`gatv.stages.settle_noise`).  Default: for such a
        model when ``noise`` is not given.
    schedule : sequence of float, optional
        Tolerances tried when ``noise`` is not given, relative to the
        spacing; default the policy's ``schedule`` (for the rigid model
        :data:`gatv.stages.NOISY_SCHEDULE`; :data:`gatv.stages.NOISE_SCHEDULE`
        for its search with ``noisy=False``).
    max_work : float, optional
        Work bound of each round's search (:func:`gatv.stages.search`);
        default the policy's ``max_work`` for a noisy search, none
        otherwise.  A round that runs out stops the peeling with that reason.
    progress : callable, optional
        ``progress(fraction, message)``.
    time_limit : float, optional
        Seconds of wall-clock time for the whole peel (numba's compilation
        not counted, as in :func:`gatv.stages.search`); a round's search
        that runs past it stops the peeling with that reason, and the
        motions found so far are returned.  ``None``: no bound.

    Returns
    -------
    Segmentation
        Motions largest first, labels per point (``-1``: unexplained),
        ``tokens`` the kept correspondences with ``token_labels`` their
        motion; ``info["reason"]`` says why the peeling stopped,
        ``info["returned"]`` how many passes searched again the points that
        rejected or dropped motions had held out (:data:`RETURNS` at most),
        ``info["joint"]`` the final joint assignment's gate, objective trace
        and rounds (``None`` with fewer than two motions or a given noise).
    """
    t_start = time.perf_counter()
    if not isinstance(problem, Problem):
        raise InputError(f"Expected `problem` to be a gatv.stages.Problem (from gatv.stages.prepare), "
                         f"got {type(problem).__name__}.")
    P = problem
    model = P.model
    max_motions = check_int(max_motions, "max_motions", 1, allow_none=True)
    min_support = check_int(min_support, "min_support", model.sample_size, allow_none=True)
    noise = check_positive(noise, "noise", allow_none=True)
    check_fraction(min_inlier_share, "min_inlier_share")
    check_fraction(confidence, "confidence", open_high=True)
    max_triples = check_int(max_triples, "max_triples", 1, allow_none=True) or MAX_SAMPLES
    if sigma is not None:
        sigma = check_positive(sigma, "sigma")
    max_candidates = check_int(max_candidates, "max_candidates", 1)
    time_limit = check_positive(time_limit, "time_limit", allow_none=True)
    deadline = None if time_limit is None else t_start + time_limit
    report = check_progress(progress)
    rng = as_rng(seed)
    policy = model.search_policy()
    if noisy is None:
        noisy = policy.settle_noise and noise is None
    noisy = bool(noisy)
    if noisy and not policy.settle_noise:
        raise InputError(f"`noisy=True` is the rigid model's search; got model={model.name!r}.")
    search_options = {}
    if noisy:
        search_options = {"max_matches": policy.max_matches, "trial_options": policy.trial_options,
                          "max_work": policy.max_work if max_work is None else float(max_work)}
    elif max_work is not None:
        search_options["max_work"] = float(max_work)
    if schedule is None:
        schedule = policy.schedule if noisy or not policy.settle_noise else stages.NOISE_SCHEDULE
    schedule = tuple(float(check_positive(r, "schedule")) for r in schedule)
    if not schedule:
        raise InputError("Expected `schedule` to hold at least one tolerance.")
    n1, n2 = P.source.shape[0], P.target.shape[0]
    k_pts = stages.sample_points(model)
    config = _Rounds(levels=tuple(stages.tolerance_levels(P, noise, schedule)), noisy=noisy, noise=noise,
                     sample_points=k_pts, smallest=max(float(min_inlier_share) * n1, float(k_pts)),
                     confidence=confidence,
                     max_triples=max_triples, min_support=min_support, sigma=sigma,
                     max_candidates=max_candidates, refine=refine, memory_budget=memory_budget,
                     search_options=search_options, deadline=deadline, time_limit=time_limit)
    state = _PeelState.start(n1, n2, config.levels)
    merged: list = []
    dropped: list = []
    while True:
        outcome = _peel_rounds(P, config, state, rng, max_motions, report)
        reason, exhausted = outcome.reason, outcome.exhausted
        pooled = None
        if noisy and noise is None and len(state.fits) > 1:
            merged.extend(_merge_found(P, state))
            pooled = _pool_and_drop(P, state, dropped)
        # Points that wrong motions held out go back for one more pass, once
        # the peel has stopped for want of a motion beating chance.
        if not (noisy and state.fits and state.returned < RETURNS and exhausted):
            break
        if not _return_held(state, config):
            break
    joint = None
    if pooled is not None:
        # The labels last: every point to its most likely motion or the outliers, poses refitted.
        state.fits, joint = joint_assignment(P, state.fits, pooled)
        joint = {**joint, "trace": [float(x) for x in joint["trace"]]}
    return _segmentation(P, state, {
        "model": model.name, "n_source": int(n1), "n_target": int(n2), "spacing": P.spacing, "mode": "peel",
        "noisy": noisy, "pooled_noise": pooled, "joint": joint, "merged": merged, "dropped": dropped, "returned": state.returned,
        "reason": reason, "rounds": state.log}, t_start, report)


@dataclass(frozen=True, eq=False)
class _Rounds:
    """What every round of a peel searches with (fixed for the whole peel)."""

    levels: tuple[float, ...]  # the tolerance schedule in data units
    noisy: bool
    noise: float | None
    sample_points: int  # points of a trial sample (the model's trial_sample_size)
    smallest: float  # smallest motion wanted, in source points
    confidence: float
    max_triples: int
    min_support: int | None
    sigma: float | None
    max_candidates: int
    refine: bool
    memory_budget: float | None
    search_options: dict
    deadline: float | None
    time_limit: float | None


@dataclass(eq=False)
class _PeelState:
    """What the rounds of a peel have found and where they search next.

    ``used_*``: points a kept (or rejected) motion took out of the search;
    ``held_*``: those a wrong motion took, which go back in a return pass.
    ``fits``, ``tolerances`` (their noise) and ``fit_rounds`` (the round that
    kept each) are in the full problem's indices.  ``round_levels``: the
    tolerances the next round searches; ``measured_noise``: the noise pooled
    over the motions kept so far (0 before the first); ``known_pool``: the
    pooled noise of an earlier pass (``None`` in the first).
    """

    used_s: np.ndarray
    used_t: np.ndarray
    held_s: np.ndarray
    held_t: np.ndarray
    round_levels: list[float]
    fits: list[Fit] = field(default_factory=list)
    tolerances: list[float] = field(default_factory=list)
    fit_rounds: list[int] = field(default_factory=list)
    log: list[dict] = field(default_factory=list)
    measured_noise: float = 0.0
    known_pool: float | None = None
    rejected: int = 0
    returned: int = 0

    @classmethod
    def start(cls, n1: int, n2: int, levels) -> _PeelState:
        return cls(np.zeros(n1, bool), np.zeros(n2, bool), np.zeros(n1, bool), np.zeros(n2, bool), list(levels))


@dataclass(frozen=True, eq=False)
class _Searched:
    """A round's search on the points still unexplained (a :class:`gatv.peel_loop.Candidate`'s detail)."""

    found: Any  # stages.search's result
    S: Problem  # the subproblem searched
    src: np.ndarray  # its rows in the full problem
    tgt: np.ndarray
    record: dict  # the round's log entry so far
    t_round: float  # when the round started


@dataclass(frozen=True, eq=False)
class _Settled:
    """A round's motion once judged (a :class:`gatv.peel_loop.Judgement`'s detail)."""

    fit: Fit  # settled at its noise (noisy peel), in the subproblem's rows
    tolerance: float
    rejection: dict | None = None  # the rejection's record


def _peel_rounds(P: Problem, config: _Rounds, state: _PeelState, rng, max_motions, report) -> PeelOutcome:
    """Rounds of search → settle → check → keep on the points still unexplained, until one finds nothing.

    :func:`gatv.peel_loop.peel_loop` with this peel's steps.  Its outcome's
    ``reason`` says why the rounds stopped and ``exhausted`` whether for
    want of a motion to find (not a time or work limit, ``max_motions`` or
    the rejection limit).
    """

    def search():
        src, tgt = np.flatnonzero(~state.used_s), np.flatnonzero(~state.used_t)
        need_pts = max(config.sample_points + 1, config.min_support or 0)
        if src.size < need_pts or tgt.size < need_pts:
            return Stop("too few points left", exhausted=True)
        S = _subproblem(P, src, tgt)
        record = {"points": (int(src.size), int(tgt.size))}
        t_round = time.perf_counter()
        found = _search_round(S, config, state, rng, record, report, len(state.fits))
        if found is None:
            state.log.append({**record, "time_s": time.perf_counter() - t_round})
            # not the time limit or the work bound: the samples ran out
            return Stop(stages.search_failure(record["levels"], config.time_limit),
                        exhausted=not any("stopped" in rec for rec in record["levels"]))
        return Candidate(found.fit, found.fit.support, _Searched(found, S, src, tgt, record, t_round))

    def accept(candidate: Candidate) -> Judgement:
        d = candidate.detail
        fit, tol = d.found.fit, d.found.tolerance
        if not config.noisy:  # the search's judge kept it against chance already
            return Judgement(True, "kept", detail=_Settled(fit, tol))
        fit, tol, rejection = _settle_and_check(P, d.S, config, state, fit, tol, d.src, d.tgt)
        if rejection is not None:
            return Judgement(False, "did not beat chance at its noise", detail=_Settled(fit, tol, rejection))
        return Judgement(True, "kept", detail=_Settled(fit, tol))

    def reject(candidate: Candidate, judgement: Judgement) -> Stop | None:
        d, settled = candidate.detail, judgement.detail
        state.log.append({**d.record, "time_s": time.perf_counter() - d.t_round, "rejected": settled.rejection})
        state.rejected += 1
        if state.rejected > N_JUDGED or settled.fit.support == 0:
            return Stop(f"{state.rejected} motions found did not beat the chance level once their noise "
                        "was measured")
        return None

    def remove(candidate: Candidate, judgement: Judgement) -> tuple[Fit]:
        d, settled = candidate.detail, judgement.detail
        found, fit, tol = d.found, settled.fit, settled.tolerance
        if config.noisy:
            # One sensor: the next rounds search at the noise measured so far
            # (pooled over the motions found, weighted by support as in
            # pool_noise), not the whole schedule.
            state.measured_noise = _support_weighted_noise([*state.fits, fit], [*state.tolerances, tol])
            state.round_levels = [max(state.measured_noise, config.levels[0])]
        state.log.append({**d.record, "time_s": time.perf_counter() - d.t_round, "support": fit.support,
                          "threshold": found.threshold, "n_tested": found.n_tested,
                          "trial_support": found.trial_support, "n_tokens": found.judged.n_tokens,
                          "sigma": found.judged.sigma})
        kept = np.column_stack([d.src[fit.correspondences[:, 0]], d.tgt[fit.correspondences[:, 1]]])
        state.fits.append(Fit(fit.matrix, kept))
        state.fit_rounds.append(len(state.log) - 1)
        state.tolerances.append(float(tol))
        state.used_s[kept[:, 0]] = True
        state.used_t[kept[:, 1]] = True
        return (state.fits[-1],)

    # The motions of earlier passes count toward max_motions.
    left = None if max_motions is None else max_motions - len(state.fits)
    return peel_loop(search, accept, remove, reject=reject, max_motions=left, full="max_motions reached")


def _search_round(S: Problem, config: _Rounds, state: _PeelState, rng, record: dict, report, n_found: int):
    """One round's :func:`gatv.stages.search` on the subproblem ``S``: its budget, listing and options.

    Fills ``record`` (the round's log entry) with the levels tried, the
    budget and the smallest motion it can find.
    """
    model = S.model
    n_src = S.source.shape[0]
    round_levels = state.round_levels
    # A motion needs the chance level's support at the finest tolerance searched to be
    # kept: smaller ones are not worth the samples that would find them.
    need_min = config.smallest
    if config.noisy:
        need_min = max(config.smallest, float(S.chance(stages.gate(min(round_levels)), N_JUDGED)))
    cap = int(min(3 * stages.sample_space(model, n_src), config.max_triples))
    # A noisy peel's rounds list congruent matches at LISTING standard
    # deviations of a side's noise (of each level's tolerance while the noise
    # is unknown), not the search's default stages.LISTING: fewer all-inlier
    # samples are listed (listed_share) and more are drawn, but each lists
    # (stages.LISTING / LISTING)³ times fewer matches, and a listed true
    # match ranks among the tightest scored far more often (design notes,
    # section 7, "The rounds").
    measured = config.noisy and n_found > 0
    listing = LISTING if config.noisy else stages.LISTING
    # A side's noise is that of the points (measured), which may lie under
    # the round's tolerance (the schedule's first level is its floor): the
    # listing then holds more than LISTING standard deviations of it.
    listed = listed_share(listing * round_levels[0] / max(state.measured_noise, 1e-300) if measured else listing,
                          config.sample_points)
    options = dict(config.search_options)
    # One index of the round's targets, for the budget's levels and the search's.
    index = model.index(S.target, stages.gate(min(round_levels)), memory_budget=config.memory_budget)
    budget, need_min = search_budget(S, round_levels, need_min, config.confidence, cap,
                                     options.get("max_matches", stages.MAX_MATCHES),
                                     memory_budget=config.memory_budget, listed=listed, index=index)
    report(float(state.used_s.mean()), f"motion {n_found + 1}: {n_src} source points left")
    tried: list = []
    if "trial_options" in options:
        # The round's budget is drawn for motions of need_min points: the
        # sequential test need not look for smaller ones.
        options["trial_options"] = dict(options["trial_options"], min_share=need_min / n_src)
        if measured:
            # A tight listing lists a few matches a sample: ranking more
            # candidate triples than LISTING_WIDE costs more than it saves.
            options["trial_options"]["wide"] = LISTING_WIDE
    # listing=: the search caps each level at the RANSAC bound for the share
    # of all-inlier samples its listing keeps (erf(listing / sqrt 2) a side).
    found = stages.search(S, round_levels, budget=max(budget, 1), rng=rng, keep=N_JUDGED, sigma=config.sigma,
                          max_candidates=config.max_candidates, polish=config.refine,
                          grow=config.noise is None and not config.noisy,
                          threshold_tests=N_JUDGED, min_support=config.min_support, confidence=config.confidence,
                          listing=listing,
                          # Family-wise over every match, as a peel keeps motions
                          # until none beats chance: register's screen level
                          # (stages.JUDGED_WRONG) gave a spurious 4th motion at 1%
                          # K=3 and stopped after one at 2% K=3 (benchmarks/motions.py).
                          judged_wrong=None,
                          # Noise unknown: the density test sees each chunk's best
                          # trials polished (LO-RANSAC), as a noisy triple's pose
                          # leaves most of a small motion outside the gate.
                          polish_trial_motions=config.noisy,
                          memory_budget=config.memory_budget, tried=tried, deadline=config.deadline, index=index,
                          **options)
    record.update(levels=tried, budget=budget, smallest=need_min)
    return found


def _settle_and_check(P: Problem, S: Problem, config: _Rounds, state: _PeelState, fit: Fit, tol: float,
                      src: np.ndarray, tgt: np.ndarray) -> tuple[Fit, float, dict | None]:
    """A noisy round's motion: its noise measured, then checked against chance there.

    Returns the settled fit, its noise and ``None`` when kept, or the
    rejection's record (the round's levels and held-out points updated).
    """
    round_levels = state.round_levels
    level = round_levels.index(tol)
    floor = P.spacing * P.model.search_policy().schedule[0] if config.noise is None else config.levels[0]
    fit, tol = stages.settle_noise(S, fit, round_levels, level, floor=floor)
    # Kept only when, at its measured noise, it still beats chance as the
    # judge asks (its pairs within gate(σ) against the chance level there,
    # family-wise over N_JUDGED): a true motion keeps ~89% of its pairs
    # there, while a wrong motion's residuals spread over the gate it was
    # found at, so its pairs thin out as the gate's volume.
    g_noise = stages.gate(tol)
    residuals = S.residuals(fit.matrix, fit.correspondences)
    within = int(np.sum(residuals <= g_noise))
    chance = S.chance(g_noise, N_JUDGED)
    if state.known_pool is not None and within >= chance:
        # A pass after the noise was pooled: checked there too, as
        # the pooled check will (a motion of its own small noise
        # was how a wrong one got in before).
        g_pool = stages.gate(state.known_pool)
        within = int(np.sum(residuals <= g_pool))
        chance = S.chance(g_pool, N_JUDGED)
    if within >= chance:
        return fit, tol, None
    record = {"support": within, "noise": float(tol), "chance": int(chance),
              "tolerance": float(round_levels[level]), "matrix": fit.matrix}
    if level > 0:
        # A random motion beat the density test's chance level at this
        # tolerance: in these data (points not uniform over the box the
        # chance level assumes) the level and the coarser ones find
        # wrong motions, so the next rounds search the finer ones only.
        state.round_levels = round_levels[:level]
    else:
        # Its points leave the search, so the next round draws anew
        # (the kept motions are re-gated over all points at the end).
        s, t = src[fit.correspondences[:, 0]], tgt[fit.correspondences[:, 1]]
        state.used_s[s] = state.held_s[s] = True
        state.used_t[t] = state.held_t[t] = True
    record["levels_next"] = [float(x) for x in state.round_levels]
    return fit, tol, record


def _merge_found(P: Problem, state: _PeelState) -> list[dict]:
    """:func:`merge_same_motions` on the motions kept, each join's record naming the rounds it joined."""
    state.fits, state.tolerances, joined = merge_same_motions(P, state.fits, state.tolerances)
    for rec in joined:  # joins in order, indices as they were then
        a, b = rec["motions"]
        rec["rounds"] = (state.fit_rounds[a], state.fit_rounds[b])
        del state.fit_rounds[b]
    return joined


def _pool_and_drop(P: Problem, state: _PeelState, dropped: list) -> float | None:
    """The motions re-gated at the noise pooled over them (:func:`pool_noise`), dropping those that fail there.

    At the pooled noise of the one sensor, every motion must still beat
    chance among the points its round searched (its pairs within gate(σ)
    against the chance level there, as the judge): a wrong motion kept in
    the first round, when the noise was unknown, had its own (small)
    noise.  Pooling runs again without it, whose pairs may belong to the
    others.  Returns the pooled noise (``None`` when one motion is left).
    """
    model = P.model
    while len(state.fits) > 1:
        pooled_fits, pooled = pool_noise(P, state.fits, state.tolerances)
        g_pool = stages.gate(pooled)
        chances = [model.chance(*state.log[r]["points"], P.volume, g_pool, N_JUDGED) for r in state.fit_rounds]
        within = [int(np.sum(P.residuals(f.matrix, f.correspondences) <= g_pool)) for f in pooled_fits]
        weak = [k for k, (w, chance) in enumerate(zip(within, chances)) if w < chance]
        if not weak or len(weak) == len(state.fits):
            state.fits = pooled_fits
            state.tolerances = [pooled] * len(state.fits)
            return pooled
        for k in sorted(weak, reverse=True):
            dropped.append({"round": state.fit_rounds[k], "within": within[k], "chance": int(chances[k]),
                            "noise": pooled})
            state.held_s[state.fits[k].correspondences[:, 0]] = True
            state.held_t[state.fits[k].correspondences[:, 1]] = True
            del state.fits[k], state.tolerances[k], state.fit_rounds[k]
    return None


def _return_held(state: _PeelState, config: _Rounds) -> bool:
    """Points held out by wrong motions back to the search for one more pass; whether there are any.

    A motion rejected at its own noise or dropped at the pooled noise was a
    wrong motion, whose chance pairs may be a true motion's points.  Once
    the peel has stopped for want of a motion beating chance, those no kept
    motion explains go back; the pass lists at the noise pooled over the
    motions kept and checks every motion it finds there too.
    """
    kept_s, kept_t = np.zeros_like(state.used_s), np.zeros_like(state.used_t)
    for fit in state.fits:
        kept_s[fit.correspondences[:, 0]] = True
        kept_t[fit.correspondences[:, 1]] = True
    if not (np.any(state.held_s & ~kept_s) or np.any(state.held_t & ~kept_t)):
        return False
    state.returned += 1
    state.used_s, state.used_t = kept_s, kept_t
    state.held_s[:] = False
    state.held_t[:] = False
    state.measured_noise = state.known_pool = _support_weighted_noise(state.fits, state.tolerances)
    state.round_levels = [max(state.measured_noise, config.levels[0])]
    return True


def _segmentation(P: Problem, state: _PeelState, info: dict, t_start: float, report) -> Segmentation:
    """The result: motions largest first, per-point labels, the tokens of each motion."""
    n1, n2 = P.source.shape[0], P.target.shape[0]
    fits, tolerances = state.fits, state.tolerances
    order = sorted(range(len(fits)), key=lambda k: (-fits[k].support, k))
    src_lab = np.full(n1, -1, np.int64)
    tgt_lab = np.full(n2, -1, np.int64)
    motions, tokens, labels, verdicts = [], [], [], []
    for new, k in enumerate(order):
        fit = fits[k]
        c = fit.correspondences
        src_lab[c[:, 0]] = new
        tgt_lab[c[:, 1]] = new
        found = state.log[state.fit_rounds[k]]
        verdicts.append(chance_verdict(fit.support, found["threshold"], found["n_tested"], method="poisson"))
        motions.append(stages.make_result(P, fit, {"label": new, "tolerance": tolerances[k], "noise": tolerances[k],
                                                   "round": state.fit_rounds[k], "verdict": verdicts[-1].to_dict()}))
        c = c[np.argsort(c[:, 0], kind="stable")]
        tokens.append(c)
        labels.append(np.full(c.shape[0], new, np.int64))
    searched = [rec for rec in state.log if "levels" in rec]
    if verdicts:
        info["verdict"] = min(verdicts, key=lambda v: v.margin).to_dict()
    else:  # the last search's best trial against its level
        info["verdict"] = stages.search_verdict(searched[-1]["levels"] if searched else []).to_dict()
    info["time_s"] = time.perf_counter() - t_start
    report(1.0, f"found {len(motions)} motions ({info['reason']})")
    return Segmentation(tuple(motions), src_lab, tgt_lab,
                        np.vstack(tokens) if tokens else np.empty((0, 2), np.int64),
                        np.concatenate(labels) if labels else np.empty(0, np.int64), info)
