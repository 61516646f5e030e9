"""Registration of real range scans (paper section 4.1, with its section-6 caveat).

Two scans of one object are sampled differently, so no source point has an
exact partner in the target (the paper's conclusion warns that this breaks
the point-to-point model).  :func:`register_surfaces` (what
:func:`gatv.register` runs for ``pipeline="scans"``, and what it chooses for
dense scans) makes the problem fit the method again:

1. **Surface tokens.** Tensor voting on the raw points (section 3.3 applied
   to the scans themselves) keeps the points that lie on salient surfaces
   and drops clutter; the ball pass gives each point its normal, as the
   paper does for its head and car models (section 4.1).
2. **Downsampling** both scans on one voxel grid, so that corresponding
   points are at most about a voxel apart: the joint-space plane becomes a
   "fuzzy" plane of that thickness.
3. **Trial motions** from congruent triples (:mod:`gatv.models.rigid.congruent`) with a
   side-length tolerance of one voxel, pruned by the normals: matched sides
   must agree in the rigid invariants ``|n_i·u|, |n_j·u|, |n_i·n_j|``
   (candidate pairs "that shared a relatively similar orientation only",
   section 4.1).  Scans have no uniform background, so the best-supported
   trials are judged after a fixed budget instead of a chance level.
4. **Tensor voting judges** the best trials in the ``{dx, dy, dz}`` joint
   space, eq. 41 verifies with the relaxed, voxel-sized tolerance, and a
   one-to-one least-squares fit follows (as :func:`gatv.register`).
5. **Point-to-plane ICP polish** (with the tensor-voting normals) with a
   gate shrinking from a voxel to a few point spacings.

In stage 1 each scan's noise is measured about its surface points
(:func:`scan_noise`), and a scan whose noise spans a few point spacings is
projected onto its surface (:func:`project_to_surface`) before the vote that
keeps its surface points: the ICP of stage 5 pairs each point with its
nearest neighbour, which in a noisy shell lies as often across the shell as
along the surface (:func:`surface_tokens`).
"""

from __future__ import annotations

import dataclasses
import functools
import time
from dataclasses import dataclass

import numpy as np
from numba import get_num_threads
from scipy.spatial import cKDTree

from . import stages
from ._fit_kernels import kabsch3
from ._icp_kernels import (
    KDTree,
    local_heights,
    nearest_heights,
    neighbourhood_axes,
    neighbourhood_noise,
    neighbourhood_normals,
    occupied_cells,
    plane_icp_many,
    plane_icp_parallel,
    screened_supports,
)
from ._validation import (
    as_points,
    as_vectors,
    check_fraction,
    check_int,
    check_nonnegative,
    check_positive,
    check_progress,
    seed_int,
)
from .candidates import median_spacing
from .models.rigid.congruent import TargetGrid, TargetIndex, n_triples_needed, trial_motions
from .errors import InputError
from .fitting import fit_rigid
from .ga import rotation_angle_deg, turn_about
from .models.base import homogeneous
from .models.rigid import MODEL as RIGID
from .motion import RigidMotion
from .verdict import Verdict, wrong_motion_verdict
from .voting import extract_surfaces, vote

__all__ = [
    "LocalScatter",
    "ScanNoise",
    "SourceFrame",
    "SurfaceMatch",
    "SurfaceProjection",
    "SurfaceTokens",
    "local_scatter",
    "match_points",
    "match_surfaces",
    "matching_voxel",
    "plane_noise",
    "point_icp",
    "pooled_noise",
    "project_to_surface",
    "refine_point_to_plane",
    "register_scans",
    "register_surfaces",
    "scan_noise",
    "spatial_order",
    "surface_points",
    "surface_rows",
    "surface_support",
    "surface_tokens",
    "surface_verdict",
    "voxel_downsample",
]


def _cell_keys(index: np.ndarray) -> np.ndarray:
    """One int64 per row of integer cell indices ``(i, j, k)``, in the rows' lexicographic order.

    Row-major over the indices' ranges, so sorting the keys sorts the cells
    as ``np.unique(index, axis=0)`` would, at a fraction of its cost; the
    rows themselves when the ranges' product would overflow.
    """
    index = index - index.min(axis=0)
    dims = index.max(axis=0) + 1
    if float(np.prod(dims.astype(np.float64))) >= 2.0**62:
        return index
    return (index[:, 0] * dims[1] + index[:, 1]) * dims[2] + index[:, 2]


def _unique_cells(index: np.ndarray, **options):
    """``np.unique`` of the cells of the rows of ``index`` (as :func:`_cell_keys`)."""
    keys = _cell_keys(index)
    return np.unique(keys, axis=0 if keys.ndim == 2 else None, **options)


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """Centroids of the points in each occupied cell of a grid of side ``voxel``."""
    pts = as_points(points, "points")
    voxel = check_positive(voxel, "voxel")
    key = np.floor((pts - pts.min(axis=0)) / voxel).astype(np.int64)
    _, inv, counts = _unique_cells(key, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    # Each cell's sum in the points' order, as np.add.at adds (and many times faster).
    out = np.stack([np.bincount(inv, weights=pts[:, k], minlength=counts.size) for k in range(3)], axis=1)
    return out / counts[:, None]


def _voxel_for(points: np.ndarray, n_points: int) -> float:
    """Voxel size leaving about ``n_points`` occupied cells (bisection in log scale)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    ext = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    lo, hi = ext / 2000.0, ext / 2.0
    for _ in range(24):
        mid = np.sqrt(lo * hi)
        n = occupied_cells(points, mid)
        if n > n_points:
            lo = mid
        else:
            hi = mid
        if hi / lo < 1.05:
            break
    return float(np.sqrt(lo * hi))


#: Radius of the neighbourhoods that measure a scan's noise, in noise
#: deviations: a ball this wide holds the noisy shell's whole thickness, so
#: the plane fit's residual is the noise, not the ball's own cut of the shell
#: (which a neighbourhood of a few spacings gives when the noise is wider).
NOISE_RADIUS = 5.0
#: Radius of the plane fits of :func:`project_to_surface`, in noise deviations.
PROJECTION_RADIUS = 3.0
#: Fewest neighbours within :data:`PROJECTION_RADIUS` deviations for a scan to
#: be projected: below it the noise is within the sampling and the fit would
#: only move each point towards a few others.
PROJECTION_MIN_NEIGHBOURS = 6
#: Most points one plane fit uses; a denser neighbourhood is drawn from a
#: random subsample of the scan (same radius, bounded cost).
FIT_POINTS = 128
#: Fewest points of a neighbourhood whose noise is measured about a quadric
#: (fewer: about its plane; a quadric's six parameters would fit the noise).
QUADRIC_POINTS = 32
#: Points of a scan whose neighbourhoods measure its noise.
NOISE_SAMPLE = 1000


@dataclass(frozen=True)
class ScanNoise:
    """A scan's noise along its surface normal, and the neighbourhood that measured it.

    Attributes
    ----------
    sigma : float
        Standard deviation of the points about their local surface (data units).
    neighbours : int
        Points (at the scan's full density) of the neighbourhoods that measured it.
    radius : float
        Their median radius, at least :data:`NOISE_RADIUS` ``sigma`` unless
        the neighbourhoods reached the whole scan.
    """

    sigma: float
    neighbours: int
    radius: float
    #: Points the measurement handled: those put into k-d trees and the neighbours fitted.
    work: int = 0

    @property
    def settled(self) -> bool:
        """Whether the neighbourhoods reached :data:`NOISE_RADIUS` deviations: on a surface they do, in
        a volume of scattered points they reach the whole set first and ``sigma`` is its own spread."""
        return self.radius >= NOISE_RADIUS * self.sigma


def _reference(points: np.ndarray, share: float, rng: np.random.Generator) -> np.ndarray:
    """A random ``share`` of the rows (all of them when ``share >= 1``)."""
    n = points.shape[0]
    if share >= 1.0:
        return points
    return points[rng.choice(n, max(FIT_POINTS + 1, round(n * share)), replace=False)]


@dataclass(frozen=True)
class LocalScatter:
    """The scatter of each query point's ``k`` nearest reference points (:func:`local_scatter`)."""

    #: (n, 3) means of the neighbourhoods.
    centroids: np.ndarray
    #: (n, k, 3) neighbours less their mean.
    offsets: np.ndarray
    #: (n, 3) eigenvalues of ``offsetsᵀ offsets``, ascending: sums of squares along each axis.
    eigenvalues: np.ndarray
    #: (n, 3, 3) the axes, ``axes[:, :, j]`` the unit eigenvector of ``eigenvalues[:, j]``.
    axes: np.ndarray
    #: (n,) distance to the farthest of the ``k`` neighbours.
    radius: np.ndarray

    @property
    def normals(self) -> np.ndarray:
        """(n, 3) least-variance axes: the normals of the neighbourhoods' least-squares planes."""
        return self.axes[:, :, 0]


def local_scatter(reference: np.ndarray, queries: np.ndarray, k: int, tree: cKDTree | None = None, *,
                  workers: int = 1) -> LocalScatter:
    """Principal axes of each query's ``k`` nearest ``reference`` points (local PCA).

    The least-variance axis is the normal of the neighbourhood's plane and
    its eigenvalue the squared residuals about it: the local surface fit of
    the normals, noise and planarity measures.  ``tree`` is a
    :class:`scipy.spatial.cKDTree` of ``reference`` (built when omitted);
    ``workers`` its query's threads.
    """
    reference = np.asarray(reference, np.float64)
    k = check_int(k, "k", 1)
    if k > reference.shape[0]:
        raise InputError(f"Expected `k` between 1 and the {reference.shape[0]} reference points, got {k}.")
    tree = cKDTree(reference) if tree is None else tree
    dist, nb = tree.query(queries, k=k, workers=workers)
    return LocalScatter(*_scatter_of(reference, nb), dist[:, -1])


def _scatter_of(reference: np.ndarray, nb: np.ndarray):
    """``(centroids, offsets, eigenvalues, axes)`` of :class:`LocalScatter` for the neighbour rows ``nb``."""
    local = reference[nb]
    centroid = local.mean(axis=1)
    local -= centroid[:, None, :]  # in place: ``local`` is the gather's own copy
    values, axes = np.linalg.eigh(np.matmul(local.transpose(0, 2, 1), local))
    return centroid, local, values, axes


def _plane_fits(points: np.ndarray, reference: np.ndarray, k: int, tree: cKDTree | KDTree | None = None, *,
                quadric: bool = False, residuals: bool = True):
    """Least-squares planes of each point's ``k`` nearest ``reference`` points.

    Returns ``(centroids, normals, residual sd, radius)`` per point.  The sd
    is robust, ``1.4826 · median |r|`` of the residuals ``r`` along the
    normal, scaled by ``sqrt(k / (k - p))`` for the fit's ``p`` parameters, so
    that a few clutter points in a neighbourhood do not count as noise.
    With ``quadric`` and at least :data:`QUADRIC_POINTS` points the residuals
    are taken about a quadric over the tangent plane (``p = 6``), so that
    the surface's curvature does not count either; else about the plane
    (``p = 3``).  The radius is the distance to the farthest neighbour.
    Without ``residuals`` the sd is None (the projection needs only the planes).
    """
    reference = np.ascontiguousarray(reference, dtype=np.float64)
    k = check_int(k, "k", 1)
    tree = cKDTree(reference) if tree is None else tree
    # numba's threads: a batch worker's share
    dist, nb = tree.query(points, k=k, workers=get_num_threads())
    nb, radius = np.ascontiguousarray(nb.reshape(-1, k), dtype=np.int64), dist.reshape(-1, k)[:, -1]
    # Accumulated in kernels, without gathering the (n, k, 3) neighbourhoods.
    centroid, _, axes = neighbourhood_axes(reference, nb, k)  # descending: axes[:, :, 2] is the normal
    normal = np.ascontiguousarray(axes[:, :, 2])
    if not residuals:
        return centroid, normal, None, radius
    sd = neighbourhood_noise(reference, nb, k, centroid, axes, radius, bool(quadric and k >= QUADRIC_POINTS))
    return centroid, normal, sd, radius


def scan_noise(points, *, at=None, seed: int = 0, trees: dict | None = None) -> ScanNoise:
    """A scan's noise along its surface, measured at the scale the noise itself sets.

    Local fits of growing neighbourhoods (8, 16, 32, ... points) about
    :data:`NOISE_SAMPLE` of the scan's points: the median of their robust
    residual deviations (:func:`_plane_fits`, about a quadric from
    :data:`QUADRIC_POINTS` points on) for the first neighbourhoods whose
    median radius reaches :data:`NOISE_RADIUS` times it.  A fixed
    neighbourhood of a few spacings cuts a shell thicker than itself and
    measures its own size instead (a quarter to half of the noise at 4% of a
    bunny's radius).  In a volume of scattered points no neighbourhood
    settles (a ball's points deviate from any plane by 0.45 of its radius),
    and ``neighbours`` reaches the whole set.  Neighbourhoods above
    ``2 * FIT_POINTS`` points are drawn from a random subsample of the scan.
    A scan of more than ``NOISE_SAMPLE * 2 * FIT_POINTS`` points starts the
    doubling at the first neighbourhood drawn from at most that many (its
    k-d tree then holds no more points than the fits gather); where that
    step already settles, the steps below it are tried, each on a subsample
    twice as dense, until one does not, and the doubling runs from 8 points
    as for any scan once they would use every point.

    ``at``: rows of the points to centre the neighbourhoods on (for example
    the scan's surface points, :func:`surface_points`, so that clutter does
    not count as noise); every point is in the fits.  Pass all points, not
    the surface ones alone: tensor voting keeps a noisy scan's points near
    the surface and drops the rest, which halves the measured noise.

    ``trees``: a dict that receives the k-d trees the fits built (``"all"``:
    the whole scan's :class:`~gatv._icp_kernels.KDTree`, where one was), for
    a caller that searches the scan again.
    """
    pts = as_points(points, "points", min_points=4)
    n = pts.shape[0]
    rng = np.random.default_rng(seed)
    rows = np.arange(n) if at is None else np.asarray(at, dtype=np.int64)
    if rows.size == 0:
        rows = np.arange(n)
    at = pts[rows[rng.choice(rows.size, min(rows.size, NOISE_SAMPLE), replace=False)]]
    # A scan of more points than the fits gather (NOISE_SAMPLE neighbourhoods of 2 FIT_POINTS) starts
    # the doubling on a subsample of at most that many: its tree then costs no more than the fits.
    # Where that first step already settles, the noise may be finer: the step below, on a subsample
    # twice as dense, until one does not settle (the one above it is the answer); at every point
    # (2 FIT_POINTS and below) the doubling from 8.  Each step's subsample is the doubling's own.
    k = 8
    while k < n - 1 and n * min(1.0, 2 * FIT_POINTS / k) > NOISE_SAMPLE * 2 * FIT_POINTS:
        k *= 2
    trees = {} if trees is None else trees
    work = 0
    if k > 8:
        noise, settled = _noise_step(pts, at, rng, k, trees)
        work += noise.work
        if not settled:  # on up from the first step
            k *= 2
        else:
            while k // 2 > 2 * FIT_POINTS:  # down while the step below (on a subsample) settles
                finer, below = _noise_step(pts, at, rng, k // 2, trees)
                work += finer.work
                if not below:
                    return ScanNoise(noise.sigma, noise.neighbours, noise.radius, work)
                noise, k = finer, k // 2
            k = 8  # the steps below use every point: the doubling from 8
    while True:
        noise, settled = _noise_step(pts, at, rng, k, trees)
        work += noise.work
        if settled:
            return ScanNoise(noise.sigma, noise.neighbours, noise.radius, work)
        k *= 2


def _noise_step(pts: np.ndarray, at: np.ndarray, rng: np.random.Generator, k: int,
                trees: dict) -> tuple[ScanNoise, bool]:
    """One step of :func:`scan_noise`'s doubling: the noise of ``k``-point neighbourhoods (``work``: this
    step's), and whether it settled.

    ``trees`` keeps the whole scan's k-d tree once built, and each step's subsample: drawn from ``rng``
    in the doubling's order (512, 1,024, ... points) whatever order the steps run in, so that a step's
    subsample, and its noise, are those of the doubling from 8.
    """
    n = pts.shape[0]
    k = min(k, n - 1)
    if 2 * FIT_POINTS >= k:
        ref = pts
    else:
        step = 8  # the doubling's first step on a subsample
        while step <= 2 * FIT_POINTS:
            step *= 2
        while step < 2 * k:
            if min(step, n - 1) not in trees:
                trees[min(step, n - 1)] = _reference(pts, 2 * FIT_POINTS / min(step, n - 1), rng)
            step *= 2
        ref = trees[k]
    work = 0
    if ref is pts and "all" not in trees:
        trees["all"] = KDTree(pts)  # the whole scan's, built once for the neighbourhoods that use every point
        work += n
    if ref is pts:
        tree = trees["all"]
    else:
        tree = KDTree(ref)
        work += ref.shape[0]
    kk = min(ref.shape[0], max(4, round(k * ref.shape[0] / n)))
    work += at.shape[0] * kk
    _, _, sd, radius = _plane_fits(at, ref, kk, tree, quadric=True)
    sigma, r = float(np.median(sd)), float(np.median(radius))
    return ScanNoise(sigma, int(k), r, int(work)), r >= NOISE_RADIUS * sigma or k >= n - 1


@dataclass(frozen=True, eq=False)
class SurfaceProjection:
    """A scan's points moved onto their local surface, and its normals there."""

    points: np.ndarray  # (N, 3)
    normals: np.ndarray  # (N, 3) unit, unoriented
    neighbours: int  # points (at full density) of each plane fit
    work: int = 0  # points handled: the fits' k-d tree and the neighbours of every point projected


def project_to_surface(points, noise: ScanNoise, *, seed: int = 0, chunk: int = 4096,
                       rows=None) -> SurfaceProjection | None:
    """Moving least-squares projection onto the plane fitted within :data:`PROJECTION_RADIUS` noise deviations.

    Each point moves along the normal of the least-squares plane of its
    neighbours within about ``PROJECTION_RADIUS * noise.sigma`` (their count
    scaled from the neighbourhood that measured the noise: a surface holds
    points in proportion to the squared radius) onto that plane (the
    projection of Levin's MLS surfaces with a plane as the local
    approximation, Alexa et al. 2003).  The noise along the normal falls
    about as the square root of the points a fit uses; the fits' own
    curvature bias is alike in two scans of one surface.  ``None`` when
    fewer than :data:`PROJECTION_MIN_NEIGHBOURS` points fall within the
    radius: the noise is within the sampling, and the scan stays as it is.

    ``rows``: project only these rows (the planes still fitted to the whole
    scan); ``points`` and ``normals`` of the result are then those rows',
    each equal to its row of the whole scan's projection.
    """
    pts = as_points(points, "points", min_points=4)
    if not isinstance(noise, ScanNoise):
        raise InputError(f"Expected `noise` a ScanNoise (as `scan_noise(points)` returns), got {type(noise).__name__}.")
    n = pts.shape[0]
    moving = pts if rows is None else pts[np.asarray(rows, dtype=np.int64)]
    k = round(noise.neighbours * (PROJECTION_RADIUS * noise.sigma / max(noise.radius, 1e-300)) ** 2)
    k = min(k, n - 1)
    if k < PROJECTION_MIN_NEIGHBOURS:
        return None
    rng = np.random.default_rng(seed)
    ref = _reference(pts, min(1.0, FIT_POINTS / k), rng)
    kk = min(ref.shape[0], max(4, round(k * ref.shape[0] / n)))
    tree = KDTree(ref)
    out = np.empty_like(moving)
    normals = np.empty_like(moving)
    # The rows in the order of cells as wide as the fits' radius: consecutive queries then visit the
    # same leaves of the tree (in the scan's own order, random for a resampled scan, each query
    # fetches its leaves anew).  Each row's fit is its own, so the result is the same bit for bit.
    order = spatial_order(moving, PROJECTION_RADIUS * noise.sigma)
    for start in range(0, moving.shape[0], chunk):
        at = order[start:start + chunk]
        p = moving[at]
        centroid, normal, _, _ = _plane_fits(p, ref, kk, tree, residuals=False)
        out[at] = p - np.einsum("ij,ij->i", p - centroid, normal)[:, None] * normal
        normals[at] = normal
    return SurfaceProjection(out, normals, int(k), int(ref.shape[0] + moving.shape[0] * kk))


def spatial_order(points: np.ndarray, cell: float) -> np.ndarray:
    """A permutation of the rows of ``points`` that visits them cell by cell (cubes of side ``cell``).

    Lexicographic in the cells' integer coordinates: rows of one cell
    are consecutive, and consecutive cells adjacent along the last axis.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.shape[0] == 0:
        return np.arange(0)
    if not np.isfinite(cell) or cell <= 0:
        return np.arange(pts.shape[0])
    index = np.floor((pts - pts.min(axis=0)) / cell).astype(np.int64)
    return np.lexsort((index[:, 2], index[:, 1], index[:, 0]))


#: Chance at which :func:`surface_points` keeps, beside the paper's threshold relative to the most salient
#: token, a token whose ball pass is planar beyond what isotropic clutter of as many voters gives
#: (:func:`gatv.voting.chance_surfaceness`): a surface sampled more sparsely than the scan's densest one.
PLANAR_CHANCE = 0.01


def surface_points(points: np.ndarray, *, max_points: int = 60000, seed: int = 0,
                   memory_budget: float | None = None):
    """Points on salient surfaces and their normals, by tensor voting (section 3.3).

    One ball pass and one stick pass (:func:`~gatv.voting.extract_surfaces`);
    a token is kept by the paper's threshold relative to the most salient
    token, or where its ball votes are planar beyond what isotropic clutter
    of as many voters gives at :data:`PLANAR_CHANCE`, so that a surface
    sampled more sparsely than the scan's densest one is kept too.

    Parameters
    ----------
    points : (N, 3) ndarray
    max_points : int
        Larger inputs are voted on a random sample of this many rows (:func:`vote_sample`; voting cost is linear).
    memory_budget : float, optional
        Bytes; a voting run needing more fails at once.

    Returns
    -------
    indices : (K,) ndarray of int
        Indices into ``points`` of the surviving points (clutter and
        isolated points dropped), ascending.
    normals : (K, 3) ndarray
        Their unoriented unit normals (``e1`` of the final tensors).
    """
    pts = as_points(points, "points", min_points=3)
    pick = vote_sample(pts.shape[0], seed, max_points)
    if pick is None:
        pick = np.arange(pts.shape[0])
    surf = extract_surfaces(pts[pick], n_stick_passes=1, memory_budget=memory_budget, planar_chance=PLANAR_CHANCE)
    idx = np.asarray(surf.indices)
    order = np.argsort(idx, kind="stable")
    return pick[idx[order]], np.asarray(surf.normals)[order]


@dataclass(frozen=True, eq=False)
class SurfaceTokens:
    """One scan's surface tokens (:func:`surface_tokens`).

    Attributes
    ----------
    points : (N, 3) ndarray
        The scan's points, projected onto its surface when ``projection`` is not None.
    rows : (K,) ndarray of int
        Rows of ``points`` on salient surfaces (without clutter removal: all of them, or ``sampled``), ascending.
    normals : (K, 3) ndarray or None
        Their unit normals (None without clutter removal or projection: none computed).
    noise : ScanNoise
    projection : SurfaceProjection or None
    voted : int
        Points tensor voting ran on (each vote counted).
    sampled : (M,) ndarray of int or None
        The rows the pipeline worked on (:func:`vote_sample`), ascending; None: every row.
    tree : KDTree or None
        The k-d tree of every row of ``points`` where stage 1 built one (the noise's fits), else None.
    """

    points: np.ndarray
    rows: np.ndarray
    normals: np.ndarray | None
    noise: ScanNoise
    projection: SurfaceProjection | None
    voted: int = 0
    sampled: np.ndarray | None = None
    tree: KDTree | None = None


#: Most points of a scan that tensor voting, and so the whole scans pipeline past its noise, works on
#: (:func:`surface_points`' ``max_points``): larger scans are voted on a random subsample of this many.
VOTE_POINTS = 60000


def vote_sample(n: int, seed: int = 0, max_points: int = VOTE_POINTS) -> np.ndarray | None:
    """The rows of an ``n``-point scan that :func:`surface_points` votes on when it votes on at most
    ``max_points`` (None: all of them)."""
    if n <= max_points:
        return None
    return np.sort(np.random.default_rng(seed).choice(n, max_points, replace=False))


def surface_tokens(points: np.ndarray, *, clutter: bool = True, seed: int = 0,
                   memory_budget: float | None = None, all_points: bool = True,
                   max_points: int = VOTE_POINTS) -> SurfaceTokens:
    """Stage 1 of :func:`register_surfaces` for one scan: its noise, its surface, its points on salient surfaces.

    Tensor voting keeps the points on salient surfaces (``clutter=True``;
    all points otherwise); the noise is measured about them
    (:func:`scan_noise`); a scan noisier than its sampling is projected onto
    its surface (:func:`project_to_surface`) and voted on again, since the
    first vote drops the noisy points of a surface along with the clutter.

    ``all_points=False``: project only the rows the vote samples from a
    scan of more than :data:`VOTE_POINTS` points (:func:`vote_sample`; the
    others stay as given in ``points``), which are all that ``rows`` can
    hold: the same ``rows`` and the same points there, at a cost that stops
    growing with the scan beyond its noise (a 128-neighbour fit a point);
    without ``clutter``, ``rows`` are then that sample too.

    ``max_points``: the most rows voted on (and, with ``all_points=False``,
    projected and kept); a larger scan is sampled (:func:`vote_sample`, its
    rows in ``sampled``).
    """
    n = points.shape[0]
    voted = 0
    # The rows kept past the noise: the vote's sample where only those are kept, else every row (None).
    sample = None if all_points else vote_sample(n, seed, max_points)
    if clutter:
        rows, normals = surface_points(points, seed=seed, max_points=max_points, memory_budget=memory_budget)
        voted += min(n, max_points)
    else:
        rows, normals = (np.arange(n) if sample is None else sample), None
    trees: dict = {}
    noise = scan_noise(points, at=rows, seed=seed, trees=trees)
    projection = project_to_surface(points, noise, seed=seed, rows=sample)
    if projection is not None:
        if sample is None:
            points = projection.points
        else:
            points = np.array(points, dtype=np.float64)
            points[sample] = projection.points
        if clutter:
            rows, normals = surface_points(points, seed=seed, max_points=max_points, memory_budget=memory_budget)
            voted += min(n, max_points)
        else:
            normals = projection.normals  # of every row, or of the sample's (then ``rows``)
    # The noise's tree of every row, where the points it holds are still the scan's.
    tree = trees.get("all") if projection is None else None
    return SurfaceTokens(points, rows, normals, noise, projection, voted, sample, tree)


def refine_point_to_plane(source, target, target_normals, rotation, translation, gate, *,
                          iterations: int = 30, tree=None, tol: float = 1e-9, stall: float = 0.0):
    """Point-to-plane ICP (Chen & Medioni 1991) inside a distance gate.

    Minimises ``sum w ((R x + t - y) · n_y)²`` over nearest pairs within
    ``gate``, linearised in a small rotation about the pairs' centroid,
    with Huber weights at the gate's scale (iteratively reweighted).  Two
    different samplings of one surface have no exact point pairs; the
    distance to the target's tangent plane has none of that sampling bias.

    Stops after ``iterations``, or once a step moves the source by less
    than ``tol`` gates (its rotation at the farthest pair plus its
    translation), or once a step under ``stall`` gates moves it by more
    than half the step before (a slide that more steps only repeat; 0:
    never).  ``tree``: a :class:`gatv._icp_kernels.KDTree` of
    ``target`` when the caller refines against it often (built otherwise).
    Runs in one numba kernel (:func:`gatv._icp_kernels.plane_icp_parallel`, its queries in parallel).
    Returns ``(rotation, translation)``.
    """
    X = as_points(source, "source")
    Y = as_points(target, "target")
    N = as_vectors(target_normals, "target_normals", Y.shape[0])
    R = np.array(rotation, dtype=np.float64)
    t = np.array(translation, dtype=np.float64).reshape(-1)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise InputError(f"Expected `rotation` a finite (3, 3) matrix, got shape {R.shape}.")
    if t.shape != (3,) or not np.all(np.isfinite(t)):
        raise InputError(f"Expected `translation` a finite 3-vector, got shape {t.shape}.")
    gate = check_positive(gate, "gate")
    iterations = check_int(iterations, "iterations", 0)
    tol = check_nonnegative(tol, "tol")
    stall = check_nonnegative(stall, "stall")
    if not isinstance(tree, KDTree) or tree.points.shape != Y.shape:
        tree = KDTree(Y)
    return plane_icp_parallel(X, tree.points, N, *tree.nodes, R, t, float(gate), int(iterations), float(tol),
                              float(stall))


def _normals(points: np.ndarray) -> np.ndarray:
    return np.asarray(vote(points).normals)


def register_scans(source, target, **options) -> RigidMotion:
    """:func:`gatv.register` with ``pipeline="scans"`` (kept for existing code).

    Takes the options of :func:`register_surfaces`.
    """
    out = register_surfaces(source, target, **options)
    out.info.update(pipeline="scans", pipeline_reason="pipeline='scans' given")
    return out


#: The stages :func:`match_surfaces` times: ``info["t_<stage>"]`` (wall) and ``info["cpu_<stage>"]``
#: (process time, every thread), seconds from the start of the call at the stage's end.
STAGES = ("prepare", "trials", "judge", "polish", "verdict")


def _clock() -> tuple[float, float]:
    return time.perf_counter(), time.process_time()


def _stamp(info: dict, stage: str, start: tuple[float, float]) -> None:
    """``info["t_<stage>"]`` and ``info["cpu_<stage>"]``: wall and process time since ``start``."""
    info[f"t_{stage}"] = time.perf_counter() - start[0]
    info[f"cpu_{stage}"] = time.process_time() - start[1]


#: Rival motions within this share of the best support make the answer
#: ambiguous (a symmetric or nearly planar object).
RIVAL_SHARE = 0.8


def _rivals(best, others, voxel: float) -> list:
    """Judged trials distinct from the best yet nearly as well supported.

    A rival differs from the best by more than 5° or more than 3 voxels of
    translation and reaches :data:`RIVAL_SHARE` of its support among the
    downsampled points; symmetric objects and nearly planar surfaces give
    such rivals.  :func:`register_surfaces` polishes each as it does the
    best and reports ``info["ambiguous"]`` only when one still reaches
    :data:`RIVAL_SHARE` of the best's support at full resolution as a
    different motion (and takes it when it does better).
    """
    R0, t0 = best.matrix[:3, :3], best.matrix[:3, 3]
    out = []
    for fit in others:
        if fit.support < RIVAL_SHARE * best.support:
            break
        angle = rotation_angle_deg(fit.matrix[:3, :3] @ R0.T)
        if angle > 5.0 or float(np.linalg.norm(fit.matrix[:3, 3] - t0)) > 3.0 * voxel:
            out.append(fit)
    return out


#: The step along the direction a surface leaves freest (:func:`surface_symmetries`): the root-mean-square
#: displacement of the surface's points, as a share of their root-mean-square distance from its centroid
#: (about 9 degrees of a turn about an axis through the centroid).
SYMMETRY_STEP = 0.15

#: The turns about each principal axis of a surface that :func:`surface_symmetries` tries: a half-turn (every
#: axis of rotational symmetry of even order, and every continuous one, contains it) and a third of a turn.
SYMMETRY_TURNS = (np.pi, 2.0 * np.pi / 3.0)


def surface_symmetries(points, normals) -> tuple[list, list]:
    """Rigid motions ``(R, t)`` that may map the surface ``points`` onto itself: candidates, not checked.

    The rival a symmetric surface gives every motion found onto it: the
    motion composed with the surface's own symmetry explains the data as
    well (the exact path's :func:`gatv.registration.symmetry_rival`, for
    surfaces).  The candidates, for the caller to polish and count:

    * turns about the principal axes of ``points`` through their centroid
      (:data:`SYMMETRY_TURNS`).  An axis of rotational symmetry is a principal
      axis, so a surface of revolution, or one a half-turn or a third of a
      turn maps onto itself, has its symmetry among them;
    * a step of :data:`SYMMETRY_STEP` each way along the motion that moves the
      points least off their tangent planes: the least eigenvector of the
      point-to-plane stability matrix ``Σ J Jᵀ``, ``J = [q × n / L, n]`` (``q``
      about the centroid, ``L`` their RMS radius; Gelfand et al. 2003), as a
      screw.  A view of a surface of revolution or of an extrusion, whose
      axis is no principal axis of the view, slides along itself so.

    ``points``: (N, 3) points of one surface (the part of the target a
    motion covers); ``normals``: their (N, 3) unit normals.  Returns
    ``(turns, slides)``, two lists of ``(R, t)``; both empty for fewer than
    six points or points all at one place.
    """
    q = as_points(points, "points", min_points=0)
    n = as_points(normals, "normals", min_points=0)
    if n.shape[0] != q.shape[0]:
        raise InputError(f"Expected `normals` to have one row per point ({q.shape[0]}), got {n.shape[0]}.")
    if q.shape[0] < 6:
        return [], []
    c = q.mean(axis=0)
    q = q - c
    L = float(np.sqrt((q * q).sum(axis=1).mean()))
    if not L > 0.0:
        return [], []
    axes = np.linalg.eigh(q.T @ q)[1].T
    turns = [turn_about(a, angle, c) for a in axes for angle in SYMMETRY_TURNS]
    slides = []
    J = np.hstack([np.cross(q, n) / L, n])
    v = np.linalg.eigh(J.T @ J)[1][:, 0]
    w, b = v[:3] / L, v[3:]  # the twist about the centroid: rotation rate and the centroid's velocity
    rms = float(np.sqrt(((np.cross(w, q) + b) ** 2).sum(axis=1).mean()))
    if rms > 0.0:
        ww = float(w @ w)
        for sign in (1.0, -1.0):
            k = sign * SYMMETRY_STEP * L / rms
            if np.sqrt(ww) * abs(k) < 1e-6:  # a turn too small to place its axis: a slide
                slides.append((np.eye(3), b * k))
                continue
            # The screw: a turn by |w| k about the axis through c + w × b / |w|², and a slide along it.
            axis = w / np.sqrt(ww)
            R, t = turn_about(axis, np.sqrt(ww) * k, c + np.cross(w, b) / ww)
            slides.append((R, t + axis * (float(w @ b) / ww) * np.sqrt(ww) * k))
    return turns, slides


#: Default smallest share of the downsampled source points that have a
#: partner on the target: a view overlapping its target by 40% keeps about
#: that share among its surface points once a share of clutter survives the
#: surface test, so the triples are drawn for half of it (8x the triples a
#: share of 0.4 would need; the trials are a small part of a call's time).
MIN_OVERLAP = 0.2


def plane_noise(source, target, target_normals, pairs) -> float:
    """Point noise of each scan from point-to-plane residuals of matched pairs.

    The residual along the target's normal carries the noise of both
    scans, so ``1.4826 · MAD / sqrt(2)`` (a robust standard deviation, the
    median absolute deviation scaled for a Gaussian) estimates each scan's
    noise along the surface normal.  NaN without pairs.
    """
    if pairs.shape[0] == 0:
        return float("nan")
    r = np.einsum("ij,ij->i", source[pairs[:, 0]] - target[pairs[:, 1]], target_normals[pairs[:, 1]])
    mad = float(np.median(np.abs(r - np.median(r))))
    return 1.4826 * mad / np.sqrt(2.0)


def pooled_noise(source_sigma: float, target_sigma: float) -> float:
    """The two scans' noise as one figure: the root mean square of each one's (:func:`scan_noise`)."""
    return float(np.sqrt(0.5 * (source_sigma**2 + target_sigma**2)))


def register_surfaces(
    source,
    target,
    *,
    n_points: int = 600,
    voxel: float | None = None,
    seed: int = 0,
    min_overlap: float = MIN_OVERLAP,
    confidence: float = 0.999,
    max_triples: int | None = None,
    feature_tol: float = 0.15,
    n_judged: int = 4,
    refine: bool = True,
    clutter: bool = True,
    memory_budget: float | None = None,
    coarse_first: bool = True,
    progress=None,
) -> RigidMotion:
    """Register two real scans of one object, with no initial guess.

    Parameters
    ----------
    source, target : (N, 3) array_like or object with ``.points``
        The scans, possibly with clutter; they need only overlap partly.
    n_points : int, default: 600
        Points left in the target after voxel downsampling; sets the voxel
        size when ``voxel`` is not given (at least :data:`SAMPLING_VOXELS`
        point spacings of the more coarsely sampled scan, see
        :func:`matching_voxel`), and the rows of each scan the stages past
        its noise work on first (:func:`match_points`: 15,000 at the
        default).
    voxel : float, optional
        Voxel size (data units); the matching tolerance scale.
    seed : int or numpy.random.Generator, default: 0
        Seed of the subsamples and the triple sampling; same seed, same result.
    min_overlap : float, default: :data:`MIN_OVERLAP`
        Smallest share of downsampled source points expected to have a
        partner; sets the number of source triples drawn (with
        ``confidence``).
    confidence : float, default: 0.999
        Probability of drawing one source triple of overlapping points.
    max_triples : int, optional
        Hard cap on the source triples drawn.
    feature_tol : float, default: 0.15
        Tolerance on the normal invariants ``|n·u|`` and ``|n_i·n_j|``.
    n_judged : int, default: 4
        Best trial motions judged by tensor voting.
    refine : bool, default: True
        ICP polish at full resolution.
    clutter : bool, default: True
        Drop points off salient surfaces by tensor voting before matching.
    memory_budget : float, optional
        Bytes; a voting run or a congruent-triple index needing more fails
        at once (see :func:`gatv._validation.check_memory`).
    coarse_first : bool, default: True
        Without ``voxel``, try first on half the ``n_points`` cells, each
        scan sampled at half the density too (:func:`match_points` of them
        at :data:`COARSE_POINTS_PER_CELL`), with the adaptive search alone
        (:data:`SEARCHES`); a motion that passes the verdict there is the
        answer, and where none does the call goes on at ``n_points``
        (``info["coarse"]``: the coarse try's rows, cells and reason).  Its
        rivals are polished and judged as at ``n_points``, but for scans
        noisier than their sampling (projected, :func:`project_to_surface`):
        there a rival that does not end on the best leaves the pair to
        ``n_points``, whose twice as many rows polish the answer closer.  A
        motion that passes there against a rival keeping
        :data:`RIVAL_SHARE` of its support (``info["ambiguous"]``) is left
        to ``n_points`` too.
    progress : callable, optional
        ``progress(fraction, message)``.

    Returns
    -------
    RigidMotion
        ``target ≈ source @ rotation.T + translation``; ``correspondences``
        index the input points (one-to-one nearest pairs within the final
        gate, on the points kept as surface).  ``info`` has the voxel size,
        the target surface's median spacing (``target_spacing``) and stage
        timings (``t_<stage>`` wall and ``cpu_<stage>`` process seconds from
        the call's start at each of :data:`STAGES`' ends); ``noise`` (the
        two scans' noise, root mean square), ``scan_noise`` (each scan's, :func:`scan_noise`),
        ``projected`` (the points of each scan's plane fits, 0 when it was
        not projected, :func:`project_to_surface`) and ``residual_noise``
        (the point-to-plane residuals of the final pairs, per scan, as
        :func:`plane_noise`).  ``work``: the points each step handled,
        both scans together (``input``; ``noise``, ``projection``: points
        put into k-d trees plus neighbours fitted; ``vote``: points voted
        on; ``match``: the surface points the matching stages take; ``output``,
        for scans past :func:`match_points`: the points of the whole scans whose
        pairs are counted), which grow no faster than the scans (and stop
        growing past :func:`match_points` a scan but for ``input``, ``noise``
        and ``output``), summed over the tries (below and ``coarse_first``).  Scans of more
        points than :func:`match_points` (``n_points``) are voted on,
        matched and judged on a random sample of that many rows each
        (:data:`MATCH_POINTS_PER_CELL`); where that gives no motion, on up
        to :data:`VOTE_POINTS` rows each (``info["sampled"]``: the sample's
        rows and its reason).  A scan whose points lie on one plane to their
        noise (:func:`flat_scan`) gives no motion before the search ("degenerate: ...").
    """
    t0 = _clock()
    X = RIGID.check_points(source, "source")
    Y = RIGID.check_points(target, "target")
    report = check_progress(progress)
    n_points = check_int(n_points, "n_points", 10)
    check_fraction(min_overlap, "min_overlap")
    check_fraction(confidence, "confidence", open_high=True)
    max_triples = check_int(max_triples, "max_triples", 1, allow_none=True)
    n_judged = check_int(n_judged, "n_judged", 1)
    if voxel is not None:
        voxel = check_positive(voxel, "voxel")
    if not isinstance(coarse_first, (bool, np.bool_)):
        raise InputError(f"Expected `coarse_first` True or False, got {coarse_first!r}.")
    seed = seed_int(seed)  # an int seeds the three random steps alike; a Generator draws one

    # Past its noise each scan is voted on, matched and judged on a sample of at most match_points(n_points)
    # rows; only the output's pairs count every point (surface_rows).  Where the sample gives no motion and
    # a scan has more rows, the whole scan (up to VOTE_POINTS rows) is tried as before the sample.
    # The tries: (rows a scan, target cells, searches).  First a coarse one, on half the cells and their
    # sample, with the adaptive search alone: most clean pairs end there; where it gives no motion, the
    # pipeline at n_points follows, as without it.
    tries = [(match_points(n_points), n_points, SEARCHES)]
    if tries[0][0] < min(VOTE_POINTS, max(X.shape[0], Y.shape[0])):
        tries.append((VOTE_POINTS, n_points, SEARCHES))
    if coarse_first and voxel is None and n_points // 2 >= COARSE_MIN_POINTS:
        tries.insert(0, (match_points(n_points // 2, COARSE_POINTS_PER_CELL), n_points // 2, SEARCHES[:1]))
    work: dict = {}
    sampled = coarse = None
    for k, (cap, cells, searches) in enumerate(tries):
        low, high = k / len(tries), (k + 1) / len(tries)
        report(low, "surface tokens")
        tx = surface_tokens(X, clutter=clutter, seed=seed, memory_budget=memory_budget, all_points=False,
                            max_points=cap)
        ty = surface_tokens(Y, clutter=clutter, seed=seed, memory_budget=memory_budget, all_points=False,
                            max_points=cap)
        ix, iy = tx.rows, ty.rows
        Xs, Ys = tx.points[ix], ty.points[iy]
        if k == 0:  # a plane in either scan: no search can determine the slide along it
            flat = (flat_scan(X if tx.sampled is None else X[tx.sampled], tx.noise, "source")
                    or flat_scan(Y if ty.sampled is None else Y[ty.sampled], ty.noise, "target"))
            if flat is not None:
                return stages.failure(RIGID, flat[0], {
                    "mode": "scans", "surface_points": (int(Xs.shape[0]), int(Ys.shape[0])),
                    "thickness": flat[1], "scan_noise": (tx.noise.sigma, ty.noise.sigma),
                    "time_s": time.perf_counter() - t0[0], "cpu_s": time.process_time() - t0[1]})
        nys = ty.normals if ty.normals is not None else _normals(Ys)
        # The coarse try leaves a rival to the finer grid only where a scan is noisier than its sampling
        # (projected): there the finer grid's twice as many rows polish the answer closer, while a clean
        # scan's coarse answer is as close as the finer grid's and its rivals are judged where they are.
        noisy = tx.projection is not None or ty.projection is not None
        prepared = np.subtract(_clock(), t0)
        match = match_surfaces(Xs, Ys, nys, n_points=cells, voxel=voxel, seed=seed, min_overlap=min_overlap,
                               confidence=confidence, max_triples=max_triples, feature_tol=feature_tol,
                               n_judged=n_judged, refine=refine, memory_budget=memory_budget,
                               verdict=True, noise=float(np.hypot(tx.noise.sigma, ty.noise.sigma)),
                               searches=searches, defer_rivals=cells < n_points and noisy,
                               progress=lambda f, m, lo=low, hi=high: report(lo + (hi - lo) * (0.05 + 0.95 * f), m))
        # Points each step handled, summed over both scans and every try: what grows with the scans' size
        # (the matching past the voxel grid works on at most VOTE_POINTS surface points a scan, and samples
        # of them).
        for key, value in (("input", X.shape[0] + Y.shape[0]), ("noise", tx.noise.work + ty.noise.work),
                           ("projection", sum(t.projection.work for t in (tx, ty) if t.projection is not None)),
                           ("vote", tx.voted + ty.voted + (Ys.shape[0] if ty.normals is None else 0)),
                           ("match", Xs.shape[0] + Ys.shape[0])):
            work[key] = int(value) if key == "input" else work.get(key, 0) + int(value)
        # The coarse try's motion stands where no rival keeps RIVAL_SHARE of its support; where one does,
        # it passed against that rival on the coarse rows, and the finer grid tells the two apart.
        close = (match.info.get("rival") or match.info.get("symmetric_rival")) if match and cells < n_points else None
        if (match and not close) or k == len(tries) - 1:
            break
        reason = match.info.get("reason", "") if not match else (
            f"ambiguous: a rival {close['angle_deg']:.0f} deg away keeps {close['on_surface']} of the motion's "
            f"{close['best_on_surface']} points on the surface (passed on this grid, left to the finer one)")
        gave = {"rows": int(cap), "reason": reason}
        if cells < n_points:
            coarse = dict(gave, n_points=int(cells))
        else:
            sampled = gave
    info = {"mode": "scans", "surface_points": (int(Xs.shape[0]), int(Ys.shape[0]))}
    info.update(match.info)
    info["work"] = work
    if coarse is not None:
        info["coarse"] = coarse  # the coarse try, which gave no motion or one with a close rival
    if sampled is not None:
        info["sampled"] = sampled  # the sample's try, which gave no motion
    # Stage timings from the start of the call.
    for stage in STAGES:
        for key, offset in zip((f"t_{stage}", f"cpu_{stage}"), prepared):
            if key in info:
                info[key] += float(offset)
    if not match:
        return stages.failure(RIGID, info["reason"], info)
    noise = pooled_noise(tx.noise.sigma, ty.noise.sigma)
    residual = plane_noise(Xs @ match.rotation.T + match.translation, Ys, nys, match.pairs)
    on = Xs[match.pairs[:, 0]]
    flat = thickness(on)
    # As thin as the pairs' own residuals (on noise-free data: flat to rounding, far below the
    # exact pipeline's finest tolerance of 1e-6 spacings): a plane, along which any slide fits.
    if flat <= PLANE_THICKNESS * max(residual, 1e-6 * match.info["target_spacing"]):
        info.update(thickness=flat, residual_noise=residual)
        return stages.failure(RIGID, (f"degenerate: the {on.shape[0]} supporting points lie on one plane "
                                      f"(thickness {flat:.3g}, residual {residual:.3g}), along which any slide "
                                      "fits as well"), info)
    # Correspondences index the input points: every point of each scan on its surface, sampled or not.
    if tx.sampled is None and ty.sampled is None:
        kept = np.stack([ix[match.pairs[:, 0]], iy[match.pairs[:, 1]]], axis=1)
    else:
        sx, sy = (surface_rows(tk, clutter=clutter) for tk in (tx, ty))
        # The whole target's tree (the noise's, where it has one) searched among its surface rows.
        on = np.zeros(ty.points.shape[0], dtype=bool)
        on[sy] = True
        # In the source rows' order, as the result sorts them (no sort by distance of every scan point).
        whole = stages.nearest_pairs(tx.points[sx] @ match.rotation.T + match.translation,
                                     ty.tree if ty.tree is not None else KDTree(ty.points), match.gate, keep=on,
                                     by_row=True)
        kept = np.stack([sx[whole[:, 0]], whole[:, 1]], axis=1)
        info["work"]["output"] = int(sx.shape[0] + sy.shape[0])
    info.update(noise=noise, thickness=flat,
                scan_noise=(tx.noise.sigma, ty.noise.sigma), residual_noise=residual,
                projected=tuple(0 if t.projection is None else t.projection.neighbours for t in (tx, ty)),
                time_s=time.perf_counter() - t0[0], cpu_s=time.process_time() - t0[1])
    report(1.0, f"{kept.shape[0]} correspondences")
    return stages.motion_result(RIGID, X, Y, stages.Fit(homogeneous(match.rotation, match.translation), kept), info)


#: The searches of :func:`match_surfaces` with the verdict, in the order it runs them until one gives a motion
#: that passes.
SEARCHES = ("adaptive", "whole budget", "partial overlap")


#: The fewest target cells :func:`register_surfaces`' coarse try runs on (half of ``n_points``).
COARSE_MIN_POINTS = 100


#: Points of each scan that :func:`register_surfaces` votes on, matches and judges, per target cell of its
#: matching grid (``n_points``; at most :data:`VOTE_POINTS`): a larger scan works on a random sample of that
#: many rows (:func:`vote_sample`; where that gives no motion, on up to :data:`VOTE_POINTS`) and only its
#: output pairs count every point (:func:`surface_rows`).  At 25
#: points a cell (about five along a voxel's side of a surface), the verdict's neighbourhoods
#: (:data:`VERDICT_NEIGHBOURS` points) stay within about one voxel and the final gate (three of the
#: sample's spacings) under one: the resolution the search matched at.  Design notes, section 6, "Speed:
#: each scan sampled to its matching grid".
MATCH_POINTS_PER_CELL = 25


#: Points of each scan per target cell in :func:`register_surfaces`' coarse try: half of
#: :data:`MATCH_POINTS_PER_CELL`, as its grid is half of ``n_points``.  The try's work (voting, the
#: verdict's supports and frames, the polish) follows its rows; the verdict judges its answer against
#: wrong motions on the same rows, and where no motion passes there the call goes on at
#: :data:`MATCH_POINTS_PER_CELL`.  Design notes, section 6, "Speed: the coarse try at half the density".
COARSE_POINTS_PER_CELL = MATCH_POINTS_PER_CELL // 2


def match_points(n_points: int, per_cell: int | None = None) -> int:
    """Rows of a scan :func:`register_surfaces` works on for a matching grid of ``n_points`` target cells,
    ``per_cell`` a cell (default :data:`MATCH_POINTS_PER_CELL`; at most :data:`VOTE_POINTS` in all)."""
    return int(min(VOTE_POINTS, (MATCH_POINTS_PER_CELL if per_cell is None else per_cell) * n_points))


def surface_rows(tokens: SurfaceTokens, *, clutter: bool = True) -> np.ndarray:
    """The rows of a whole scan on its surface, ascending: ``tokens.rows``, and of the rows its vote did
    not sample (``tokens.sampled``) those on the surface the kept rows sample (every row without
    ``clutter``).

    A row is on it when its nearest kept row ``q`` lies within :data:`SURFACE_REACH` times the kept rows'
    median spacing ``s`` (a point of a surface sampled at random lies that close to the sample with
    probability ``1 - 2^-9``) and its height over ``q``'s tangent plane (``tokens.normals``) is within
    ``s`` plus three of the scan's noise deviations (``tokens.noise``): clutter counts only where it
    touches the surface, as the vote keeps it.
    """
    n = tokens.points.shape[0]
    if tokens.sampled is None:
        return tokens.rows
    if not clutter or tokens.normals is None:
        return np.arange(n)
    rest = np.ones(n, dtype=bool)
    rest[tokens.sampled] = False
    rest = np.flatnonzero(rest)
    if tokens.rows.size < 2 or rest.size == 0:
        return tokens.rows
    tree = KDTree(tokens.points[tokens.rows])
    s = median_spacing(tree.points, tree=tree)
    height = nearest_heights(np.ascontiguousarray(tokens.points, dtype=np.float64), rest,
                             np.ascontiguousarray(tokens.normals, dtype=np.float64), tree.points, *tree.nodes,
                             SURFACE_REACH * s)
    on = np.zeros(n, dtype=bool)
    on[tokens.rows] = True
    on[rest[height <= s + 3.0 * tokens.noise.sigma]] = True
    return np.flatnonzero(on)


#: :func:`surface_rows`' reach, in the kept rows' median spacings.
SURFACE_REACH = 3.0


#: A motion's supporting points lie on one plane (and the motion can slide
#: along it) when their spread along their least axis, ``sqrt(λ3)``, is within
#: this many times their noise (the final pairs' residual deviation in
#: :func:`register_surfaces`, the scans' local noise in motion segmentation):
#: a floor or a wall is as thick as its noise, any solid object seen from one
#: side far more.
PLANE_THICKNESS = 3.0


def thickness(points: np.ndarray) -> float:
    """Standard deviation of the points along their least axis, ``sqrt(λ3)`` of their covariance (0 on a plane)."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.shape[0] < 4:
        return 0.0
    ev = np.linalg.eigvalsh(np.cov(pts.T))
    return float(np.sqrt(max(ev[0], 0.0)))


#: A scan is a plane when its spread along its least axis is within this many times its noise along its
#: surface (:func:`flat_scan`): a noisy plane's spread there is its noise, which :func:`scan_noise` may
#: measure 10-15% low (the xfail of ``test_scans``).  Design notes §6, "A plane told before the search",
#: has the ratios of planes and of real views.
FLAT_NOISE = 1.5

#: A scan whose spread along its least axis is within this share of its spread along all three is flat to
#: rounding (an exact plane, noise 0): the covariance's least eigenvalue is known to about eps times its
#: largest, so its square root, the thickness, to about ``sqrt(eps)`` = 1.5e-8 of the spread.
FLAT_ROUNDING = 1e-6


def flat_scan(points: np.ndarray, noise: ScanNoise, name: str) -> tuple[str, float] | None:
    """``(reason, thickness)`` when a scan's points lie on one plane, else None.

    Flat: the spread along the least axis (:func:`thickness`) within :data:`FLAT_NOISE` times the scan's
    noise along its surface (``noise.sigma``, :func:`scan_noise`), or within :data:`FLAT_ROUNDING` of its
    spread along all three axes (exact data): no more than the noise of a plane.  ``points``: the scan's
    rows as given, as the noise was measured on them (not the vote's rows, which keep the points nearest
    the surface and so are thinner than the noise; clutter makes a plane thicker, and a cluttered plane
    goes on to the search).  Any motion that maps a plane onto the other scan can slide along it and
    still fit as well, and every supporting set is flat too (as :func:`register_surfaces` checks it,
    against the pairs' residuals, once a motion is found), so the pipeline ends before its search.
    None where the noise did not settle (``noise.settled``): in a volume ``sigma`` is the volume's own
    spread, no measure of a surface's thickness.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.shape[0] < 4 or not noise.settled:
        return None
    sigma = noise.sigma
    flat = thickness(pts)
    spread = float(np.sqrt(np.trace(np.cov(pts.T))))
    if flat > max(FLAT_NOISE * sigma, FLAT_ROUNDING * spread):
        return None
    return (f"degenerate: the {name}'s {pts.shape[0]} points lie on one plane (thickness {flat:.3g}, "
            f"its noise {sigma:.3g}), along which any slide fits as well"), flat


def aligning_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A rotation taking unit vector ``a`` onto unit vector ``b``; for ``(n, 3)`` rows, ``(n, 3, 3)`` of
    each row of ``a`` onto the same row of ``b``."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if a.ndim == 1:
        return aligning_rotation(a[None], b[None])[0]
    v = np.cross(a, b)
    c = np.einsum("ij,ij->i", a, b)
    opposite = c < -1.0 + 1e-12
    # Rodrigues about the unit axis v / |v| by the angle whose sine is |v| and cosine c: orthonormal to
    # rounding however near opposite a and b are (``I + [v]x + [v]x² / (1 + c)``, the same rotation, loses
    # eps / (1 + c) there: 3e-12 at c = -0.9998).
    s = np.linalg.norm(v, axis=1)
    kx = _skew(v / np.where(s > 0.0, s, 1.0)[:, None])
    out = np.eye(3) + s[:, None, None] * kx + (1.0 - c)[:, None, None] * (kx @ kx)
    if np.any(opposite):  # a half-turn about any axis normal to a
        ao = a[opposite]
        u = np.cross(ao, np.where((np.abs(ao[:, 0]) < 0.9)[:, None], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]))
        u /= np.linalg.norm(u, axis=1)[:, None]
        out[opposite] = 2.0 * u[:, :, None] * u[:, None, :] - np.eye(3)
    return out


def _skew(v: np.ndarray) -> np.ndarray:
    """``(n, 3, 3)`` cross-product matrices ``[v]×`` of the rows of ``v``."""
    out = np.zeros((v.shape[0], 3, 3))
    out[:, 0, 1], out[:, 0, 2] = -v[:, 2], v[:, 1]
    out[:, 1, 0], out[:, 1, 2] = v[:, 2], -v[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -v[:, 1], v[:, 0]
    return out


def tangent_motions(source: np.ndarray, target: np.ndarray, n: int, rng: np.random.Generator, *,
                    source_tree: cKDTree | KDTree | None = None, target_tree: cKDTree | KDTree | None = None,
                    k: int = 12) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` wrong but plausible rigid motions: a random source point onto a random target point,
    the source's surface normal there turned onto the target's (random sign), a random spin about it.

    The two surfaces touch tangentially, as under the wrong hypotheses a
    search of surface triples with agreeing normals makes.  Normals are the
    least-variance axes of ``k`` nearest neighbours.  Returns ``(R, t)``
    pairs; the draws use ``rng`` in a fixed order (points, signs, spins).
    """
    X = np.asarray(source, dtype=np.float64)
    Y = np.asarray(target, dtype=np.float64)
    ia = rng.integers(0, X.shape[0], n)
    ib = rng.integers(0, Y.shape[0], n)
    sx = cKDTree(X) if source_tree is None else source_tree
    sy = cKDTree(Y) if target_tree is None else target_tree
    na = local_scatter(X, X[ia], min(k, X.shape[0]), sx).normals
    nb = local_scatter(Y, Y[ib], min(k, Y.shape[0]), sy).normals
    signs = rng.choice([-1.0, 1.0], n)
    spins = rng.uniform(0.0, 2.0 * np.pi, n)
    b = signs[:, None] * nb
    K = _skew(b)
    spin = np.eye(3) + np.sin(spins)[:, None, None] * K + (1.0 - np.cos(spins))[:, None, None] * (K @ K)  # Rodrigues
    R = spin @ aligning_rotation(na, b)
    t = Y[ib] - np.einsum("nij,nj->ni", R, X[ia])
    return list(zip(R, t))


#: Wrong motions drawn for a scans motion's verdict (:func:`surface_verdict`),
#: each screened by a short ICP at the voxel gate ...
VERDICT_DRAWS = 128
#: ... of which the best-screened are polished as the search polishes its own.
VERDICT_POLISHED = 16
#: Second word of the verdict's seed, ``[seed, VERDICT_STREAM]``: its draws leave the search's stream as it was.
VERDICT_STREAM = 0x7E4D1C7
#: Point-to-plane iterations a gate of a wrong motion's polish (the search's own: 30).
VERDICT_ITERATIONS = 10
#: Source points each draw is screened on.
VERDICT_SCREEN = 1000
#: Source points the polish of a wrong draw moves (a random share of the search's coarse sample, an
#: eighth of its :data:`FINE_SAMPLE`): the polish only has to reach the draw's local minimum, whose
#: supports are then counted on every source point; the levels move with the sample by far less than
#: the verdict's margins (design notes, section 6).
VERDICT_SAMPLE = 1000
#: Gates the verdict counts supports at: the final gate and its halves (a true
#: motion's pairs sit at the noise, a wrong one's fill the gate).
VERDICT_GATES = 5
#: Deviations of the scans' noise a point on the surface may lie off its
#: nearest target sample, beyond the gate, for the verdict's finer gates.
NOISE_REACH = 3.0

#: The sequential verdict (:func:`surface_verdict` with ``sure=``): once at least :data:`VERDICT_MIN_WRONG`
#: wrong draws, best screened first, are polished and counted, a motion whose margin over them reaches
#: ``VERDICT_SURE`` passes without the others.  A motion that fails is judged against every draw.  The
#: threshold is more than 1.5 times the largest margin a failing verdict reached over its first three
#: draws or more on the recorded null and true pairs (1.94; design notes, section 6, "The verdict: draws
#: shared, polished in order" and "The sequential verdict from the first draw").
VERDICT_SURE = 3.0
#: Wrong draws counted before the sequential verdict stops at ``VERDICT_SURE``: after one or two, failing
#: verdicts reached margins of up to 3.37 (design notes, section 6).
VERDICT_MIN_WRONG = 3
#: Before :data:`VERDICT_MIN_WRONG` wrong draws are counted, the sequential verdict stops at this margin
#: (or at ``sure`` where that is higher): three times the largest margin a failing verdict reached over
#: its first one or two wrong draws on the recorded null and true pairs (3.37), where the clean scan
#: pairs' reach 4-58, half of them 10 or more (design notes, section 6, "The sequential verdict from
#: the first draw").
VERDICT_SURE_FIRST = 10.0
#: From this many wrong draws on (half of :data:`VERDICT_POLISHED`), the sequential verdict stops at
#: :data:`VERDICT_SURE_LATE` (or at ``sure`` where that is lower).
VERDICT_LATE_WRONG = 8
#: The sequential verdict's margin from :data:`VERDICT_LATE_WRONG` wrong draws on: 1.75 times the largest
#: margin a failing verdict reached over its first eight draws or more on the recorded null and true pairs
#: (1.135), where a right motion that a draw follows closely (margin 2.5-2.9 over every prefix from the
#: third draw on) would otherwise polish all 16 (design notes, section 6, "The sequential verdict from the
#: first draw").
VERDICT_SURE_LATE = 2.0


def point_icp(X, Y, tree, R, t, gate, iterations=10, *, fit=fit_rigid):
    """Point-to-point ICP inside ``gate``: what a polish does to a wrong start (the cheap screens of
    :func:`surface_verdict` and of :func:`gatv.motions.scans.chance_support`).

    Returns ``(R, t, support)``: the motion reached and the points of ``X``
    within ``gate`` of ``Y`` under it (the last query's count when the ICP
    stopped at the motion it queried).  ``fit(source, target) -> (R, t)``:
    :func:`gatv.fitting.fit_rigid`, or the numba ``kabsch3`` (equal to
    rounding, cheaper on the verdict's many small fits).
    """
    for _ in range(iterations):
        d, j = tree.query(X @ R.T + t, k=1, distance_upper_bound=gate)
        ok = np.isfinite(d)
        if np.count_nonzero(ok) < 3:
            return R, t, int(np.count_nonzero(ok))
        R_new, t_new = fit(X[ok], Y[j[ok]])
        if np.abs(R_new - R).max() < 1e-9 and np.abs(t_new - t).max() < 1e-9 * gate:
            return R, t, int(np.count_nonzero(ok))
        R, t = R_new, t_new
    d, _ = tree.query(X @ R.T + t, k=1, distance_upper_bound=gate)
    return R, t, int(np.count_nonzero(np.isfinite(d)))


#: Cosine of the largest angle between a source point's normal (moved) and its target sample's at which
#: the two surfaces count as one there (about 26°): where a wrong motion lays one surface across the other,
#: the two cross within the gate at an angle; under the right motion the normals agree to their noise.
NORMAL_AGREEMENT = 0.9
#: Source points (each with its ``VERDICT_NEIGHBOURS - 1`` nearest on its own scan) over which a point's
#: height above the target's tangent plane is averaged for the verdict's finer gates (:func:`surface_support`).
VERDICT_NEIGHBOURS = 16


@dataclass(frozen=True, eq=False)
class SourceFrame:
    """What the verdict needs of the source once, for every motion it counts (:func:`surface_support`)."""

    #: (N, 3) unit normals, unoriented (least-variance axes of 12 neighbours, as :func:`tangent_motions`).
    normals: np.ndarray
    #: (N, VERDICT_NEIGHBOURS) rows of each point's nearest source points, itself first.
    neighbours: np.ndarray
    #: The source's k-d tree, when kept (the tangent wrong motions' source normals query it too).
    tree: cKDTree | KDTree | None = None

    @classmethod
    def of(cls, X: np.ndarray, tree: cKDTree | KDTree | None = None) -> "SourceFrame":
        tree = KDTree(X) if tree is None else tree
        k = min(VERDICT_NEIGHBOURS, X.shape[0])
        # One query: the normals' 12 nearest are the first 12 of the VERDICT_NEIGHBOURS nearest.
        neighbours = tree.query(X, k=k, workers=get_num_threads())[1].reshape(X.shape[0], -1)
        normals = neighbourhood_normals(X, neighbours, min(12, X.shape[0]))
        return cls(normals, neighbours, tree)


def surface_support(X, Y, normals, tree, R, t, gates, reach, frame: SourceFrame) -> np.ndarray:
    """Source points on the target's surface under ``(R, t)``, at each of ``gates`` (descending).

    A point counts where its normal, moved, agrees with its nearest target
    sample's (:data:`NORMAL_AGREEMENT`) and it lies within ``gates[0]`` of
    that sample; for each finer gate, within ``reach`` (at least
    ``gates[0]``) of a sample and with its *local height* within the gate:
    its height above the sample's tangent plane averaged over its
    :data:`VERDICT_NEIGHBOURS` nearest source points.  The distance to the
    surface, not to its samples, so that a coarse sampling (a mesh's
    vertices) counts as a dense one; averaged, so that the scans' noise
    falls by about the square root of the neighbours while the gap between
    two surfaces that a wrong motion lays tangentially onto each other,
    smooth over that neighbourhood, stays.
    """
    moved = np.ascontiguousarray(X @ R.T + t)
    d, j = tree.query(moved, k=1, distance_upper_bound=max(reach, gates[0]))
    idx = np.where(np.isfinite(d), j, -1).astype(np.int64)
    # Each neighbour's offset from its own nearest sample, along this point's sample's normal, averaged
    # (inf where the normals disagree: such a point does not count).
    h = local_heights(moved, idx, np.ascontiguousarray(Y, dtype=np.float64),
                      np.ascontiguousarray(normals, dtype=np.float64), np.ascontiguousarray(frame.normals @ R.T),
                      np.ascontiguousarray(frame.neighbours, dtype=np.int64), NORMAL_AGREEMENT)
    agree = np.isfinite(h)
    return np.array([np.count_nonzero(agree & (d <= gates[0]))] + [np.count_nonzero(h <= g) for g in gates[1:]])


class WrongDraws:
    """The verdict's tangent wrong motions on one pair of scans (:func:`surface_verdict`): drawn and
    screened at once, polished and counted only as a verdict asks for them, best screened first, and kept
    for the next verdict on the same data (:func:`match_surfaces`' searches judge their motions against
    the same draws: the verdict's stream, sample and polish do not depend on the motion judged).

    ``n_draws`` tangent motions (:func:`tangent_motions`, from ``rng``) are screened by a short
    point-to-point ICP at the ``voxel`` gate on :data:`VERDICT_SCREEN` source points (their *ranks*: the
    screen points within the gate at its end); the ``n_polished`` best, in the order of their ranks, go
    through ``polish(R, t) -> (R, t, gate, _)`` when first asked for.  ``screen_target``: the target
    points the screen pairs with (by default ``Ys``), and ``screen_source`` the source points it moves
    (by default :data:`VERDICT_SCREEN` random rows of ``Xs``): :func:`match_surfaces` passes its voxel
    grids' centroids, where the search itself matched (a few hundred points a scan against tens of
    thousands), so that a draw ranks by the cells it lays on cells, as a trial motion is found.
    Every draw's screen runs in one numba kernel (:func:`gatv._icp_kernels.screened_supports`, equal to
    :func:`point_icp` with ``fit=kabsch3``), draws in parallel.  ``polish_many(motions) -> [(R, t), ...]``:
    ``polish`` of several motions at once (in parallel); draws are then polished as many at a time as numba
    has threads, and :func:`surface_verdict` polishes its motion's start with the first draws, as many as
    fill the threads beside it.
    """

    def __init__(self, Xs, Ys, target_normals, tree: cKDTree | KDTree, frame: SourceFrame, *, polish, voxel: float,
                 rng: np.random.Generator, n_draws: int = VERDICT_DRAWS, n_polished: int = VERDICT_POLISHED,
                 screen_target: np.ndarray | None = None, screen_source: np.ndarray | None = None,
                 polish_many=None):
        self.Xs, self.Ys, self.target_normals, self.tree, self.frame = Xs, Ys, target_normals, tree, frame
        self.polish = polish
        self.polish_many = polish_many
        starts = tangent_motions(Xs, Ys, n_draws, rng, source_tree=frame.tree, target_tree=tree)
        if screen_source is not None:
            screen = np.ascontiguousarray(screen_source, dtype=np.float64)
        elif Xs.shape[0] <= VERDICT_SCREEN:
            screen = Xs
        else:
            screen = Xs[rng.choice(Xs.shape[0], VERDICT_SCREEN, replace=False)]
        Yq = Ys if screen_target is None else screen_target
        # Every draw's point_icp(screen, Yq, ..., voxel, fit=kabsch3) in one kernel (draws in parallel).  On
        # voxel centroids (about one a voxel) a lookup visits the 2 x 2 x 2 cells of two voxels, not the
        # 3 x 3 x 3 of one, for the same answers (design notes, section 6, "Speed: the coarse try at half
        # the density").
        grid = TargetGrid.of(Yq, voxel, cell_radii=2.0 if screen_target is not None else 1.0)
        ranks = screened_supports(screen, grid, starts, voxel, 10)
        order = np.argsort(ranks, kind="stable")[::-1][:n_polished]
        #: The draws kept for polishing, best screened first, and their ranks (descending).
        self.starts = [starts[k] for k in order]
        self.ranks = ranks[order]
        #: Source points each draw was screened on.
        self.n_screen = int(screen.shape[0])
        self.n_drawn = int(n_draws)
        self._polished: list = []
        self._supports: dict = {}

    def __len__(self) -> int:
        return len(self.starts)

    def polished(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """The ``i``-th best screened draw, polished (polishing every better one first, once)."""
        if len(self._polished) <= i:
            # With polish_many, as many at once as numba has threads: they polish in parallel.
            self.polish_with(max(i + 1, len(self._polished) + (get_num_threads() if self.polish_many else 1)))
        return self._polished[i]

    def polish_with(self, k: int, others=()) -> list:
        """Polish the ``k`` best screened draws (those not polished yet) and the motions ``others`` (``(R, t)``
        pairs) in one ``polish_many`` call when given (in parallel), else one by one; returns ``others``
        polished."""
        todo = list(self.starts[len(self._polished):max(len(self._polished), min(k, len(self.starts)))])
        motions = todo + list(others)
        if self.polish_many is not None and motions:
            done = self.polish_many(motions)
        else:
            done = [self.polish(R, t)[:2] for R, t in motions]
        self._polished.extend(done[:len(todo)])
        return done[len(todo):]

    @property
    def n_polished(self) -> int:
        """The draws polished so far."""
        return len(self._polished)

    def supports(self, i: int, gates, reach: float) -> np.ndarray:
        """:func:`surface_support` of the ``i``-th draw, polished, at ``gates`` (counted once)."""
        key = (i, tuple(float(g) for g in gates), float(reach))
        if key not in self._supports:
            R, t = self.polished(i)
            self._supports[key] = surface_support(self.Xs, self.Ys, self.target_normals, self.tree, R, t, gates,
                                                  reach, self.frame)
        return self._supports[key]


def gate_verdicts(found, wrong, n_tested: float, n_points: int, n_drawn: int | None = None) -> list:
    """:func:`surface_verdict`'s verdict at each gate: supports ``found`` (one a gate) against the rows of
    ``wrong`` (a wrong motion's supports at the same gates), each raised by three Poisson deviations (small
    counts at fine gates do not pass on noise); ``n_drawn``: the draws' extreme-value level too
    (:func:`gatv.verdict.wrong_motion_verdict`)."""
    found = np.asarray(found).reshape(-1)
    wrong = np.array(wrong, dtype=np.float64).reshape(-1, found.size)
    wrong = wrong + 3.0 * np.sqrt(wrong)
    return [wrong_motion_verdict(int(found[i]), wrong[:, i], n_tested, n_points=n_points, n_looks=found.size,
                                 n_drawn=n_drawn) for i in range(found.size)]


def sure_after(n_wrong: int, sure: float) -> float:
    """The margin at which :func:`surface_verdict`'s sequential verdict (``sure``) stops, passing, after
    ``n_wrong`` wrong draws: ``sure`` from :data:`VERDICT_MIN_WRONG` on, higher before
    (:data:`VERDICT_SURE_FIRST`), lower from :data:`VERDICT_LATE_WRONG` on (:data:`VERDICT_SURE_LATE`)."""
    if n_wrong < VERDICT_MIN_WRONG:
        return max(sure, VERDICT_SURE_FIRST)
    if n_wrong >= VERDICT_LATE_WRONG:
        return min(sure, VERDICT_SURE_LATE)
    return sure


def surface_verdict(Xs, Ys, target_normals, rotation, translation, *, polish, voxel: float, gate: float,
                    n_tested: float, rng: np.random.Generator | None, tree: cKDTree | None = None,
                    noise: float = 0.0, n_draws: int = VERDICT_DRAWS,
                    n_polished: int = VERDICT_POLISHED, frame: SourceFrame | None = None,
                    searched=(), draws: WrongDraws | None = None,
                    sure: float | None = None, start=None) -> tuple[Verdict, dict]:
    """Whether the motion ``(rotation, translation)`` beats wrong motions polished as it was.

    The verdict stage of the scans pipeline (:mod:`gatv.verdict`, null
    ``"wrong motions"``).  ``n_draws`` tangent wrong motions
    (:func:`tangent_motions`) are screened by a short ICP at the ``voxel``
    gate; the ``n_polished`` best go through ``polish`` (the search's own
    coarse-to-fine point-to-plane ICP, ``polish(R, t) -> (R, t, gate, _)``);
    those that end on the motion itself (within 2° and 3 gates at the
    source's centroid) are not wrong ones (when none is left, nothing
    rivals the motion and it passes).  Supports are the source points whose
    normals agree with the target's there and that lie within ``gate`` of a
    target point and, at ``gate``'s halves (:data:`VERDICT_GATES` gates in
    all), whose local height over the target's tangent plane
    (``target_normals``), averaged over their source neighbours, is within
    that gate (:func:`surface_support`): two surfaces that a wrong motion lays
    onto each other touch, part and cross, so its points fill the gate,
    while a right motion's sit at the noise, which the averaging shrinks.
    At each gate the level is the best wrong motion's support (plus three
    of its Poisson deviations, for small counts) times the search's gain
    (:func:`gatv.verdict.wrong_motion_verdict`); the gate where the motion
    stands out most decides.  ``n_tested``: the motions the search tried,
    recorded.  ``noise``: the two scans' noise along the normal, combined
    (``hypot`` of each one's :func:`scan_noise`): a point on the surface
    lies that far off its nearest target sample, so the finer gates count
    points within ``gate + NOISE_REACH * noise`` of a sample
    (:data:`NOISE_REACH`); on scans far less noisy than their sampling,
    about the gate.  ``frame``: ``SourceFrame.of(Xs)`` when the caller
    judges several motions of one source.  ``searched``: ``(R, t)`` of
    motions the search itself polished and ranked as it did this one (a
    rival nearly as well supported, the partial-overlap search's other
    trials): those that did not end on the motion are wrong motions
    selected as it was, and count before the draws (``figures["searched"]``
    of them).  ``draws``: the :class:`WrongDraws`
    of an earlier verdict on the same scans, polish and stream (``polish``,
    ``rng``, ``n_draws`` and ``n_polished`` are then not used); the draws
    already polished are not polished again.

    ``sure``: a sequential verdict.  The draws are polished best screened
    first, and once :data:`VERDICT_MIN_WRONG` wrong ones are counted the
    verdict stops, passing, as soon as the motion's margin over them
    reaches ``sure`` (:data:`VERDICT_SURE`); over fewer, from the first,
    once it reaches :data:`VERDICT_SURE_FIRST` (or ``sure``, where
    higher); over :data:`VERDICT_LATE_WRONG` or more, once it reaches
    :data:`VERDICT_SURE_LATE` (or ``sure``, where lower).  A margin that
    far over the best screened draws is not undone by the draws left
    (measured on recorded verdicts, every draw polished: a failing
    verdict's margin over its first wrong draw was at most 3.37, over its
    first three or more at most 1.94, over its first eight or more at most
    1.135).  The level is then that of the draws polished; a motion that
    fails still fails as without ``sure`` (it only ends a verdict that
    passes).
    ``figures["polished"]`` counts the draws polished.

    ``start``: ``(R, t)`` of the trial motion the search polished into
    ``(rotation, translation)``.  It is polished again as the wrong draws
    are (``polish``), and at each gate the motion counts with the smaller
    of its two supports (``figures["support"]``; the two are
    ``figures["support_polished"]`` and ``figures["support_alike"]``): the
    level is set by draws polished on :data:`VERDICT_SAMPLE` points for
    :data:`VERDICT_ITERATIONS` iterations a gate, and a wrong motion
    polished on four times the points for three times the iterations
    slides further onto the surface (a parasaurolophus view against a
    cropped chef view: 6,711 points at the final gate polished so, 3,264
    polished as the draws, whose best holds 4,106), while a right one
    holds the same points either way (within 3% on the recorded true
    pairs; design notes, section 6, "The lone wrong motion").  Returns the
    verdict and its per-gate figures (``info["verdict_gates"]``).
    """
    R0, t0 = np.asarray(rotation, np.float64), np.asarray(translation, np.float64)
    tree = cKDTree(Ys) if tree is None else tree
    gates = [gate / 2.0**k for k in range(VERDICT_GATES)]
    # A point on the surface is off its nearest sample by the two scans' noise along the normal too.
    reach = gate + NOISE_REACH * float(noise)
    frame = SourceFrame.of(Xs) if frame is None else frame
    polished_support = found = surface_support(Xs, Ys, target_normals, tree, R0, t0, gates, reach, frame)
    if draws is None:
        draws = WrongDraws(Xs, Ys, target_normals, tree, frame, polish=polish, voxel=voxel, rng=rng,
                           n_draws=n_draws, n_polished=n_polished)
    alike = None
    if start is not None:
        # Polished with the first draws a sequential verdict may stop at, as many as fill the threads beside
        # it (at once, in parallel, where the draws polish many at a time).
        first = (draws.n_polished + max(1, get_num_threads() - 1)
                 if sure is not None and draws.polish_many is not None else 0)
        (Ra, ta), = draws.polish_with(first, [start])
        alike = surface_support(Xs, Ys, target_normals, tree, Ra, ta, gates, reach, frame)
        found = np.minimum(found, alike)
    c = Xs.mean(axis=0)

    def judged(wrong, extreme=True):
        # A motion judged against the draws alone (no motion the search selected as it was): the draws' level
        # is raised for the search's selection among its n_tested motions (extreme values).
        lone = extreme and start is not None and n_searched == 0
        return list(zip(gate_verdicts(found, wrong, n_tested, Xs.shape[0], draws.n_drawn if lone else None), gates))

    def on_the_motion(R, t):
        """Whether ``(R, t)`` ended on the motion judged (within 2° and three gates at the centroid)."""
        return rotation_angle_deg(R @ R0.T) < 2.0 and np.linalg.norm(R @ c + t - R0 @ c - t0) < 3.0 * gate

    # The search's own polished trial motions that did not end on the motion are wrong motions found the
    # way it was found: they count first.
    wrong = [surface_support(Xs, Ys, target_normals, tree, R, t, gates, reach, frame) for R, t in searched
             if not on_the_motion(R, t)]
    n_searched = len(wrong)
    polished = 0
    for i in range(len(draws)):
        R, t = draws.polished(i)
        polished = i + 1
        if not on_the_motion(R, t):
            wrong.append(draws.supports(i, gates, reach))
            per_gate = judged(wrong)
            # More draws only raise the gain's levels: once every gate's is reached, the motion has failed
            # (the levels without the extreme-value excess; a motion not judged alone has no other).
            plain = judged(wrong, extreme=False) if start is not None and n_searched == 0 else per_gate
            if not any(v for v, _ in plain):
                break
            # Sequential: far enough over the best screened wrong draws, the motion passes without the rest.
            if sure is not None and max(v.margin for v, _ in per_gate) >= sure_after(len(wrong) - n_searched, sure):
                break
    per_gate = judged(wrong)
    wrong = np.array(wrong, dtype=np.int64).reshape(-1, len(gates))
    # The gate where the motion stands out most over its level decides.
    best, g = max(per_gate, key=lambda vg: vg[0].margin)
    figures = {"gates": [float(x) for x in gates], "support": [int(x) for x in found],
               "chance": [float(v.chance) for v, _ in per_gate], "p_value": [float(v.p_value) for v, _ in per_gate],
               "gate": float(g), "reach": float(reach), "wrong_motions": int(wrong.shape[0]), "drawn": draws.n_drawn,
               "searched": n_searched, "polished": polished,
               "wrong_support": wrong.tolist()}
    if alike is not None:
        figures.update(support_polished=[int(x) for x in polished_support], support_alike=[int(x) for x in alike])
    return best, figures


@dataclass(frozen=True, eq=False)
class _Ranked:
    """A polished trial motion (4x4) and its support on the surface (:func:`match_surfaces`' partial search)."""

    matrix: np.ndarray
    support: int


@dataclass(frozen=True, eq=False)
class SurfaceMatch:
    """What :func:`match_surfaces` found: the motion, its final pairs and support.

    Falsy, with ``rotation`` and ``translation`` ``None`` and
    ``info["reason"]``, when no trial motion survived.
    """

    rotation: np.ndarray | None
    translation: np.ndarray | None
    gate: float
    pairs: np.ndarray  # (K, 2) one-to-one (source row, target row) within ``gate``
    on_surface: int  # source points within ``gate`` of the target's surface points
    info: dict

    def __bool__(self) -> bool:
        return self.rotation is not None


#: Source points of the point-to-plane polish (a random subsample of larger scans).
FINE_SAMPLE = 8000

#: The polish's levels above the finest stop once a step moves the source by less than this share of their
#: gate: they only have to bring the motion well within the next, halved gate.  A right motion's steps fall
#: to 1e-4 of the gate in 4 iterations and then drift by 2e-5 a step for the other 26 (bun000<-bun045,
#: voxel gate).  The finest level polishes on to rounding while its steps keep shrinking (exact data: an
#: order of magnitude or more a step), and stops once a step under this share of its gate moves the source
#: by more than half the step before: a slide along a direction the surface barely holds, which more steps
#: only repeat (a parasaurolophus view: 1.66e-4 of the gate, step after step, for all 30 iterations;
#: :func:`gatv._icp_kernels.plane_icp`'s ``stall``).  (The verdict's polish of its wrong draws, on
#: :data:`VERDICT_SAMPLE` points, keeps its :data:`VERDICT_ITERATIONS` and its tolerance: its levels stay
#: as measured.)
COARSE_STEP = 1e-3

#: Triples a batch of :func:`match_surfaces`'s adaptive search (the whole-budget search: 512): the
#: adaptive stop is checked after each batch, and a right motion's share of a scan pair's voxel points
#: (0.5-0.95) needs 5-70 triples.
ADAPTIVE_BATCH = 64

#: Trial motions the partial-overlap search (:func:`match_surfaces`' third attempt) polishes and ranks by
#: the source points they bring onto the target's surface.  At 40% overlap the right motion's congruent
#: triples rank 8th to 25th by their support among the voxel points (a half-turn laid across a cropped
#: target covers more of its voxels), and only the polish at the fine gates, counting points whose normals
#: agree, tells it apart (11,053 against 7,400 points on bun090<-bun045).
PARTIAL_TRIALS = 32

#: Smallest voxel of :func:`match_surfaces`, in median point spacings of the
#: more coarsely sampled scan: a voxel holds a few of its points (about four
#: on a surface), so both scans' voxel centroids are local means of their
#: surfaces, not of one scan's sample positions.
SAMPLING_VOXELS = 2.0


def matching_voxel(Xs: np.ndarray, Ys: np.ndarray, n_points: int, *, target_spacing: float | None = None,
                   source_spacing: float | None = None) -> float:
    """Voxel of :func:`match_surfaces`: about ``n_points`` occupied target cells, and at least
    :data:`SAMPLING_VOXELS` median spacings of the more coarsely sampled of the two scans.

    Scans sampled differently (a 40k-point range scan against a 450-vertex
    mesh) have their congruent triples matched within a voxel: a voxel
    finer than the coarse scan's spacing leaves its points where they were
    sampled and the dense scan's centroids elsewhere, and no triple matches.
    ``target_spacing``, ``source_spacing``: ``median_spacing(Ys)`` and ``median_spacing(Xs)`` when the
    caller has them.
    """
    if target_spacing is None:
        target_spacing = median_spacing(Ys)
    if source_spacing is None:
        source_spacing = median_spacing(Xs)
    coarse = max(source_spacing, target_spacing)
    return max(_voxel_for(Ys, int(n_points)), SAMPLING_VOXELS * coarse)


def match_surfaces(Xs, Ys, target_normals, *, n_points: int = 600, voxel: float | None = None, seed: int = 0,
                   min_overlap: float = MIN_OVERLAP, confidence: float = 0.999, max_triples: int | None = None,
                   feature_tol: float = 0.15, n_judged: int = 4, refine: bool = True,
                   memory_budget: float | None = None, coarse_points: int = FINE_SAMPLE,
                   verdict: bool = False, noise: float = 0.0, searches: tuple = SEARCHES,
                   defer_rivals: bool = False, progress=None) -> SurfaceMatch:
    """Stages 2–5 of :func:`register_surfaces` on points already kept as surface.

    ``Xs``, ``Ys`` are the two scans' surface points (for example rows of
    :func:`surface_points`) and ``target_normals`` the target's unit normals
    there, so that a caller registering many subsets of two scans (motion
    segmentation) votes on each scan once.  Downsampling on one voxel grid
    of about ``n_points`` target cells (:func:`matching_voxel`),
    normal-pruned congruent triples (drawn for the share ``min_overlap`` of
    overlapping points with ``confidence``), tensor voting judging the
    ``n_judged`` best trials (a trial that a fit judged already explains,
    :func:`gatv.stages.judged_alike`, is not judged again; ``info["judged"]``
    counts the judge's calls), rivals polished with the best and compared
    (:data:`RIVAL_SHARE`), point-to-plane ICP with a gate shrinking from a
    voxel to three point spacings.  Options as
    in :func:`register_surfaces`; they are not checked again here.  The
    polish runs on :data:`FINE_SAMPLE` source points, its levels above the
    finest on ``coarse_points`` of them (fewer: faster, but rivals a degree
    or two apart may stay apart and be reported as ambiguous).

    ``verdict``: the motion must also pass the verdict
    (:func:`surface_verdict`: wrong motions polished as it was), recorded
    in ``info["verdict"]``; a motion that fails it gives a falsy match
    whose reason says so.  A polished rival that keeps
    :data:`RIVAL_SHARE` of the motion's support (``info["ambiguous"]``)
    counts there as a wrong motion, first: the motion passes only where it
    explains the surface better than its rival at some gate (a right
    motion's points sit at the noise, a wrong one's fill the gate); where
    the rival alone sets a level it does not reach, the reason begins
    ``"ambiguous: two motions ... apart explain the data alike"`` and
    ``info["rival"]["supports"]`` has the rival's supports at the gates.
    The surface's own symmetry gives a rival too, whether or not the search
    found one: the motion composed with each of :func:`surface_symmetries`
    of the target's points it covers, screened (a turn must lay
    :data:`RIVAL_SHARE` of the motion's sample points within a voxel, a
    slide within the final gate) and polished as the verdict's wrong draws;
    one that stays apart and keeps :data:`RIVAL_SHARE` of the support is
    ``info["symmetric_rival"]`` and counts in the verdict as the search's
    rival does.
    False leaves the verdict to the caller (motion segmentation has its
    own levels).  ``noise``: the two scans' noise
    combined, for the verdict's reach (:func:`surface_verdict`).

    With the verdict, the search stops at the first motion that passes it:
    the triples are drawn in batches of :data:`ADAPTIVE_BATCH` until they
    are as many as the best trial's inlier share needs (adaptive RANSAC
    termination, ``trial_motions(adaptive_confidence=confidence)``); when
    that motion fails the verdict (or none is found) short of the budget,
    the whole budget is drawn from the seed's stream as without the stop.
    When the whole budget's motion fails too, a third search assumes a
    partial overlap: its triples' sides need only span a quarter of the
    *smaller* scan (a triangle of the overlap lies in both), and its
    :data:`PARTIAL_TRIALS` best trial motions are each polished (as the
    verdict polishes its wrong draws) and ranked by their supports on the
    surface (:func:`surface_support` at the final gate), not by the voxel
    points' support and tensor voting; the best then goes on as before
    (rivals, polish, verdict).  ``info["search"]`` says which search gave
    the answer (``"adaptive"``, ``"whole budget"`` or ``"partial
    overlap"``; after the first, ``info["adaptive"]`` and after the second
    ``info["whole_budget"]``: the triples drawn and why they gave no
    motion).  ``searches``: those of :data:`SEARCHES` to run, in that
    order (:func:`register_surfaces`' coarse try runs the adaptive one
    alone).  ``defer_rivals``: the best trial motion and its rivals are
    first polished as the verdict's wrong draws are (fewer points and
    iterations, at once); where a rival does not end on the best, the
    search gives no motion (``"ambiguous: ... not judged on this grid"``)
    instead of polishing and judging the two, for a caller that tries a
    finer grid next; where every rival ends on the best, the best alone is
    polished on.
    """
    t0 = _clock()
    if not searches or any(m not in SEARCHES for m in searches):
        raise InputError(f"`searches` must name some of {SEARCHES}; got {tuple(searches)!r}.")
    report = progress if progress is not None else (lambda fraction, message="": None)
    # C-ordered float64 for the numba kernels (one specialisation each)
    Xs, Ys = (np.ascontiguousarray(a, dtype=np.float64) for a in (Xs, Ys))
    info: dict = {}
    none = np.empty((0, 2), np.int64)
    tree = KDTree(Ys)  # nearest targets in numba kernels (the polish's, the verdict's supports)
    # The source's tree, when a spacing or the verdict's source neighbourhoods (SourceFrame) ask for it.
    source_tree = functools.cache(lambda: KDTree(Xs))
    target_spacing = median_spacing(Ys, tree=tree)
    if voxel is None:
        voxel = matching_voxel(Xs, Ys, n_points, target_spacing=target_spacing,
                               source_spacing=median_spacing(Xs, tree=source_tree()))
    Xd, Yd = voxel_downsample(Xs, voxel), voxel_downsample(Ys, voxel)
    info.update(voxel=voxel, n_downsampled=(int(Xd.shape[0]), int(Yd.shape[0])), target_spacing=target_spacing)
    if Xd.shape[0] < 3 or Yd.shape[0] < 3:
        return SurfaceMatch(None, None, voxel, none, 0, dict(info, reason="too few voxels"))
    nx, ny = _normals(Xd), _normals(Yd)
    _stamp(info, "prepare", t0)

    # Trial motions: voxel-sized tolerances; long sides for a stable rotation.
    report(0.1, "trial motions")
    gate = voxel
    index = TargetIndex(Yd, gate, memory_budget=memory_budget)
    diameter = float(np.linalg.norm(Xd.max(axis=0) - Xd.min(axis=0)))
    target_diameter = float(np.linalg.norm(Yd.max(axis=0) - Yd.min(axis=0)))
    budget = n_triples_needed(float(min_overlap), confidence)
    if max_triples is not None:
        budget = min(budget, max_triples)
    P = stages.prepare(Xd, Yd, RIGID)
    fine = 3.0 * target_spacing
    # The polish's gates: a voxel, halved down to three point spacings (the last).
    levels = [gate]
    while levels[-1] > fine:
        levels.append(max(fine, levels[-1] / 2.0))
    normals_c = np.ascontiguousarray(target_normals, dtype=np.float64)
    rng_sub = np.random.default_rng(seed)
    sub = Xs if Xs.shape[0] <= FINE_SAMPLE else Xs[rng_sub.choice(Xs.shape[0], FINE_SAMPLE, replace=False)]
    coarse = sub if sub.shape[0] <= coarse_points else sub[rng_sub.choice(sub.shape[0], coarse_points,
                                                                          replace=False)]
    # The wrong motions of the verdict are polished as the search's, on :data:`VERDICT_SAMPLE` of its coarse
    # sample and for fewer iterations a gate (a wrong start wanders where a right one settles at once).
    sample = coarse if coarse.shape[0] <= VERDICT_SAMPLE else coarse[
        rng_sub.choice(coarse.shape[0], VERDICT_SAMPLE, replace=False)]
    source_frame = functools.cache(lambda: SourceFrame.of(Xs, source_tree()))  # once for both attempts' verdicts

    def verdict_polish(R, t):
        return polish(R, t, sample, VERDICT_ITERATIONS, False)

    verdict_polished: dict = {}  # verdict_polish_many's motions, by their start

    def verdict_polish_many(motions) -> list:
        """``verdict_polish`` of each ``(R, t)`` of ``motions``, in parallel (one numba kernel), each start
        once: the coarse try's best, polished so beside its rivals, is the verdict's start."""
        if not refine:
            return [(np.asarray(R, np.float64), np.asarray(t, np.float64)) for R, t in motions]
        keys = [(np.asarray(R, np.float64).tobytes(), np.asarray(t, np.float64).tobytes()) for R, t in motions]
        todo = [k for k, key in enumerate(keys) if key not in verdict_polished]
        if todo:
            Rs, ts = plane_icp_many(np.ascontiguousarray(sample), tree.points, normals_c, *tree.nodes,
                                    np.array([motions[k][0] for k in todo], np.float64).reshape(-1, 3, 3),
                                    np.array([motions[k][1] for k in todo], np.float64).reshape(-1, 3),
                                    np.array(levels, np.float64), VERDICT_ITERATIONS, np.full(len(levels), 1e-9),
                                    np.zeros(len(levels)))
            verdict_polished.update((keys[k], (R, t)) for k, R, t in zip(todo, Rs, ts))
        return [verdict_polished[key] for key in keys]

    # The verdict's wrong draws do not depend on the motion judged: drawn, screened and polished once for
    # every attempt's verdict (as many as the verdicts ask for).
    wrong_draws = functools.cache(lambda: WrongDraws(Xs, Ys, target_normals, tree, source_frame(),
                                                       polish=verdict_polish, voxel=voxel,
                                                       rng=np.random.default_rng([seed, VERDICT_STREAM]),
                                                       screen_target=Yd, screen_source=Xd,
                                                       polish_many=verdict_polish_many))

    def on_surface(R, t, g) -> int:
        """Source points within ``g`` of a target point whose normals agree with its (:func:`surface_support`)."""
        return int(surface_support(Xs, Ys, target_normals, tree, R, t, [g], g + NOISE_REACH * float(noise),
                                   source_frame())[0])

    def polish(R, t, points=None, iterations=30, count=True):
        """Point-to-plane ICP with a gate shrinking from a voxel (on ``points`` at every gate when given);
        the points brought onto the surface (None without ``count``: the verdict counts its own;
        ``count="normals"``: those whose normals agree too, :func:`on_surface`)."""
        g = gate
        if refine:
            for g in levels:
                moving = points if points is not None else sub if g <= fine else coarse
                # The motion's own polish stops at COARSE_STEP above the finest level, and there on a stall.
                tol = 1e-9 if g <= fine or points is not None else COARSE_STEP
                # refine_point_to_plane's kernel, its inputs checked once by the caller
                R, t = plane_icp_parallel(moving, tree.points, normals_c, *tree.nodes,
                                          np.ascontiguousarray(R, np.float64), np.ascontiguousarray(t, np.float64),
                                          float(g), int(iterations), tol, 0.0 if points is not None else COARSE_STEP)
        return counted(R, t, g, count)

    def counted(R, t, g, count):
        if not count:
            return R, t, g, None
        if count == "normals":
            return R, t, g, on_surface(R, t, g)
        # Source points on the target's surface (within the gate): a measure
        # that does not favour a motion for landing on the very sample
        # points (the one-to-one pairs do).
        return R, t, g, int(np.count_nonzero(tree.nearest(Xs @ R.T + t, g) >= 0))

    centroid = Xs.mean(axis=0)

    def same_motion(Ra, ta, Rb, tb, g) -> bool:
        """Whether two polished motions are one: within 1° and three gates ``g`` at the source's centroid."""
        return rotation_angle_deg(Ra @ Rb.T) < 1.0 and float(np.linalg.norm((Ra - Rb) @ centroid + ta - tb)) < 3.0 * g

    def symmetric_rival(R, t, g, on, count):
        """The motion ``(R, t)`` composed with a symmetry of the surface it covers (:func:`surface_symmetries`
        of the target's points the source's sample lands on within ``g``), polished as the verdict's wrong
        draws: the best distinct one keeping :data:`RIVAL_SHARE` of its support ``on`` (counted as
        ``count``), as ``(R, t, support)``, or None."""
        def landed(R, t, g):  # the sample's points within g of a target point
            return np.count_nonzero(tree.nearest(np.ascontiguousarray(sample @ R.T + t), g) >= 0)

        j = tree.nearest(np.ascontiguousarray(sample @ R.T + t), g)
        j = j[j >= 0]  # the target points the sample lands on: as many as landed(R, t, g)
        turns, slides = surface_symmetries(Ys[j], normals_c[j])
        # A turn the surface allows lays its points within a voxel before any polish (it is exact but for the
        # principal axes' error, which the turn carries across the surface); a slide along a direction the
        # surface leaves free, a small step, keeps them within the finest gate.
        own = RIVAL_SHARE * landed(R, t, gate)
        motions = [(Rr, tr) for Rr, tr in ((Rs @ R, Rs @ t + ts) for Rs, ts in turns) if landed(Rr, tr, gate) >= own]
        own = RIVAL_SHARE * j.size
        motions += [(Rr, tr) for Rr, tr in ((Rs @ R, Rs @ t + ts) for Rs, ts in slides) if landed(Rr, tr, g) >= own]
        found = None
        for Rr, tr in (verdict_polish_many(motions) if motions else []):
            if same_motion(Rr, tr, R, t, g) or landed(Rr, tr, g) < own:
                continue  # the polish brought it back (the surface holds the motion there), or it holds less
            on_r = counted(Rr, tr, g, count)[3]
            if on_r >= RIVAL_SHARE * on and (found is None or on_r > found[2]):
                found = (Rr, tr, on_r)
        return found

    def ranked_on_surface(trials) -> list:
        """The trial motions polished as the verdict's wrong draws, best supported on the surface first."""
        out = []
        for R, t in zip(trials.rotations, trials.translations):
            R, t, _, count = polish(R, t, sample, VERDICT_ITERATIONS, "normals")
            out.append(_Ranked(homogeneous(R, t), count))
        return sorted(out, key=lambda f: -f.support)

    def attempt(mode: str, info: dict) -> SurfaceMatch:
        """Stages 2-5 from the seed's streams: with the adaptive stop, drawing the whole budget, or for a
        partial overlap (shorter sides, more trials, ranked on the surface)."""
        rng = np.random.default_rng(seed)
        # Adaptive RANSAC termination in small batches; the verdict below catches a wrong motion it stops at.
        stop = (dict(batch=ADAPTIVE_BATCH, adaptive_confidence=confidence, min_share=min_overlap)
                if mode == "adaptive" else {})
        partial = mode == "partial overlap"
        span = min(diameter, target_diameter) if partial else diameter
        trials = trial_motions(Xd, index, eps=voxel, max_triples=budget, rng=rng,
                               keep=max(n_judged, PARTIAL_TRIALS) if partial else n_judged,
                               min_side=0.25 * span, max_matches=256, accept=0,
                               source_normals=nx, target_normals=ny, feature_tol=feature_tol,
                               progress=lambda f, m: report(0.1 + 0.6 * f, m), **stop)
        info.update(triples=trials.n_triples, congruent=trials.n_congruent)
        _stamp(info, "trials", t0)
        if not len(trials):
            return SurfaceMatch(None, None, voxel, none, 0, dict(info, reason="no congruent triples"))

        if partial:
            # Polished and counted on the surface, where the voxel points' support ranks a wrong motion first.
            report(0.7, "trial motions on the surface")
            fits = ranked_on_surface(trials)
        else:
            # Tensor voting judges the best trials on the downsampled sets.
            report(0.7, "tensor voting")
            tol = gate / 3.5  # so that the judge's gate is one voxel
            judged, calls = [], 0
            for m in trials.matrices:
                # A trial within the judge's reach of a motion judged already is that motion found again.
                if not any(stages.judged_alike(j, P, m, tol) for j in judged):
                    calls += 1
                    j = stages.judge(P, m, tol, max_candidates=4)
                    if j is not None:
                        judged.append(j)
            info["judged"] = calls  # of the trials' n_judged best
            fits = [j.fit for j in judged]
        if not fits:
            return SurfaceMatch(None, None, voxel, none, 0,
                                dict(info, reason="tensor voting found no consistent plane"))
        fits.sort(key=lambda f: -f.support)
        best = fits[0]
        info.update(judged_support=best.support)
        _stamp(info, "judge", t0)
        rivals = _rivals(best, fits[1:], voxel)

        # Polish: point-to-plane ICP with a shrinking gate, using the target's
        # normals.
        report(0.85, "refine")
        # The partial search compares rivals as it ranked them: by the points whose normals agree too (a
        # half-turn laid across a cropped target brings more points within the gate: 7,644 against 7,351).
        count = "normals" if partial else True
        # The rivals (judged nearly as well) are polished too, with the best and at once (in parallel), and
        # compared at full resolution.
        if defer_rivals and rivals:
            # Polished as the verdict's wrong draws are, at once: a rival that does not end on the best is
            # left to a finer grid; rivals that do are the best found again.
            motions = [(f.matrix[:3, :3], f.matrix[:3, 3]) for f in [best, *rivals]]
            if verdict:
                # The verdict polishes its first draws anyway (up to VERDICT_MIN_WRONG before it may stop at
                # VERDICT_SURE): those that fill the threads this polish would leave idle are polished with it.
                draws = wrong_draws()
                spare = min(-len(motions) % get_num_threads(), VERDICT_MIN_WRONG - draws.n_polished)
                (Rq, tq), *others = draws.polish_with(draws.n_polished + max(spare, 0), others=motions)
            else:
                (Rq, tq), *others = verdict_polish_many(motions)
            for Rr, tr in others:
                if not same_motion(Rr, tr, Rq, tq, fine):
                    return SurfaceMatch(None, None, gate, none, 0, dict(info, reason=(
                        f"ambiguous: a rival {rotation_angle_deg(Rr @ Rq.T):.0f} deg away from the best trial "
                        "motion did not end on it when polished (not judged on this grid)")))
            rivals = []
        # One after the other, each with its queries in parallel: a wrong rival polishes on for every
        # iteration where the best stops in a few, so the two side by side (one a thread) leave a thread idle.
        polished = [polish(f.matrix[:3, :3], f.matrix[:3, 3], count=count) for f in [best, *rivals]]
        R, t, g, on = polished[0]
        start = best.matrix  # the trial the motion was polished from (the verdict polishes it as its draws)
        info["ambiguous"] = False
        rival_motion = None  # a distinct polished motion holding RIVAL_SHARE of the best's support
        for rival, (Rr, tr, gr, on_r) in zip(rivals, polished[1:]):
            if same_motion(Rr, tr, R, t, max(g, gr)):
                continue  # polishing brought it onto the best motion
            if on_r > on:
                R, t, g, on, Rr, tr, gr, on_r = Rr, tr, gr, on_r, R, t, g, on
                start = rival.matrix
            if on_r >= RIVAL_SHARE * on:
                info["ambiguous"] = True
                info["rival"] = {"on_surface": on_r, "best_on_surface": on, "angle_deg": rotation_angle_deg(Rr @ R.T)}
                rival_motion = (Rr, tr)
                break
        rival_motions = {} if rival_motion is None else {"rival": rival_motion}
        if verdict and refine:
            # The surface's own symmetry may give a rival the search never drew: it finds one of the motions
            # a symmetric surface holds alike, and rivals only among those it found.
            symmetric = symmetric_rival(R, t, g, on, count)
            if symmetric is not None:
                Rr, tr, on_r = symmetric
                info["ambiguous"] = True
                info["symmetric_rival"] = {"on_surface": on_r, "best_on_surface": on,
                                           "angle_deg": rotation_angle_deg(Rr @ R.T)}
                rival_motions["symmetric_rival"] = (Rr, tr)
        info.update(final_gate=g, on_surface=on)
        _stamp(info, "polish", t0)
        if verdict:
            report(0.95, "verdict")
            # The rival is a wrong motion if this one is right: it counts first, as the search's own wrong
            # motions do, so that the verdict decides between the two at the gate where they differ most (a
            # right motion's points sit at the noise, a wrong one laid across the surface fills the gate);
            # where it cannot, the answer is no motion, not one of two motions the data hold equally.
            searched = list(rival_motions.values())
            if partial:
                searched += [(f.matrix[:3, :3], f.matrix[:3, 3]) for f in fits]
            judged, figures = surface_verdict(Xs, Ys, target_normals, R, t, voxel=voxel, gate=g,
                                               polish=verdict_polish, n_tested=max(trials.n_congruent, 1),
                                               tree=tree, noise=noise, rng=None, frame=source_frame(),
                                               searched=searched, draws=wrong_draws(), sure=VERDICT_SURE,
                                               start=(start[:3, :3], start[:3, 3]))
            info.update(verdict=judged.to_dict(), verdict_gates=figures)
            _stamp(info, "verdict", t0)
            if not judged:
                reason = judged.reason()
                for key, motion in rival_motions.items():
                    # Against the rival alone (the level it sets at each gate; the gate where this motion
                    # stands out most): failing there, the data do not tell the two apart.
                    rival_support = surface_support(Xs, Ys, target_normals, tree, *motion,
                                                    figures["gates"], figures["reach"], source_frame())
                    rival = max(gate_verdicts(figures["support"], [rival_support], max(trials.n_congruent, 1),
                                              Xs.shape[0]), key=lambda v: v.margin)
                    info[key].update(supports=[int(x) for x in rival_support])
                    if not rival:
                        reason = (f"ambiguous: two motions {info[key]['angle_deg']:.0f} deg apart explain the "
                                  f"data alike (at best {rival.support} points against the other's level of "
                                  f"{rival.chance:.0f}); " + reason)
                        break
                return SurfaceMatch(None, None, g, none, 0, dict(info, reason=reason))
        pairs = stages.nearest_pairs(Xs @ R.T + t, tree, g)
        return SurfaceMatch(R, t, g, pairs, on, info)

    if not verdict:
        return attempt("whole budget", info)
    # Stop at the first motion that passes the verdict: the adaptive search draws as many triples as the best
    # trial's inlier share needs; when its motion fails (or none is found) and it stopped short of the
    # budget, the whole budget is drawn, as without the adaptive stop; when that fails too, the search for a
    # partial overlap.
    gave: dict = {}  # the searches that gave no motion before the last one run
    out, ran = None, None
    for mode in (m for m in SEARCHES if m in searches):
        if mode == "whole budget" and out is not None and out.info["triples"] >= budget:
            continue  # the adaptive search drew the whole budget already
        if out is not None:
            gave[ran.replace(" ", "_")] = {"triples": out.info["triples"], "reason": out.info.get("reason", "")}
        out, ran = attempt(mode, dict(info)), mode
        if out:
            break
    return dataclasses.replace(out, info=dict(out.info, search=ran, **gave))
