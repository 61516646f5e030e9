"""Candidate pairs (tokens) and the one-to-one selection.

A candidate pair ``(i, j)`` matches source point ``i`` with target point
``j``; its token in the ``{dx, dy, dz}`` joint space of eq. 30 is
``d = target[j] - source[i]`` (after the source is rotated by a trial
rotation, when there is one).
"""

from __future__ import annotations

import numpy as np
from numba import get_num_threads, njit
from scipy.spatial import cKDTree

from ._validation import check_finite_array, check_memory
from .errors import InputError

__all__ = [
    "all_pairs",
    "pairs_within",
    "bounded_pairs",
    "one_to_one",
    "median_spacing",
]

#: Bytes one candidate pair costs downstream (indices, token, votes, eigen).
BYTES_PER_CANDIDATE_PAIR = 2 * 8 + 3 * 8 + 9 * 8 + 12 * 8


def median_spacing(points, *, tree=None) -> float:
    """Median distance from each point to its nearest other point (> 0).

    Duplicated points are left out of the median (their distance 0 says
    nothing of the sampling).  When no positive distance is left, a small
    fraction (1e-6) of the bounding-box diagonal, or 1.0 for a single point.

    Parameters
    ----------
    points : (N, d) array_like or object with ``.points``
    tree : optional
        A k-d tree of ``points`` the caller holds (:class:`scipy.spatial.cKDTree`
        or the scans pipeline's numba tree: anything with ``query(x, k=2)``);
        built when omitted.

    Examples
    --------
    >>> median_spacing([[0.0, 0, 0], [1, 0, 0], [3, 0, 0]])
    1.0
    """
    if hasattr(points, "points") and not isinstance(points, np.ndarray):
        points = points.points
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[0] < 1:
        raise InputError(f"Expected `points` to have shape (N, d), got {p.shape}.")
    check_finite_array(p, "points")
    if p.shape[0] < 2:
        return 1.0
    tree = cKDTree(p) if tree is None else tree
    d, _ = tree.query(p, k=2, workers=get_num_threads())  # numba's threads: a batch worker's share
    nn = d[:, 1]
    pos = nn[nn > 0]
    if pos.size:
        return float(np.median(pos))
    diag = float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))
    return 1e-6 * diag if diag > 0 else 1.0


def all_pairs(n_source: int, n_target: int, *, memory_budget=None) -> np.ndarray:
    """Every pair ``(i, j)``, the paper's default matching scheme (section 3.4)."""
    check_memory(float(n_source) * n_target * BYTES_PER_CANDIDATE_PAIR,
                 f"{n_source} x {n_target} = {n_source * n_target} candidate pairs", memory_budget)
    i, j = np.meshgrid(np.arange(n_source), np.arange(n_target), indexing="ij")
    return np.stack([i.ravel(), j.ravel()], axis=1)


def pairs_within(moved_source: np.ndarray, target: np.ndarray, radius, *,
                 tree: cKDTree | None = None, memory_budget=None) -> np.ndarray:
    """Pairs ``(i, j)`` with ``|target[j] - moved_source[i]| <= radius``, sorted.

    ``radius`` may be a scalar or one radius per source point.
    """
    tree = cKDTree(target) if tree is None else tree
    r = np.broadcast_to(np.asarray(radius, dtype=np.float64), (moved_source.shape[0],))
    if moved_source.shape[0] == 0:
        return np.zeros((0, 2), np.int64)
    # Expected count from the mean density, checked before materialising.
    n_t = target.shape[0]
    vol = float(np.prod(np.maximum(np.ptp(target, axis=0), 1e-300)))
    expected = float(np.sum(np.minimum(n_t, n_t * (4.0 / 3.0) * np.pi * r**3 / vol)))
    check_memory(expected * BYTES_PER_CANDIDATE_PAIR, f"about {expected:.3g} candidate pairs", memory_budget)
    m = cKDTree(moved_source).sparse_distance_matrix(tree, float(r.max()), output_type="ndarray")
    keep = m["v"] <= r[m["i"]]
    pairs = np.stack([m["i"][keep], m["j"][keep]], axis=1).astype(np.int64)
    order = np.lexsort((pairs[:, 1], pairs[:, 0]))
    return pairs[order]


def bounded_pairs(source: np.ndarray, target: np.ndarray, max_angle: float,
                  max_translation: float | None, *, memory_budget=None) -> np.ndarray:
    """Pairs a bounded motion allows (the paper's small-motion "optimised version").

    A motion ``x' = R x + t`` with rotation angle at most ``max_angle``
    (radians, about the coordinate origin) and ``|t| <= max_translation``
    moves ``x`` by at most ``max_translation + 2 sin(max_angle / 2) |x|``,
    so only target points within that radius of ``x`` are candidates.
    With ``max_translation=None`` the translation is unbounded and the
    bound is applied after removing the centroid difference.
    """
    if max_translation is None:
        shift = target.mean(axis=0) - source.mean(axis=0)
        moved = source + shift
        # Unknown translation: the centroid shift absorbs it up to the
        # rotation of the centroid and the outliers' imbalance; allow the
        # spread of the sets as slack.
        slack = float(np.linalg.norm(target.std(axis=0)) + np.linalg.norm(source.std(axis=0)))
        radius = 2.0 * np.sin(max_angle / 2.0) * np.linalg.norm(source - source.mean(axis=0), axis=1) + slack
        return pairs_within(moved, target, radius, memory_budget=memory_budget)
    radius = max_translation + 2.0 * np.sin(max_angle / 2.0) * np.linalg.norm(source, axis=1)
    return pairs_within(source, target, radius, memory_budget=memory_budget)


@njit(cache=True)
def _greedy_unique(i_idx, j_idx, order, n_i, n_j):
    used_i = np.zeros(n_i, np.bool_)
    used_j = np.zeros(n_j, np.bool_)
    keep = np.empty(order.shape[0], np.int64)
    m = 0
    for k in order:
        i = i_idx[k]
        j = j_idx[k]
        if used_i[i] or used_j[j]:
            continue
        used_i[i] = True
        used_j[j] = True
        keep[m] = k
        m += 1
    return keep[:m]


@njit(cache=True)
def _cheapest_rows(targets, cost, n_targets):
    """:func:`one_to_one_rows`' rows: each target's cheapest (the earlier on a tie), ascending."""
    best = np.full(n_targets, -1, np.int64)
    for k in range(targets.shape[0]):
        b = best[targets[k]]
        if b < 0 or cost[k] < cost[b]:  # strictly cheaper: a tie stays with the earlier row
            best[targets[k]] = k
    keep = np.empty(targets.shape[0], np.int64)
    m = 0
    for k in range(targets.shape[0]):
        if best[targets[k]] == k:
            keep[m] = k
            m += 1
    return keep[:m]


def one_to_one_rows(targets: np.ndarray, cost: np.ndarray) -> np.ndarray:
    """:func:`one_to_one` of the pairs ``(k, targets[k])``, one a source row, in row order.

    With every source index used once, only targets can clash, and the
    greedy rule keeps each target's cheapest row (ties to the earlier):
    the same rows as ``sorted(one_to_one(...))``, in linear time, without
    sorting by cost (each moved point's nearest target, made one to one).
    Returns the kept rows' indices, ascending.
    """
    targets = np.asarray(targets, dtype=np.int64).reshape(-1)
    cost = np.asarray(cost, dtype=np.float64).reshape(-1)
    if targets.shape != cost.shape:
        raise InputError(f"Expected `targets` and `cost` of one length, got {targets.shape[0]} and {cost.shape[0]}.")
    if targets.size == 0:
        return np.zeros(0, np.int64)
    if targets.min() < 0:
        raise InputError(f"Expected `targets` of indices >= 0, got {int(targets.min())}.")
    return _cheapest_rows(targets, cost, int(targets.max()) + 1)


def one_to_one(pairs: np.ndarray, cost: np.ndarray) -> np.ndarray:
    """Greedy one-to-one subset of ``pairs``, cheapest first.

    Each source index and each target index is used at most once; ties go
    to the earlier pair.  Returns the kept rows' indices into ``pairs``.
    """
    if pairs.shape[0] == 0:
        return np.zeros(0, np.int64)
    pairs = np.asarray(pairs, dtype=np.int64)
    order = np.argsort(np.asarray(cost, dtype=np.float64), kind="stable")
    return _greedy_unique(np.ascontiguousarray(pairs[:, 0]), np.ascontiguousarray(pairs[:, 1]),
                          order, int(pairs[:, 0].max()) + 1, int(pairs[:, 1].max()) + 1)
