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

from .. import stages
from .._validation import check_positive
from ..errors import InputError
from ..registration import TIME_LIMIT, checked_pipeline, reject_exact_options
from .peeling import peel
from .result import Segmentation
from .scans import segment_scans
from .segmentation import GROUPINGS, NOISY_FROM, PROBE_TRIPLES, segment_problem

__all__ = ["segment"]


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
        (``grouping="peel"``, or ``"auto"`` on noisy sets), counted from
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
        ``info["reason"]`` says why the search stopped.

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
        out = segment_problem(P, noise=noise, grouping="graph" if grouping == "auto" else grouping, **common)
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
    return out
