"""Registration without initialization (paper sections 2.1–3.4, Algorithm 1).

:func:`register` finds the rigid motion (or, with ``model="similarity"``,
the similarity) between two point sets with an unknown motion of any size
and many outliers in both sets, and a one-to-one set of correspondences,
with no initial guess.  It is a short sequence of the stages of
:mod:`gatv.stages`: ``prepare`` → the model's ``trial_motions`` → ``judge``
(``candidate_tokens`` → ``vote_tokens`` → ``constraint`` →
``select_one_to_one`` → ``fit_and_gate``) → ``refine`` → ``grow_tolerance``
→ ``make_result``.  The steps below are written for the rigid model; the
similarity model replaces side lengths by their ratios.

How it works
------------
1. **Trial rotations** (replacing Algorithm 1's exhaustive grid, see
   :mod:`gatv.congruent`): source triples are matched to congruent target
   triples; each match gives a trial motion, scored by a cheap density
   test.  A trial built from true matches leaves a residual rotation near
   zero.
2. **Tensor voting judges the best trials.** The source is rotated by the
   trial rotation and the ``{dx, dy, dz}`` joint space (eq. 30) is populated
   with the candidate pairs inside the voting reach of the trial's
   translation.  A sparse ball pass (section 3.3) makes the true pairs
   stand out as the dense pure-translation cluster of section 3.4; where
   the residual rotation is not negligible they form a plane patch whose
   normal (the ball pass's ``e1``) is the rotation axis.
3. **Eq. 41** against the most salient tokens (``V × (A × Vs) = 0``,
   relaxed to the noise level; without a reliable axis, its
   length-preservation half ``V · Vs = 0``) drops false and multiple
   matches.  A least-squares fit (Kabsch/Horn) on the consistent pairs,
   a residual gate and a greedy one-to-one selection give the
   correspondences; a plane with less support than a random motion would
   collect is rejected.
4. Optional ICP polish on the found motion.

With ``max_angle`` (and optionally ``max_translation``) the trial search is
skipped: only the candidate pairs the bounds allow are voted on, with the
ball pass and stick passes of section 3.3 extracting the plane — the
paper's "optimised version" for small motions.

Noise: with ``noise=None`` a schedule of tolerances is tried, from
exact (relative 1e-6 of the point spacing) up to 5% of the spacing, in
round robin (a chunk of triples at each in turn); the first tolerance at
which a motion beats the chance level wins, and the tolerance then grows
while the support does.  Give ``noise`` (standard deviation of the point
noise, data units) for noisier data, or use :func:`gatv.register_scans`
for real scans.
"""

from __future__ import annotations

import time

import numpy as np

from . import stages
from ._validation import as_rng, check_fraction, check_int, check_positive, check_progress
from .candidates import bounded_pairs
from .congruent import n_triples_needed
from .errors import InputError
from .models import Motion
from .stages import NOISE_SCHEDULE, Problem, gate

__all__ = ["register", "NOISE_SCHEDULE"]


def _bounded(P: Problem, max_angle, max_translation, levels, sigma, refine, memory_budget, info):
    """Small-motion mode: vote on the bounded candidate pairs, no search."""
    from .voting import default_sigma, extract_surfaces

    pairs = bounded_pairs(P.source, P.target, max_angle, max_translation, memory_budget=memory_budget)
    info["n_tokens"] = int(pairs.shape[0])
    if pairs.shape[0] < 3:
        return None
    xs, ys = P.source[pairs[:, 0]], P.target[pairs[:, 1]]
    tokens = stages.Tokens(pairs, xs, ys, P.model.tokens(xs, ys))
    if sigma is None:
        # ~40 tokens within the voting radius of a typical token, estimated
        # from 500 of them (the full estimate costs more than the voting).
        sigma = default_sigma(tokens.coords, sample=500)
    # The paper's optimised version: one ball pass and one stick pass.
    surf = extract_surfaces(tokens.coords, sigma, n_stick_passes=1)
    idx = np.asarray(surf.indices)
    if idx.size < 3:
        return None
    saliency = np.zeros(pairs.shape[0])
    saliency[idx] = surf.surfaceness
    votes = stages.Votes(saliency, np.zeros((pairs.shape[0], 3)), float(surf.sigma))
    for tol in levels:
        g = gate(tol)
        best = stages.constraint(tokens, votes, 2.0 * g, P.model)
        if best is None:
            continue
        sub = best[stages.select_one_to_one(pairs[best], -saliency[best])]
        fit = stages.fit_and_gate(P, pairs, pairs[sub], g)
        if fit is None:
            continue
        if fit.support >= P.chance(g):
            if refine:
                fit = stages.refine(P, fit, g)
            if len(levels) > 1:
                fit, grown = stages.grow_tolerance(P, fit, levels, levels.index(tol))
                tol = levels[grown]
            info.update(tolerance=tol, sigma=float(surf.sigma))
            return stages.make_result(P, fit, info, score=float(np.mean(surf.surfaceness)))
    return None


def register(
    source,
    target,
    *,
    model="rigid",
    seed=0,
    max_angle: float | None = None,
    max_translation: float | None = None,
    noise: float | None = None,
    refine: bool = True,
    min_inlier_share: float = 0.04,
    confidence: float = 0.999,
    max_triples: int | None = None,
    sigma: float | None = None,
    n_judged: int = 4,
    max_candidates: int = 8,
    memory_budget: float | None = None,
    progress=None,
) -> Motion:
    """Register ``source`` onto ``target`` with no initial guess.

    Parameters
    ----------
    source, target : (N, 3) array_like or object with ``.points``
        The two point sets; any share of either may be outliers.
    model : {"rigid", "similarity"} or MotionModel, default: "rigid"
        The kind of motion (:mod:`gatv.models`): ``"similarity"`` adds a
        uniform scale (``target ≈ scale · source @ rotation.T + translation``).
    seed : int or numpy.random.Generator, default: 0
        Seed of the random source-triple sampling; same seed, same result.
    max_angle : float, optional
        Bound on the rotation angle in **degrees**. Enables the small-motion
        mode (no trial search; only candidate pairs the bounds allow).
    max_translation : float, optional
        Bound on ``|t|`` (data units) in the small-motion mode.
    noise : float, optional
        Standard deviation of the point noise (data units). Default: the
        schedule :data:`gatv.stages.NOISE_SCHEDULE`, from exact (1e-6 of
        the point spacing) to 5% of the point spacing.
    refine : bool, default: True
        Polish the motion with one-to-one ICP iterations inside the
        noise gate.
    min_inlier_share : float, default: 0.04
        Smallest share of source points expected to have a true match;
        sets how many source triples are drawn (with ``confidence``).
    confidence : float, default: 0.999
        Probability of drawing one all-inlier triple when the inlier share
        is ``min_inlier_share``.
    max_triples : int, optional
        Hard cap on the source triples drawn per tolerance level.
    sigma : float, optional
        Tensor-voting scale (data units). Default from the data: half the
        spacing of false tokens near the trial translation, and at least
        twice the noise gate.
    n_judged : int, default: 4
        Best trial motions handed to tensor voting.
    max_candidates : int, default: 8
        Cap on the candidate pairs per source point in the joint space
        voted on (the nearest targets to the trial position); bounds the
        work on dense real scans.
    memory_budget : float, optional
        Bytes; inputs needing more fail at once (see
        :func:`gatv._validation.check_memory`).
    progress : callable, optional
        ``progress(fraction, message)`` called as work proceeds.

    Returns
    -------
    RigidMotion or SimilarityMotion
        ``target ≈ source @ rotation.T + translation`` with one-to-one
        ``correspondences``. Falsy, with ``info["reason"]``, when no motion
        beats the chance level.

    Raises
    ------
    ValueError
        Fewer than 3 points, NaN/inf, wrong shapes, identical or collinear
        points, bad options, or a token count over the memory budget.

    Examples
    --------
    >>> import numpy as np
    >>> from gatv import Rotor, register
    >>> rng = np.random.default_rng(0)
    >>> x = rng.uniform(-5, 5, (40, 3))
    >>> R = Rotor.from_axis_angle([1, 1, 0], np.radians(150))
    >>> y = (R >> x) + [3.0, -2.0, 1.0]
    >>> m = register(x, rng.permutation(y))
    >>> m.support, round(m.angle_deg, 6)
    (40, 150.0)
    """
    t_start = time.perf_counter()
    P = stages.prepare(source, target, model)
    if P.model.name not in ("rigid", "similarity"):
        msg = (f"`register` handles the 'rigid' and 'similarity' models, got {P.model.name!r}; "
               "use gatv.motions.segment for 'affine2d'.")
        raise InputError(msg)
    noise = check_positive(noise, "noise", allow_none=True)
    check_fraction(min_inlier_share, "min_inlier_share")
    check_fraction(confidence, "confidence", open_high=True)
    if sigma is not None:
        sigma = check_positive(sigma, "sigma")
    max_candidates = check_int(max_candidates, "max_candidates", 1)
    n_judged = check_int(n_judged, "n_judged", 1)
    max_triples = check_int(max_triples, "max_triples", 1, allow_none=True)
    rng = as_rng(seed)
    report = check_progress(progress)
    levels = stages.tolerance_levels(P, noise)
    n, n2 = P.source.shape[0], P.target.shape[0]
    info: dict = {"model": P.model.name, "n_source": int(n), "n_target": int(n2), "spacing": P.spacing}

    if max_angle is not None:
        if P.model.name != "rigid":
            raise InputError("`max_angle` (the small-motion mode) is for the 'rigid' model only.")
        ang = check_positive(max_angle, "max_angle")
        if ang > 180.0:
            raise InputError(f"Expected `max_angle` in degrees, at most 180, got {ang!r}.")
        mt = check_positive(max_translation, "max_translation", allow_none=True)
        info["mode"] = "bounded"
        out = _bounded(P, np.radians(ang), mt, levels, sigma, refine, memory_budget, info)
        info["time_s"] = time.perf_counter() - t_start
        return out if out is not None else stages.failure(P.model, "no plane with support above chance", info)
    if max_translation is not None:
        raise InputError("`max_translation` needs `max_angle` (the small-motion mode).")

    info["mode"] = "congruent-triples"
    need = n_triples_needed(max(float(min_inlier_share), 3.0 / n), confidence)
    n_possible = n * (n - 1) * (n - 2) // 6
    budget = int(min(need, 3 * n_possible if n_possible < 10**6 else need))
    if max_triples is not None:
        budget = min(budget, max_triples)
    tried: list = []
    found = stages.search(P, levels, budget=budget, rng=rng, keep=n_judged, sigma=sigma,
                          max_candidates=max_candidates, polish=refine, grow=noise is None,
                          memory_budget=memory_budget, progress=report, tried=tried)
    if found is None:
        info.update(trials=tried, time_s=time.perf_counter() - t_start)
        return stages.failure(P.model, "no trial motion beat the chance level", info)
    info.update(tolerance=found.tolerance, sigma=found.judged.sigma, n_tokens=found.judged.n_tokens,
                trials=tried, trial_support=found.trial_support, chance_support=found.threshold,
                time_s=time.perf_counter() - t_start)
    report(1.0, f"found {found.fit.support} correspondences")
    return stages.make_result(P, found.fit, info)
