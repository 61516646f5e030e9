"""Several overlapping rigid motions at once (paper section 5, Fig. 12).

Every rigid motion present among the candidate pairs is its own plane in
the ``{dx, dy, dz}`` joint space (eq. 30).  :func:`segment` finds all of
them, however many there are, and gives each point to at most one.

How it works
------------
1. **One trial search** (:mod:`gatv.models.rigid.congruent`): source triples matched to
   congruent target triples; *every* trial motion whose support beats
   chance and brings points no earlier trial explains is kept, not only
   the best one.  Triples are drawn from the unexplained source points
   only, so the pool shrinks as motions are found; the search stops by
   the RANSAC bound for the smallest motion wanted.
2. **One voting run per new surface.** Trials are taken best first; a
   trial whose inliers are already explained by an earlier hypothesis is
   skipped, the others are judged by tensor voting in the joint space of
   the trial-rotated source and eq. 41 (:func:`gatv.stages.judge`),
   so voting is never redone for a motion already found.
3. **Surfaces.** Hypotheses whose tokens lie on one eq.-30 plane (same
   axis and same translation along it) share one salient surface in
   ``{dx, dy, dz}`` — the ambiguity the paper points out in section 5.
4. **Eq. 41 inside each surface, as a graph** (``grouping="graph"``):
   tokens are nodes, eq.-41-consistent token pairs (with the surface's
   axis; no shared source or target point) are edges.  The tokens of one
   motion form a clique; two motions sharing axis and translation are not
   linked, since eq. 41 also demands that the pair distance be kept
   (Fig. 2 b/e).  Motions are read off as dense components: the
   ``k``-core (``k`` = support threshold − 1) is peeled from its
   highest-degree node's dense neighbourhood.
5. **Split by eqs. 27–29 and resolve conflicts.** Every token is given to
   the motion whose four joint-space planes (eqs. 27–30) it lies closest
   to.  For two motions on one shared eq.-30 plane the eq.-30 residuals
   are equal and the planes of eqs. 27–29, which differ through ``q0``,
   decide.  The four plane residuals of a token, squared and summed,
   equal its squared Euclidean residual ``|x' - R x - t|²``, so "closest
   planes" is "smaller residual".  Each motion's correspondences are made
   one-to-one, it is refitted, and a motion left with less support than a
   random motion would collect is dropped.

``grouping="greedy"`` replaces steps 3–4 by taking each judged
hypothesis's own correspondences (the alternative measured in
``benchmarks/motions.py``).

The support threshold comes from the data: the count a wrong motion
reaches by chance (:func:`gatv.models.rigid.congruent.chance_support`), at the
family-wise level over all hypotheses judged.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .. import stages
from .._validation import (
    as_rng,
    check_fraction,
    check_int,
    check_positive,
    check_progress,
)
from ..candidates import one_to_one
from ..models.rigid.congruent import n_triples_needed
from ..errors import InputError
from ..fitting import fit_rigid
from ..ga import (
    Rotor,
    eq41_length_residual,
    eq41_residual,
    joint_space_coordinates,
    joint_space_planes,
)
from ..models.base import homogeneous
from ..peel_loop import Candidate, Judgement, Stop, peel_loop
from ..stages import Fit, Problem
from ..verdict import Verdict, chance_verdict
from .peeling import peel
from .result import Segmentation

__all__ = ["Segmentation", "joint_space_residuals", "segment_points", "segment_problem"]

GROUPINGS = ("graph", "greedy")


# ------------------------------------------------------------------ helpers
def joint_space_residuals(source, target, pairs, rotation, translation) -> np.ndarray:
    """Residuals of candidate pairs to a motion's four joint-space planes.

    Parameters
    ----------
    source, target : (N, 3) ndarray
    pairs : (T, 2) ndarray of int
    rotation : (3, 3) ndarray
    translation : (3,) ndarray

    Returns
    -------
    (T, 4) ndarray
        Column ``k`` is ``n · u + c`` for the plane of eq. ``27 + k``
        (:func:`gatv.ga.joint_space_planes`) at the pair's coordinates
        ``u`` in that joint space.  With a unit rotor the row norm is the
        Euclidean residual ``|x' - R x - t|``; motions with one axis and
        one translation have equal eq.-30 residuals and differ in eqs. 27–29.
    """
    planes = joint_space_planes(Rotor.from_matrix(rotation), translation)
    u = joint_space_coordinates(source[pairs[:, 0]], target[pairs[:, 1]])
    return np.einsum("kj,ktj->tk", planes[:, :3], u) + planes[:, 3]


def _rt(fit: Fit):
    """Rotation and translation of a rigid ``fit``."""
    return fit.matrix[:3, :3], fit.matrix[:3, 3]


def _residual(P: Problem, pairs, fit: Fit) -> np.ndarray:
    return P.residuals(fit.matrix, pairs)


def _gated_pairs(P: Problem, fit: Fit, gate) -> np.ndarray:
    """Every pair ``(i, j)`` with ``|y_j - R x_i - t| <= gate`` (multiple matches too)."""
    R, t = _rt(fit)
    lists = P.tree.query_ball_point(P.source @ R.T + t, gate)
    counts = np.fromiter((len(x) for x in lists), np.int64, len(lists))
    i = np.repeat(np.arange(len(lists)), counts)
    j = np.fromiter((v for x in lists for v in x), np.int64, int(counts.sum()))
    return np.stack([i, j], axis=1)


def _axis(R) -> np.ndarray | None:
    """Unit rotation axis, ``None`` for (nearly) pure translation."""
    rv = Rotor.from_matrix(R)
    if rv.angle < 1e-6:
        return None
    return np.asarray(rv.axis, dtype=np.float64)


@dataclass(frozen=True, eq=False)
class Hypothesis:
    """A judged trial motion: its fit, every pair within its gate, its axis (None: translation)."""

    fit: Fit
    gated: np.ndarray
    axis: np.ndarray | None

    @classmethod
    def from_fit(cls, P: Problem, fit: Fit, gate: float) -> Hypothesis:
        return cls(fit, _gated_pairs(P, fit, gate), _axis(fit.matrix[:3, :3]))

    def on_plane(self, P: Problem, pairs, tau) -> np.ndarray:
        """Which ``pairs`` lie on this hypothesis's eq.-30 plane ``A · (d - t) = 0``."""
        d = P.target[pairs[:, 1]] - P.source[pairs[:, 0]]
        t = self.fit.matrix[:3, 3]
        if self.axis is None:  # pure translation: the "plane" is the cluster at t
            return np.linalg.norm(d - t, axis=1) <= tau
        return np.abs((d - t) @ self.axis) <= tau


@dataclass(frozen=True, eq=False)
class SearchOptions:
    """Bounds of the trial search and of the voting runs of :func:`segment`."""

    sigma: float | None
    max_candidates: int
    refine: bool
    max_trials: int
    max_judged: int
    chunk: int
    confidence: float
    max_triples: int
    min_points: float


@dataclass(frozen=True, eq=False)
class Trial:
    """A trial motion kept by the search, with the count of points it brings onto targets."""

    matrix: np.ndarray
    inliers: int


# ------------------------------------------------------------ trial stage
def _trial_search(P: Problem, index, tol, rng, threshold, opts: SearchOptions, log) -> list[Trial]:
    """One trial search that keeps every distinct trial motion beating chance.

    Triples are drawn in chunks from the source points no trial has
    explained yet, so the pool shrinks as motions are found and the share
    of the motions still hidden grows.  The search stops when, since the
    last new motion, enough triples were drawn to hit a motion of
    ``opts.min_points`` points in the pool with ``opts.confidence``
    (the RANSAC bound), or at ``opts.max_triples``.
    """
    gate = stages.gate(tol)
    n1 = P.source.shape[0]
    explained = np.zeros(n1, bool)
    found: list[Trial] = []
    drawn = since_new = n_congruent = 0
    beat = best = 0
    while drawn < opts.max_triples:
        pool = np.flatnonzero(~explained)
        if pool.size < max(3, threshold):
            break
        need = n_triples_needed(min(1.0, opts.min_points / pool.size), opts.confidence)
        if since_new >= need:
            break
        chunk = int(min(opts.chunk, opts.max_triples - drawn, need - since_new))
        trials = P.model.trial_motions(P.source[pool], index, eps=2.0 * gate, max_triples=max(chunk, 1),
                                       rng=rng, keep=opts.max_trials, max_matches=64,
                                       accept=np.iinfo(np.int64).max)
        drawn += trials.n_triples
        since_new += trials.n_triples
        n_congruent += trials.n_congruent
        if len(trials):
            best = max(best, int(trials.support[0]))
        for k, matrix in enumerate(trials.matrices):
            if trials.support[k] < trials.threshold:
                break
            beat += 1
            R0, t0 = matrix[:3, :3], matrix[:3, 3]
            d, _ = P.tree.query(P.source @ R0.T + t0, k=1, distance_upper_bound=gate)
            inl = np.isfinite(d)
            if np.count_nonzero(inl & ~explained) < threshold:
                continue  # nothing new: a trial already kept explains it
            explained |= inl
            found.append(Trial(matrix, int(np.count_nonzero(inl))))
            since_new = 0
    log.append({"tolerance": tol, "triples": drawn, "congruent": n_congruent, "beat_chance": beat,
                "kept": len(found), "best_support": best, "threshold": threshold, "n_tests": opts.max_judged})
    return found


def _hypotheses(P: Problem, trials: list[Trial], tol, threshold, opts: SearchOptions) -> list[Hypothesis]:
    """Judge each kept trial by tensor voting and eq. 41 (one voting run each)."""
    gate = stages.gate(tol)
    out = []
    explained = np.zeros(P.source.shape[0], bool)
    for trial in sorted(trials, key=lambda x: -x.inliers)[: opts.max_judged]:
        judged = stages.judge(P, trial.matrix, tol, sigma=opts.sigma, max_candidates=opts.max_candidates)
        if judged is None:
            continue
        fit = judged.fit
        if opts.refine:
            polished = stages.refine(P, fit, gate)
            if polished.support >= fit.support:
                fit = polished
        if np.count_nonzero(~explained[fit.correspondences[:, 0]]) < threshold:
            continue
        explained[fit.correspondences[:, 0]] = True
        out.append(Hypothesis.from_fit(P, fit, gate))
    return out


# --------------------------------------------------------- grouping stage
def _surfaces(P: Problem, hyps: list[Hypothesis], gate) -> list[list[int]]:
    """Group hypotheses whose tokens lie on one eq.-30 plane (union-find)."""
    parent = list(range(len(hyps)))

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    tau = 2.0 * gate
    for a in range(len(hyps)):
        for b in range(a + 1, len(hyps)):
            ha, hb = hyps[a], hyps[b]
            if (ha.axis is None) != (hb.axis is None):
                continue
            if (np.mean(ha.on_plane(P, hb.fit.correspondences, tau)) >= 0.9
                    and np.mean(hb.on_plane(P, ha.fit.correspondences, tau)) >= 0.9):
                parent[find(b)] = find(a)
    groups: dict[int, list[int]] = {}
    for a in range(len(hyps)):
        groups.setdefault(find(a), []).append(a)
    return list(groups.values())


def _eq41_graph(P: Problem, pairs, axis, tau):
    """Tokens as nodes, eq.-41-consistent token pairs as edges (networkx)."""
    import networkx as nx

    d = P.target[pairs[:, 1]] - P.source[pairs[:, 0]]
    s = P.target[pairs[:, 1]] + P.source[pairs[:, 0]]
    T = pairs.shape[0]
    G = nx.Graph()
    G.add_nodes_from(range(T))
    for a in range(T - 1):
        db, sb = d[a + 1:], s[a + 1:]
        if axis is None:  # pure translation: length preservation V · Vs = 0
            r = eq41_length_residual(db, sb, d[a], s[a])
        else:
            r = eq41_residual(db, sb, d[a], s[a], axis, normalize="length")
        shared = (pairs[a + 1:, 0] == pairs[a, 0]) | (pairs[a + 1:, 1] == pairs[a, 1])
        nb = np.flatnonzero((r <= tau) & ~shared) + a + 1
        G.add_edges_from((a, int(b)) for b in nb)
    return G


def _dense_components(P: Problem, G, pairs, threshold, gate) -> list[Fit]:
    """Motions as dense components: peel the k-core from its densest node.

    The one peel loop (:func:`gatv.peel_loop.peel_loop`) on the eq.-41
    graph: the search proposes the densest node's neighbourhood in the
    k-core, the accept step fits it (:func:`gatv.stages.fit_and_gate`) and
    keeps it when its support reaches ``threshold``; a kept motion's pairs
    and those sharing a point with them leave the graph, a rejected
    neighbourhood's nodes leave it too, and the peeling goes on until the
    core is smaller than ``threshold``.
    """
    import networkx as nx

    G = G.copy()
    k = max(int(threshold) - 1, 1)

    def search():
        if G.number_of_nodes() < threshold:
            return Stop("fewer graph nodes than a motion needs", exhausted=True)
        core = nx.k_core(G, k)
        if core.number_of_nodes() < threshold:
            return Stop("the k-core is smaller than a motion", exhausted=True)
        v = max(core.degree, key=lambda nd: (nd[1], -nd[0]))[0]
        C = list(core[v]) + [v]
        sub = core.subgraph(C)
        need = 0.5 * (len(C) - 1)
        C = np.asarray(sorted(u for u in C if sub.degree(u) >= need), np.int64)
        return Candidate(C, int(C.size))

    def accept(candidate: Candidate) -> Judgement:
        C = candidate.motion
        fit = stages.fit_and_gate(P, pairs, pairs[C], gate) if C.size >= 3 else None
        if fit is None or fit.support < threshold:
            return Judgement(False, "below the threshold")
        return Judgement(True, "kept", detail=fit)

    def set_aside(candidate: Candidate, judgement: Judgement) -> None:
        G.remove_nodes_from(candidate.motion.tolist())
        return None

    def remove(candidate: Candidate, judgement: Judgement) -> tuple[Fit]:
        fit = judgement.detail
        kept = fit.correspondences
        used_s, used_t = set(kept[:, 0].tolist()), set(kept[:, 1].tolist())
        G.remove_nodes_from([u for u in list(G.nodes) if int(pairs[u, 0]) in used_s
                             or int(pairs[u, 1]) in used_t])
        return (fit,)

    # a round that sets a neighbourhood aside takes its densest node at least out of the graph
    return list(peel_loop(search, accept, remove, reject=set_aside, max_rounds=G.number_of_nodes() + 1).found)


def _resolve(P: Problem, motions: list[Fit], tokens, threshold, gate, rounds=3):
    """Each token to the motion whose joint-space planes it lies closest to; one-to-one; refit.

    Returns the surviving fits and the token labels.
    """
    motions = list(motions)
    labels = np.full(tokens.shape[0], -1, np.int64)
    for _ in range(rounds):
        if not motions or tokens.shape[0] == 0:
            return [], np.full(tokens.shape[0], -1, np.int64)
        # (M, T) residual via the four joint-space planes (eqs. 27-30)
        res = np.stack([np.linalg.norm(joint_space_residuals(P.source, P.target, tokens, *_rt(f)), axis=1)
                        for f in motions])
        best = np.argmin(res, axis=0)
        rbest = res[best, np.arange(tokens.shape[0])]
        labels = np.where(rbest <= gate, best, -1)
        # a point belongs to at most one motion: the one explaining it best
        cost = np.where(labels >= 0, rbest, np.inf)
        keep_tok = one_to_one(tokens, cost)
        keep_tok = keep_tok[np.isfinite(cost[keep_tok])]
        new = []
        for m in range(len(motions)):
            sel = keep_tok[labels[keep_tok] == m]
            if sel.size < max(threshold, 3):
                continue
            pm = tokens[sel]
            R, t = fit_rigid(P.source[pm[:, 0]], P.target[pm[:, 1]])
            new.append(Fit(homogeneous(R, t), pm))
        changed = len(new) != len(motions) or any(
            a.correspondences.shape != b.correspondences.shape
            or not np.array_equal(a.correspondences, b.correspondences) for a, b in zip(new, motions))
        motions = new
        if not changed:
            break
    if not motions:
        return [], np.full(tokens.shape[0], -1, np.int64)
    res = np.stack([_residual(P, tokens, f) for f in motions])
    best = np.argmin(res, axis=0)
    labels = np.where(res[best, np.arange(tokens.shape[0])] <= gate, best, -1)
    return motions, labels


# ------------------------------------------------------------------ entry
#: Triples the exact probe of ``grouping="auto"`` draws: data without noise
#: shows its motions at the exact tolerance long before.
PROBE_TRIPLES = 20000
#: The noisy search skips the schedule's levels below this share of the
#: spacing once the exact probe found nothing: the level of 0.05 spacing
#: holds noise from there down to the probe's exact level.
NOISY_FROM = 0.04


def segment_points(
    source,
    target,
    *,
    model="rigid",
    max_motions: int | None = None,
    min_support: int | None = None,
    seed=0,
    noise: float | None = None,
    grouping: str = "graph",
    refine: bool = True,
    min_inlier_share: float = 0.03,
    confidence: float = 0.999,
    max_triples: int | None = None,
    max_judged: int = 32,
    sigma: float | None = None,
    max_candidates: int = 8,
    memory_budget: float | None = None,
    progress=None,
) -> Segmentation:
    """Every rigid motion between two point sets by the graph grouping of section 5 (exact pipeline).

    Parameters
    ----------
    source, target : (N, 3) array_like or object with ``.points``
        The two point sets; any share of either may be outliers ((N, 2)
        for ``model="affine2d"``).
    model : {"rigid", "similarity", "affine2d"} or MotionModel, default: "rigid"
        The kind of each motion (:mod:`gatv.models`).  The rigid model runs
        the grouping of section 5 below; the others peel one motion at a
        time (:func:`gatv.motions.peel`).
    max_motions : int, optional
        Cap on the number of motions returned (largest first). The number
        of motions is found from the data; this only caps it.
    min_support : int, optional
        Smallest number of correspondences a motion needs.  Default from
        the data: the support a random motion reaches by chance
        (:func:`gatv.models.rigid.congruent.chance_support`), at least 3.
    seed : int or numpy.random.Generator, default: 0
        Seed of the random triple sampling; same seed, same result.
    noise : float, optional
        Standard deviation of the point noise (data units).  Default: the
        schedule of :func:`gatv.register`, from exact to 5% of the point
        spacing.
    grouping : {"graph", "greedy"}, default: "graph"
        How tokens are grouped into motions: dense components of the
        eq.-41 graph inside each salient surface, or each judged
        hypothesis's own correspondences.
    refine : bool, default: True
        ICP polish of each hypothesis inside the noise gate.
    min_inlier_share : float, default: 0.03
        Smallest motion to be found, as a share of the source points: the
        trial search stops once, since its last new motion, it drew enough
        triples from the unexplained points to hit such a motion with
        ``confidence``.
    confidence : float, default: 0.999
    max_triples : int, optional
        Hard cap on the triples drawn per tolerance level (default 2e6).
    max_judged : int, default: 32
        Cap on the trial motions judged by tensor voting per search.
    sigma : float, optional
        Tensor-voting scale; default as in :func:`gatv.register`.
    max_candidates : int, default: 8
        Cap on candidate pairs per source point in a voting run.
    memory_budget : float, optional
        Bytes; inputs needing more fail at once.
    progress : callable, optional
        ``progress(fraction, message)``.

    Returns
    -------
    Segmentation
        Falsy (no motions) when no motion beats the chance level.

    Raises
    ------
    ValueError
        Bad points (as :func:`gatv.register`), ``max_motions < 1``,
        ``min_support < 3`` or other bad options.

    References
    ----------
    Reyes, Medioni & Bayro, IJCV 75(3) 2007: eqs. 27–30 (joint spaces),
    eq. 41 (the geometric constraint), section 5 (multiple motions).

    Examples
    --------
    >>> from gatv.motions import fig12_scene, segment_points
    >>> scene = fig12_scene(seed=0)
    >>> seg = segment_points(scene.source, scene.target)
    >>> len(seg), sorted(m.support for m in seg)
    (3, [40, 40, 40])
    """
    return segment_problem(stages.prepare(source, target, model), max_motions=max_motions,
                           min_support=min_support, seed=seed, noise=noise, grouping=grouping, refine=refine,
                           min_inlier_share=min_inlier_share, confidence=confidence, max_triples=max_triples,
                           max_judged=max_judged, sigma=sigma, max_candidates=max_candidates,
                           memory_budget=memory_budget, progress=progress)


def segment_problem(P: Problem, *, max_motions: int | None = None, min_support: int | None = None, seed=0,
                    noise: float | None = None, grouping: str = "graph", refine: bool = True,
                    min_inlier_share: float = 0.03, confidence: float = 0.999, max_triples: int | None = None,
                    max_judged: int = 32, sigma: float | None = None, max_candidates: int = 8,
                    memory_budget: float | None = None, progress=None,
                    time_limit: float | None = None) -> Segmentation:
    """:func:`segment_points` on a prepared :class:`~gatv.stages.Problem` (validated once by its caller).

    A model whose :class:`~gatv.models.SearchPolicy` has no
    ``graph_grouping`` is peeled one motion at a time (:func:`gatv.motions.peel`),
    within ``time_limit`` seconds (None: no bound) as that peel counts them.
    """
    t_start = time.perf_counter()
    if not P.model.search_policy().graph_grouping:
        return peel(P, max_motions=max_motions, min_support=min_support, seed=seed, noise=noise,
                    refine=refine, min_inlier_share=min_inlier_share, confidence=confidence,
                    max_triples=max_triples, sigma=sigma, max_candidates=max_candidates,
                    memory_budget=memory_budget, progress=progress, time_limit=time_limit)
    max_motions = check_int(max_motions, "max_motions", 1, allow_none=True)
    min_support = check_int(min_support, "min_support", 3, allow_none=True)
    noise = check_positive(noise, "noise", allow_none=True)
    if grouping not in GROUPINGS:
        raise InputError(f"Expected `grouping` to be one of {GROUPINGS}, got {grouping!r}.")
    check_fraction(min_inlier_share, "min_inlier_share")
    check_fraction(confidence, "confidence", open_high=True)
    max_judged = check_int(max_judged, "max_judged", 1)
    max_candidates = check_int(max_candidates, "max_candidates", 1)
    if sigma is not None:
        sigma = check_positive(sigma, "sigma")
    report = check_progress(progress)
    rng = as_rng(seed)
    levels = stages.tolerance_levels(P, noise)
    n1 = P.source.shape[0]
    max_triples = check_int(max_triples, "max_triples", 1, allow_none=True) or 2_000_000
    opts = SearchOptions(sigma=sigma, max_candidates=max_candidates, refine=bool(refine), max_trials=16,
                         max_judged=max_judged, chunk=8192, confidence=float(confidence),
                         max_triples=max_triples, min_points=max(3.0, float(min_inlier_share) * n1))
    info: dict = {"model": P.model.name, "n_source": n1, "n_target": int(P.target.shape[0]),
                  "spacing": P.spacing, "grouping": grouping}
    log: list = []
    index = None

    def threshold_fn(gate, n_tests=max_judged):
        if min_support is not None:
            return min_support
        return max(3, P.chance(gate, n_tests=n_tests))

    hyps: list[Hypothesis] = []
    level = 0
    tol = levels[0]
    for level, tol in enumerate(levels):
        gate = stages.gate(tol)
        if index is None:
            index = P.model.index(P.target, gate, memory_budget=memory_budget)
        else:
            index.set_radius(gate)
        report(level / len(levels), f"tolerance {tol:.3g}: trial search")
        trials = _trial_search(P, index, tol, rng, threshold_fn(gate), opts, log)
        if trials:
            hyps = _hypotheses(P, trials, tol, threshold_fn(gate), opts)
        if hyps:
            break
    gate = stages.gate(tol)
    threshold = threshold_fn(gate)
    info.update(tolerance=tol, support_threshold=threshold, trials=log)
    if not hyps:
        info.update(reason="no trial motion beat the chance level", time_s=time.perf_counter() - t_start,
                    verdict=stages.search_verdict(log).to_dict())
        return _empty(P, info)

    report(0.8, f"{len(hyps)} hypotheses: grouping")
    motions, tokens, labels, extra = _group(P, hyps, grouping, threshold, gate)
    info.update(n_hypotheses=len(hyps), **extra)

    # grow each motion's tolerance while its support grows beyond chance
    if noise is None and len(levels) > 1 and motions:
        grown = []
        top = level
        for fit in motions:
            fit, lv = stages.grow_tolerance(P, fit, levels, level)
            grown.append(fit)
            top = max(top, lv)
        if top > level:
            gate = stages.gate(levels[top])
            info["tolerance"] = levels[top]
            tokens = np.unique(np.vstack([tokens] + [_gated_pairs(P, f, gate) for f in grown]), axis=0)
            motions, labels = _resolve(P, grown, tokens, threshold, gate)

    order = sorted(range(len(motions)), key=lambda m: (-motions[m].support, m))
    if max_motions is not None:
        order = order[:max_motions]
    remap = np.full(len(motions) + 1, -1, np.int64)
    remap[np.asarray(order, np.int64)] = np.arange(len(order))
    labels = remap[labels]
    src_lab = np.full(n1, -1, np.int64)
    tgt_lab = np.full(P.target.shape[0], -1, np.int64)
    out, verdicts = [], []
    n_tests = 1.0 if min_support is not None else float(max_judged)
    for new, m in enumerate(order):
        fit = motions[m]
        kept = fit.correspondences
        src_lab[kept[:, 0]] = new
        tgt_lab[kept[:, 1]] = new
        verdicts.append(chance_verdict(fit.support, threshold, n_tests, method="poisson"))
        out.append(stages.make_result(P, fit, {"label": new, "verdict": verdicts[-1].to_dict()}))
    info["verdict"] = run_verdict(verdicts, log).to_dict()
    info["time_s"] = time.perf_counter() - t_start
    if max_motions is not None and len(motions) > max_motions:
        info.setdefault("reason", "max_motions reached")
    info.setdefault("reason", "the trial search drew, since its last new motion, enough triples to find a motion "
                              "of min_inlier_share of the points (the RANSAC bound); no further trial beat chance")
    report(1.0, f"found {len(out)} motions")
    return Segmentation(tuple(out), src_lab, tgt_lab, tokens, labels, info)


def run_verdict(verdicts: list[Verdict], tried: list) -> Verdict:
    """A segmentation's verdict: its weakest motion's (smallest margin), or, with none, the best
    support its search saw against that level (:func:`gatv.stages.search_verdict` on ``tried``)."""
    if verdicts:
        return min(verdicts, key=lambda v: v.margin)
    return stages.search_verdict(tried)


def _empty(P: Problem, info) -> Segmentation:
    return Segmentation((), np.full(P.source.shape[0], -1), np.full(P.target.shape[0], -1),
                        np.empty((0, 2), np.int64), np.empty(0, np.int64), info)


def _group(P: Problem, hyps: list[Hypothesis], grouping, threshold, gate):
    """Hypotheses → motions (fits), tokens and token labels."""
    tokens = np.unique(np.vstack([h.gated for h in hyps] + [h.fit.correspondences for h in hyps]), axis=0)
    extra: dict = {}
    if grouping == "greedy":
        cands = [h.fit for h in sorted(hyps, key=lambda h: -h.fit.support)]
        motions, labels = _resolve(P, cands, tokens, threshold, gate)
        return motions, tokens, labels, extra
    surfaces = _surfaces(P, hyps, gate)
    cands: list[Fit] = []
    split = []
    n_edges = 0
    for members in surfaces:
        big = max(members, key=lambda a: hyps[a].fit.support)
        axis = hyps[big].axis
        pairs = np.unique(np.vstack([hyps[a].gated for a in members]), axis=0)
        G = _eq41_graph(P, pairs, axis, 2.0 * gate)
        n_edges += G.number_of_edges()
        found = _dense_components(P, G, pairs, threshold, gate)
        if len(found) > 1:
            split.append({"hypotheses": len(members), "motions": len(found),
                          "angles_deg": [float(np.degrees(Rotor.from_matrix(f.matrix[:3, :3]).angle))
                                         for f in found]})
        cands.extend(found)
    cands.sort(key=lambda c: -c.support)
    motions, labels = _resolve(P, cands, tokens, threshold, gate)
    extra.update(n_surfaces=len(surfaces), shared_surfaces=split, graph_edges=n_edges)
    return motions, tokens, labels, extra
