"""Registration without initialization (paper sections 2.1–3.4, Algorithm 1).

:func:`register` finds the rigid motion (or, with ``model="similarity"``,
the similarity; with any model of :mod:`gatv.models`, its motion) between two point sets with an unknown motion of any size
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
   :mod:`gatv.models.rigid.congruent`): source triples are matched to congruent target
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

Noise: with ``noise=None`` the search tries the tolerances of
:data:`gatv.stages.NOISY_SCHEDULE`, from exact (1e-6 of the point spacing)
up to 0.3 of the spacing, in round robin (a chunk of source triples at each
in turn).  Under noise a triple matches many target triples; the search
draws triples with long, rarely matched sides and scores the matches whose
side lengths agree best, within a bounded amount of work.  Once a motion
beats the chance level, the noise is measured from its residuals and the
correspondences are re-gated there (``info["noise"]``).

Pipelines: this is the *exact* pipeline, for sets whose inliers are the
same points in both.  Dense, differently sampled range scans take the
*scans* pipeline (:mod:`gatv.scans`); ``register`` chooses between them
from the data (:func:`choose_pipeline`) unless ``pipeline=`` says.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from . import stages
from ._validation import (
    as_points,
    as_rng,
    check_fraction,
    check_int,
    check_positive,
    check_progress,
    memory_budget_limit,
)
from .candidates import bounded_pairs
from .models.rigid.congruent import TargetGrid, TargetIndex, trial_motions
from .errors import InputError
from .ga import rotation_angle_deg, turn_about
from .models import Motion, apply_matrix, get_model
from .models.base import MAX_WORK, homogeneous
from .scans import RIVAL_SHARE, local_scatter, register_surfaces, scan_noise
from .stages import NOISE_SCHEDULE, NOISY_SCHEDULE, Problem, gate
from .stats import samples_needed
from .verdict import chance_verdict
from .voting import default_sigma, extract_surfaces

__all__ = ["MAX_WORK", "NOISE_SCHEDULE", "NOISY_SCHEDULE", "TIME_LIMIT", "checked_pipeline", "choose_pipeline",
           "count_ceiling", "register", "register_budget", "reject_exact_options", "resolve_pipeline",
           "Rivals", "rival_draws", "surface_likeness", "symmetry_rival"]

# MAX_WORK, the default work bound of register's search, is gatv.models.base's (re-exported).
#: Default wall-clock bound of a call's search, seconds: on a slow or busy
#: machine the work bound alone can take minutes.
TIME_LIMIT = 60.0


def _bounded(P: Problem, max_angle, max_translation, levels, sigma, refine, memory_budget, info):
    """Small-motion mode: vote on the bounded candidate pairs, no search."""
    pairs = bounded_pairs(P.source, P.target, max_angle, max_translation, memory_budget=memory_budget)
    info["n_tokens"] = int(pairs.shape[0])
    info["verdict"] = chance_verdict(0, P.chance(gate(levels[0])), 1.0, method="poisson").to_dict()
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
    best_seen = None
    for tol in levels:
        g = gate(tol)
        best = stages.constraint(tokens, votes, 2.0 * g, P.model)
        if best is None:
            continue
        sub = best[stages.select_one_to_one(pairs[best], -saliency[best])]
        fit = stages.fit_and_gate(P, pairs, pairs[sub], g)
        if fit is None:
            continue
        level = P.chance(g)
        if best_seen is None or fit.support / max(level, 1e-300) > best_seen.margin:
            best_seen = chance_verdict(fit.support, level, 1.0, method="poisson")
        if fit.support >= level:
            if refine:
                fit = stages.refine(P, fit, g)
            if len(levels) > 1:
                fit, grown = stages.grow_tolerance(P, fit, levels, levels.index(tol))
                tol = levels[grown]
            info.update(tolerance=tol, sigma=float(surf.sigma),
                        verdict=chance_verdict(fit.support, level, 1.0, method="poisson").to_dict())
            return stages.make_result(P, fit, info, score=float(np.mean(surf.surfaceness)))
    if best_seen is not None:
        info["verdict"] = best_seen.to_dict()
    return None


#: Above this many points in either set the auto choice is the scans
#: pipeline: the exact search's index grows as N² and its trials as N.
EXACT_MAX_POINTS = 5000
#: Sets of at least this many points (both) that lie on surfaces
#: (:func:`surface_likeness`) are treated as scans by the auto choice.
SCAN_MIN_POINTS = 1500
#: Median local planarity ``λ3 / (λ1 + λ2 + λ3)`` below which a set is a
#: sampled surface (a volume of scattered points gives about 0.1 to 0.2; a
#: densely sampled surface the squared noise over the squared spacing).
SURFACE_PLANARITY = 0.03
#: Largest share of a set in the neighbourhoods that measure its noise
#: (:func:`gatv.scans.scan_noise`) for the set to count as a noisy surface:
#: on a surface the plane fits' residual settles at the noise once the
#: neighbourhoods reach five deviations; in a volume it grows with them
#: (a ball's points deviate from any plane by 0.45 of its radius) and never does.
SURFACE_NEIGHBOURHOOD = 0.125


def surface_likeness(points: np.ndarray, *, k: int = 12, sample: int = 400, seed: int = 0) -> float:
    """Median local planarity ``λ3 / (λ1 + λ2 + λ3)`` of ``k``-neighbourhoods.

    The eigenvalues are those of the covariance of each sampled point's
    ``k`` nearest neighbours (at most ``sample`` points, drawn with a fixed
    seed).  Near 0 for points on a surface, about 0.1–0.2 for points
    scattered through a volume.
    """
    pts = np.asarray(points, dtype=np.float64)
    n = pts.shape[0]
    k = min(int(k), n)
    if k < 4:
        return float("nan")
    rng = np.random.default_rng(seed)
    pick = rng.choice(n, min(n, int(sample)), replace=False)
    ev = local_scatter(pts, pts[pick], k).eigenvalues
    return float(np.median(ev[:, 0] / np.maximum(ev.sum(axis=1), 1e-300)))


def choose_pipeline(source, target, *, memory_budget: float | None = None) -> tuple[str, str]:
    """The pipeline ``register`` takes for these sets: ``("exact" | "scans", reason)``.

    Scans when either set has more than :data:`EXACT_MAX_POINTS` points or
    its congruent-triple index would not fit the memory budget, or when
    both sets have at least :data:`SCAN_MIN_POINTS` points lying on surfaces
    (:func:`surface_likeness` below :data:`SURFACE_PLANARITY`, or, for
    surfaces noisier than their sampling, a noise that neighbourhoods of at
    most :data:`SURFACE_NEIGHBOURHOOD` of the points measure,
    :func:`gatv.scans.scan_noise`): dense samplings of surfaces, which two
    scans never sample at the same points.
    Exact otherwise.
    """
    X = as_points(source, "source")
    Y = as_points(target, "target")
    n1, n2 = X.shape[0], Y.shape[0]
    if max(n1, n2) > EXACT_MAX_POINTS:
        return "scans", f"{max(n1, n2)} points, more than the exact search's {EXACT_MAX_POINTS}"
    need = 20.0 * n2 * n2
    limit = memory_budget_limit(memory_budget)
    if need > limit:
        return "scans", f"the exact search's index of {n2} target points would need {need / 2**30:.2f} GiB"
    if min(n1, n2) >= SCAN_MIN_POINTS and X.shape[1] == 3:
        flat = max(surface_likeness(X), surface_likeness(Y))
        if flat < SURFACE_PLANARITY:
            return "scans", (f"{n1} and {n2} points on surfaces (local planarity {flat:.3g} < "
                             f"{SURFACE_PLANARITY})")
        # Noisier than the sampling, a surface is not flat at twelve neighbours; at the noise's own scale it is.
        share = scan_noise(X).neighbours / n1
        if share <= SURFACE_NEIGHBOURHOOD:  # the target's only when the source passes
            share = max(share, scan_noise(Y).neighbours / n2)
        if share <= SURFACE_NEIGHBOURHOOD:
            return "scans", (f"{n1} and {n2} points on noisy surfaces (their noise measured on neighbourhoods of "
                             f"{share:.1%} of the points)")
    return "exact", f"{n1} and {n2} points, not dense surfaces"


def reject_exact_options(options: dict, why: str) -> None:
    """An error naming the exact-pipeline ``options`` given (not None) when the data took the scans one."""
    given = [name for name, value in options.items() if value is not None]
    if given:
        msg = (f"{', '.join('`' + g + '`' for g in given)} apply to the exact pipeline, but the data "
               f"took the scans pipeline ({why}); pass pipeline='exact' to force the exact one, or drop "
               "the option.")
        raise InputError(msg)


def _check_exact_memory(target, memory_budget) -> None:
    """The exact search's index over the budget: an error that names the scans pipeline."""
    n2 = int(target.shape[0])  # validated by stages.prepare
    need, limit = 20.0 * n2 * n2, memory_budget_limit(memory_budget)
    if need > limit:
        msg = (f"The exact pipeline's congruent-triple index of {n2} target points would need about "
               f"{need / 2**30:.2f} GiB, over the memory budget of {limit / 2**30:.2f} GiB. For dense "
               "scans use pipeline='scans' (or pipeline='auto', the default; `gatv register --scans`), "
               "or downsample, or raise `memory_budget=`.")
        raise InputError(msg)


def resolve_pipeline(source, target, model, pipeline: str = "auto", memory_budget=None) -> tuple[str, str]:
    """``(pipeline, reason)`` for ``register``'s (and ``segment``'s) ``pipeline=`` argument.

    See :func:`checked_pipeline`, which also returns the points it checked.
    """
    return checked_pipeline(source, target, model, pipeline, memory_budget)[:2]


def checked_pipeline(source, target, model, pipeline: str = "auto", memory_budget=None):
    """The pipeline for ``register``'s (and ``segment``'s) ``pipeline=`` argument, and why.

    Returns ``(pipeline, reason, points)``: ``points`` the model-checked
    ``(source, target)`` arrays when the choice checked them (give them to
    :func:`gatv.stages.prepare` with ``validated=True``), else ``None``.

    ``"exact"`` and ``"scans"`` are taken as given (the scans pipeline is for
    models whose :class:`~gatv.models.SearchPolicy` has ``scans``: rigid
    motions); ``"auto"`` is :func:`choose_pipeline` for those and
    ``"exact"`` for the others.  The model's own point checks run first, so
    their errors name the model's dimension.
    """
    if pipeline not in ("auto", "exact", "scans"):
        raise InputError(f"Expected `pipeline` 'auto', 'exact' or 'scans', got {pipeline!r}.")
    model = get_model(model)
    name = model.name
    scans = model.search_policy().scans
    if pipeline == "exact":
        return "exact", "pipeline='exact' given", None
    if pipeline == "scans":
        if not scans:
            raise InputError(f"The scans pipeline registers rigid motions; got model={name!r}.")
        model.check_points(source, "source")
        model.check_points(target, "target")
        return "scans", "pipeline='scans' given", None
    if not scans:
        return "exact", f"the {name!r} model has the exact pipeline only", None
    # The model's own checks first: their errors name the model's dimension.
    X, Y = model.check_points(source, "source"), model.check_points(target, "target")
    return (*choose_pipeline(X, Y, memory_budget=memory_budget), (X, Y))


def register(
    source,
    target,
    *,
    model="rigid",
    pipeline: str = "auto",
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
    max_work: float | None = MAX_WORK,
    time_limit: float | None = TIME_LIMIT,
    scan_options: dict | None = None,
    check_rivals: bool = True,
    progress=None,
) -> Motion:
    """Register ``source`` onto ``target`` with no initial guess.

    Parameters
    ----------
    source, target : (N, 3) array_like or object with ``.points``
        The two point sets; any share of either may be outliers ((N, 2)
        for ``model="affine2d"``).
    model : {"rigid", "similarity", "affine2d"}, a registered name or a MotionModel, default: "rigid"
        The kind of motion (:mod:`gatv.models`): ``"similarity"`` adds a
        uniform scale (``target ≈ scale · source @ rotation.T + translation``);
        ``"affine2d"`` is one 2D affine map.  The search follows the
        model's :class:`~gatv.models.SearchPolicy` (tolerances, matches per
        sample, noise settling, the symmetry rival; which of the small-motion
        mode and the scans pipeline apply).
    pipeline : {"auto", "exact", "scans"}, default: "auto"
        ``"exact"``: the congruent-triple search on the points themselves,
        for sets whose inliers are the same points in both (synthetic sets,
        landmarks, mesh vertices), noisy or not.  ``"scans"``: the surface
        pipeline for dense, differently sampled range scans
        (:func:`gatv.scans.register_surfaces`: tensor-voting surface tokens,
        voxel downsampling, normal-pruned congruent triples, point-to-plane
        polish at full resolution).  ``"auto"`` chooses from the data
        (:func:`choose_pipeline`); ``info["pipeline"]`` and
        ``info["pipeline_reason"]`` say which and why.
    seed : int or numpy.random.Generator, default: 0
        Seed of the random source-triple sampling; same seed, same result.
    max_angle : float, optional
        Bound on the rotation angle in **degrees**. Enables the small-motion
        mode (no trial search; only candidate pairs the bounds allow).
    max_translation : float, optional
        Bound on ``|t|`` (data units) in the small-motion mode.
    noise : float, optional
        Standard deviation of the point noise (data units), exact pipeline.
        Default: measured from the data: the search tries the tolerances of
        :data:`gatv.stages.NOISY_SCHEDULE` (from 1e-6 to 0.3 of the point
        spacing), and once a motion beats chance the noise is estimated
        from its residuals (:func:`gatv.stages.settle_noise`) and the
        correspondences re-gated there.  ``info["noise"]`` holds the
        estimate (per coordinate, of each set).
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
    max_work : float or None, default: :data:`MAX_WORK`
        Bound on the exact search's work (units of about a microsecond of
        one core); past it the call returns a falsy result whose
        ``info["reason"]`` says so.  ``None``: no bound.
    time_limit : float or None, default: :data:`TIME_LIMIT`
        Seconds of wall-clock time the exact search may take; past it the
        call returns a falsy result whose ``info["reason"]`` says so.
        Unlike ``max_work`` it depends on the machine's speed and load, so
        a run stopped by it may not repeat exactly.  The first call of a
        process may also compile the kernels (numba, up to a minute); that
        time is not counted.  ``None``: no limit.
    scan_options : dict, optional
        Options of the scans pipeline only (``n_points``, ``voxel``,
        ``min_overlap``, ``feature_tol``, ``clutter``; see
        :func:`gatv.scans.register_surfaces`).
    check_rivals : bool, default: True
        Exact pipeline (every model whose policy has ``turned_copies``:
        rigid, similarity, 2D affine): the motion found must beat its turned
        and shifted copies, polished on the same data (:func:`rival_draws`);
        where the data are structured and a copy holds about as much
        (:attr:`Rivals.ambiguous`: planes laid on planes, dense cores on
        dense cores, lattices, symmetric sets) the result is falsy,
        ``info["reason"]`` starting "ambiguous".  ``info["rivals"]`` holds
        the figures either way.  Callers that look for several motions
        themselves (instance search) or judge a motion by other means pass
        ``False``.
    progress : callable, optional
        ``progress(fraction, message)`` called as work proceeds.

    Returns
    -------
    Motion
        The model's result (``RigidMotion``, ``SimilarityMotion``,
        ``Affine2DMotion``, ...): ``target ≈ source @ rotation.T + translation``
        with one-to-one ``correspondences``. Falsy, with ``info["reason"]``,
        when no motion beats the chance level.  ``info["verdict"]`` (found
        or not, exact pipeline): the support, the chance level it had to
        reach and the tests that level is family-wise over
        (:meth:`gatv.verdict.Verdict.to_dict`); without a motion, the best
        trial support the search saw against its level.  ``info["ambiguous"]`` is true when a
        distinct motion explains the data nearly as well (a symmetric
        object; :func:`symmetry_rival` on the exact path, the surface
        rivals on the scans path), with ``info["rival"]`` describing it.

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
    chosen, why, checked = checked_pipeline(source, target, model, pipeline, memory_budget)
    if chosen == "scans":
        reject_exact_options({"max_angle": max_angle, "max_translation": max_translation, "noise": noise,
                              "sigma": sigma,
                              "min_inlier_share": None if min_inlier_share == 0.04 else min_inlier_share}, why)
        out = register_surfaces(source, target, seed=seed, confidence=confidence, max_triples=max_triples,
                                n_judged=n_judged, refine=refine, memory_budget=memory_budget,
                                progress=progress, **(scan_options or {}))
        out.info.update(pipeline="scans", pipeline_reason=why)
        return out
    if scan_options:
        raise InputError("`scan_options` apply to the scans pipeline only; pass pipeline='scans'.")
    P = stages.prepare(*(checked or (source, target)), model, validated=checked is not None)
    if max_angle is None:
        _check_exact_memory(P.target, memory_budget)
    policy = P.model.search_policy()
    noise = check_positive(noise, "noise", allow_none=True)
    check_fraction(min_inlier_share, "min_inlier_share")
    check_fraction(confidence, "confidence", open_high=True)
    if sigma is not None:
        sigma = check_positive(sigma, "sigma")
    max_candidates = check_int(max_candidates, "max_candidates", 1)
    n_judged = check_int(n_judged, "n_judged", 1)
    max_triples = check_int(max_triples, "max_triples", 1, allow_none=True)
    time_limit = check_positive(time_limit, "time_limit", allow_none=True)
    rng = as_rng(seed)
    report = check_progress(progress)
    levels = stages.tolerance_levels(P, noise, policy.schedule)
    n, n2 = P.source.shape[0], P.target.shape[0]
    info: dict = {"model": P.model.name, "pipeline": "exact", "pipeline_reason": why, "n_source": int(n),
                  "n_target": int(n2), "spacing": P.spacing}

    if max_angle is not None:
        if not policy.small_motion:
            raise InputError(f"`max_angle` (the small-motion mode) is for the 'rigid' model only; got "
                             f"model={P.model.name!r}.")
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
    share, budget = register_budget(P, min_inlier_share, confidence)
    if max_triples is not None:
        budget = min(budget, max_triples)
    tried: list = []
    settle = noise is None and policy.settle_noise
    found = stages.search(P, levels, budget=budget, rng=rng, keep=n_judged, sigma=sigma,
                          max_candidates=max_candidates, polish=refine,
                          grow=noise is None and not policy.settle_noise,
                          memory_budget=memory_budget, progress=report, tried=tried,
                          max_matches=policy.max_matches, max_work=max_work, confidence=confidence,
                          trial_options=policy.trials(share),
                          deadline=None if time_limit is None else t_start + time_limit)
    if found is None:
        info.update(trials=tried, time_s=time.perf_counter() - t_start)
        info["verdict"] = stages.search_verdict(tried).to_dict()
        return stages.failure(P.model, stages.search_failure(tried, time_limit), info)
    fit, tolerance = found.fit, found.tolerance
    if settle:
        fit, tolerance = stages.settle_noise(P, fit, levels, levels.index(tolerance), floor=levels[0],
                                             remeasure=True)
    verdict = stages.found_verdict(found, fit.support)
    info["verdict"] = verdict.to_dict()
    info.update(tolerance=tolerance, noise=tolerance, sigma=found.judged.sigma,
                n_tokens=found.judged.n_tokens, trials=tried, trial_support=found.trial_support,
                chance_support=int(verdict.chance))
    if policy.rival_check:
        info.update(symmetry_rival(P, fit, tolerance, rng, memory_budget=memory_budget))
    if policy.turned_copies:
        rivals = rival_draws(P, fit.matrix, fit.correspondences, gate(tolerance), rng)
        info["rivals"] = rivals.to_dict()
        if check_rivals and rivals.ambiguous:
            if not info.get("ambiguous"):
                info.update(ambiguous=True, rival={"support": rivals.rival, "best_support": rivals.support,
                                                   "angle_deg": rivals.angle_deg})
            info["verdict"] = {**info["verdict"], "passed": False}  # the search's level, not the answer
            info["time_s"] = time.perf_counter() - t_start
            return stages.failure(P.model, rivals.reason(), info)
    info["time_s"] = time.perf_counter() - t_start
    report(1.0, f"found {fit.support} correspondences")
    return stages.make_result(P, fit, info)


def register_budget(P: stages.Problem, min_inlier_share: float = 0.04,
                    confidence: float = 0.999) -> tuple[float, int]:
    """``(share, budget)`` of :func:`register`'s search: the smallest inlier share it looks for (at
    least a sample's points) and the samples that find such a motion with ``confidence``."""
    n = P.source.shape[0]
    share = max(float(min_inlier_share), P.model.sample_size / n)
    need = samples_needed(share, confidence, stages.sample_points(P.model))
    n_possible = stages.sample_space(P.model, n)
    return share, int(min(need, 3 * n_possible if n_possible < 10**6 else need))


def count_ceiling(P: stages.Problem, matrix: np.ndarray, *, min_inlier_share: float = 0.04,
                  confidence: float = 0.999, likelihood: bool = False) -> bool:
    """Whether the motion ``matrix`` (the truth, in a benchmark) could be kept by :func:`register`'s search.

    The search keeps a motion found at a tolerance level only when its
    refined pairs within that level's gate or a finer one's beat chance
    family-wise over every match its budget scores
    (:func:`gatv.stages.level_counts`).  Here the motion itself is refined
    at each level's gate (:func:`gatv.stages.refine`) and counted the same
    way: no trial pose is closer to it, so a motion that fails at every
    level is beyond any trial generator of this search (the count test's
    power, not the search's reach).  Optimistic: the density test, the judge
    and the sample that finds the motion are taken to succeed.

    ``likelihood``: a level also passes on the likelihood-ratio test of the
    motion cross-fitted at the level's gate (:func:`gatv.stages.likelihood_counts`, at the odds of
    ``min_inlier_share``): what a final test that weighs each pair by its
    likelihood ratio would keep (the search does not use it, design notes).
    """
    share, n_final, refined = _refined_at_each_level(P, matrix, min_inlier_share, confidence)
    for g, levels, fit in refined:
        if stages.passing_level(P, fit, levels, n_final) is not None:
            return True
        if likelihood and stages.likelihood_passes(
                stages.likelihood_counts(P, matrix, g, levels, n_final, share)) is not None:
            return True
    return False


def count_alpha(P: stages.Problem, matrix: np.ndarray, *, min_inlier_share: float = 0.04,
                confidence: float = 0.999) -> float:
    """The smallest family-wise level at which :func:`count_ceiling` keeps ``matrix`` on its count.

    The same refinement at each level's gate and the same counts as
    :func:`count_ceiling` (without ``likelihood``), each turned into the
    level its count would need (:func:`gatv.stages.level_alphas`, Bonferroni
    over the budget's matches and the gates looked at); the smallest of
    them.  So ``count_ceiling(P, matrix)`` is ``count_alpha(P, matrix) <=``
    :data:`gatv.stats.ALPHA`.  Above 1 it bounds how many of the search's
    wrong motions would reach the truth's count: how far a target set
    against the maximum-likelihood estimate lies beyond a search that keeps
    no wrong motion (design notes, section 1).  The model must say the
    level its count needs (its ``chance_alpha`` hook, as the built-in
    models do).
    """
    if getattr(P.model, "chance_alpha", None) is None:
        raise InputError(f"count_alpha needs a model with a chance_alpha(support, n_source, n_target, measure, "
                         f"gate, n_tests) method; {type(P.model).__name__} has none: add it beside its chance()")
    _, n_final, refined = _refined_at_each_level(P, matrix, min_inlier_share, confidence)
    return float(min(min(stages.level_alphas(P, fit, levels, n_final)) for _, levels, fit in refined))


def _refined_at_each_level(P: stages.Problem, matrix: np.ndarray, min_inlier_share: float, confidence: float):
    """:func:`count_ceiling`'s budget and refinements: ``(share, n_final, refined)``.

    ``share`` and ``n_final``: the smallest inlier share the search looks
    for and the matches its budget scores; ``refined`` yields, coarser level
    by level, ``(gate, levels up to it, matrix refined at that gate)``.
    """
    policy = P.model.search_policy()
    share, budget = register_budget(P, min_inlier_share, confidence)
    levels = stages.tolerance_levels(P, None, policy.schedule)
    start = stages.Fit(np.asarray(matrix, float), np.empty((0, 2), np.int64))
    refined = ((stages.gate(tol), levels[:k + 1], stages.refine(P, start, stages.gate(tol)))
               for k, tol in enumerate(levels))
    return share, float(budget) * policy.max_matches, refined


#: Source triples of the found inliers matched among themselves by
#: :func:`symmetry_rival`: on a symmetric set nearly every triple has a
#: moved copy, so a few dozen show the symmetry.
RIVAL_SAMPLES = 64


#: Turns of :func:`rival_draws` about each axis, degrees (each both ways but the half-turn).
RIVAL_TURNS = (20.0, 45.0, 90.0, 135.0, 180.0)
#: Random axes :func:`rival_draws` turns about, beside the inliers' three principal axes.
RIVAL_AXES = 5
#: Shifts of :func:`rival_draws` along each principal axis (both ways), in standard
#: deviations of the inliers along it.
RIVAL_SHIFTS = (0.5, 1.0)
#: Shifts of :func:`rival_draws` by the step from a random target point to one of its
#: nearest neighbours: a repeated structure's period (a lattice's vectors).
RIVAL_STEPS = 12


@dataclass(frozen=True)
class Rivals:
    """A motion against turns and shifts of itself, each polished on the same data (:func:`rival_draws`).

    ``support``: the motion's own pairs within the gate, polished as its
    rivals are; ``rival``: the most any distinct rival holds (0 when none);
    ``angle_deg``: the rotation between that rival and the motion and
    ``offset`` the median distance between where the two put the inliers;
    ``n_draws``: the rivals polished; ``even``: the most the same draws
    hold, polished the same way, from as many source points spread evenly
    over the source's box onto the target (what chance gives a polished
    rival at the target's own density, with nothing the two sets share);
    measured only where the rival is :attr:`close` (``None`` otherwise).
    """

    support: int
    rival: int
    angle_deg: float
    offset: float
    n_draws: int
    even: int | None

    @property
    def ambiguous(self) -> bool:
        """The data do not tell the motion from its best rival.

        Where the best rival holds no more than the draws do from evenly spread source points
        (:attr:`structured` false), the rivals hold chance pairs at the target's density, and the
        motion stands on the search's own level.  Where it holds more, the two sets share
        structure the Poisson levels do not model (planes, dense cores, a repeated structure, a
        symmetric set) and the motion must beat the rival: the
        rival holds :data:`gatv.scans.RIVAL_SHARE` of its support, or the motion does not beat the
        rival's count by three of its Poisson deviations (the scans verdict's margin over a wrong
        motion, before its search gain, :func:`gatv.scans.gate_verdicts`), and it is ambiguous.
        """
        return self.support > 0 and self.close and self.structured

    @property
    def close(self) -> bool:
        """The rival holds :data:`gatv.scans.RIVAL_SHARE` of the support, or the motion does not beat
        it by three of its Poisson deviations (:attr:`level`)."""
        return self.rival >= RIVAL_SHARE * self.support or self.support < self.level

    @property
    def structured(self) -> bool:
        """The best rival beats, by more than three Poisson deviations (of at least one), the best the
        same draws reach from evenly spread source points (:attr:`even`; ``None``, not measured,
        where the rival is not :attr:`close`: the motion stands either way)."""
        return self.even is not None and self.rival > self.even + 3.0 * np.sqrt(max(self.even, 1))

    @property
    def level(self) -> float:
        """The count the motion must reach: its best rival's plus three Poisson deviations."""
        return self.rival + 3.0 * np.sqrt(self.rival)

    def to_dict(self) -> dict:
        return {"support": int(self.support), "rival": int(self.rival), "angle_deg": float(self.angle_deg),
                "offset": float(self.offset), "n_draws": int(self.n_draws),
                "even": None if self.even is None else int(self.even),
                "level": float(self.level),
                "ambiguous": bool(self.ambiguous)}

    def reason(self) -> str:
        """Why a motion with this rival is not reported."""
        return (f"ambiguous: a motion {self.angle_deg:.1f} deg from the one found, putting its points "
                f"{self.offset:.3g} away, holds {self.rival} points against its {self.support} (a turn or shift "
                f"of it, polished; the motion needs {max(self.level, self.rival / RIVAL_SHARE):.0f}): the "
                "data do not tell the two apart")


def _turn(axis: np.ndarray, degrees: float, centre: np.ndarray) -> np.ndarray:
    """The 4×4 rotation by ``degrees`` about ``axis`` through ``centre`` (:func:`gatv.ga.turn_about`)."""
    return homogeneous(*turn_about(axis, np.radians(degrees), centre))


def _turn2(degrees: float, centre: np.ndarray) -> np.ndarray:
    """The 3×3 rotation of the plane by ``degrees`` about ``centre``."""
    a = np.radians(degrees)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    Q = np.eye(3)
    Q[:2, :2] = R
    Q[:2, 2] = centre - R @ centre
    return Q


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """The angle between the rotations of two linear maps (their polar factors: a rotation or a
    similarity's exactly, an affine map's nearest rotation), degrees."""
    def polar(m):
        u, _, vt = np.linalg.svd(m)
        return u @ vt
    r = polar(a) @ polar(b).T
    if r.shape[0] == 2:
        return float(abs(np.degrees(np.arctan2(r[1, 0], r[0, 0]))))
    return rotation_angle_deg(r)


def _polisher(problem: Problem, gate_radius: float):
    """``polish(source, starts) -> (linear, translation)``: homogeneous ``starts`` polished by ICP within
    ``gate_radius`` on ``problem.target`` (:func:`gatv.stages.polished_motions`: all at once where the
    model has the ``polish_motions`` hook, on one grid of the target for every call)."""
    grid = (TargetGrid.of(problem.target, gate_radius, cell_radii=2.0, max_side=64)
            if getattr(problem.model, "polish_motions", None) is not None else None)
    d = problem.dim

    def polish(source, starts):
        linear, shift, _ = stages.polished_motions(replace(problem, source=source), starts[:, :d, :d],
                                                   starts[:, :d, d], gate_radius, grid)
        return linear, shift
    return polish


def _held(tree, source: np.ndarray, R: np.ndarray, t: np.ndarray, gate_radius: float,
          home: np.ndarray | None = None) -> np.ndarray:
    """For each motion ``(R[k], t[k])``, the points of ``source`` it puts within ``gate_radius`` of a point of
    ``tree``, leaving out those it puts within two gates of their ``home`` position: a point moved less may
    still land on the partner it has within the gate of home (one query for all)."""
    moved = np.einsum("kij,nj->kni", R, source) + t[:, None, :]
    keep = np.ones(moved.shape[:2], bool)
    if home is not None:
        keep = np.linalg.norm(moved - home, axis=2) > 2.0 * gate_radius
    held = np.zeros(moved.shape[:2], bool)
    if keep.any():
        d, _ = tree.query(moved[keep], distance_upper_bound=gate_radius)
        held[keep] = np.isfinite(d)
    return held.sum(axis=1)


def rival_draws(problem: Problem, matrix: np.ndarray, pairs: np.ndarray, gate_radius: float,
                rng: np.random.Generator, *, others=()) -> Rivals:
    """The motion ``matrix`` against wrong but plausible motions on the same data.

    Any model whose motions are homogeneous matrices in 2D or 3D (turns about
    the inliers' centroid in the plane; a model without the ``polish_motions``
    hook is polished by :func:`gatv.stages.refine`).

    The Poisson levels of the exact pipeline spread the target evenly over
    a box (or over the density of its other points where the motion
    lands).  Points on a plane, a thin or dense cloud, or a repeated
    structure break that: two unrelated sets laid plane on plane, or core
    on core, collect many more pairs than the level expects, and the search,
    which maximises support, finds such a lay.  Its rivals show it: the
    same lay turned about an axis of its inliers or shifted along one holds
    about as many points, where a true motion's turned copies hold chance
    pairs only.  The rivals are the motion composed with turns of
    :data:`RIVAL_TURNS` about the three principal axes of its source inliers
    (``pairs[:, 0]``) and :data:`RIVAL_AXES` random axes, through their
    centroid, shifts of :data:`RIVAL_SHIFTS` standard deviations along
    the principal axes, and :data:`RIVAL_STEPS` shifts by the step from a
    random target point to one of its six nearest (a lattice's period moves
    its sites onto sites); each, and the motion itself, polished by ICP within
    ``gate_radius`` (the model's ``polish_motions``, :func:`gatv.stages.refine`'s
    steps).  A polished rival counts when it moves the inliers by more than
    twice the gate (median) from the polished motion and from each of
    ``others`` (matrices of motions found beside it, which are not rivals),
    and its support counts only the source points it puts more than two
    gates from where the motion puts them (nearer, a point may still land
    on the motion's own partner).

    Returns
    -------
    Rivals
        Ambiguous when the best rival holds more than the draws do from
        evenly spread source points, and :data:`gatv.scans.RIVAL_SHARE` of
        the motion's support or enough that the motion does not beat it by
        three Poisson deviations (:attr:`Rivals.ambiguous`).
    """
    X = problem.source[np.asarray(pairs, np.int64).reshape(-1, 2)[:, 0]]
    d = problem.dim
    if X.shape[0] < d + 1:
        return Rivals(int(X.shape[0]), 0, 0.0, 0.0, 0, None)  # no rival drawn, nothing measured
    centre = X.mean(axis=0)
    spread, principal = np.linalg.eigh(np.cov(X.T))
    signed = [sign * deg for deg in RIVAL_TURNS for sign in ((1.0,) if deg == 180.0 else (1.0, -1.0))]
    if d == 3:
        axes = list(principal.T)
        for _ in range(RIVAL_AXES):
            a = rng.normal(size=3)
            axes.append(a / np.linalg.norm(a))
        draws = [_turn(a, deg, centre) for a in axes for deg in signed]
    else:  # in the plane: turns about the centroid
        draws = [_turn2(deg, centre) for deg in signed]
    for k in range(d):
        for f in RIVAL_SHIFTS:
            for sign in (1.0, -1.0):
                Q = np.eye(d + 1)
                Q[:d, d] = sign * f * np.sqrt(max(float(spread[k]), 0.0)) * principal[:, k]
                draws.append(Q)
    M = np.asarray(matrix, np.float64)
    starts = [M @ Q for Q in draws]
    Y = problem.target
    if Y.shape[0] > 1:
        k = min(2 * d + 1, Y.shape[0])  # each point and its 2d nearest (a lattice's neighbours)
        _, near = problem.tree.query(Y[rng.integers(0, Y.shape[0], RIVAL_STEPS)], k=k)
        for row in near:
            step = np.eye(d + 1)
            step[:d, d] = Y[row[rng.integers(1, k)]] - Y[row[0]]
            starts.append(step @ M)
    n_draws = len(starts)
    starts = np.array(starts + [M])
    polish = _polisher(problem, gate_radius)
    R, t = polish(problem.source, starts)
    # Every source point where the polished motion puts it; a rival counts only the points it puts
    # elsewhere (beyond two gates), so a turn keeps no credit for the motion's own pairs near its axis.
    home_all = problem.source @ R[-1].T + t[-1]
    own = int(_held(problem.tree, problem.source, R[-1:], t[-1:], gate_radius)[0])
    held = _held(problem.tree, problem.source, R[:n_draws], t[:n_draws], gate_radius, home_all)
    home = X @ R[-1].T + t[-1]
    refs = [home] + [apply_matrix(np.asarray(o, np.float64), X) for o in others]
    best, angle, offset = 0, 0.0, 0.0
    for k in np.argsort(-held, kind="stable"):
        if held[k] <= best:
            break
        moved = X @ R[k].T + t[k]
        apart = [float(np.median(np.linalg.norm(moved - ref, axis=1))) for ref in refs]
        if min(apart) > 2.0 * gate_radius:
            best, angle, offset = int(held[k]), _angle_deg(R[k], R[-1]), apart[0]
    found = Rivals(own, best, float(angle), offset, n_draws, None)
    if not found.close:  # the motion beats its best rival whatever the data's structure
        return found
    # The same draws from as many source points spread evenly over the source's box, polished and
    # counted alike on the target: the target's own density (overlapping objects, dense parts) stays,
    # what the two sets share (a plane on a plane, core on core, sites on sites) goes.
    Xs = problem.source
    flat = rng.uniform(Xs.min(axis=0), Xs.max(axis=0), Xs.shape)
    Re, te = polish(flat, starts[:n_draws])
    even = int(_held(problem.tree, flat, Re, te, gate_radius).max(initial=0))
    return replace(found, even=even)


def symmetry_rival(problem: Problem, fit: stages.Fit, tolerance: float, rng: np.random.Generator, *,
                   memory_budget=None) -> dict:
    """Whether a distinct motion explains the found pairs nearly as well (a symmetric set).

    A motion ``M`` whose inliers ``X`` map onto themselves by a rigid
    motion ``Q`` that moves some of them beyond twice the gate (a symmetry
    of the set) has a rival ``M Q`` with the support of ``Q`` on ``X``:
    the data cannot tell them apart.  ``Q`` is searched as any motion is
    (congruent triples of ``X`` matched among ``X``, scored within the
    gate of ``tolerance``).  Returns ``{"ambiguous": bool}``, with
    ``"rival"`` (its support, the found one's, the angle between them)
    when its support reaches :data:`gatv.scans.RIVAL_SHARE` of the found
    motion's.  The inliers are at most the target's points, so their
    index fits the ``memory_budget`` the search's did.
    """
    X = problem.source[fit.correspondences[:, 0]]
    if X.shape[0] < 4:
        return {"ambiguous": False}
    g = stages.gate(tolerance)
    trials = trial_motions(X, TargetIndex(X, g, memory_budget=memory_budget), eps=2.0 * stages.LISTING * tolerance,
                           max_triples=RIVAL_SAMPLES, rng=rng, keep=32, accept=0)
    best, angle = 0, 0.0
    for matrix, support in zip(trials.matrices, trials.support):
        if np.linalg.norm(apply_matrix(matrix, X) - X, axis=1).max() > 2.0 * g and support > best:
            best, angle = int(support), rotation_angle_deg(matrix[:3, :3])
    if best < RIVAL_SHARE * fit.support:
        return {"ambiguous": False}
    return {"ambiguous": True, "rival": {"support": best, "best_support": int(fit.support), "angle_deg": angle}}
