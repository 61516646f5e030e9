"""Numba kernels of the scans pipeline: its ICPs, its k-d tree, its local planes and heights.

* :func:`screen_icp`: the short point-to-point ICP screens of the
  verdict's wrong draws (:class:`gatv.scans.WrongDraws`) and of
  :func:`gatv.motions.scans.chance_support`, every draw's whole ICP in one
  kernel, draws in parallel, nearest targets looked up in a dense grid
  (:class:`gatv.models.rigid.congruent.TargetGrid`); :func:`screened_supports`
  their supports for a list of motions.
* :class:`KDTree`: nearest and k-nearest points within a bound, as
  ``cKDTree.query`` answers, in parallel kernels; :func:`nearest_heights`:
  heights over the nearest point's tangent plane (the output's surface rows,
  :func:`gatv.scans.surface_rows`).
* :func:`occupied_cells`: the cells of a voxel grid that hold a point.
* :func:`plane_icp`, :func:`plane_icp_parallel`, :func:`plane_icp_many`:
  the point-to-plane polish (:func:`gatv.scans.refine_point_to_plane`) of
  one motion, its queries in parallel, or of several motions in parallel;
  a point's nearest target is searched again only when the point has
  moved far enough to change it (:func:`nearest_kept`).
* :func:`neighbourhood_axes`, :func:`neighbourhood_normals`,
  :func:`neighbourhood_noise`: local least-squares planes and the noise
  about them (the scans' noise and projection onto their surface, the
  verdict's source normals); :func:`local_heights`: the verdict's local
  heights (:func:`gatv.scans.surface_support`).

Pure functions over contiguous float64 arrays; each is checked against its
numpy (or scipy) reference in ``tests/test_scans_kernels.py``.
"""

from __future__ import annotations

import numpy as np
from numba import get_num_threads, njit, prange

from ._fit_kernels import kabsch3, neighbourhood_scatter
from .models.rigid.congruent_kernels import build_grid, nearest_in_grid
from .voting._eigen import eig3_batch


@njit(cache=True)
def _icp_one(X, Y, start, order, origin, cell, dims, R, t, gate, iterations, moved, idx):
    """One point-to-point ICP within ``gate`` from ``(R, t)``; returns ``(R, t, support)`` as
    :func:`gatv.scans.point_icp` (``moved`` and ``idx``: scratch of ``X``'s length)."""
    n = X.shape[0]
    for _ in range(iterations + 1):
        cnt = 0
        for i in range(n):
            for a in range(3):
                moved[i, a] = R[a, 0] * X[i, 0] + R[a, 1] * X[i, 1] + R[a, 2] * X[i, 2] + t[a]
            j = nearest_in_grid(moved[i], Y, start, order, origin, cell, dims, gate)
            idx[i] = j
            if j >= 0:
                cnt += 1
        if _ == iterations or cnt < 3:
            return R, t, cnt
        src = np.empty((cnt, 3))
        dst = np.empty((cnt, 3))
        k = 0
        for i in range(n):
            if idx[i] >= 0:
                src[k] = X[i]
                dst[k] = Y[idx[i]]
                k += 1
        R_new, t_new = kabsch3(src, dst)
        if np.abs(R_new - R).max() < 1e-9 and np.abs(t_new - t).max() < 1e-9 * gate:
            return R, t, cnt
        R, t = R_new, t_new
    return R, t, 0  # not reached


@njit(cache=True, parallel=True)
def screen_icp(X, Y, start, order, origin, cell, dims, rotations, translations, gate, iterations):
    """:func:`gatv.scans.point_icp` from each of ``rotations``, ``translations`` (draws in parallel).

    Returns ``(rotations, translations, supports)``: the motion each ICP
    reached and its points of ``X`` within ``gate`` of a point of ``Y``
    (the grid ``start, order, origin, cell, dims`` of ``Y``,
    :class:`gatv.models.rigid.congruent.TargetGrid`, cells at least ``gate``).
    """
    m = rotations.shape[0]
    n = X.shape[0]
    out_R = np.empty_like(rotations)
    out_t = np.empty_like(translations)
    support = np.empty(m, np.int64)
    for k in prange(m):
        moved = np.empty((n, 3))
        idx = np.empty(n, np.int64)
        R, t, c = _icp_one(X, Y, start, order, origin, cell, dims, rotations[k].copy(), translations[k].copy(),
                           gate, iterations, moved, idx)
        out_R[k] = R
        out_t[k] = t
        support[k] = c
    return out_R, out_t, support


def screened_supports(points: np.ndarray, grid, motions, gate: float, iterations: int) -> np.ndarray:
    """:func:`screen_icp`'s supports for each ``(R, t)`` of ``motions`` from ``points``, against ``grid``
    (a :class:`gatv.models.rigid.congruent.TargetGrid` of the target): ``(len(motions),)`` int64."""
    return screen_icp(np.ascontiguousarray(points, dtype=np.float64), grid.target, grid.start, grid.order,
                      grid.origin, grid.cell, grid.dims, np.array([R for R, _ in motions]).reshape(-1, 3, 3),
                      np.array([t for _, t in motions]).reshape(-1, 3), float(gate), int(iterations))[2]


# ------------------------------------------------------------------ voxels
@njit(cache=True)
def occupied_cells(points, cell):
    """The number of cubes ``floor(points / cell)`` that hold a point: ``len(np.unique(np.floor(points /
    cell).astype(np.int64), axis=0))`` without the sort (an open-addressing table of the cells' integer
    coordinates; collisions compare the whole coordinates, so the count is exact)."""
    n = points.shape[0]
    size = 1
    while size < 2 * n:
        size *= 2
    mask = size - 1
    used = np.zeros(size, np.bool_)
    keys = np.empty((size, 3), np.int64)
    count = 0
    for p in range(n):
        i = np.int64(np.floor(points[p, 0] / cell))
        j = np.int64(np.floor(points[p, 1] / cell))
        k = np.int64(np.floor(points[p, 2] / cell))
        h = ((i * 73856093) ^ (j * 19349663) ^ (k * 83492791)) & mask
        while used[h]:
            if keys[h, 0] == i and keys[h, 1] == j and keys[h, 2] == k:
                break
            h = (h + 1) & mask
        else:
            used[h] = True
            keys[h, 0], keys[h, 1], keys[h, 2] = i, j, k
            count += 1
    return count


# ------------------------------------------------------------------ k-d tree
#: Most points of a k-d tree leaf (:func:`kdtree_build`).
LEAF_SIZE = 16
#: Entries of a query's node stack: a search keeps at most one deferred node a level (and the median split
#: halves every level: 2⁶⁰ points).
STACK = 128


@njit(cache=True)
def _select(order, keys, lo, hi, k):
    """Reorder ``order[lo:hi + 1]`` and ``keys[lo:hi + 1]`` alike (``keys[s]``: the key of ``order[s]``) so
    that ``keys[k]`` is their ``k``-th smallest key, no key before it larger and none after it smaller
    (Hoare's selection, median-of-three pivots: linear time)."""
    while hi > lo:
        m = (lo + hi) // 2
        a, b, c = keys[lo], keys[m], keys[hi]
        pivot = max(min(a, b), min(max(a, b), c))
        i, j = lo, hi
        while i <= j:
            while keys[i] < pivot:
                i += 1
            while keys[j] > pivot:
                j -= 1
            if i <= j:
                order[i], order[j] = order[j], order[i]
                keys[i], keys[j] = keys[j], keys[i]
                i += 1
                j -= 1
        # keys[lo:j+1] <= pivot <= keys[i:hi+1], and keys[j+1:i] equal the pivot.
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            return


@njit(cache=True)
def _split_node(points, order, keys, leafsize, k, lo, hi, axis, split, left, right, count):
    """Split node ``k`` at the median of its points' widest axis into nodes ``count`` and ``count + 1``
    (True), or leave it a leaf (False: at most ``leafsize`` points, or all of them equal)."""
    a, b = lo[k], hi[k]
    if b - a <= leafsize:
        return False
    # The widest axis of the node's points (their bounding box in one pass).
    x0 = y0 = z0 = np.inf
    x1 = y1 = z1 = -np.inf
    for s in range(a, b):
        j = order[s]
        x, y, z = points[j, 0], points[j, 1], points[j, 2]
        x0, x1 = min(x0, x), max(x1, x)
        y0, y1 = min(y0, y), max(y1, y)
        z0, z1 = min(z0, z), max(z1, z)
    best, width = 0, x1 - x0
    if y1 - y0 > width:
        best, width = 1, y1 - y0
    if z1 - z0 > width:
        best, width = 2, z1 - z0
    if width <= 0.0:
        return False  # every point equal: a leaf however many
    mid = (a + b) // 2
    for s in range(a, b):  # the node's keys, contiguous for the selection
        keys[s] = points[order[s], best]
    _select(order, keys, a, b - 1, mid)
    axis[k] = best
    split[k] = keys[mid]
    lo[count], hi[count] = a, mid
    lo[count + 1], hi[count + 1] = mid, b
    left[k], right[k] = count, count + 1
    return True


@njit(cache=True)
def _grow(points, order, keys, leafsize, root, lo, hi, axis, split, left, right, count, stack):
    """Split node ``root`` and its descendants down to the leaves, the new nodes numbered from ``count``;
    returns the next free number."""
    stack[0] = root
    top = 1
    while top > 0:
        top -= 1
        k = stack[top]
        if _split_node(points, order, keys, leafsize, k, lo, hi, axis, split, left, right, count):
            stack[top] = count
            stack[top + 1] = count + 1
            top += 2
            count += 2
    return count


@njit(cache=True)
def _node_cap(n, leafsize):
    """Nodes a tree of ``n`` points may need: a node splits only above ``leafsize`` points into halves of
    at least ``leafsize // 2 + 1`` (or stays a leaf), at most ``2 n / (leafsize // 2 + 1)`` nodes; this
    bound is over twice that."""
    return 4 * (n // max(leafsize, 1) + 1) + 2


@njit(cache=True)
def _grown(a, size, fill):
    """``a`` in an array of ``size`` entries, the rest ``fill``."""
    out = np.full(size, fill, a.dtype)
    out[:a.shape[0]] = a
    return out


#: Points from which :func:`kdtree_build` grows subtrees in parallel (below, starting the threads costs more
#: than the build).
PARALLEL_BUILD = 4096


def kdtree_build(points, leafsize):
    """A balanced k-d tree of ``points`` (split at the median of the widest axis, found by selection).

    Returns ``(order, lo, hi, axis, split, left, right)``: node ``k`` holds
    ``order[lo[k]:hi[k]]``; an inner node splits on ``axis[k]`` at
    ``split[k]`` into ``left[k]`` (at most ``split``) and ``right[k]``; a
    leaf has ``axis[k] == -1``.  Node 0 is the root.

    The top levels split breadth first until twice as many nodes as numba
    has threads wait; their subtrees then grow in parallel, each numbered
    within its own share of the node arrays (a share's unused numbers are
    empty leaves that no node points to).  Every node splits as it would
    in any order, so ``order`` and the tree's shape do not depend on the
    threads.
    """
    if points.shape[0] < PARALLEL_BUILD:
        return _kdtree_build_serial(points, leafsize)
    return _kdtree_build(points, leafsize, 2 * get_num_threads())


@njit(cache=True)
def _empty_nodes(cap, n):
    """``(lo, hi, axis, split, left, right)`` of ``cap`` nodes: the root holding all ``n`` points, the others
    empty leaves."""
    lo = np.zeros(cap, np.int64)
    hi = np.zeros(cap, np.int64)
    lo[0], hi[0] = 0, n
    return lo, hi, np.full(cap, -1, np.int64), np.zeros(cap), np.full(cap, -1, np.int64), np.full(cap, -1, np.int64)


@njit(cache=True)
def _kdtree_build_serial(points, leafsize):
    """:func:`kdtree_build` in one thread, its nodes numbered depth first."""
    n = points.shape[0]
    cap = _node_cap(n, leafsize)
    lo, hi, axis, split, left, right = _empty_nodes(cap, n)
    order = np.arange(n)
    used = _grow(points, order, np.empty(n), leafsize, 0, lo, hi, axis, split, left, right, 1, np.empty(cap, np.int64))
    return order, lo[:used], hi[:used], axis[:used], split[:used], left[:used], right[:used]


@njit(cache=True, parallel=True)
def _kdtree_build(points, leafsize, frontier_size):
    """:func:`kdtree_build` with ``frontier_size`` nodes at the top levels' end."""
    n = points.shape[0]
    order = np.arange(n)
    keys = np.empty(n)
    cap = _node_cap(n, leafsize)  # every node of the tree, the top levels' among them
    lo, hi, axis, split, left, right = _empty_nodes(cap, n)
    # The top levels, breadth first.
    queue = np.empty(cap, np.int64)
    head, tail, count = 0, 1, 1
    queue[0] = 0
    while 0 < tail - head < frontier_size:
        k = queue[head]
        head += 1
        if _split_node(points, order, keys, leafsize, k, lo, hi, axis, split, left, right, count):
            queue[tail] = count
            queue[tail + 1] = count + 1
            tail += 2
            count += 2
    roots = queue[head:tail].copy()
    m = roots.shape[0]
    base = np.empty(m + 1, np.int64)
    base[0] = count
    for i in range(m):
        base[i + 1] = base[i] + _node_cap(hi[roots[i]] - lo[roots[i]], leafsize)
    if base[m] > cap:  # the subtrees' shares past the arrays: larger ones, the top levels copied
        lo, hi, axis, split, left, right = (_grown(lo, base[m], 0), _grown(hi, base[m], 0), _grown(axis, base[m], -1),
                                            _grown(split, base[m], 0.0), _grown(left, base[m], -1),
                                            _grown(right, base[m], -1))
    ends = np.empty(m, np.int64)
    for i in prange(m):
        stack = np.empty(base[i + 1] - base[i] + 2, np.int64)
        ends[i] = _grow(points, order, keys, leafsize, roots[i], lo, hi, axis, split, left, right, base[i], stack)
    used = count
    for i in range(m):
        used = max(used, ends[i])
    return order, lo[:used], hi[:used], axis[:used], split[:used], left[:used], right[:used]


@njit(cache=True)
def bounding_box(points):
    """(2, 3): the least and greatest coordinates of ``points`` along each axis, in one pass over the rows
    (numpy's ``points.min(axis=0)`` on ``(N, 3)`` rows is a strided reduction, far slower)."""
    box = np.empty((2, 3))
    box[0, :] = np.inf
    box[1, :] = -np.inf
    for i in range(points.shape[0]):
        for a in range(3):
            v = points[i, a]
            box[0, a] = min(box[0, a], v)
            box[1, a] = max(box[1, a], v)
    return box


@njit(cache=True, inline="always")
def _distance2(points, j, p):
    """Squared distance from ``points[j]`` to ``p``."""
    dx = points[j, 0] - p[0]
    dy = points[j, 1] - p[1]
    dz = points[j, 2] - p[2]
    return dx * dx + dy * dy + dz * dz


@njit(cache=True, inline="always")
def _push_root(p, box, stack, offsets, bounds):
    """Start a search from ``p``: the root on the stack with its box's offsets from ``p`` along each axis
    and their squared sum (the box's distance); returns the stack's height."""
    lb = 0.0
    for a in range(3):
        off = max(box[0, a] - p[a], 0.0, p[a] - box[1, a])
        offsets[0, a] = off
        lb += off * off
    stack[0] = 0
    bounds[0] = lb
    return 1


@njit(cache=True, inline="always")
def _push_children(p, node, top, lb, axis, split, left, right, stack, offsets, bounds):
    """Replace the inner ``node`` just popped from slot ``top`` (its box ``lb`` off ``p``) by its far child,
    then its near child above it; returns the stack's height.  The far child's box is at least the
    split's distance off along the split axis (Arya & Mount's incremental distance)."""
    d = axis[node]
    diff = p[d] - split[node]
    near, far = (left[node], right[node]) if diff < 0.0 else (right[node], left[node])
    o0, o1, o2 = offsets[top, 0], offsets[top, 1], offsets[top, 2]
    old = offsets[top, d]
    stack[top] = far
    bounds[top] = lb - old * old + diff * diff
    offsets[top, d] = abs(diff)
    stack[top + 1] = near
    bounds[top + 1] = lb
    offsets[top + 1, 0] = o0
    offsets[top + 1, 1] = o1
    offsets[top + 1, 2] = o2
    return top + 2


@njit(cache=True, inline="always")
def _nearest_two(p, points, order, lo, hi, axis, split, left, right, box, radius, stack, offsets, bounds, keep,
                 second):
    """``(j, d1, d2)``: the search of :func:`kdtree_nearest` (``j``, ``d1`` its squared distance, both -1 and
    ``radius²`` where no point is closer) and ``d2``, the squared distance of the next nearest point found;
    ``second``: nodes are skipped by ``d2`` rather than ``d1``, so that ``d2`` is the next nearest point's
    (or ``radius²``) and not only the nearest found before ``j``."""
    some = keep.shape[0] > 0
    best = -1
    d1 = radius * radius
    d2 = d1
    top = _push_root(p, box, stack, offsets, bounds)
    while top > 0:
        top -= 1
        k = stack[top]
        lb = bounds[top]
        if lb >= (d2 if second else d1):
            continue
        if axis[k] < 0:
            for s in range(lo[k], hi[k]):
                j = order[s]
                if some and not keep[j]:
                    continue
                d = _distance2(points, j, p)
                if d < d1:
                    d2 = d1
                    d1 = d
                    best = j
                elif d < d2:
                    d2 = d
            continue
        top = _push_children(p, k, top, lb, axis, split, left, right, stack, offsets, bounds)
    return best, d1, d2


@njit(cache=True)
def kdtree_nearest(p, points, order, lo, hi, axis, split, left, right, box, radius, stack, offsets, bounds, keep):
    """Index of the point of ``points`` nearest ``p`` closer than ``radius`` (or -1), as
    ``cKDTree.query(p, distance_upper_bound=radius)``; of the points ``keep`` marks alone where ``keep``
    is not empty (a search among some of the points, on the tree of all of them).

    ``box``: (2, 3) the points' bounding box.  A node is skipped when its
    box is no closer than the best found: each deferred node keeps its
    box's offset from ``p`` along each axis (Arya & Mount's incremental
    distance).  ``stack``, ``offsets`` (:data:`STACK`, 3), ``bounds``:
    scratch of :data:`STACK` entries.
    """
    return _nearest_two(p, points, order, lo, hi, axis, split, left, right, box, radius, stack, offsets, bounds, keep,
                        False)[0]


@njit(cache=True)
def kdtree_nearest2(p, points, order, lo, hi, axis, split, left, right, box, radius, stack, offsets, bounds):
    """``(j, d1, d2)``: ``j`` the point :func:`kdtree_nearest` answers for ``p`` within ``radius`` (-1: none
    closer), ``d1`` its squared distance and ``d2`` the next nearest point's (``radius²`` where none is
    closer; both ``radius²`` without ``j``).

    The same search, bounded by the second nearest found instead of the nearest: it visits the nodes
    :func:`kdtree_nearest` visits, in the same order, and more, none of which holds a point nearer than
    the nearest found before it (its box is no nearer), so ``j`` is the same point, ties included.
    """
    return _nearest_two(p, points, order, lo, hi, axis, split, left, right, box, radius, stack, offsets, bounds,
                        EVERY_POINT, True)


#: The empty mask of :func:`kdtree_nearest`'s ``keep``: every point (a constant of the compiled kernels).
EVERY_POINT = np.zeros(0, np.bool_)


@njit(cache=True)
def kdtree_knearest(p, points, order, lo, hi, axis, split, left, right, box, radius, stack, offsets, bounds,
                    best_d, best_j):
    """The ``k = best_d.shape[0]`` points of ``points`` nearest ``p`` closer than ``radius``, as
    ``cKDTree.query(p, k, distance_upper_bound=radius)``: ``best_j`` their indices, nearest first (the
    point count where fewer than ``k`` are that close), ``best_d`` their squared distances (``inf`` there).

    The search of :func:`kdtree_nearest`, bounded by the ``k``-th nearest found so far (kept sorted by
    insertion; from :data:`KNN_HEAP` neighbours on, :func:`kdtree_knn` keeps them in a heap instead,
    :func:`kdtree_knearest_heap`).
    """
    k = best_d.shape[0]
    n = points.shape[0]
    r2 = radius * radius
    for m in range(k):
        best_d[m] = np.inf
        best_j[m] = n
    top = _push_root(p, box, stack, offsets, bounds)
    while top > 0:
        top -= 1
        node = stack[top]
        lb = bounds[top]
        if lb >= min(best_d[k - 1], r2):
            continue
        if axis[node] < 0:
            for s in range(lo[node], hi[node]):
                j = order[s]
                d2 = _distance2(points, j, p)
                if d2 < best_d[k - 1] and d2 < r2:
                    m = k - 1
                    while m > 0 and best_d[m - 1] > d2:
                        best_d[m] = best_d[m - 1]
                        best_j[m] = best_j[m - 1]
                        m -= 1
                    best_d[m] = d2
                    best_j[m] = j
            continue
        top = _push_children(p, node, top, lb, axis, split, left, right, stack, offsets, bounds)


#: Neighbours from which :func:`kdtree_knn` keeps the nearest found so far in a heap (below, a sorted list:
#: an insertion moves up to ``k`` entries against a heap's ``log k``, but most move few): the two cost alike
#: at about 128 neighbours on a bunny scan (design notes, section 6, "Speed: the coarse try at half the
#: density").
KNN_HEAP = 128


@njit(cache=True, inline="always")
def _sift_up(hd, hj, i):
    """Restore the max-heap ``hd`` (``hj`` alike) above its new entry ``i``."""
    while i > 0 and hd[(i - 1) // 2] < hd[i]:
        q = (i - 1) // 2
        hd[i], hd[q] = hd[q], hd[i]
        hj[i], hj[q] = hj[q], hj[i]
        i = q


@njit(cache=True, inline="always")
def _sift_down(hd, hj, start, size):
    """Restore the max-heap ``hd`` (``hj`` alike) below ``start`` among its first ``size`` entries."""
    i = start
    while True:
        c = 2 * i + 1
        if c >= size:
            return
        if c + 1 < size and hd[c + 1] > hd[c]:
            c += 1
        if hd[c] <= hd[i]:
            return
        hd[i], hd[c] = hd[c], hd[i]
        hj[i], hj[c] = hj[c], hj[i]
        i = c


@njit(cache=True)
def kdtree_knearest_heap(p, points, order, lo, hi, axis, split, left, right, box, radius, stack, offsets, bounds,
                         best_d, best_j):
    """:func:`kdtree_knearest` for a large ``k``: the ``k`` nearest found so far in a max-heap, sorted
    nearest first at the end (among points at one distance, in another order)."""
    k = best_d.shape[0]
    n = points.shape[0]
    r2 = radius * radius
    size = 0
    top = _push_root(p, box, stack, offsets, bounds)
    while top > 0:
        top -= 1
        node = stack[top]
        lb = bounds[top]
        if lb >= min(best_d[0] if size == k else np.inf, r2):
            continue
        if axis[node] < 0:
            for s in range(lo[node], hi[node]):
                j = order[s]
                d2 = _distance2(points, j, p)
                if d2 >= r2:
                    continue
                if size < k:
                    best_d[size], best_j[size] = d2, j
                    _sift_up(best_d, best_j, size)
                    size += 1
                elif d2 < best_d[0]:
                    best_d[0], best_j[0] = d2, j
                    _sift_down(best_d, best_j, 0, size)
            continue
        top = _push_children(p, node, top, lb, axis, split, left, right, stack, offsets, bounds)
    # Heapsort: the farthest to the back, nearest first; the places no point filled: inf and n.
    for end in range(size - 1, 0, -1):
        best_d[0], best_d[end] = best_d[end], best_d[0]
        best_j[0], best_j[end] = best_j[end], best_j[0]
        _sift_down(best_d, best_j, 0, end)
    for m in range(size, k):
        best_d[m] = np.inf
        best_j[m] = n


@njit(cache=True, parallel=True)
def kdtree_knn(queries, points, order, lo, hi, axis, split, left, right, box, radius, k):
    """:func:`kdtree_knearest` of every row of ``queries`` (in parallel): ``(distances, indices)``, each
    ``(n, k)``, as ``cKDTree.query(queries, k, distance_upper_bound=radius)``."""
    n = queries.shape[0]
    dist = np.empty((n, k))
    idx = np.empty((n, k), np.int64)
    chunk = 256
    for c in prange((n + chunk - 1) // chunk):
        stack = np.empty(STACK, np.int64)
        offsets = np.empty((STACK, 3))
        bounds = np.empty(STACK)
        best_d = np.empty(k)
        best_j = np.empty(k, np.int64)
        for i in range(c * chunk, min(n, (c + 1) * chunk)):
            if k >= KNN_HEAP:
                kdtree_knearest_heap(queries[i], points, order, lo, hi, axis, split, left, right, box, radius,
                                     stack, offsets, bounds, best_d, best_j)
            else:
                kdtree_knearest(queries[i], points, order, lo, hi, axis, split, left, right, box, radius, stack,
                                offsets, bounds, best_d, best_j)
            for m in range(k):
                dist[i, m] = np.sqrt(best_d[m])
                idx[i, m] = best_j[m]
    return dist, idx


class KDTree:
    """A k-d tree for the numba kernels (:func:`kdtree_build`): nearest points within a bound.

    ``query(x, k, distance_upper_bound=r)`` answers as
    :meth:`scipy.spatial.cKDTree.query` does for an integer ``k`` (distances,
    and ``inf`` and the point count where fewer are closer than ``r``; for
    ``k > 1`` an ``(n, k)`` result, nearest first), in a parallel kernel.
    """

    def __init__(self, points: np.ndarray, leafsize: int = LEAF_SIZE):
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        if self.points.ndim != 2 or self.points.shape[1] != 3 or self.points.shape[0] < 1:
            raise ValueError(f"Expected `points` of shape (N, 3), N >= 1, got {self.points.shape}.")
        #: ``(order, lo, hi, axis, split, left, right, box)``: the kernels' arguments after ``points``.
        self.nodes = (*kdtree_build(self.points, int(leafsize)), bounding_box(self.points))

    @property
    def data(self) -> np.ndarray:
        """The points (as ``cKDTree.data``)."""
        return self.points

    @property
    def n(self) -> int:
        """The point count (as ``cKDTree.n``)."""
        return int(self.points.shape[0])

    def nearest(self, queries: np.ndarray, radius: float, keep: np.ndarray | None = None) -> np.ndarray:
        """Index of each query's nearest point closer than ``radius``, or -1; ``keep``: a boolean mask of
        the points, the nearest among those it marks."""
        q = np.ascontiguousarray(queries, dtype=np.float64).reshape(-1, 3)
        if keep is None:
            keep = EVERY_POINT
        elif np.shape(keep) != (self.n,):
            raise ValueError(f"Expected `keep` of shape ({self.n},), got {np.shape(keep)}.")
        return kdtree_query(q, self.points, *self.nodes, float(radius), np.asarray(keep, dtype=np.bool_))

    def query(self, x, k=1, distance_upper_bound=np.inf, *, keep: np.ndarray | None = None, **options):
        """``(distances, indices)`` as :meth:`scipy.spatial.cKDTree.query`; for ``k = 1``, among the points
        the boolean mask ``keep`` marks where given (:meth:`nearest`)."""
        x = np.asarray(x, dtype=np.float64)
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
            raise ValueError(f"Expected `k` to be a positive integer, got {k!r}.")
        if k != 1:
            if keep is not None:
                raise ValueError("`keep` is for the nearest point alone (k=1).")
            q = np.ascontiguousarray(x).reshape(-1, 3)
            d, j = kdtree_knn(q, self.points, *self.nodes, float(distance_upper_bound), int(k))
            return d.reshape(x.shape[:-1] + (k,)), j.reshape(x.shape[:-1] + (k,))
        j = self.nearest(x, distance_upper_bound, keep)
        d = np.full(j.shape[0], np.inf)
        ok = j >= 0
        d[ok] = np.sqrt(((x.reshape(-1, 3)[ok] - self.points[j[ok]]) ** 2).sum(axis=1))
        j[~ok] = self.n
        return d.reshape(x.shape[:-1]), j.reshape(x.shape[:-1])


@njit(cache=True, parallel=True)
def kdtree_query(queries, points, order, lo, hi, axis, split, left, right, box, radius, keep):
    """:func:`kdtree_nearest` of every row of ``queries`` (in parallel; ``keep``: its mask, empty for
    every point)."""
    n = queries.shape[0]
    out = np.empty(n, np.int64)
    chunk = 256
    for c in prange((n + chunk - 1) // chunk):
        stack = np.empty(STACK, np.int64)
        offsets = np.empty((STACK, 3))
        bounds = np.empty(STACK)
        for i in range(c * chunk, min(n, (c + 1) * chunk)):
            out[i] = kdtree_nearest(queries[i], points, order, lo, hi, axis, split, left, right, box, radius, stack,
                                    offsets, bounds, keep)
    return out


@njit(cache=True, parallel=True)
def nearest_heights(points, rows, normals, tree_points, order, lo, hi, axis, split, left, right, box, radius):
    """For each of ``rows`` (rows of ``points``): the height ``|(p - y) · n|`` of its point ``p`` over the
    tangent plane of its nearest tree point ``y`` within ``radius`` (:func:`kdtree_query`; ``n`` that
    point's row of ``normals``), ``inf`` where none is that close (:func:`gatv.scans.surface_rows`' test, in
    one kernel: no numpy copies of the nearest points and their normals)."""
    n = rows.shape[0]
    q = np.empty((n, 3))
    for i in prange(n):
        for a in range(3):
            q[i, a] = points[rows[i], a]
    near = kdtree_query(q, tree_points, order, lo, hi, axis, split, left, right, box, radius, EVERY_POINT)
    out = np.full(n, np.inf)
    for i in prange(n):
        j = near[i]
        if j >= 0:
            out[i] = abs((q[i, 0] - tree_points[j, 0]) * normals[j, 0] + (q[i, 1] - tree_points[j, 1]) * normals[j, 1]
                         + (q[i, 2] - tree_points[j, 2]) * normals[j, 2])
    return out


# ------------------------------------------------------------------ point-to-plane ICP
@njit(cache=True)
def rotvec_matrix(w):
    """Rotation matrix of the rotation vector ``w`` (Rodrigues; the identity below 1e-300)."""
    theta = np.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    R = np.eye(3)
    if theta < 1e-300:
        return R
    a = w / theta
    K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return R + np.sin(theta) * K + (1.0 - np.cos(theta)) * (K @ K)


@njit(cache=True)
def _plane_step(Y, N, moved, idx, R, t, gate):
    """One step of :func:`plane_icp` from the moved source points and their nearest targets ``idx`` (-1:
    none within the gate): ``(R, t, step)``, the motion updated and ``step`` how far it moved the source,
    in gates (the rotation at the farthest pair plus the translation); the motion unchanged and ``step``
    -1 when fewer than six pair."""
    n = moved.shape[0]
    cnt = 0
    c = np.zeros(3)
    for i in range(n):
        if idx[i] >= 0:
            cnt += 1
            c += moved[i]
    if cnt < 6:
        return R, t, -1.0
    c /= cnt
    huber = 0.3 * gate
    rcond = 6.0 * np.finfo(np.float64).eps  # numpy's lstsq default for a 6 x 6 system
    M = np.zeros((6, 6))
    v = np.zeros(6)
    row = np.empty(6)
    reach = 0.0
    for i in range(n):
        j = idx[i]
        if j < 0:
            continue
        px, py, pz = moved[i, 0] - c[0], moved[i, 1] - c[1], moved[i, 2] - c[2]
        nx, ny, nz = N[j, 0], N[j, 1], N[j, 2]
        r = (moved[i, 0] - Y[j, 0]) * nx + (moved[i, 1] - Y[j, 1]) * ny + (moved[i, 2] - Y[j, 2]) * nz
        w = 1.0 if abs(r) <= huber else huber / max(abs(r), 1e-300)
        row[0] = py * nz - pz * ny
        row[1] = pz * nx - px * nz
        row[2] = px * ny - py * nx
        row[3], row[4], row[5] = nx, ny, nz
        for a in range(6):
            v[a] -= w * row[a] * r
            for b in range(6):
                M[a, b] += w * row[a] * row[b]
        reach = max(reach, abs(px), abs(py), abs(pz))
    x = np.linalg.lstsq(M, v, rcond)[0]
    omega = x[:3].copy()
    delta = x[3:].copy()
    Rinc = rotvec_matrix(omega)
    R = Rinc @ R
    t = Rinc @ (t - c) + c + delta
    return R, t, (np.sqrt(omega @ omega) * reach + np.sqrt(delta @ delta)) / gate


@njit(cache=True, inline="always")
def _stops(step, last, tol, stall):
    """Whether :func:`plane_icp` ends after a step of ``step`` gates (-1: fewer than six pairs) that followed
    one of ``last``: under ``tol``, or under ``stall`` without halving the last.  Near its minimum a
    well-held motion's steps shrink by an order of magnitude or more each; steps that stay alike are a
    slide along a direction the surface barely holds, or pairs traded back and forth, which more steps
    only repeat (``stall`` 0: polish on to ``tol``)."""
    return step < tol or (step < stall and step > 0.5 * last)


#: The reach of :func:`nearest_kept`'s searches, in gates: how far a point's next nearest target is looked
#: for; a point with no target that close stays without one, unsearched, until it has moved ``REACH - 1``
#: gates.  A farther reach keeps more points unsearched and makes every search dearer: on the clean and
#: 50% clutter benchmark rows' polishes, 1.25-1.5 gates searched least (design notes, section 6, "Speed:
#: the coarse try at half the density").
REACH = 1.5


@njit(cache=True, inline="always")
def nearest_kept(q, Y, order, lo, hi, axis, split, left, right, box, gate, margin, anchor, near, gap, i, stack,
                 offsets, bounds):
    """:func:`kdtree_nearest` of ``q`` within ``gate`` (the same index, to the last bit), searched again
    only when the point ``i`` has moved far enough since its last search to need it.

    A search from ``anchor[i]`` found its nearest target ``near[i]`` (-1: none within :data:`REACH`
    gates) and ``gap[i]``: the next nearest one's distance less the nearest's, less ``margin`` (rounding).
    After a move by ``D = |q - anchor[i]|`` the nearest is ``near[i]`` still while ``2 D < gap[i]`` (it
    came at most ``D`` nearer, every other target at most ``D`` farther: the triangle inequality), and
    it pairs where its own distance is under the gate, as the search would find; a point with no
    target within the reach has none within the gate while ``D`` is under the reach less the gate and
    ``margin``.  Otherwise a search (:func:`kdtree_nearest2` at the reach) starts again from ``q``.  Set
    ``anchor[i]`` to NaN to search the first time.  An ICP near its minimum moves its points by a small
    share of the sampling each step, so most of its steps search for few of them.
    """
    d = 0.0
    for a in range(3):
        d += (q[a] - anchor[i, a]) ** 2
    moved = np.sqrt(d)  # NaN before the first search: no test below passes
    j = near[i]
    reach = REACH * gate
    if j >= 0:
        if 2.0 * moved < gap[i]:
            return j if _distance2(Y, j, q) < gate * gate else -1
    elif moved < reach - gate - margin:
        return -1
    j, d1, d2 = kdtree_nearest2(q, Y, order, lo, hi, axis, split, left, right, box, reach, stack, offsets, bounds)
    for a in range(3):
        anchor[i, a] = q[a]
    near[i] = j
    gap[i] = np.sqrt(d2) - np.sqrt(d1) - margin
    return j if j >= 0 and d1 < gate * gate else -1


@njit(cache=True, inline="always")
def _move_and_pair(i, X, R, t, moved, idx, Y, order, lo, hi, axis, split, left, right, box, gate, margin, anchor,
                   near, gap, stack, offsets, bounds):
    """``moved[i] = R X[i] + t`` and ``idx[i]`` its nearest target within ``gate`` (-1: none), by
    :func:`nearest_kept`."""
    for a in range(3):
        moved[i, a] = R[a, 0] * X[i, 0] + R[a, 1] * X[i, 1] + R[a, 2] * X[i, 2] + t[a]
    idx[i] = nearest_kept(moved[i], Y, order, lo, hi, axis, split, left, right, box, gate, margin, anchor, near, gap,
                          i, stack, offsets, bounds)


@njit(cache=True)
def pairing_state(n, box, gate):
    """``(anchor, near, gap, margin)`` of :func:`nearest_kept` for ``n`` points, before any search, on
    targets in ``box``: ``margin`` covers the rounding of distances between coordinates of that size."""
    anchor = np.full((n, 3), np.nan)
    near = np.full(n, -1, np.int64)
    gap = np.zeros(n)
    scale = 0.0
    for a in range(3):
        scale = max(scale, abs(box[0, a]), abs(box[1, a]))
    return anchor, near, gap, 1e-9 * gate + 1e-12 * scale


@njit(cache=True)
def plane_icp(X, Y, N, order, lo, hi, axis, split, left, right, box, R, t, gate, iterations, tol, stall):
    """Point-to-plane ICP inside ``gate``: :func:`gatv.scans.refine_point_to_plane` with its nearest
    targets from the k-d tree ``order, ..., box`` of ``Y`` (:class:`KDTree`); ``N``: ``Y``'s unit normals.

    Each iteration minimises ``sum w ((R x + t - y) · n_y)²`` linearised in a small rotation about the
    pairs' centroid (Huber weights at 0.3 ``gate``), its 6 x 6 normal equations solved for least squares
    of minimum norm (:func:`_plane_step`).  Stops after ``iterations``, when fewer than six points pair,
    once a step moves the source by less than ``tol`` gates, or once a step under ``stall`` gates moves
    it by more than half the step before (:func:`_stops`).  Returns ``(R, t)``.  One thread (the
    kernel of :func:`plane_icp_many`'s parallel starts); :func:`plane_icp_parallel` queries in parallel.
    """
    n = X.shape[0]
    idx = np.empty(n, np.int64)
    moved = np.empty((n, 3))
    stack = np.empty(STACK, np.int64)
    offsets = np.empty((STACK, 3))
    bounds = np.empty(STACK)
    anchor, near, gap, margin = pairing_state(n, box, gate)
    R = R.copy()
    t = t.copy()
    last = np.inf
    for _ in range(iterations):
        for i in range(n):
            _move_and_pair(i, X, R, t, moved, idx, Y, order, lo, hi, axis, split, left, right, box, gate, margin,
                           anchor, near, gap, stack, offsets, bounds)
        R, t, step = _plane_step(Y, N, moved, idx, R, t, gate)
        if _stops(step, last, tol, stall):
            break
        last = step
    return R, t


@njit(cache=True, parallel=True)
def plane_icp_parallel(X, Y, N, order, lo, hi, axis, split, left, right, box, R, t, gate, iterations, tol, stall):
    """:func:`plane_icp` with each iteration's nearest-target queries in parallel (chunks of points; the
    step that follows sums in the points' order, so the result is :func:`plane_icp`'s to the last bit)."""
    n = X.shape[0]
    idx = np.empty(n, np.int64)
    moved = np.empty((n, 3))
    anchor, near, gap, margin = pairing_state(n, box, gate)
    R = R.copy()
    t = t.copy()
    last = np.inf
    chunk = 256
    for _ in range(iterations):
        for ch in prange((n + chunk - 1) // chunk):
            stack = np.empty(STACK, np.int64)
            offsets = np.empty((STACK, 3))
            bounds = np.empty(STACK)
            for i in range(ch * chunk, min(n, (ch + 1) * chunk)):
                _move_and_pair(i, X, R, t, moved, idx, Y, order, lo, hi, axis, split, left, right, box, gate,
                               margin, anchor, near, gap, stack, offsets, bounds)
        R, t, step = _plane_step(Y, N, moved, idx, R, t, gate)
        if _stops(step, last, tol, stall):
            break
        last = step
    return R, t


@njit(cache=True, parallel=True)
def plane_icp_many(X, Y, N, order, lo, hi, axis, split, left, right, box, rotations, translations, gates,
                   iterations, tols, stalls):
    """:func:`plane_icp` from each of ``rotations``, ``translations`` through every gate of ``gates`` in
    turn (``iterations``, ``tols[g]`` and ``stalls[g]`` at gate ``g``), the starts in parallel: the
    coarse-to-fine polish of several motions at once.  Returns ``(rotations, translations)``."""
    m = rotations.shape[0]
    out_R = np.empty_like(rotations)
    out_t = np.empty_like(translations)
    for k in prange(m):
        R = rotations[k].copy()
        t = translations[k].copy()
        for g in range(gates.shape[0]):
            R, t = plane_icp(X, Y, N, order, lo, hi, axis, split, left, right, box, R, t, gates[g], iterations,
                             tols[g], stalls[g])
        out_R[k] = R
        out_t[k] = t
    return out_R, out_t


# ------------------------------------------------------------------ local planes
def neighbourhood_axes(points: np.ndarray, neighbours: np.ndarray, m: int):
    """``(centroids, values, axes)``: the mean of each row's first ``m`` ``neighbours`` (rows of ``points``),
    and the eigenvalues (descending) and unit eigenvectors (``axes[i, :, j]`` of ``values[i, j]``) of their
    scatter about it: ``axes[:, :, 2]`` is the normal (unoriented) of their least-squares plane.  As
    :func:`gatv.scans.local_scatter`'s (ascending there) up to sign and rounding."""
    centroids, scatter = neighbourhood_scatter(np.ascontiguousarray(points, dtype=np.float64),
                                               np.ascontiguousarray(neighbours, dtype=np.int64), int(m))
    values = np.empty((scatter.shape[0], 3))
    axes = np.empty((scatter.shape[0], 3, 3))
    eig3_batch(scatter, values, axes)
    return centroids, values, axes


def neighbourhood_normals(points: np.ndarray, neighbours: np.ndarray, m: int) -> np.ndarray:
    """``(N, 3)`` unit least-variance axes (unoriented) of each row's first ``m`` ``neighbours``: the normals
    of their least-squares planes (:func:`neighbourhood_axes`)."""
    return np.ascontiguousarray(neighbourhood_axes(points, neighbours, m)[2][:, :, 2])


@njit(cache=True, parallel=True)
def neighbourhood_noise(points, neighbours, m, centroids, axes, radius, quadric):
    """Robust deviation of each row's first ``m`` ``neighbours`` (rows of ``points``) about its local
    surface: ``1.4826 · median |r|`` of their residuals ``r`` along the normal ``axes[i, :, 2]`` from the
    plane through ``centroids[i]``, or with ``quadric`` from the least-squares quadric over the tangent
    plane (axes ``axes[i, :, 0]``, ``axes[i, :, 1]``, in units of ``radius[i]``, ridge 1e-9), scaled by
    ``sqrt(m / (m - p))`` for the fit's ``p`` parameters (3 or 6): :func:`gatv.scans.scan_noise`'s fits.
    ``axes``: :func:`neighbourhood_axes`'s (descending)."""
    n = neighbours.shape[0]
    sd = np.empty(n)
    params = 6 if quadric else 3
    factor = 1.4826 * np.sqrt(m / max(m - params, 1))
    for i in prange(n):
        h = np.empty(m)
        basis = np.empty((m, 6))  # the quadric's terms in the tangent plane
        scale = max(radius[i], 1e-300)
        for a in range(m):
            q = neighbours[i, a]
            x = points[q, 0] - centroids[i, 0]
            y = points[q, 1] - centroids[i, 1]
            z = points[q, 2] - centroids[i, 2]
            h[a] = x * axes[i, 0, 2] + y * axes[i, 1, 2] + z * axes[i, 2, 2]
            if quadric:
                u = (x * axes[i, 0, 0] + y * axes[i, 1, 0] + z * axes[i, 2, 0]) / scale
                v = (x * axes[i, 0, 1] + y * axes[i, 1, 1] + z * axes[i, 2, 1]) / scale
                basis[a, 0], basis[a, 1], basis[a, 2] = u * u, u * v, v * v
                basis[a, 3], basis[a, 4], basis[a, 5] = u, v, 1.0
        if quadric:
            normal = np.empty((6, 6))
            rhs = np.empty(6)
            for p in range(6):
                for q in range(p, 6):
                    acc = 0.0
                    for a in range(m):
                        acc += basis[a, p] * basis[a, q]
                    normal[p, q] = acc
                    normal[q, p] = acc
                normal[p, p] += 1e-9
                acc = 0.0
                for a in range(m):
                    acc += basis[a, p] * h[a]
                rhs[p] = acc / scale
            coef = _cholesky_solve(normal, rhs)
            for a in range(m):
                fit = 0.0
                for p in range(6):
                    fit += basis[a, p] * coef[p]
                h[a] -= scale * fit
        for a in range(m):
            h[a] = abs(h[a])
        sd[i] = factor * _median(h)
    return sd


@njit(cache=True)
def _cholesky_solve(A, b):
    """``A⁻¹ b`` for a small symmetric positive definite ``A`` (the ridged normal equations of
    :func:`neighbourhood_noise`'s quadric), by Cholesky: hand-written, as numba's ``np.linalg.solve`` in a
    ``prange`` body cost seconds of compilation."""
    n = b.shape[0]
    L = np.zeros((n, n))
    for j in range(n):
        d = A[j, j]
        for k in range(j):
            d -= L[j, k] * L[j, k]
        d = np.sqrt(max(d, 1e-300))
        L[j, j] = d
        for r in range(j + 1, n):
            v = A[r, j]
            for k in range(j):
                v -= L[r, k] * L[j, k]
            L[r, j] = v / d
    y = np.empty(n)
    for r in range(n):
        v = b[r]
        for k in range(r):
            v -= L[r, k] * y[k]
        y[r] = v / L[r, r]
    x = np.empty(n)
    for r in range(n - 1, -1, -1):
        v = y[r]
        for k in range(r + 1, n):
            v -= L[k, r] * x[k]
        x[r] = v / L[r, r]
    return x


@njit(cache=True)
def _median(a):
    """``np.median(a)`` of a non-empty array, reordering it: the middle value, or the mean of the two."""
    n = a.shape[0]
    _select(np.empty(n, np.int64), a, np.int64(0), np.int64(n - 1), np.int64(n // 2))  # the k-d tree's selection
    upper = a[n // 2]
    if n % 2:
        return upper
    lower = a[0]
    for t in range(n // 2):  # after the selection the lower half holds the n // 2 smallest
        lower = max(lower, a[t])
    return 0.5 * (lower + upper)


# ------------------------------------------------------------------ the verdict's local heights
@njit(cache=True, parallel=True)
def local_heights(moved, idx, Y, N, moved_normals, neighbours, agreement):
    """Each moved source point's *local height* over its nearest target sample's tangent plane
    (:func:`gatv.scans.surface_support`): where its normal (``moved_normals``) agrees with the sample's
    (``|cos| >= agreement``), the mean over its ``neighbours`` (rows of ``moved``, itself among them) that
    have a nearest sample (``idx >= 0``) of their offset from that sample along this point's sample's
    normal, in absolute value; ``inf`` where it has no sample or the normals disagree."""
    n = moved.shape[0]
    k = neighbours.shape[1]
    h = np.full(n, np.inf)
    for i in prange(n):
        j = idx[i]
        if j < 0:
            continue
        nx, ny, nz = N[j, 0], N[j, 1], N[j, 2]
        if abs(moved_normals[i, 0] * nx + moved_normals[i, 1] * ny + moved_normals[i, 2] * nz) < agreement:
            continue
        s = 0.0
        c = 0
        for m in range(k):
            q = neighbours[i, m]
            jq = idx[q]
            if jq >= 0:
                s += (moved[q, 0] - Y[jq, 0]) * nx + (moved[q, 1] - Y[jq, 1]) * ny + (moved[q, 2] - Y[jq, 2]) * nz
                c += 1
        h[i] = abs(s) / max(c, 1)
    return h
