"""Non-rigid registration, the local-constraint mode of section 5.1.

A motion that is rigid only locally (a twist, a bend, an elastic warp) no
longer puts the true pairs on one plane of the ``{dx, dy, dz}`` joint space
(eq. 30) but on a *curved* surface — or, for motions whose displacement
varies along one direction only (a plane rolled around a cylinder), on a
3D *curve* (the paper's conclusions).  Tensor voting finds both; eq. 41 is
then enforced only locally, between each token and its closest active
neighbour (Fig. 14).

How it works
------------
:func:`register` runs the stages of :mod:`gatv.nonrigid.stages`:

1. **Candidate pairs and tokens.** All pairs for small sets (section 3.4);
   with ``max_displacement`` only the targets that close, and for large
   sets at most ``max_candidates`` nearest ones per source point.  Each
   pair's token is ``target[j] − source[i]``.
2. **Tensor votes** (section 3.3): a ball pass, then stick passes with
   growing σ; curved surfaces are kept as they are, and curve-like tokens
   (λ2 − λ3 > λ1 − λ2 after the ball pass) are extracted as a curve.
3. **Local eq. 41** between each token and its closest active neighbour,
   with the tolerance relaxed to ``strain · |Δx| + gate`` (local strain,
   noise).
4. **Seeds:** one-to-one selection of the verified tokens by saliency,
   dropping those off the local affine trend of their neighbours.
5. **Hypotheses** (:mod:`gatv.nonrigid.hypotheses`), each a one-to-one
   matching: *voting* (the seeds grown ring by ring by local affine maps,
   then a thin-plate warp re-matched until stable); *coarse*
   (coarse-to-fine thin-plate matching from the identity: voted tokens are
   mostly wrong for a near-identity motion or a hinge); *anneal*
   (deterministic-annealing soft matching with an outlier class: for
   displacements of several spacings among many outliers); *rigid*
   (coarse-to-fine from the dominant rigid motion of :func:`gatv.register`:
   for a non-rigid motion on top of a large rigid one), tried with
   ``prealign=True`` or, by default, only when nothing else counts or the
   annealed hypothesis wins.
6. **Verification against chance:** a hypothesis's matches pass when
   their displacement is within 0.2 target spacings of the affine trend of
   their neighbouring matches; a hypothesis counts only when the passes
   expected by chance are at most a quarter of its support and it explains
   a tenth of the smaller set.  When none counts the result is empty, with
   ``info["reason"]``: fewer, correct matches rather than many wrong ones.
7. **Seeds in every part** (:mod:`gatv.nonrigid.parts`): where the growth
   did not reach (a limb past a joint that turned), rigid windows of the
   uncovered rows are registered and grown over the rows no part holds,
   one-to-one; a part counts when its growth is as large as a hypothesis
   must be and meets the earlier matches continuously or at a joint.  The
   multi-resolution path gates each target row by its local spacing
   (:func:`gatv.nonrigid.multiscale.local_gates`), and, when no
   identity-placed window counts, tries a bounded rigid pre-alignment before
   the coarse solve, and where that finds nothing (a rotation with a change of
   scale) the similarity of the principal axes.
8. **Fit:** the winner is grown and re-verified; each correspondence gets
   the rigid motion fitted on its nearest matches, and the thin-plate
   warp's smoothing is chosen by 5-fold cross-validation unless given;
   the matches are split into near-rigid parts with their joints
   (``info["parts"]``, ``info["joints"]``).
"""

from __future__ import annotations

import time

from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from .._validation import (
    as_points,
    check_fraction,
    check_int,
    check_memory,
    check_positive,
    check_progress,
    seed_int,
)
from ..candidates import median_spacing
from ..errors import InputError
from ..models import get_model, model_names
from ..models.rigid import check_spread
from ..registration import register as rigid_register
from . import multiscale as ms
from .hypotheses import farthest_points
from .motion import Diagnostics, NonRigidMotion
from .parts import parts_info, seed_parts
from ..verdict import chance_verdict
from .stages import (
    ANNEAL_PREFERENCE,
    AUTO_RIGID_TRIPLES,
    CHANCE_SHARE,
    MIN_SHARE,
    Problem,
    Settings,
    anneal_hypothesis,
    candidate_pairs,
    choose_hypothesis,
    coarse_hypothesis,
    fit_local_motions,
    joint_tokens,
    local_eq41,
    local_hypothesis,
    refine_winner,
    rigid_hypothesis,
    select_seeds,
    tensor_votes,
    voting_hypothesis,
    wants_rigid_start,
)

__all__ = ["register"]


#: The verdict's ``method`` of the non-rigid pipelines: matches that pass the local-affine
#: check against those expected to pass by chance (:func:`gatv.nonrigid.stages.verify_matches`).
VERDICT_METHOD = "local consistency"


def _hypothesis_verdict(problem: Problem, verdict, support: int | None = None) -> dict:
    """``info["verdict"]`` of the direct mode: the chosen hypothesis (or, with none, the one
    closest to counting) against the level :func:`~gatv.nonrigid.stages.choose_hypothesis` holds it
    to: ``max(4, MIN_SHARE · smaller set, chance / CHANCE_SHARE)``, over the hypotheses scored.
    ``support``: the reported matches (default the hypothesis's verified ones)."""
    least = max(4.0, MIN_SHARE * problem.n_smaller)
    scores = verdict.scores

    def level(k):
        return max(least, float(scores[k].chance) / CHANCE_SHARE)

    if not scores:
        return chance_verdict(0, least, 1.0, method=VERDICT_METHOD).to_dict()
    key = verdict.best
    if key is None:
        key = max(scores, key=lambda k: scores[k].support / level(k))
    n = scores[key].support if support is None else support
    return chance_verdict(n, level(key), len(scores), method=VERDICT_METHOD).to_dict()


def _add_parts(info: dict, source_points, target_points, spacing: float, floor: float, seed: int) -> None:
    """``info["parts"]``, ``info["joints"]``, ``info["part_labels"]`` (per correspondence) of the
    reported matches (:func:`gatv.nonrigid.parts.parts_info`)."""
    t0 = time.perf_counter()
    # the matched targets' own spacing: the dense rows' median is a face's or a hand's on a body
    spacing = median_spacing(target_points) if len(target_points) >= 2 else spacing
    parts, joints, labels = parts_info(source_points, target_points, spacing=spacing, floor=floor, seed=seed)
    info.update(parts=parts, joints=joints, part_labels=labels, time_parts_s=time.perf_counter() - t0)


def _on_surfaces(X, Y, pairs, gates, info) -> np.ndarray:
    """``pairs`` less the matches off either surface (:func:`gatv.nonrigid.multiscale.on_surfaces`,
    at each match's local gate); counted in ``info["n_off_surface"]``."""
    ok = ms.on_surfaces(X, Y, pairs, gates[pairs[:, 1]])
    if ok is None or ok.sum() < 4:
        return pairs
    info["n_off_surface"] = info.get("n_off_surface", 0) + int((~ok).sum())
    return pairs[ok]


def _check_points(points, name: str) -> np.ndarray:
    """``points`` as (N, 3), at least 4, neither all identical nor collinear (no local rigidity to find)."""
    p = as_points(points, name, min_points=4)
    check_spread(p, name, "a non-rigid motion needs spread points",
                 "a non-rigid motion needs a surface or a volume")
    return p


def _non_negative(value, name: str) -> float:
    return check_fraction(value, name, high=np.inf, open_low=False)


def _failure(reason: str, info: dict, diagnostics=None) -> NonRigidMotion:
    """The falsy result: no correspondences, ``info["reason"]`` says why."""
    z = np.empty((0, 3))
    return NonRigidMotion(np.empty((0, 2), np.int64), z, z, np.empty((0, 3, 3)), z, 0.0,
                          diagnostics, dict(info, reason=reason))


def register(
    source,
    target,
    *,
    seed=0,
    progress=None,
    memory_budget: float | None = None,
    noise: float | None = None,
    max_displacement: float | None = None,
    max_candidates: int | None = None,
    max_pairs: int = 1_500_000,
    sigma: float | None = None,
    n_stick_passes: int = 3,
    structure: str = "auto",
    strain: float = 0.35,
    gate: float | None = None,
    smoothing: float | None = None,
    neighbours: int = 8,
    grow: bool = True,
    prealign: bool | str = "auto",
    model: str = "rigid",
    multiscale: bool | str = "auto",
    coarse_points: int = 700,
    window_points: int = 400,
) -> NonRigidMotion:
    """Register ``source`` onto ``target`` under a locally rigid, non-rigid motion.

    Parameters
    ----------
    source, target : (N, 3), (M, 3) array_like or object with ``.points``
        The two point sets (at least 4 points each, not collinear); any share
        of either may be outliers.
    seed : int or numpy.random.Generator, default: 0
        Seed of the voting scale's subsample, of the annealed hypothesis's
        subsample, of the rigid search and of the smoothing
        cross-validation folds; same int, same result.  A ``Generator``
        draws one integer used for all of them.
    progress : callable, optional
        ``progress(fraction, message)`` called at each stage.
    memory_budget : float, optional
        Bytes; inputs needing more fail at once.
    noise : float, optional
        Standard deviation of the point noise (data units); widens every
        gate by ``3.5 noise``.
    max_displacement : float, optional
        Bound on how far a point moves (data units): only target points that
        close to a source point are candidates.
    max_candidates : int, optional
        At most this many candidates (the nearest target points) per source
        point.  Default: all pairs while ``N·M <= max_pairs``, else
        ``max_pairs // N``.
    max_pairs : int, default: 1_500_000
        Largest number of candidate pairs voted on by default.
    sigma : float, optional
        Tensor-voting scale; default :func:`gatv.voting.default_sigma`.
    n_stick_passes : int, default: 3
        Stick passes (curve mode: ball passes) of the extraction.
    structure : {"auto", "surface", "curve"}, default: "auto"
        Structure of the true tokens in the joint space.
    strain : float, default: 0.35
        Relative length change between neighbours still called locally
        rigid in the local eq.-41 test.
    gate : float, optional
        Match radius of the voted seeds' growth (data units). Default
        ``max(0.3 · target spacing, 3.5 · noise)``.
    smoothing : float, optional
        Thin-plate smoothing of the warp; default chosen by 5-fold
        cross-validation of the matched displacements (0 for exact data).
    neighbours : int, default: 8
        Matches in each local rigid fit.
    grow : bool, default: True
        Grow the seeds and run the coarse-to-fine and annealed hypotheses;
        without it the correspondences are the seeds that pass the
        verification.
    prealign : {"auto", True, False}, default: "auto"
        Also start the coarse-to-fine matching from the dominant rigid motion
        of :func:`gatv.register` — for non-rigid motions on top of a large
        rigid one.  ``"auto"``: only when no other hypothesis beats chance
        or the annealed one wins, with a bounded search; ``True``: always,
        unbounded (slow on large, cluttered sets); ``False``: never.
    model : {"rigid", "similarity"}, default: "rigid"
        Model of that dominant motion (:func:`gatv.register`'s ``model``):
        ``"similarity"`` for a deformation on top of a rotation and a scale
        change.  In the multi-resolution path with ``prealign=True`` the
        source is first moved by it (the pre-alignment).
    multiscale : {"auto", True, False}, default: "auto"
        Multi-resolution solve (:mod:`gatv.nonrigid.multiscale`) for sets of
        10⁴–10⁵ points: a coarse solve on about ``coarse_points`` points per
        set, the direct solve of a window of about ``window_points`` source
        points at full resolution (the paper's local mode, seeds), growth of
        those seeds over the whole set, and final local matching within the
        sampling gate checked by local eq. 41.  O(N + M) memory.
        ``"auto"``: when the direct solve would vote on more than
        ``max_pairs`` pairs and no ``max_displacement``/``max_candidates``
        bound is given.
    coarse_points : int, default: 700
        Points per set of the coarse solve (voxel-grid subsample).
    window_points : int, default: 400
        Source points of each full-resolution window.

    Returns
    -------
    NonRigidMotion
        One-to-one ``correspondences``, local rigid motions and
        :meth:`~NonRigidMotion.warp`; falsy with ``info["reason"]`` when
        nothing was found.  ``info["hypothesis"]`` names the hypothesis
        reported, ``info["hypotheses"]`` the support and chance of each.
        ``info["parts"]``: the near-rigid parts of the matches
        (:func:`gatv.nonrigid.parts.parts_info`), each with its rigid motion
        (``rotor`` scalar first, ``rotation``, ``translation``, ``angle_deg``,
        ``size``, ``rms``, ``joints``); ``info["joints"]``: between parts that
        meet, the axis, angle and centre of their relative rotation;
        ``info["part_labels"]``: the part of each correspondence (-1: none).
        ``info["part_windows"]``: the windows searched where the first growth
        did not reach (:func:`gatv.nonrigid.parts.seed_parts`).

    Raises
    ------
    gatv.errors.InputError
        Fewer than 4 points, NaN/inf, wrong shapes, identical or collinear
        points, bad options, or more candidate pairs than the memory budget
        (the multi-resolution path: more than its linear memory estimate,
        :func:`gatv.nonrigid.multiscale.memory_estimate`).

    References
    ----------
    Reyes, Medioni & Bayro, IJCV 75(3) 2007, eq. 41, section 5.1, Figs. 13–14.

    Examples
    --------
    >>> import numpy as np
    >>> from gatv.nonrigid import register
    >>> from gatv.nonrigid.deformations import sample_plane, twist
    >>> x = sample_plane(100, 10.0, seed=0)
    >>> y = twist(x, 45.0)
    >>> m = register(x, y[::-1])
    >>> bool(np.mean(m.correspondences[:, 1] == 99 - m.correspondences[:, 0]) > 0.95)
    True
    """
    t_start = time.perf_counter()
    X = _check_points(source, "source")
    Y = _check_points(target, "target")
    if structure not in ("auto", "surface", "curve"):
        raise InputError(f"Expected `structure` to be 'auto', 'surface' or 'curve', got {structure!r}.")
    if not isinstance(model, str) or model.lower() not in model_names() or get_model(model).dim != 3:
        raise InputError(f"Expected `model` to be 'rigid' or 'similarity' (a 3D model), got {model!r}.")
    if prealign not in (True, False, "auto"):
        raise InputError(f"Expected `prealign` to be True, False or 'auto', got {prealign!r}.")
    settings = Settings(
        seed=seed_int(seed),
        max_displacement=check_positive(max_displacement, "max_displacement", allow_none=True),
        max_candidates=check_int(max_candidates, "max_candidates", 1, allow_none=True),
        max_pairs=check_int(max_pairs, "max_pairs", 1),
        noise=check_positive(noise, "noise", allow_none=True),
        sigma=check_positive(sigma, "sigma", allow_none=True),
        n_stick_passes=check_int(n_stick_passes, "n_stick_passes", 1),
        structure=structure,
        strain=_non_negative(strain, "strain"),
        gate=check_positive(gate, "gate", allow_none=True),
        smoothing=None if smoothing is None else _non_negative(smoothing, "smoothing"),
        neighbours=check_int(neighbours, "neighbours", 3),
        grow=bool(grow),
        prealign=prealign,
        memory_budget=memory_budget,
        model=model,
        local=prealign is not False,
    )
    report = check_progress(progress)
    options = {"coarse_points": check_int(coarse_points, "coarse_points", 50),
               "window_points": check_int(window_points, "window_points", 20)}
    if multiscale not in (True, False, "auto"):
        raise InputError(f"Expected `multiscale` to be True, False or 'auto', got {multiscale!r}.")
    if multiscale is True or (multiscale == "auto" and wants_multiscale(X, Y, settings)):
        return _register_multiscale(X, Y, settings, report, t_start, **options)
    return _register_direct(X, Y, settings, report, t_start)


def wants_local_start(settings: Settings, best: str | None) -> bool:
    """Try the *local* hypothesis (:func:`gatv.nonrigid.stages.local_hypothesis`): when growing,
    ``settings.local`` (not ``prealign=False``; the full-resolution windows keep it while they turn
    the global rigid start off), and the best so far is none or a fallback it may beat (the
    annealed or the rigid start: a bent body has no dominant rigid motion)."""
    return settings.grow and settings.local and best in (None, "anneal", "rigid")


def wants_multiscale(X, Y, settings: Settings) -> bool:
    """The direct solve would vote on more than ``max_pairs`` candidate pairs with no bound given."""
    return (settings.max_displacement is None and settings.max_candidates is None
            and X.shape[0] * Y.shape[0] > settings.max_pairs)


def _register_direct(X, Y, settings: Settings, report, t_start) -> NonRigidMotion:
    """The direct mode of section 5.1 on all candidate pairs (stages 1–7)."""
    problem = Problem.build(X, Y, settings)
    info: dict = {"n_source": int(X.shape[0]), "n_target": int(Y.shape[0]),
                  "spacing": problem.spacing, "gate": problem.gate}

    report(0.0, "candidate pairs")
    t0 = time.perf_counter()
    candidates = candidate_pairs(problem, settings)
    info.update(candidates=candidates.scheme, n_candidates=int(candidates.pairs.shape[0]))
    if candidates.pairs.shape[0] < 4:
        report(1.0, "done: fewer than 4 candidate pairs")
        info["verdict"] = chance_verdict(int(candidates.pairs.shape[0]), 4.0, 1.0, method=VERDICT_METHOD).to_dict()
        return _failure("fewer than 4 candidate pairs", info)
    tokens = joint_tokens(problem, candidates)

    report(0.1, "tensor voting")
    votes = tensor_votes(problem, candidates, tokens, settings)
    info.update(sigma=votes.sigma, structure=votes.structure, n_voted=int(votes.pairs.shape[0]),
                time_voting_s=time.perf_counter() - t0)

    report(0.4, "local eq. 41")
    check = local_eq41(problem, votes, settings)
    seeds = select_seeds(problem, votes, check)
    info["gate"] = seeds.gate
    diagnostics = Diagnostics(
        votes.structure, votes.sigma, int(candidates.pairs.shape[0]), votes.pairs, votes.tokens,
        votes.normals, votes.saliency, np.column_stack([np.arange(votes.pairs.shape[0]), check.partner]),
        np.where(np.isfinite(check.ratio), check.ratio, -1.0), check.verified, seeds.pairs)
    info.update(n_verified=seeds.n_verified, n_seeds=int(seeds.pairs.shape[0]),
                scale=problem.scale, verify_gate=problem.verify_gate)

    report(0.5, "hypotheses")
    hypotheses: dict[str, np.ndarray] = {}
    voted = voting_hypothesis(problem, seeds, settings)
    if voted is not None:
        hypotheses["voting"] = voted
    verdict = None
    if settings.grow:
        hypotheses["coarse"] = coarse_hypothesis(problem)
        # the annealed hypothesis wins only with ANNEAL_PREFERENCE times the best other counted
        # support, and its support is at most the smaller set: skip it when it cannot win
        verdict = choose_hypothesis(problem, hypotheses)
        best = verdict.scores[verdict.best].support if verdict.best is not None else 0
        if ANNEAL_PREFERENCE * best <= problem.n_smaller:
            t0 = time.perf_counter()
            hypotheses["anneal"] = anneal_hypothesis(problem, settings.seed)
            info["time_anneal_s"] = time.perf_counter() - t0
            verdict = None
        else:
            info["anneal_skipped"] = "cannot win"

    report(0.75, "verification against chance")
    if verdict is None:
        verdict = choose_hypothesis(problem, hypotheses)
    info["hypotheses"] = verdict.summary()
    if wants_rigid_start(settings, verdict.best):
        report(0.8, "rigid prealignment")
        rigid = rigid_hypothesis(problem, settings)
        info["prealign"] = (None if rigid is None else
                             {"angle_deg": rigid.angle_deg, "support": rigid.support})
        if rigid is not None:
            hypotheses["rigid"] = rigid.pairs
            verdict = choose_hypothesis(problem, hypotheses)
            info["hypotheses"] = verdict.summary()
    if wants_local_start(settings, verdict.best):
        report(0.85, "local windows")
        local = local_hypothesis(problem, settings)
        info["local_windows"] = list(local.windows)
        if local.pairs.shape[0] >= 5:
            hypotheses["local"] = local.pairs
            verdict = choose_hypothesis(problem, hypotheses)
            info["hypotheses"] = verdict.summary()
    info["hypothesis"] = verdict.best
    if verdict.best is None:
        info["verdict"] = _hypothesis_verdict(problem, verdict)
        info["time_s"] = time.perf_counter() - t_start
        report(1.0, "done: no hypothesis beats chance")
        return _failure("no hypothesis has more locally consistent matches than chance", info,
                        diagnostics)

    report(0.9, "fit")
    matched = refine_winner(problem, hypotheses, verdict, settings)
    if settings.grow and settings.parts and matched.shape[0] >= 4:
        # seeds in every part, as in the multi-resolution path
        rows_x, rows_y = ms.dense_rows(X), ms.dense_rows(Y)
        found = seed_parts(X, Y, cKDTree(X), problem.tree, rows_x, rows_y, matched, gate=problem.verify_gate,
                           spacing=problem.spacing, spacing_x=median_spacing(X[rows_x]),
                           least=max(4.0, MIN_SHARE * problem.n_smaller), strain=settings.strain,
                           seed=settings.seed, noise=settings.noise)
        if found.windows:
            info.update(part_windows=list(found.windows), n_part_growths=int(found.growth.max()))
        matched = found.pairs
    fit = fit_local_motions(problem, matched, settings)
    info["verdict"] = _hypothesis_verdict(problem, verdict, int(fit.pairs.shape[0]))
    if settings.parts:  # not inside a window or the coarse solve
        _add_parts(info, fit.source_points, fit.target_points, problem.spacing, problem.noise_floor,
                   settings.seed)
    info["time_s"] = time.perf_counter() - t_start
    report(1.0, "done")
    return NonRigidMotion(fit.pairs, fit.source_points, fit.target_points, fit.rotations,
                          fit.translations, fit.smoothing, diagnostics, info)


def _register_multiscale(X, Y, settings: Settings, report, t_start, *, coarse_points: int,
                         window_points: int) -> NonRigidMotion:
    """The multi-resolution path (:mod:`gatv.nonrigid.multiscale`), O(N + M) memory.

    1. optional pre-alignment (``prealign=True``): the dominant motion of
       ``settings.model`` found on the coarse sets moves the source;
    2. coarse solve: the direct mode on voxel-grid subsamples of both sets
       (differently sampled: the gates widen by half a coarse spacing);
    3. windows: the direct mode at full resolution on a source window of
       about ``window_points`` points and the target window that must hold
       their partners under the coarse warp (plus three coarse spacings);
       the first window whose result beats chance gives the seeds;
    4. growth of the seeds over the whole set (:func:`multiscale.grow`),
       polish, and final local matching within the sampling gate
       (half a target spacing plus the noise floor), each match checked by
       local eq. 41 (:func:`multiscale.local_eq41_pairs`).
    """
    n1, n2 = X.shape[0], Y.shape[0]
    need = ms.memory_estimate(n1, n2, coarse_points)
    try:
        check_memory(need, f"the multi-resolution solve of {n1} x {n2} points", settings.memory_budget)
    except InputError as exc:
        msg = (f"{exc} The multi-resolution solve's memory grows with N + M: subsample the inputs, "
               f"or lower `coarse_points` (now {coarse_points}).")
        raise InputError(msg) from None
    info: dict = {"n_source": int(n1), "n_target": int(n2), "multiscale": True,
                  "memory_estimate_bytes": need}
    floor = settings.noise_floor
    tree_y = cKDTree(Y)
    X0 = X

    # 1. pre-alignment by the dominant rigid/similarity motion
    prior = None
    dx, dy = ms.dense_rows(X), ms.dense_rows(Y)  # on the structure, not among scattered outliers
    spacing = median_spacing(Y[dy])
    si = dx[ms.grid_subsample(X[dx], coarse_points, min_share=0.25)]
    ti = dy[ms.grid_subsample(Y[dy], coarse_points, min_share=0.25)]
    coarse_spacing = median_spacing(Y[ti])
    if settings.prealign is True:
        report(0.02, f"pre-alignment ({settings.model})")
        found = rigid_register(X[si], Y[ti], model=settings.model, seed=settings.seed,
                               noise=max(settings.noise or 0.0, 0.5 * coarse_spacing / 3.5),
                               max_triples=AUTO_RIGID_TRIPLES, check_rivals=False)
        if found:
            prior = np.asarray(found.matrix, dtype=float)
            info["prealign"] = {"model": settings.model, "support": found.support}
        elif get_model(settings.model).search_policy().moment_prealign:
            prior = ms.moment_prealign(X[dx], Y[dy], seed=settings.seed)
            info["prealign"] = {"model": "principal axes + similarity ICP",
                                "reason": found.info.get("reason")}
        else:
            info["prealign"] = {"model": settings.model, "reason": found.info.get("reason")}
        if prior is not None:
            X = X @ prior[:3, :3].T + prior[:3, 3]

    # 2.–3. placement of the full-resolution windows: first the identity (after any
    # pre-alignment), and the coarse solve only when no identity-placed window beats chance
    tree_x = cKDTree(X)
    # windows hold the structure's rows only (outliers scattered through the volume would fill a
    # ball around a surface point), centred on the denser half of the coarse subsample
    tree_xd = cKDTree(X[dx])
    core = _core(X, dx, tree_xd, si)
    margin = 3.0 * coarse_spacing + floor
    identity = _identity
    tried: list = []
    by_identity = _window_order(X, None, core, MAX_WINDOWS)
    # the local hypothesis (16 rigid searches) only when the window's other hypotheses fail in
    # every identity window: then the same windows again with it
    quick = replace(settings, local=False)
    seeds, local = _seed_windows(X, Y, tree_xd, dx, tree_y, by_identity[:1], identity, margin, quick,
                                 window_points, report, tried, "identity")
    rigid = None  # (matrix, moved source, its tree) of the bounded rigid pre-alignment
    rigid_tried = False
    if seeds is None and settings.prealign == "auto" and prior is None:
        # a large rigid motion on top of the warp (a body turned by 60° or 180°): the dominant rigid
        # motion of the coarse sets (bounded search) places the same windows; kept only when one
        # counts.  It goes before the identity's second window when it explains more of the coarse
        # sets than the identity does (an identity-placed window on a turned body holds thousands
        # of targets and fails after 15–27 s)
        report(0.06, "rigid pre-alignment (bounded)")
        t0 = time.perf_counter()
        found = rigid_register(X[si], Y[ti], model="rigid", seed=settings.seed,
                               noise=max(settings.noise or 0.0, 0.5 * coarse_spacing / 3.5),
                               max_triples=AUTO_RIGID_TRIPLES, check_rivals=False)
        info["auto_prealign"] = {"support": int(found.support) if found else 0,
                                 "time_s": time.perf_counter() - t0}
        if found:
            A = np.asarray(found.matrix, dtype=float)
            Xp = X @ A[:3, :3].T + A[:3, 3]
            rigid = (A, Xp, cKDTree(Xp[dx]))
            tree_ti = cKDTree(Y[ti])
            explained = (_explained(X[si], tree_ti, coarse_spacing), _explained(Xp[si], tree_ti, coarse_spacing))
            info["auto_prealign"].update(angle_deg=float(found.angle_deg), explained=explained)
            if explained[1] > explained[0]:
                rigid_tried = True
                seeds, local = _seed_windows(Xp, Y, rigid[2], dx, tree_y, by_identity[:IDENTITY_WINDOWS],
                                             identity, margin, quick, window_points, report, tried, "rigid")
    if seeds is None:
        seeds, local = _seed_windows(X, Y, tree_xd, dx, tree_y, by_identity[1:IDENTITY_WINDOWS], identity,
                                     margin, quick, window_points, report, tried, "identity")
    if seeds is None and rigid is not None and not rigid_tried:
        seeds, local = _seed_windows(rigid[1], Y, rigid[2], dx, tree_y, by_identity[:IDENTITY_WINDOWS],
                                     identity, margin, quick, window_points, report, tried, "rigid")
    moments = None  # (matrix, moved source, its tree) of the similarity from principal axes
    if seeds is None and settings.prealign == "auto" and prior is None and rigid is None:
        # a rotation with a change of scale (the bcpd bunny: 93°, scale 0.83): the rigid search finds
        # nothing, and identity-placed windows do not hold the partners.  The similarity of the
        # principal axes and trimmed ICP (:func:`multiscale.moment_prealign`, the fallback of
        # ``prealign=True, model="similarity"``) places the same windows, with the local hypothesis;
        # kept only when it explains more of the coarse sets than the identity and a window counts
        report(0.07, "similarity pre-alignment (principal axes)")
        t0 = time.perf_counter()
        A = ms.moment_prealign(X[dx], Y[dy], seed=settings.seed)
        Xm = X @ A[:3, :3].T + A[:3, 3]
        tree_ti = cKDTree(Y[ti])
        explained = (_explained(X[si], tree_ti, coarse_spacing), _explained(Xm[si], tree_ti, coarse_spacing))
        info["auto_similarity"] = {"scale": float(np.cbrt(np.linalg.det(A[:3, :3]))), "explained": explained,
                                   "time_s": time.perf_counter() - t0}
        if explained[1] > explained[0]:
            moments = (A, Xm, cKDTree(Xm[dx]))
            seeds, local = _seed_windows(Xm, Y, moments[2], dx, tree_y, by_identity[:IDENTITY_WINDOWS], identity,
                                         margin, settings, window_points, report, tried, "similarity")
    if seeds is not None and tried[-1]["placement"] in ("rigid", "similarity"):
        prior, X, tree_xd = rigid if tried[-1]["placement"] == "rigid" else moments
        tree_x = cKDTree(X)
    if seeds is None and settings.local:
        seeds, local = _seed_windows(X, Y, tree_xd, dx, tree_y, by_identity[:IDENTITY_WINDOWS], identity,
                                     margin, settings, window_points, report, tried, "identity")
    coarse = None
    if seeds is None:
        report(0.1, f"coarse solve on {si.size} x {ti.size} points")
        t0 = time.perf_counter()
        sampling = 0.5 * coarse_spacing / 3.5
        coarse_settings = replace(settings, noise=float(np.hypot(settings.noise or 0.0, sampling)),
                                  gate=None, smoothing=None, parts=False,
                                  prealign=False if prior is not None else settings.prealign)
        coarse = _register_direct(X[si], Y[ti], coarse_settings, lambda *a: None, time.perf_counter())
        info.update(coarse_hypothesis=coarse.info.get("hypothesis"), coarse_support=coarse.support,
                    time_coarse_s=time.perf_counter() - t0)
        if coarse:  # identity windows already failed: place by the coarse warp
            order = _window_order(X, X[si[coarse.correspondences[:, 0]]], core, MAX_WINDOWS)
            seeds, local = _seed_windows(X, Y, tree_xd, dx, tree_y, order, coarse.warp, margin, settings,
                                         window_points, report, tried, "coarse")
        else:  # nothing to place by: the identity's other windows
            seeds, local = _seed_windows(X, Y, tree_xd, dx, tree_y, by_identity[IDENTITY_WINDOWS:], identity,
                                         margin, settings, window_points, report, tried, "identity")
    info.update(coarse_points=(int(si.size), int(ti.size)), coarse_spacing=coarse_spacing,
                windows=tried, placement=tried[-1]["placement"] if seeds is not None else None)
    if seeds is None:
        info["verdict"] = _window_verdict(tried)
        info["time_s"] = time.perf_counter() - t_start
        report(1.0, "done: no window beats chance")
        return _failure("no full-resolution window has more locally consistent matches than chance",
                        info)
    info["hypothesis"] = local.info.get("hypothesis")
    # one non-rigid motion is continuous: grow from the seeds' largest part that is connected in
    # the source and moves continuously (segment.motion_parts); a few wrong seeds apart from it
    # would otherwise grow a locally consistent wrong region (a slide along the surface)
    gate = 0.5 * spacing + floor
    # half the local spacing where the target is sampled more sparsely than the median (a body's
    # limbs against its face and hands)
    gates = ms.local_gates(Y, tree_y, gate, floor, rows=dy)
    if seeds.shape[0] >= 4:
        parts = ms.motion_parts(X[seeds[:, 0]], Y[seeds[:, 1]], settings.strain, gates[seeds[:, 1]])
        info["n_seeds_off_part"] = int(np.sum(parts != 0))
        seeds = seeds[parts == 0]

    # 4. growth, polish, final local matching within the sampling gate, local eq. 41
    spacing_x = median_spacing(X[dx])  # the growth's step, the same in every round
    report(0.5, f"growth from {seeds.shape[0]} seeds")
    t0 = time.perf_counter()
    pairs = ms.grow(X, Y, tree_y, seeds, gates, spacing=spacing_x, tree_x=tree_x,
                    report=lambda f, m: report(0.5 + 0.3 * f, m))
    info.update(n_seeds=int(seeds.shape[0]), n_grown=int(pairs.shape[0]),
                time_growth_s=time.perf_counter() - t0)
    # seeds in every part: the rows the first growth left uncovered (a limb past a joint that
    # turned) are searched again by rigid windows and grown over what no part holds
    t0 = time.perf_counter()
    report(0.8, "part windows")
    found = seed_parts(X, Y, tree_x, tree_y, dx, dy, pairs, gate=gates, spacing=spacing,
                       spacing_x=spacing_x, least=max(4.0, MIN_SHARE * min(dx.size, dy.size)),
                       strain=settings.strain, seed=settings.seed, noise=settings.noise)
    pairs = found.pairs[np.argsort(found.pairs[:, 0], kind="stable")]
    info.update(part_windows=list(found.windows), n_part_growths=int(found.growth.max()),
                time_part_windows_s=time.perf_counter() - t0)
    report(0.85, "final local matching")
    refined = ms.refine(X, Y, tree_y, ms.LocalAffineWarp(X[pairs[:, 0]], Y[pairs[:, 1]] - X[pairs[:, 0]]),
                        spacing, spacing, floor, max_iter=2, local=gates)
    if refined.pairs.shape[0] >= 4:
        pairs = refined.pairs
    # grow again from the polished matches: their warp predicts the rows past a strongly bent
    # joint better than the first growth's did; until a round adds under REGROW_GAIN of them
    rounds = 0
    # off-surface matches are dropped once: on_surfaces is not idempotent (the planes and the median
    # height change with the matches it drops, and a second pass drops more)
    filtered = False
    while rounds < REGROW_ROUNDS and pairs.shape[0] >= 4:
        rounds += 1
        grown = ms.grow(X, Y, tree_y, pairs, gates, spacing=spacing_x, tree_x=tree_x)
        again = ms.refine(X, Y, tree_y, ms.LocalAffineWarp(X[grown[:, 0]], Y[grown[:, 1]] - X[grown[:, 0]]),
                          spacing, spacing, floor, max_iter=2, local=gates)
        if again.pairs.shape[0] < 4:
            break
        kept = _on_surfaces(X, Y, again.pairs, gates, info)
        gain = kept.shape[0] - pairs.shape[0]
        pairs, filtered = kept, True
        if gain < REGROW_GAIN * pairs.shape[0]:
            break
    info["regrow_rounds"] = rounds
    if not filtered:
        pairs = _on_surfaces(X, Y, pairs, gates, info)
    # matches no farther from the local affine trend than 8 median residuals (as the seeds on
    # exact data): a match shifted by one sample stands out by about a spacing
    res = ms.loo_affine_residuals(X[pairs[:, 0]], Y[pairs[:, 1]] - X[pairs[:, 0]])
    if res.size:
        g = gates[pairs[:, 1]]  # 8 median residuals, scaled where the local gate is wider
        keep = res <= np.minimum(g, (8.0 * float(np.median(res)) + floor + 1e-9 * spacing) * g / gate)
        if keep.sum() >= 4:
            info["n_trend_rejected"] = int((~keep).sum())
            pairs = pairs[keep]
    passed, R, t = ms.local_eq41_pairs(X, Y, pairs, settings.strain, gates[pairs[:, 1]])
    info.update(n_eq41_rejected=int((~passed).sum()), gate=gate, spacing=spacing)
    pairs, R, t = pairs[passed], R[passed], t[passed]
    if prior is not None:  # local rigid motions of the original source points
        _, R, t = ms.local_eq41_pairs(X0, Y, pairs, settings.strain, gates[pairs[:, 1]])
    _add_parts(info, X0[pairs[:, 0]], Y[pairs[:, 1]], spacing, floor, settings.seed)
    info["verdict"] = dict(_window_verdict(tried), support=int(pairs.shape[0]))
    info["verdict"].update(passed=info["verdict"]["support"] >= info["verdict"]["chance"],
                           margin=info["verdict"]["support"] / max(info["verdict"]["chance"], 1e-300))
    info["time_s"] = time.perf_counter() - t_start
    report(1.0, "done")
    return NonRigidMotion(pairs, X0[pairs[:, 0]], Y[pairs[:, 1]], R, t, 0.0,
                          local.diagnostics, info)


#: Growth-and-polish rounds after the first polish, at most (a body's shoulders: R 0.900 with
#: none, 0.911 with one, 0.927 with three).
REGROW_ROUNDS = 5
#: ... stopped when a round adds fewer than this share of the matches.
REGROW_GAIN = 0.005
#: Full-resolution windows tried with the coarse solve's placement before the path gives up.
MAX_WINDOWS = 4
#: Identity-placed windows tried before the coarse solve (the centre of the structure, then
#: the farthest point from it): a near-identity warp (faces, small strains) needs no coarse solve.
IDENTITY_WINDOWS = 2
#: A window's direct solve gives the seeds when it matches this share of its smaller set.
MIN_WINDOW_SHARE = 0.15


def _identity(p):
    return np.array(p, dtype=float)


def _explained(points, tree, gate: float) -> int:
    """How many of ``points`` have a row of ``tree`` within ``gate``: the share of the coarse sets
    that a placement (the identity, a rigid motion) already explains."""
    d = tree.query(points, k=1, distance_upper_bound=gate)[0]
    return int(np.isfinite(d).sum())


def _core(X, dx, tree_xd, si) -> np.ndarray:
    """The rows of the coarse subsample ``si`` whose 8th neighbour among the structure's rows ``dx``
    is at most the median such distance of ``si``: window centres on the structure, not among the
    outliers that pass :func:`multiscale.dense_rows` near it.  All of ``si`` when fewer than 8 rows."""
    if dx.size <= 9 or si.size < 2:
        return si
    r = tree_xd.query(X[si], k=9)[0][:, -1]
    core = si[r <= np.median(r)]
    return core if core.size >= 2 else si


def _seed_windows(X, Y, tree_x, rows_x, tree_y, centres, warp, margin: float, settings, window_points: int,
                  report, tried: list, placement: str):
    """The direct mode of section 5.1 on full-resolution windows at ``centres``, in order; the first
    whose result beats chance and matches ``MIN_WINDOW_SHARE`` of its smaller set gives the seeds.
    A window's source rows are the ``window_points`` rows of ``rows_x`` (``tree_x`` is their k-d
    tree) nearest the centre; its target rows all within that radius plus ``margin`` of the centre
    moved by ``warp``.  The global rigid start is off in a window; the local windows are not.

    Returns ``(seeds, local)``: seeds as (K, 2) rows of ``X``, ``Y`` and the window's
    :class:`NonRigidMotion`, or ``(None, None)``.  Appends one record per window to ``tried``.
    """
    k = min(rows_x.size, window_points)
    for c in centres:
        t0 = time.perf_counter()
        dist, near = tree_x.query(X[c], k=k)
        radius = float(np.atleast_1d(dist)[-1])
        src = np.sort(rows_x[np.atleast_1d(near)])
        moved = warp(X[c][None])[0]
        tgt = np.sort(np.asarray(tree_y.query_ball_point(moved, radius + margin), np.int64))
        report(0.05 + 0.05 * len(tried), f"window {len(tried) + 1} ({placement}): {src.size} x {tgt.size} points")
        record = {"placement": placement, "source": int(src.size), "target": int(tgt.size), "support": 0,
                  "local": settings.local}
        tried.append(record)
        if src.size < 4 or tgt.size < 4:
            continue
        # placed rows (the identity after any pre-alignment): each local patch against the targets
        # within the margin of it, the window's own assumption; a coarse warp moves only the centre
        reach = margin if warp is _identity else None
        local = _register_direct(X[src], Y[tgt], replace(settings, prealign=False, parts=False, local_reach=reach),
                                 lambda *a: None, time.perf_counter())
        record.update(support=local.support, hypothesis=local.info.get("hypothesis"),
                      verdict=local.info.get("verdict"),
                      time_voting_s=local.info.get("time_voting_s"), time_anneal_s=local.info.get("time_anneal_s"),
                      hypotheses=local.info.get("hypotheses"), time_s=time.perf_counter() - t0)
        if local and local.support >= MIN_WINDOW_SHARE * min(src.size, tgt.size):
            return np.column_stack([src[local.correspondences[:, 0]], tgt[local.correspondences[:, 1]]]), local
    return None, None


def _window_verdict(tried: list) -> dict:
    """``info["verdict"]`` of the multi-resolution path: the seeding window's (the last tried), or,
    with none seeding, the window closest to counting (by margin); over the windows tried."""
    ran = [r["verdict"] for r in tried if r.get("verdict")]
    if not ran:
        return chance_verdict(0, 4.0, max(len(tried), 1), method=VERDICT_METHOD).to_dict()
    best = ran[-1] if tried and tried[-1].get("verdict") and tried[-1]["verdict"]["passed"] else max(
        ran, key=lambda v: v["margin"])
    return dict(best, n_tested=float(max(len(tried), 1)))


def _window_order(X, matched, si, n: int) -> np.ndarray:
    """``n`` window centres among the coarse subsample ``X[si]``: the one nearest the centroid of
    ``matched`` (the coarse matches; the whole subsample when None) first, then spread out (farthest
    points), so a failed window is followed by a distant one."""
    base = X[si] if matched is None or len(matched) < 4 else matched
    centre = base.mean(axis=0)
    first = int(np.argmin(np.sum((X[si] - centre) ** 2, axis=1)))
    sub = X[si]
    sub = np.vstack([sub[first:first + 1], np.delete(sub, first, axis=0)])
    idx = np.r_[first, np.delete(np.arange(si.size), first)]
    spread = idx[farthest_points(sub, min(n, si.size))]
    return si[spread]
