"""Several motions between two real scans of a scene (section 5 on the scans pipeline).

Two scans of a scene in which several objects moved sample every surface
differently, so the point-to-point joint space of section 5 has no exact
planes; :func:`segment_scans` peels motions with the surface pipeline of
:func:`gatv.register` (``pipeline="scans"``, :mod:`gatv.scans`) instead,
one at a time, on the points no motion explains yet (the paper's "removed
its tokens ... and the process was repeated until no more planes were
found"):

1. **The identity first.** A static part of the scene (background, a
   table) is a motion like any other; it is tried explicitly, since a
   search draws its trials from the moving parts as readily as from it.
   Being one fixed motion, it must also beat itself displaced by a few
   gates (:func:`displaced_level`): clutter and crossing surfaces where the
   two scenes overlap explain nearly as much shifted as unshifted, a static
   part does not.  Its points then join the parts' connectivity only:
   explained, they are neither searched with an object resting on them nor
   counted by a later motion or by the chance level (a floor slides on
   itself).
2. **Peel.** The surface registration of ``register(pipeline="scans")``
   (:func:`register_part`) on the unexplained points, with each scan's
   surface points and normals voted once (:func:`scan_surfaces`); its
   motion labels every unexplained source point that lands within the
   sampling gate (a few point spacings) of an unexplained target point, at
   full input resolution; the one-to-one nearest pairs are its
   correspondences.
3. **Keep it only when it beats chance.** A random rigid motion that puts
   one unexplained source point onto one unexplained target point also
   brings some of the scene's surfaces within the gate where they cross;
   :func:`chance_support` measures the largest support of such motions on
   the points still unexplained (the sampling and clutter found in the
   data), and on the searched part alone (a small or thin part fits some
   target surface whole).  A motion is kept when its support exceeds both;
   otherwise the peeling stops (``info["reason"]``), so leftovers of
   partial overlap and clutter give nothing.
4. **Degenerate surfaces.** A motion whose supporting points lie on one
   plane (as thin as the scans' noise) slides along that plane with equal
   support, and a part that the search fits nearly as well by a distinct
   rival motion (``ambiguous``: it slides on a curved surface, or matches
   two) has no determined motion either: neither is kept, the plane is
   reported in ``info["degenerate"]`` (its points set aside, not peeled
   into a set of spurious motions), the other in ``info["ambiguous"]``.
   A plane that the identity explains (a floor, a wall) is kept as the
   static part and also listed as degenerate: a slide along it would fit
   as well.

Steps 2 to 4 are the search, accept, reject and remove steps of the one
peel loop, :func:`gatv.peel_loop.peel_loop`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numba import get_num_threads
from scipy.spatial import cKDTree
from scipy.stats import norm, poisson

from .. import stages
from .._icp_kernels import KDTree, screened_supports
from .._validation import (
    check_fraction,
    check_int,
    check_positive,
    check_progress,
    seed_int,
)
from ..candidates import median_spacing
from ..errors import InputError
from ..models.base import homogeneous
from ..models.rigid import MODEL as RIGID
from ..models.rigid.congruent import TargetGrid
from ..peel_loop import Candidate, Judgement, Stop, peel_loop
from ..scans import (
    PLANE_THICKNESS,
    local_scatter,
    match_surfaces,
    plane_noise,
    pooled_noise,
    surface_tokens,
    tangent_motions,
    thickness,
)
from ..verdict import chance_verdict
from ..voting import vote
from .segmentation import Segmentation

__all__ = [
    "NOISE_FACTOR",
    "PART_OPTIONS",
    "PLANE_THICKNESS",
    "SAMPLING_GATE",
    "DisplacedLevel",
    "ScanSurfaces",
    "chance_support",
    "coherent_pairs",
    "displaced_level",
    "local_noise",
    "register_part",
    "residual_noise",
    "scan_surfaces",
    "segment_scans",
    "thickness",
]

#: Gate of a scans motion's labels and correspondences, in target point
#: spacings: two samplings of one surface put a point's partner within
#: about one spacing, noise and the motion's error add to it.
SAMPLING_GATE = 3.0
#: Random motions drawn for the chance level (:func:`chance_support`).
N_CHANCE = 64
#: ... for a searched part's own level: its search keeps the best of some hundred
#: triples' motions, judged and polished, and on a leftover of clutter the best of 64
#: polished draws falls short of that now and then (the spread of their supports is
#: as large as their mean).
N_PART_CHANCE = 256
#: A motion's point-to-plane residuals (:func:`residual_noise`) may exceed the
#: scans' own noise at its points (:func:`local_noise`) by this factor: a
#: right motion leaves residuals at the noise (its own error and curvature
#: add a little), two surfaces that only resemble each other several times it.
NOISE_FACTOR = 2.5
#: Pairs the noise of a motion is measured on.
NOISE_SAMPLE = 2000
#: Source points the chance level is measured on (counts are scaled up).
CHANCE_SAMPLE = 4000
#: Source points every polished chance draw is first screened on; the
#: :data:`N_CHANCE_FINAL` best-ranked draws are then polished and counted on
#: :data:`CHANCE_SAMPLE` points, from their own starts.
CHANCE_SCREEN = 1000
N_CHANCE_FINAL = 8
#: A fixed motion (the identity) is compared with itself displaced by
#: :data:`DISPLACEMENT` sampling gates along this many evenly spread
#: directions (:func:`displaced_level`).
N_DISPLACED = 32
#: Displacement of :func:`displaced_level`, in sampling gates: far enough
#: that a matched surface leaves the counting radius (:data:`STATIC_GATE`
#: gates) for all directions but those within ``asin(STATIC_GATE /
#: DISPLACEMENT)`` of its own plane (an eighth of the sphere, which the
#: median ignores), near enough that the two scans' volumes overlap nearly
#: as much as undisplaced (the rest is extrapolated).
DISPLACEMENT = 4.0
#: Share of the sampling gate within which :func:`displaced_level` counts a
#: fixed motion's pairs: 1.5 spacings, where two samplings of one surface
#: put nearly every point's partner, while clutter and crossing surfaces
#: collect pairs in proportion to the gate's volume or width.
STATIC_GATE = 0.5
#: Source neighbours of :func:`displaced_level`'s coherence: a pair counts
#: when most of its point's neighbours are paired too (a matched surface is
#: paired all over, a crossing surface along a band, clutter here and there).
COHERENCE_NEIGHBOURS = 10
#: Standard deviations of the displaced counts the motion's count must
#: exceed their background by.  A veto on top of the family-wise chance level
#: the identity beat already, so a level of one test (one-sided, about 1e-3).
DISPLACED_Z = 3.0


def _random_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` rotations uniform over SO(3) (unit quaternions from a 4D Gaussian)."""
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], axis=1)


def _support(X: np.ndarray, tree: cKDTree | KDTree, R: np.ndarray, t: np.ndarray, gate: float,
             workers: int = 1) -> np.ndarray:
    """Which rows of ``X`` land within ``gate`` of a target point under ``(R, t)`` (``workers``: query threads)."""
    d, _ = tree.query(X @ R.T + t, k=1, distance_upper_bound=gate, workers=workers)
    return np.isfinite(d)


def _unit_normals(points: np.ndarray, tree: cKDTree, at: np.ndarray, k: int = 12) -> np.ndarray:
    """Unit normals at rows ``at`` of ``points``: least-variance axis of their ``k`` nearest neighbours."""
    return local_scatter(points, points[at], min(k, points.shape[0]), tree).normals


def chance_support(source: np.ndarray, target: np.ndarray, gate: float, *, n_draws: int = N_CHANCE,
                   tangent: bool = True, polish: int = 10, seed=0, tree: cKDTree | None = None,
                   sample: int = CHANCE_SAMPLE) -> int:
    """Largest support of ``n_draws`` wrong rigid motions that put a source point onto a target point.

    Each draw takes a random source point onto a random target point.  With
    ``tangent=True`` (what a search's wrong hypotheses look like: it matches
    triples of surface points with agreeing normals) the source's surface
    normal there is turned onto the target's, with a random sign and a random
    spin about it, so the two surfaces touch tangentially; otherwise the
    rotation is uniform over SO(3) (what one fixed hypothesis, such as the
    identity, is compared with; it also has to beat itself displaced,
    :func:`displaced_level`).  A draw's support is the number of
    source points landing within ``gate`` of a target point (counted on at
    most ``sample`` source points and scaled up): where the surfaces touch
    or cross, plus clutter, as for a wrong motion.  A plane that slides on
    itself reaches its full support.  Polished draws are ranked first on
    :data:`CHANCE_SCREEN` points; the :data:`N_CHANCE_FINAL` best are polished
    and counted on the whole sample from their own starts, so the level is
    that of all draws whenever the screen ranks the best one among them.
    Same seed, same level.
    """
    X = np.asarray(source, dtype=np.float64)
    Y = np.asarray(target, dtype=np.float64)
    if X.shape[0] < 4 or Y.shape[0] < 4:
        return 0
    rng = np.random.default_rng(seed)
    tree = cKDTree(Y) if tree is None else tree
    sub = X if X.shape[0] <= sample else X[rng.choice(X.shape[0], sample, replace=False)]
    scale = X.shape[0] / sub.shape[0]
    if tangent:
        starts = tangent_motions(X, Y, n_draws, rng, target_tree=tree)
    else:
        ia = rng.integers(0, X.shape[0], n_draws)
        ib = rng.integers(0, Y.shape[0], n_draws)
        rots = _random_rotations(rng, n_draws)
        starts = [(R, q - R @ p) for R, p, q in zip(rots, X[ia], Y[ib])]
    if not starts:
        return 0
    if not polish:
        best = max(int(np.count_nonzero(_support(sub, tree, R, t, gate))) for R, t in starts)
        return int(np.ceil(best * scale))
    # Each draw's point_icp(points, Y, ..., gate, polish) in one kernel, draws in parallel (nearest targets
    # from a grid of Y; the fit is the numba Kabsch, point_icp's to rounding).
    grid = TargetGrid.of(Y, gate)
    if len(starts) > N_CHANCE_FINAL and sub.shape[0] > CHANCE_SCREEN:
        # Screen every draw on a smaller sample; only the best-ranked few are polished
        # and counted on the whole sample (the maximum is decided among them).
        screen = sub[rng.choice(sub.shape[0], CHANCE_SCREEN, replace=False)]
        ranks = screened_supports(screen, grid, starts, gate, polish)
        starts = [starts[k] for k in np.argsort(ranks, kind="stable")[::-1][:N_CHANCE_FINAL]]
    return int(np.ceil(int(screened_supports(sub, grid, starts, gate, polish).max()) * scale))


def _sphere_directions(n: int) -> np.ndarray:
    """``n`` unit vectors spread evenly over the sphere (the Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (1.0 + np.sqrt(5.0)) * i
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def _near_rows(X: np.ndarray, neighbours: int) -> np.ndarray:
    """Rows of each point's ``neighbours`` nearest other points of ``X``."""
    return cKDTree(X).query(X, k=int(neighbours) + 1, workers=get_num_threads())[1][:, 1:]


def coherent_pairs(source: np.ndarray, tree: cKDTree, R: np.ndarray, t: np.ndarray, radius: float, *,
                   neighbours: int = COHERENCE_NEIGHBOURS, near_rows: np.ndarray | None = None) -> np.ndarray:
    """Which source points land within ``radius`` of a target point under ``(R, t)`` with most of their
    ``neighbours`` nearest source points: a matched surface is paired all over, a crossing surface
    along a band, clutter here and there (``near_rows``: those neighbours' rows, when known)."""
    X = np.asarray(source, dtype=np.float64)
    if X.shape[0] <= neighbours:
        return np.zeros(X.shape[0], bool)
    near_rows = _near_rows(X, neighbours) if near_rows is None else near_rows
    paired = _support(X, tree, np.asarray(R, dtype=np.float64), t, radius, workers=get_num_threads())
    return paired & (paired[near_rows].mean(axis=1) > 0.5)


@dataclass(frozen=True)
class DisplacedLevel:
    """A fixed motion's coherent pairs and the level they must exceed (:func:`displaced_level`).

    Attributes
    ----------
    support : int
        Source points within the counting radius of a target point under the
        motion, most of whose neighbours are too.
    level : int
        What the same motion displaced collects, plus the test's margin.
    """

    support: int
    level: int


def displaced_level(source: np.ndarray, tree: cKDTree, R: np.ndarray, t: np.ndarray, radius: float,
                    displacement: float, *, directions: int = N_DISPLACED, z: float = DISPLACED_Z,
                    neighbours: int = COHERENCE_NEIGHBOURS) -> DisplacedLevel:
    """Does a fixed motion ``(R, t)`` explain more than the overlap of the two scans?

    A fixed hypothesis such as the identity keeps the two scenes' clutter and
    their crossing surfaces where they overlap most, which random motions
    (:func:`chance_support`) move apart.  Its own null is the same motion
    displaced by ``displacement`` (data units, many times ``radius``): a
    static part falls out of the radius, the overlap of clutter and of
    crossing surfaces changes little.  Pairs are counted within ``radius``
    and only where most of a point's ``neighbours`` nearest source points are
    paired too (coherent: a matched surface is paired all over, a crossing
    surface along a band, clutter here and there).  Two boxes of clutter
    overlap most undisplaced and lose overlap linearly with the displacement,
    so the background at no displacement is extrapolated from two shells,
    ``2 m(D) - m(2D)``, where ``m(r)`` is the median count over ``directions``
    evenly spread displacements of length ``r``.  The level adds ``z``
    standard deviations of the counts at ``D``, taken from their lower
    quartile (a static plane slides along its own directions, which raises
    the upper tail only) and at least the Poisson deviation, and is at least
    the Poisson quantile of the same one-sided level.

    A veto, not a detector: a few coherent pairs where two surfaces cross
    pass it now and then, which the chance level of random motions
    (:func:`chance_support`), which the identity must beat as well, does not
    let through.
    """
    X = np.asarray(source, dtype=np.float64)
    if X.shape[0] <= neighbours:
        return DisplacedLevel(0, 0)
    near_rows = _near_rows(X, neighbours)

    def coherent(shift):
        return int(np.count_nonzero(coherent_pairs(X, tree, R, t + shift, radius, near_rows=near_rows)))

    units = _sphere_directions(int(directions))
    near = np.array([coherent(shift) for shift in float(displacement) * units])
    far = np.array([coherent(shift) for shift in 2.0 * float(displacement) * units])
    median = float(np.median(near))
    background = max(2.0 * median - float(np.median(far)), 0.0)
    spread = max((median - float(np.percentile(near, 25))) / 0.6745, np.sqrt(max(median, 1.0)))
    # at least the Poisson quantile of the same one-sided level, which small counts need
    floor = float(poisson.isf(norm.sf(float(z)), background))
    return DisplacedLevel(coherent(np.zeros(3)), int(np.ceil(max(background + float(z) * spread, floor))))


def local_noise(points: np.ndarray, at: np.ndarray, *, k: int = 10, tree: cKDTree | None = None) -> float:
    """Median scan noise at rows ``at`` of ``points``: residual deviation of each one's ``k + 1`` neighbours from their plane.

    ``sqrt(λ3 / (k - 2))`` of the neighbourhood's scatter (``k + 1`` points,
    three parameters of the plane), median over ``at``: the sensor noise
    along the surface normal, measured on one scan alone.
    """
    kk = min(int(k) + 1, points.shape[0])
    ev = local_scatter(points, points[at], kk, tree).eigenvalues
    return float(np.median(np.sqrt(np.maximum(ev[:, 0], 0.0) / max(kk - 3, 1))))


def residual_noise(X: np.ndarray, Y: np.ndarray, R: np.ndarray, t: np.ndarray, pairs: np.ndarray, *,
                   tree: cKDTree) -> float:
    """Robust deviation of the point-to-plane residuals of ``pairs`` under ``(R, t)``, per scan.

    ``1.4826 · MAD / sqrt(2)`` of ``(R x + t - y) · n_y`` with the target's
    local normals (as :func:`gatv.scans.plane_noise`): what
    :func:`local_noise` measures on each scan when the motion is right.
    """
    if pairs.shape[0] < 4:
        return float("inf")
    n = _unit_normals(Y, tree, pairs[:, 1])
    rows = np.arange(pairs.shape[0])
    return float(plane_noise(X[pairs[:, 0]] @ R.T + t, Y[pairs[:, 1]], n, np.stack([rows, rows], axis=1)))


def _pairs(X, Y, R, t, gate, src, tgt, tree):
    """One-to-one nearest pairs (indices into the full sets) of ``src`` landing within ``gate`` of ``tgt``."""
    rows = stages.nearest_pairs(X[src] @ R.T + t, tree, gate)
    return np.stack([src[rows[:, 0]], tgt[rows[:, 1]]], axis=1)


def regions(points: np.ndarray, link: float, *, min_points: int = 1) -> list[np.ndarray]:
    """Connected parts of a point set: points closer than ``link`` are joined; largest first.

    Returns the row indices of each part of at least ``min_points`` points.
    Objects of a scene are connected surfaces sampled at a few times less
    than ``link``; clutter falls apart into small parts.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = points.shape[0]
    if n == 0:
        return []
    pairs = cKDTree(points).query_pairs(link, output_type="ndarray")
    graph = coo_matrix((np.ones(pairs.shape[0]), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    counts = np.bincount(comp)
    order = np.argsort(-counts, kind="stable")
    by_comp = np.argsort(comp, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)])
    return [np.sort(by_comp[starts[c]:starts[c + 1]]) for c in order if counts[c] >= min_points]


@dataclass(frozen=True, eq=False)
class ScanSurfaces:
    """A scan's points on salient surfaces and their normals, voted once for every round.

    Attributes
    ----------
    points : (N, 3) ndarray
        The scan, projected onto its surfaces when it is noisier than its
        sampling (:func:`gatv.scans.surface_tokens`), else as given.
    mask : (N,) ndarray of bool
        Which rows of the scan lie on a salient surface (:func:`gatv.scans.surface_points`).
    normals : (N, 3) ndarray
        Their unit normals (rows off the surfaces: zero).
    noise : float
        The scan's noise along its surfaces (:func:`gatv.scans.scan_noise`).
    projected : int
        Points of each plane fit of the projection; 0 when not projected.
    """

    points: np.ndarray
    mask: np.ndarray
    normals: np.ndarray
    noise: float
    projected: int


def scan_surfaces(points: np.ndarray, *, clutter: bool = True, seed: int = 0,
                  memory_budget: float | None = None) -> ScanSurfaces:
    """Tensor voting on a whole scan once (section 3.3): its surface points and their normals.

    Every round of :func:`segment_scans` registers a subset of the scans (the
    points no motion explains yet); the surfaces and normals of the whole scan
    serve them all, so the voting is not repeated on each subset.  With
    ``clutter=False`` every point is kept, with the normals of one ball pass.
    A noisy scan is projected onto its surfaces first, as
    :func:`gatv.register` does (:func:`gatv.scans.surface_tokens`).
    """
    n = points.shape[0]
    tokens = surface_tokens(points, clutter=clutter, seed=seed, memory_budget=memory_budget)
    mask = np.zeros(n, bool)
    normals = np.zeros((n, 3))
    mask[tokens.rows] = True
    normals[tokens.rows] = tokens.normals if tokens.normals is not None else np.asarray(vote(tokens.points).normals)
    projected = 0 if tokens.projection is None else tokens.projection.neighbours
    return ScanSurfaces(tokens.points, mask, normals, tokens.noise.sigma, projected)


#: Tolerance on the normal invariants of a part's congruent triples (:func:`register_part`).
FEATURE_TOL = 0.15
#: A part whose best motion was rejected is searched once more with the tolerance on its normal
#: invariants this many times wider: where few points a voxel or much clutter make the normals poor
#: (true pairs' normals 20-40 degrees apart instead of 8-10), the true triples' matches were pruned.
WIDER_NORMALS = 2.0
#: Options of :func:`register_part` a user may set through ``scan_options``.
PART_OPTIONS = ("n_points", "voxel", "min_overlap", "feature_tol", "clutter")
#: Source points of the coarse levels of each round's point-to-plane polish
#: (:func:`gatv.scans.match_surfaces`' ``coarse_points``): they only bring the
#: motion within the next, halved gate, and a round's motion is judged again.
COARSE_SAMPLE = 2000


def register_part(X: np.ndarray, Y: np.ndarray, src: np.ndarray, tgt: np.ndarray, surf_x: ScanSurfaces,
                  surf_y: ScanSurfaces, *, seed: int = 0, confidence: float = 0.999,
                  max_triples: int | None = None, n_judged: int = 4, refine: bool = True,
                  memory_budget: float | None = None, n_points: int = 600, voxel: float | None = None,
                  min_overlap: float = 0.4, feature_tol: float = FEATURE_TOL, clutter: bool = True):
    """The surface registration of :func:`gatv.scans.register_surfaces` for rows ``src`` of ``X`` onto rows ``tgt`` of ``Y``.

    :func:`gatv.scans.match_surfaces` (voxel grid of about ``n_points``
    target cells, congruent triples pruned by the normals, tensor voting
    judges the best ``n_judged``, rivals polished and compared,
    point-to-plane ICP with a gate shrinking from a voxel to three point
    spacings) on the surface points and normals voted once on each whole
    scan (:func:`scan_surfaces`) instead of on every subset again.  A part
    is one object's share of the scene, so the triples are drawn for an
    overlap of ``min_overlap`` = 0.4 of it by default.

    Returns ``(R, t, info)`` with ``target ≈ R x + t``, or ``None`` with a
    reason in ``info`` when no trial motion is found.
    """
    if clutter:
        src = src[surf_x.mask[src]]
        tgt = tgt[surf_y.mask[tgt]]
    if src.size < 10 or tgt.size < 10:
        return None, {"reason": "too few surface points"}
    match = match_surfaces(X[src], Y[tgt], surf_y.normals[tgt], n_points=n_points, voxel=voxel, seed=seed,
                           min_overlap=min_overlap, confidence=confidence, max_triples=max_triples,
                           feature_tol=feature_tol, n_judged=n_judged, refine=refine,
                           memory_budget=memory_budget, coarse_points=COARSE_SAMPLE)
    keys = ("voxel", "n_downsampled", "triples", "congruent", "reason", "ambiguous", "rival", "final_gate",
            "on_surface")
    info = {k: match.info[k] for k in keys if k in match.info}
    return ((match.rotation, match.translation) if match else None), info


@dataclass(frozen=True, eq=False)
class _PartSearch:
    """One round's part and its search (a :class:`gatv.peel_loop.Candidate`'s detail)."""

    part: np.ndarray  # its source rows
    smallest: int  # the least support a part needs (the chance level among the unexplained points)
    feature_tol: float  # the tolerance on its triples' normal invariants
    found_info: dict  # register_part's diagnostics


def segment_scans(source, target, *, max_motions: int | None = None, seed=0, confidence: float = 0.999,
                  max_triples: int | None = None, n_judged: int = 4, refine: bool = True,
                  memory_budget: float | None = None, scan_options: dict | None = None,
                  progress=None) -> Segmentation:
    """Find every rigid motion between two real scans of a scene, K unknown.

    Parameters
    ----------
    source, target : (N, 3) array_like or object with ``.points``
        The two scans of the scene (clutter and parts seen in one only allowed).
    max_motions : int, optional
        Stop after this many motions (the identity counts when found).
    seed : int, default: 0
        Same seed, same result.
    confidence, max_triples, n_judged, refine, memory_budget
        As :func:`gatv.register` (scans pipeline).
    scan_options : dict, optional
        Options of every round's surface registration (:func:`register_part`,
        as in :func:`gatv.scans.register_surfaces`): :data:`PART_OPTIONS`.
    progress : callable, optional
        ``progress(fraction, message)``.

    Returns
    -------
    Segmentation
        Motions in the order found (the identity first when the scene has a
        static part); ``source_labels``/``target_labels`` at full
        resolution (``-1``: unexplained); ``tokens`` the correspondences.
        ``info["reason"]`` says why it stopped; ``info["degenerate"]``
        lists plane-like parts set aside, ``info["ambiguous"]`` parts whose
        motion a distinct rival fits nearly as well; ``info["rounds"]`` each
        round's support against its chance levels (a searched part's
        ``feature_tol``: the tolerance on its triples' normal invariants; a
        part whose motion is rejected is searched once more at
        :data:`WIDER_NORMALS` times it; ``chance``: the
        unexplained points'; ``part_chance``: the searched part's own;
        ``displaced``: once the identity beat ``chance``, its level against
        itself displaced, which its coherent ``static_support`` must exceed
        too, :func:`displaced_level`).
    """
    t_start = time.perf_counter()
    X = RIGID.check_points(source, "source")
    Y = RIGID.check_points(target, "target")
    max_motions = check_int(max_motions, "max_motions", 1, allow_none=True)
    n_judged = check_int(n_judged, "n_judged", 1)
    report = check_progress(progress)
    seed = seed_int(seed)
    options = dict(scan_options or {})
    unknown = sorted(set(options) - set(PART_OPTIONS))
    if unknown:
        raise InputError(f"Unknown `scan_options` {unknown} for segment on scans; choose from {list(PART_OPTIONS)}.")
    if "n_points" in options:
        options["n_points"] = check_int(options["n_points"], "scan_options['n_points']", 10)
    if options.get("voxel") is not None:
        options["voxel"] = check_positive(options["voxel"], "scan_options['voxel']")
    if "min_overlap" in options:
        check_fraction(options["min_overlap"], "scan_options['min_overlap']")
    if "feature_tol" in options:
        options["feature_tol"] = check_positive(options["feature_tol"], "scan_options['feature_tol']")
    n1, n2 = X.shape[0], Y.shape[0]
    clutter = bool(options.get("clutter", True))
    surf_x = scan_surfaces(X, clutter=clutter, seed=seed, memory_budget=memory_budget)
    surf_y = scan_surfaces(Y, clutter=clutter, seed=seed, memory_budget=memory_budget)
    X_in, Y_in = X, Y  # the points as given: the motions' rms is reported on them, as register does
    X, Y = surf_x.points, surf_y.points  # noisy scans projected onto their surfaces; rows as given
    spacing = median_spacing(Y)
    gate = SAMPLING_GATE * spacing
    tree_x, tree_y = cKDTree(X), cKDTree(Y)
    free_s = np.ones(n1, bool)
    free_t = np.ones(n2, bool)
    rounds, degenerate = [], []
    ambiguous = []  # (the entry of info["ambiguous"], the source points of its part)

    def judge(R, t, kind, src, extra, least=4):
        """The verdict on motion ``(R, t)`` for source points ``src`` of the unexplained ones.

        A plane is reported degenerate only when its support reaches ``least``,
        the size a part needs to be searched at all, and beats the chance level
        (fewer thin points are a sliver of some surface, not a plane of the
        scene).
        """
        tgt = np.flatnonzero(free_t)
        tree = KDTree(Y[tgt])  # the many nearest queries below (supports, displaced counts) in numba kernels
        inl = _support(X[src], tree, R, t, gate)
        support = int(np.count_nonzero(inl))
        searched = kind != "identity"
        chance = chance_support(X[np.flatnonzero(free_s & ~static_s)], Y[tgt], gate, seed=seed + len(rounds),
                                tree=tree, tangent=searched, polish=10 if searched else 0)
        displaced = None
        if not searched and support > chance:
            # One fixed motion: random motions move the source scene's volume off the target's, so it
            # also has to beat itself displaced, where the two scenes overlap as much.
            displaced = displaced_level(X[src], tree, R, t, STATIC_GATE * gate, DISPLACEMENT * gate)
        flat = thickness(X[src[inl]]) if support >= 4 else 0.0
        pairs = _pairs(X, Y, R, t, gate, src, tgt, tree)
        pick = pairs if pairs.shape[0] <= NOISE_SAMPLE else pairs[np.random.default_rng(seed).choice(
            pairs.shape[0], NOISE_SAMPLE, replace=False)]
        fit_noise = residual_noise(X, Y, R, t, pick, tree=tree_y)
        scan_noise = local_noise(X, pick[:, 0], tree=tree_x) if pick.shape[0] else float("nan")
        rec = dict(extra, kind=kind, support=support, chance=chance, thickness=flat, noise=fit_noise,
                   scan_noise=scan_noise, unexplained=(int(np.count_nonzero(free_s & ~static_s)), int(tgt.size)))
        if displaced is not None:
            rec["static_support"], rec["displaced"] = displaced.support, displaced.level
        rounds.append(rec)
        if searched and support > chance:
            # The search maximised the support over this part alone: a small or thin part (a strip
            # of surface that one scan sees, a few clutter points) fits some target surface whole,
            # which random motions of the whole pool do not show.  Its own chance level does.
            rec["part_chance"] = chance_support(X[src], Y[tgt], gate, n_draws=N_PART_CHANCE,
                                                seed=seed + len(rounds), tree=tree)
        if searched and support >= least and support > chance and flat <= PLANE_THICKNESS * scan_noise:
            verdict = "degenerate"
            degenerate.append({"points": support, "thickness": flat,
                               "centroid": X[src[inl]].mean(axis=0).tolist()})
            free_s[src[inl]] = False
            free_t[pairs[:, 1]] = False
        elif support <= max(chance, rec.get("part_chance", 0)) or (
                displaced is not None and displaced.support <= displaced.level):
            verdict = "chance"
        elif not fit_noise <= NOISE_FACTOR * scan_noise:
            verdict = "noise"
        elif searched and extra.get("ambiguous"):
            # A distinct rival motion fits the part nearly as well (gatv.scans.RIVAL_SHARE): the
            # part slides on a target surface or matches two of them; the data do not fix its motion.
            verdict = "ambiguous"
            ambiguous.append(({"points": support, "rival_angle_deg": extra.get("rival_angle_deg"),
                               "centroid": X[src[inl]].mean(axis=0).tolist()}, src))
        else:
            verdict = "kept"
            if not searched and flat <= PLANE_THICKNESS * scan_noise:
                # a static plane: any slide along it fits as well; the identity is reported
                degenerate.append({"points": support, "thickness": flat, "motion": "identity",
                                   "centroid": X[src[inl]].mean(axis=0).tolist()})
            level = max(chance, rec.get("part_chance", 0))
            draws = N_CHANCE + (N_PART_CHANCE if "part_chance" in rec else 0)
            kept.append((R, t, dict(extra, kind=kind, chance_support=chance, thickness=flat, noise=fit_noise,
                                    scan_noise=scan_noise,
                                    verdict=chance_verdict(support, level, draws, method="wrong motions").to_dict())))
            # every unexplained source point it explains, also beyond the part (an object cut in two)
            free = np.flatnonzero(free_s)
            mine = free[_support(X[free], tree, R, t, gate)]
            moved = X[mine] @ R.T + t
            d, _ = cKDTree(moved).query(Y[tgt], k=1, distance_upper_bound=gate)
            if searched:
                free_s[mine] = False
                free_t[tgt[np.isfinite(d)]] = False
            else:
                # The static part stays in the pool, for the connectivity of the parts only: moving
                # objects cross their old place and would be cut where they do.  It is explained,
                # so it is no evidence for any later motion (neither searched nor counted).
                static_s[mine] = True
        rec["verdict"] = verdict
        return verdict

    kept: list = []
    static_s = np.zeros(n1, bool)
    report(0.0, "identity (static part)")
    judge(np.eye(3), np.zeros(3), "identity", np.arange(n1), {})
    tried = np.zeros(n1, bool)  # source points of parts whose best motion was rejected
    widened = np.zeros(n1, bool)  # ... once, and searched again with wider normal invariants

    def search_part():
        """The largest unexplained part not set aside, registered (:func:`register_part`); or why none is left."""
        open_s = np.flatnonzero(free_s & ~tried)
        tgt = np.flatnonzero(free_t)
        # a part whose unexplained points are fewer than the chance level among them cannot beat it
        smallest = max(10, chance_support(X[np.flatnonzero(free_s & ~static_s)], Y[tgt], gate, seed=seed,
                                          n_draws=16, polish=0) if tgt.size >= 4 else 10)
        # Parts are connected over the pool (the static part included, so that an object resting
        # on it or crossing its old place stays whole); each is searched on the points of it that
        # no kept motion explains: an identity-explained floor under an object would otherwise be
        # searched (and counted) with it, and its slides compete with the object's motion.
        regs = [open_s[r] for r in regions(X[open_s], gate, min_points=smallest)] if open_s.size else []
        parts = sorted((p for p in (r[~static_s[r]] for r in regs) if p.size >= smallest), key=len, reverse=True)
        if not parts or tgt.size < 10:
            return Stop("no unexplained part of the scene is left that a motion could explain beyond the "
                        "chance level" if tgt.size >= 10 else "too few target points left", exhausted=True)
        part = parts[0]
        report(float(1.0 - open_s.size / n1), f"round {len(rounds)}: part of {part.size} points, "
                                              f"{open_s.size} source points left")
        feature_tol = options.get("feature_tol", FEATURE_TOL) * (WIDER_NORMALS if widened[part].any() else 1.0)
        found, found_info = register_part(X, Y, part, tgt, surf_x, surf_y, seed=seed + len(rounds),
                                          confidence=confidence, max_triples=max_triples, n_judged=n_judged,
                                          refine=refine, memory_budget=memory_budget,
                                          **dict(options, feature_tol=feature_tol))
        # The part's newest search decides: an ambiguity reported on an earlier search of it goes.
        ambiguous[:] = [(a, p) for a, p in ambiguous if np.isin(p, part).mean() <= 0.5]
        # found None: the part's search found nothing; the round is judged "none" (set aside below)
        return Candidate(found, 0, _PartSearch(part, smallest, feature_tol, found_info))

    def judge_part(candidate: Candidate) -> Judgement:
        """:func:`judge`'s verdict on the part's motion (``"none"`` when its search found nothing)."""
        d = candidate.detail
        if candidate.motion is None:
            rounds.append({"kind": "search", "part": int(d.part.size), "feature_tol": d.feature_tol,
                           "verdict": "none", "reason": d.found_info.get("reason", "")})
            return Judgement(False, "none")
        extra = {"part": int(d.part.size), "feature_tol": d.feature_tol, "ambiguous": d.found_info.get("ambiguous"),
                 "voxel": d.found_info.get("voxel")}
        if d.found_info.get("rival"):
            extra["rival_angle_deg"] = float(d.found_info["rival"]["angle_deg"])
        verdict = judge(*candidate.motion, "search", d.part, extra, least=d.smallest)
        return Judgement(verdict == "kept", verdict)

    def set_aside(candidate: Candidate, judgement: Judgement) -> None:
        """A rejected part is searched again once with wider normal invariants (:data:`WIDER_NORMALS`), then
        set aside; a degenerate one has left the pool already (:func:`judge`)."""
        if judgement.reason in ("none", "chance", "noise", "ambiguous"):
            part = candidate.detail.part
            if widened[part].all():
                tried[part] = True
            widened[part] = True
        return None

    def search_again(candidate: Candidate, judgement: Judgement) -> tuple:
        """The kept motion (:func:`judge`, shared with the identity's round, took its points out of the pool).

        The parts searched in vain so far are searched again: the kept motion's target
        points have left the pool, and with them the surfaces that a part's wrong motion
        laid it onto (an object searched before a larger one whose surfaces it also fits).
        """
        tried[:] = False
        return (kept[-1],)

    # the identity, when kept, counts toward max_motions
    outcome = peel_loop(search_part, judge_part, search_again, reject=set_aside,
                        max_motions=None if max_motions is None else max_motions - len(kept),
                        full="max_motions reached")
    reason = outcome.reason

    # Labels: each point to the kept motion that brings it closest to the other scan.
    src_lab = np.full(n1, -1, np.int64)
    tgt_lab = np.full(n2, -1, np.int64)
    if kept:
        dist = np.stack([tree_y.query(X @ R.T + t, k=1, distance_upper_bound=gate)[0] for R, t, _ in kept])
        best = np.argmin(dist, axis=0)
        src_lab = np.where(np.isfinite(dist[best, np.arange(n1)]), best, -1)
        dist_t = np.full((len(kept), n2), np.inf)
        for k, (R, t, _) in enumerate(kept):
            mine = np.flatnonzero(src_lab == k)
            if mine.size:
                dist_t[k] = cKDTree(X[mine] @ R.T + t).query(Y, k=1, distance_upper_bound=gate)[0]
        best_t = np.argmin(dist_t, axis=0)
        tgt_lab = np.where(np.isfinite(dist_t[best_t, np.arange(n2)]), best_t, -1)
    motions, tokens, token_labels = [], [], []
    for k, (R, t, extra) in enumerate(kept):
        src, tgt = np.flatnonzero(src_lab == k), np.flatnonzero(tgt_lab == k)
        pairs = _pairs(X, Y, R, t, gate, src, tgt, cKDTree(Y[tgt])) if tgt.size else np.empty((0, 2), np.int64)
        motions.append(stages.motion_result(RIGID, X_in, Y_in, stages.Fit(homogeneous(R, t), pairs),
                                            dict(extra, label=k, gate=gate)))
        c = pairs[np.argsort(pairs[:, 0], kind="stable")]
        tokens.append(c)
        token_labels.append(np.full(c.shape[0], k, np.int64))
    info = {"pipeline": "scans", "n_source": int(n1), "n_target": int(n2), "spacing": spacing, "gate": gate,
            "reason": reason, "rounds": rounds, "degenerate": degenerate, "ambiguous": [a for a, _ in ambiguous],
            "noise": pooled_noise(surf_x.noise, surf_y.noise),
            "scan_noise": (surf_x.noise, surf_y.noise), "projected": (surf_x.projected, surf_y.projected),
            "static": bool(motions) and motions[0].info.get("kind") == "identity",
            "time_s": time.perf_counter() - t_start}
    report(1.0, f"found {len(motions)} motions ({reason})")
    return Segmentation(tuple(motions), src_lab, tgt_lab,
                        np.vstack(tokens) if tokens else np.empty((0, 2), np.int64),
                        np.concatenate(token_labels) if token_labels else np.empty(0, np.int64), info)
