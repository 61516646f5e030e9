"""Several motions between two point sets, whatever the data: :func:`segment`.

It validates and prepares the input once (:func:`gatv.stages.prepare`),
chooses the pipeline as :func:`gatv.register` does
(:func:`gatv.registration.resolve_pipeline`) and runs it: the scans
pipeline (:func:`gatv.motions.segment_scans`), the graph grouping of section
5 (:func:`gatv.motions.segmentation.segment_problem`), or motions peeled
one at a time (:func:`gatv.motions.peel`), as the model's
:class:`~gatv.models.SearchPolicy` says.  It sits above the modules of
those searches, none of which imports it.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from .. import stages
from .._validation import as_rng, check_positive
from ..errors import InputError
from ..registration import TIME_LIMIT, checked_pipeline, reject_exact_options, rival_draws
from .peeling import peel
from .result import Segmentation
from .scans import segment_scans
from .segmentation import GROUPINGS, NOISY_FROM, PROBE_TRIPLES, segment_problem

__all__ = ["drop_ambiguous", "segment"]


def segment(
    source,
    target,
    *,
    model="rigid",
    pipeline: str = "auto",
    max_motions: int | None = None,
    min_support: int | None = None,
    seed=0,
    noise: float | None = None,
    grouping: str = "auto",
    refine: bool = True,
    min_inlier_share: float = 0.03,
    confidence: float = 0.999,
    max_triples: int | None = None,
    max_judged: int = 32,
    sigma: float | None = None,
    max_candidates: int = 8,
    memory_budget: float | None = None,
    scan_options: dict | None = None,
    progress=None,
    time_limit: float | None = TIME_LIMIT,
) -> Segmentation:
    """Find every motion between ``source`` and ``target``, K unknown (section 5).

    Parameters
    ----------
    source, target : (N, 3) array_like or object with ``.points``
        The two point sets; any share of either may be outliers ((N, 2)
        for ``model="affine2d"``).
    model : {"rigid", "similarity", "affine2d"} or MotionModel, default: "rigid"
        The kind of each motion (:mod:`gatv.models`).  The rigid model runs
        the grouping of section 5 below; the others peel one motion at a
        time (:func:`gatv.motions.peel`).
    pipeline : {"auto", "exact", "scans"}, default: "auto"
        As :func:`gatv.register`: ``"scans"`` for dense, differently
        sampled range scans (:func:`gatv.motions.scans.segment_scans`: the
        identity first, then motions peeled with the surface pipeline, each
        kept only when it beats chance and fits at the scans' noise; planes
        reported as degenerate), ``"exact"`` for sets whose inliers are the
        same points in both; ``"auto"`` chooses from the data
        (:func:`gatv.registration.choose_pipeline`).  ``info["pipeline"]``
        and ``info["pipeline_reason"]`` say which and why.
    grouping : {"auto", "graph", "greedy", "peel"}, default: "auto"
        Exact pipeline, rigid model.  ``"graph"``: one trial search, then
        dense components of the eq.-41 graph inside each salient surface
        (the shared-axis split of eqs. 27–29); ``"greedy"``: each judged
        hypothesis's own correspondences; ``"peel"``: one motion at a time
        with the noise-aware search of :func:`gatv.register`
        (:func:`gatv.motions.peel` with ``noisy=True``: noise measured from
        each motion's residuals).  ``"auto"``: a short probe at the exact
        tolerance (:data:`PROBE_TRIPLES` triples); motions there mean
        noise-free data and ``"graph"``, none mean noise and ``"peel"``
        (given ``noise=``: ``"graph"`` at that noise).
    scan_options : dict, optional
        Options of each round's surface registration on scans
        (:data:`gatv.motions.scans.PART_OPTIONS`: ``n_points``, ``voxel``,
        ``min_overlap``, ``feature_tol``, ``clutter``, as in
        :func:`gatv.scans.register_surfaces`).
    time_limit : float or None, default: :data:`gatv.registration.TIME_LIMIT`
        Seconds of wall-clock time for the noisy point-set search
        (``grouping="peel"``, or ``"auto"`` on noisy sets) and for a model
        peeled at every noise (``"similarity"``, ``"affine2d"``), counted from
        the call; past it the motions found so far are returned and
        ``info["reason"]`` says that the time ran out.  As in
        :func:`gatv.register`, numba's compilation is not counted.
        ``None``: no bound.

    Other parameters are those of the exact pipeline's graph grouping
    (:func:`segment_points`); ``max_motions``, ``seed``, ``confidence``,
    ``max_triples``, ``refine`` and ``memory_budget`` apply to every path.

    Returns
    -------
    Segmentation
        Falsy (no motions) when no motion beats the chance level;
        ``info["reason"]`` says why the search stopped.  Exact pipeline,
        every model with turned copies (rigid, similarity, 2D affine): a
        motion that a turned or shifted copy of itself explains as well, on
        structured data, is dropped
        (:func:`drop_ambiguous`; ``info["ambiguous"]``, ``info["rivals"]``).

    Raises
    ------
    ValueError
        Bad points (as :func:`gatv.register`), ``max_motions < 1``,
        ``min_support < 3``, options of the exact pipeline when the data
        took the scans pipeline, or other bad options.

    Examples
    --------
    >>> from gatv.motions import fig12_scene, segment
    >>> scene = fig12_scene(seed=0)
    >>> seg = segment(scene.source, scene.target)
    >>> len(seg), sorted(m.support for m in seg)
    (3, [40, 40, 40])
    """
    t_call = time.perf_counter()
    time_limit = check_positive(time_limit, "time_limit", allow_none=True)
    chosen, why, checked = checked_pipeline(source, target, model, pipeline, memory_budget)
    if grouping not in GROUPINGS + ("auto", "peel"):
        raise InputError(f"Expected `grouping` to be one of {('auto',) + GROUPINGS + ('peel',)}, "
                         f"got {grouping!r}.")
    if chosen == "scans":
        reject_exact_options({"noise": noise, "sigma": sigma, "min_support": min_support,
                              "grouping": None if grouping == "auto" else grouping}, why)
        out = segment_scans(source, target, max_motions=max_motions, seed=seed, confidence=confidence,
                            max_triples=max_triples, refine=refine, memory_budget=memory_budget,
                            scan_options=scan_options, progress=progress)
        out.info.update(pipeline="scans", pipeline_reason=why)
        return out
    if scan_options:
        raise InputError("`scan_options` apply to the scans pipeline only; pass pipeline='scans'.")
    common = {"max_motions": max_motions, "min_support": min_support, "seed": seed,
              "refine": refine, "min_inlier_share": min_inlier_share, "confidence": confidence,
              "max_triples": max_triples, "max_judged": max_judged, "sigma": sigma,
              "max_candidates": max_candidates, "memory_budget": memory_budget, "progress": progress}
    P = stages.prepare(*(checked or (source, target)), model, validated=checked is not None)
    policy = P.model.search_policy()
    if not policy.graph_grouping or grouping in GROUPINGS or (grouping == "auto" and noise is not None):
        # A model without graph grouping is peeled (the time limit bounds that peel).
        out = segment_problem(P, noise=noise, grouping="graph" if grouping == "auto" else grouping, **common,
                              time_limit=None if time_limit is None
                              else max(time_limit - (time.perf_counter() - t_call), 1e-9))
    else:
        out = None
        if grouping == "auto":
            t0 = time.perf_counter()
            probe = segment_problem(P, noise=P.spacing * stages.NOISE_SCHEDULE[0],
                                    **dict(common, max_triples=min(max_triples or PROBE_TRIPLES, PROBE_TRIPLES),
                                           progress=None))
            if probe:
                out = segment_problem(P, noise=None, grouping="graph", **common)
            probe_s = time.perf_counter() - t0
        if out is None:
            schedule = policy.schedule
            if grouping == "auto":  # the probe found no exact motion: skip the exact levels
                schedule = tuple(r for r in schedule if r >= NOISY_FROM)
            out = peel(P, max_motions=max_motions, min_support=min_support, seed=seed, noise=noise,
                       refine=refine, min_inlier_share=min_inlier_share, confidence=confidence,
                       max_triples=max_triples, sigma=sigma, max_candidates=max_candidates,
                       memory_budget=memory_budget, noisy=True, schedule=schedule, progress=progress,
                       time_limit=None if time_limit is None
                       else max(time_limit - (time.perf_counter() - t_call), 1e-9))
            out.info["grouping"] = "peel"
        if grouping == "auto":
            out.info["probe_s"] = probe_s
    out.info.update(pipeline="exact", pipeline_reason=why)
    if policy.turned_copies:
        out = drop_ambiguous(P, out, as_rng(seed))
    return out


def drop_ambiguous(P: stages.Problem, seg: Segmentation, rng) -> Segmentation:
    """``seg`` less the motions a turned or shifted copy of themselves explains as well.

    Each motion is checked as :func:`gatv.register` checks its one
    (:func:`gatv.registration.rival_draws`, at the gate of its tolerance; the
    other motions found are not its rivals).  One that a rival holds
    alike is a lay of unrelated points (plane on plane, dense core on dense
    core, a lattice on itself) that the Poisson levels took for a motion:
    it is dropped and its points labelled as outliers.
    ``info["ambiguous"]`` lists the dropped (points, rival's angle and
    support); ``info["rivals"]`` every motion's figures, in order.
    """
    matrices = [m.as_matrix() for m in seg.motions]
    keep = list(range(len(seg.motions)))
    checks: dict = {}
    while True:
        # Motions found beside one are not its rivals, but a dropped one is: several wrong lays
        # of one structure would otherwise each be the others' best rival and all stay.
        for k in keep:
            m = seg.motions[k]
            tol = m.info.get("tolerance", seg.info.get("tolerance"))
            others = [matrices[j] for j in keep if j != k]
            checks[k] = rival_draws(P, matrices[k], m.correspondences, stages.gate(float(tol)), rng, others=others)
        left = [k for k in keep if not checks[k].ambiguous]
        if len(left) == len(keep):
            break
        keep = left
    seg.info["rivals"] = [checks[k].to_dict() for k in range(len(seg.motions))]
    seg.info["ambiguous"] = [{"points": int(seg.motions[k].support), "rival_angle_deg": checks[k].angle_deg,
                              "rival": checks[k].rival, "reason": checks[k].reason()}
                             for k in range(len(seg.motions)) if k not in keep]
    if not seg.info["ambiguous"]:
        return seg
    remap = np.full(len(seg.motions) + 1, -1, np.int64)  # index -1 stays -1
    remap[np.asarray(keep, np.int64)] = np.arange(len(keep))
    motions = tuple(replace(seg.motions[k], info={**seg.motions[k].info, "label": new})
                    for new, k in enumerate(keep))
    info = dict(seg.info)
    if not motions:
        info["reason"] = seg.info["ambiguous"][0]["reason"]
        info["verdict"] = {**info.get("verdict", {}), "passed": False}
    return Segmentation(motions, remap[seg.source_labels], remap[seg.target_labels], seg.tokens,
                        remap[seg.token_labels], info)
