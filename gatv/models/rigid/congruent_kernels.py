"""Numba kernels for trial rotations from congruent point triples.

Side lengths of a triangle survive any rigid motion, so three true
matches ``(a, b, c) <-> (k, l, m)`` are found by looking up target pairs
of the same length (:func:`triple_hypotheses`); side-length *ratios*
survive any similarity, so :func:`similar_triple_hypotheses` looks up
target triangles of the same shape at any scale in a range.  :func:`polish_icp`
polishes trial motions by ICP on the scoring grid (LO-RANSAC's local step).
The kernels here are pure: arrays and scalars in, arrays out.
:mod:`gatv.models.rigid.congruent` validates input and drives them.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..._fit_kernels import kabsch3, triangle_pose, umeyama3

# Defaults of the optional array arguments (no visiting order, no occupancy grid).
_NO_VISIT = np.zeros(0, np.int64)
_NO_OCC = np.zeros(0, np.uint8)
_HALF_BOX = np.zeros(0)
_ORIGIN = np.zeros(3)
_DIMS = np.ones(3, np.int64)


def _prange_only():
    """numba's ``parallel`` option with only ``prange`` loops made parallel.

    ``parallel=True`` also turns the kernels' output allocations (``np.zeros``,
    ``np.full``) into parallel loops, each compiled as one more outlined
    function with its wrappers.  A fresh dict for each use: numba empties
    the one it is given.
    """
    return {"comprehension": False, "reduction": False, "inplace_binop": False, "setitem": False,
            "numpy": False, "stencil": False, "fusion": False, "prange": True}


@njit(cache=True)
def pair_table(points):
    """All pairs ``i < j`` of ``points`` sorted by length.

    Returns ``(lengths, i, j)`` with ``lengths`` ascending.
    """
    n = points.shape[0]
    m = n * (n - 1) // 2
    lengths = np.empty(m)
    pi = np.empty(m, np.int32)
    pj = np.empty(m, np.int32)
    k = 0
    for i in range(n):
        for j in range(i + 1, n):
            dx = points[i, 0] - points[j, 0]
            dy = points[i, 1] - points[j, 1]
            dz = points[i, 2] - points[j, 2]
            lengths[k] = np.sqrt(dx * dx + dy * dy + dz * dz)
            pi[k] = i
            pj[k] = j
            k += 1
    order = np.argsort(lengths, kind="mergesort")
    return lengths[order], pi[order], pj[order]


@njit(cache=True, parallel=True)
def sorted_neighbours(points):
    """For each point, the other points sorted by distance.

    Returns ``(dist, idx)``, both (n, n - 1), rows ascending in distance.
    """
    n = points.shape[0]
    dist = np.empty((n, n - 1))
    idx = np.empty((n, n - 1), np.int32)
    for i in prange(n):
        d = np.empty(n - 1)
        ix = np.empty(n - 1, np.int32)
        c = 0
        for j in range(n):
            if j == i:
                continue
            dx = points[i, 0] - points[j, 0]
            dy = points[i, 1] - points[j, 1]
            dz = points[i, 2] - points[j, 2]
            d[c] = np.sqrt(dx * dx + dy * dy + dz * dz)
            ix[c] = j
            c += 1
        o = np.argsort(d)
        for c in range(n - 1):
            dist[i, c] = d[o[c]]
            idx[i, c] = ix[o[c]]
    return dist, idx


@njit(cache=True)
def _lower_bound_in(a, x, lo, hi):
    """First index ``i`` in ``[lo, hi]`` with ``a[i] >= x`` (``a`` ascending; the answer known to lie there)."""
    while lo < hi:
        mid = (lo + hi) >> 1
        if a[mid] < x:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True)
def _lower_bound(a, x):
    """First index of the ascending ``a`` with ``a[i] >= x`` (``np.searchsorted``, side ``left``)."""
    return _lower_bound_in(a, x, np.int64(0), a.shape[0])


@njit(cache=True)
def length_lookup(plen, per_bucket=16):
    """Bucket table of the sorted lengths ``plen``: ``(bounds, step)``.

    ``bounds[b]`` is the first index of ``plen`` at or above ``b * step``,
    with buckets holding ``per_bucket`` lengths on average: a lower bound
    then searches one bucket's range (:func:`_lower_bound_lookup`) instead
    of the whole table, whose random reads miss the cache when it holds
    10⁵–10⁶ lengths.
    """
    n = plen.shape[0]
    buckets = max(1, n // per_bucket)
    top = plen[n - 1] if n > 0 else 0.0
    step = top / buckets if top > 0.0 else 1.0
    bounds = np.empty(buckets + 1, np.int64)
    for b in range(buckets + 1):
        bounds[b] = _lower_bound(plen, b * step)
    return bounds, step


@njit(cache=True)
def _lower_bound_lookup(plen, x, bounds, step):
    """:func:`_lower_bound` of ``x`` in ``plen`` through its :func:`length_lookup` table (same answer)."""
    if x <= 0.0:  # lengths are never negative
        return 0
    last = bounds.shape[0] - 1
    fb = x / step
    if fb >= last:
        return _lower_bound_in(plen, x, bounds[last - 1] if last > 0 else 0, plen.shape[0])
    b = int(fb)
    # One bucket's margin on each side: ``x / step`` may round across a bound.
    lo = bounds[b - 1] if b > 0 else 0
    hi = bounds[b + 2] if b + 2 <= last else plen.shape[0]
    return _lower_bound_in(plen, x, lo, hi)


@njit(cache=True, parallel=True)
def side_widths(points, triples, plen, bounds, step, eps):
    """(M, 3) number of lengths in the sorted ``plen`` within ``eps`` of each triple's sides.

    Sides in the order ``(0, 1), (0, 2), (1, 2)``; a length ``d`` counts the
    entries in ``[d - eps, d + eps)`` (two lower bounds through the
    :func:`length_lookup` table ``bounds, step``), the window of target
    pairs the congruent listing scans for that side.
    """
    m = triples.shape[0]
    width = np.empty((m, 3), np.int64)
    for r in prange(m):
        for q in range(3):
            u = 0 if q < 2 else 1
            v = 1 if q == 0 else 2
            d = _dist(points, triples[r, u], points, triples[r, v])
            w = (_lower_bound_lookup(plen, d + eps, bounds, step)
                 - _lower_bound_lookup(plen, d - eps, bounds, step))
            width[r, q] = max(w, 0)
    return width


@njit(cache=True, parallel=True)
def triangle_heights(points, triples):
    """Smallest height of each triangle ``points[triples]``: twice its area over its longest side."""
    m = triples.shape[0]
    out = np.empty(m)
    tiny = np.finfo(np.float64).tiny
    for r in prange(m):
        a, b, c = triples[r, 0], triples[r, 1], triples[r, 2]
        ux = points[b, 0] - points[a, 0]
        uy = points[b, 1] - points[a, 1]
        uz = points[b, 2] - points[a, 2]
        vx = points[c, 0] - points[a, 0]
        vy = points[c, 1] - points[a, 1]
        vz = points[c, 2] - points[a, 2]
        cx = uy * vz - uz * vy
        cy = uz * vx - ux * vz
        cz = ux * vy - uy * vx
        area2 = np.sqrt(cx * cx + cy * cy + cz * cz)
        longest = max(_dist(points, a, points, b), _dist(points, a, points, c), _dist(points, b, points, c))
        out[r] = area2 / max(longest, tiny)
    return out


@njit(cache=True)
def gather_rows(out, points, i, j, k):
    """Rows ``i, j, k`` of ``points`` into the (3, 3) array ``out`` (a sample triangle)."""
    for r in range(3):
        out[0, r] = points[i, r]
        out[1, r] = points[j, r]
        out[2, r] = points[k, r]


@njit(cache=True)
def _dist(p, i, q, j):
    dx = p[i, 0] - q[j, 0]
    dy = p[i, 1] - q[j, 1]
    dz = p[i, 2] - q[j, 2]
    return np.sqrt(dx * dx + dy * dy + dz * dz)


# ------------------------------------------------------------------ grid
@njit(cache=True)
def build_grid(points, origin, cell, dims):
    """Counting-sort ``points`` into a dense grid of ``dims`` cells of size ``cell``.

    Returns ``(start, order)``: points of cell ``c`` are
    ``order[start[c]:start[c + 1]]``.
    """
    n = points.shape[0]
    ncell = dims[0] * dims[1] * dims[2]
    key = np.empty(n, np.int64)
    count = np.zeros(ncell + 1, np.int64)
    for i in range(n):
        cx = min(max(int((points[i, 0] - origin[0]) / cell), 0), dims[0] - 1)
        cy = min(max(int((points[i, 1] - origin[1]) / cell), 0), dims[1] - 1)
        cz = min(max(int((points[i, 2] - origin[2]) / cell), 0), dims[2] - 1)
        key[i] = (cx * dims[1] + cy) * dims[2] + cz
        count[key[i] + 1] += 1
    for c in range(ncell):
        count[c + 1] += count[c]
    order = np.empty(n, np.int64)
    fill = count[:-1].copy()
    for i in range(n):
        order[fill[key[i]]] = i
        fill[key[i]] += 1
    return count, order


@njit(cache=True)
def nearest_in_grid(p, target, start, order, origin, cell, dims, radius):
    """Index of the nearest target point within ``radius`` of ``p`` (or -1).

    Visits only the cells the ball of ``radius`` overlaps (at most two a side
    when ``cell >= 2 radius``); ``cell`` must be at least ``radius``.
    """
    x0 = max(int(np.floor((p[0] - radius - origin[0]) / cell)), 0)
    y0 = max(int(np.floor((p[1] - radius - origin[1]) / cell)), 0)
    z0 = max(int(np.floor((p[2] - radius - origin[2]) / cell)), 0)
    x1 = min(int(np.floor((p[0] + radius - origin[0]) / cell)), dims[0] - 1)
    y1 = min(int(np.floor((p[1] + radius - origin[1]) / cell)), dims[1] - 1)
    z1 = min(int(np.floor((p[2] + radius - origin[2]) / cell)), dims[2] - 1)
    best = -1
    bd = radius * radius
    for ix in range(x0, x1 + 1):
        for iy in range(y0, y1 + 1):
            for iz in range(z0, z1 + 1):
                c = (ix * dims[1] + iy) * dims[2] + iz
                for s in range(start[c], start[c + 1]):
                    j = order[s]
                    dx = target[j, 0] - p[0]
                    dy = target[j, 1] - p[1]
                    dz = target[j, 2] - p[2]
                    d2 = dx * dx + dy * dy + dz * dz
                    if d2 <= bd:
                        bd = d2
                        best = j
    return best


@njit(cache=True)
def _polish_one(X, Y, start, order, origin, cell, dims, R, t, gate, iterations, extent, spacing):
    """:func:`gatv.stages.refine` of a rigid motion: nearest target within ``gate`` (the grid
    ``start, order, origin, cell, dims`` of ``Y``), one-to-one cheapest first, Kabsch refit, until the
    pairs repeat or the motion moves by less than 1e-9 of ``spacing`` (rotation scaled by ``extent``).
    Returns ``(R, t, support)``: the pairs of the last refit counted; support -1 when fewer than 3
    points ever had a target within the gate, one-to-one (the motion is then returned unchanged)."""
    n = X.shape[0]
    idx = np.empty(n, np.int64)
    d2 = np.empty(n)
    used = np.zeros(Y.shape[0], np.bool_)
    kept_i = np.empty(0, np.int64)  # the pairs of the last refit (none before the first)
    kept_j = np.empty(0, np.int64)
    p = np.empty(3)
    for _ in range(iterations):
        cnt = 0
        for i in range(n):
            for a in range(3):
                p[a] = R[a, 0] * X[i, 0] + R[a, 1] * X[i, 1] + R[a, 2] * X[i, 2] + t[a]
            j = nearest_in_grid(p, Y, start, order, origin, cell, dims, gate)
            idx[i] = j
            if j >= 0:
                dx, dy, dz = Y[j, 0] - p[0], Y[j, 1] - p[1], Y[j, 2] - p[2]
                d2[i] = dx * dx + dy * dy + dz * dz
                cnt += 1
        if cnt < 3:
            break
        ok = np.empty(cnt, np.int64)
        keys = np.empty(cnt)
        k = 0
        for i in range(n):
            if idx[i] >= 0:
                ok[k] = i
                keys[k] = d2[i]
                k += 1
        # One-to-one, cheapest first, ties to the earlier source point (candidates.one_to_one).
        new_i = np.empty(cnt, np.int64)
        new_j = np.empty(cnt, np.int64)
        m = 0
        for k in np.argsort(keys, kind="mergesort"):
            j = idx[ok[k]]
            if used[j]:
                continue
            used[j] = True
            new_i[m] = ok[k]
            new_j[m] = j
            m += 1
        for k in range(m):
            used[new_j[k]] = False
        if m < 3:  # points sharing targets: too few pairs to fit
            break
        new_i, new_j = new_i[:m], new_j[:m]
        src = np.empty((m, 3))
        dst = np.empty((m, 3))
        for k in range(m):
            src[k] = X[new_i[k]]
            dst[k] = Y[new_j[k]]
        R_new, t_new = kabsch3(src, dst)
        # m >= 3 pairs, so never the same as the none kept before the first refit
        same = m == kept_i.shape[0] and np.all(new_i == kept_i) and np.all(new_j == kept_j)
        step = np.abs(R_new - R).max() * extent + np.abs(t_new - t).max()
        R, t = R_new, t_new
        kept_i, kept_j = new_i, new_j
        if same or step < 1e-9 * spacing:
            break
    return R, t, (kept_i.shape[0] if kept_i.shape[0] > 0 else -1)


@njit(cache=True, parallel=_prange_only())
def polish_icp(X, Y, start, order, origin, cell, dims, rotations, translations, gate, iterations, extent, spacing):
    """:func:`_polish_one` from each of ``rotations``, ``translations`` (motions in parallel): the
    peel's polish of its trial motions (:func:`gatv.stages.polish_trials`).  Returns ``(rotations,
    translations, supports)``; a support of -1 marks a motion left as it was (no refit)."""
    m = rotations.shape[0]
    out_R = np.empty_like(rotations)
    out_t = np.empty_like(translations)
    support = np.empty(m, np.int64)
    for k in prange(m):
        R, t, c = _polish_one(X, Y, start, order, origin, cell, dims, rotations[k].copy(), translations[k].copy(),
                              gate, iterations, extent, spacing)
        out_R[k] = R
        out_t[k] = t
        support[k] = c
    return out_R, out_t, support


@njit(cache=True)
def build_occupancy(points, origin, cell, dims, radius):
    """Cells of a dense grid that some point's ball of ``radius`` meets.

    Returns a ``uint8`` array over ``dims`` cells of size ``cell`` from
    ``origin``: 1 where the cell's box comes within ``radius`` of a point.
    A position in a 0 cell has no point within ``radius`` (a sure miss, one
    memory read); in a 1 cell it may (:func:`nearest_in_grid` decides).
    """
    occ = np.zeros(dims[0] * dims[1] * dims[2], np.uint8)
    reach = radius * (1.0 + 1e-9) + cell * 1e-9  # rounding slack: a sure miss must be sure
    r2 = reach * reach
    for i in range(points.shape[0]):
        p = points[i]
        lo = np.empty(3, np.int64)
        hi = np.empty(3, np.int64)
        for a in range(3):
            lo[a] = max(int(np.floor((p[a] - reach - origin[a]) / cell)), 0)
            hi[a] = min(int(np.floor((p[a] + reach - origin[a]) / cell)), dims[a] - 1)
        for ix in range(lo[0], hi[0] + 1):
            dx = max(origin[0] + ix * cell - p[0], 0.0, p[0] - origin[0] - (ix + 1) * cell)
            for iy in range(lo[1], hi[1] + 1):
                dy = max(origin[1] + iy * cell - p[1], 0.0, p[1] - origin[1] - (iy + 1) * cell)
                for iz in range(lo[2], hi[2] + 1):
                    dz = max(origin[2] + iz * cell - p[2], 0.0, p[2] - origin[2] - (iz + 1) * cell)
                    if dx * dx + dy * dy + dz * dz <= r2:
                        occ[(ix * dims[1] + iy) * dims[2] + iz] = 1
    return occ


@njit(cache=True)
def maybe_occupied(p, occ, origin, cell, dims):
    """False when ``p`` lies in a 0 cell of :func:`build_occupancy` or outside its grid."""
    if occ.shape[0] == 0:
        return True
    ix = int(np.floor((p[0] - origin[0]) / cell))
    iy = int(np.floor((p[1] - origin[1]) / cell))
    iz = int(np.floor((p[2] - origin[2]) / cell))
    if ix < 0 or iy < 0 or iz < 0 or ix >= dims[0] or iy >= dims[1] or iz >= dims[2]:
        return False
    return occ[(ix * dims[1] + iy) * dims[2] + iz] != 0


@njit(cache=True)
def count_inliers(R, t, source, target, start, order, origin, cell, dims, radius, need=0,
                  visit=_NO_VISIT, slope=0.0, offset=0.0):
    """Number of source points whose moved position has a target within ``radius``.

    Gives up (returning a count below ``need``) as soon as ``need`` can no
    longer be reached.  The source is visited in the order ``visit`` (a
    permutation; empty: index order), and the count stops early, returned
    so far, once fewer than ``slope * v + offset`` of the first ``v``
    visited points matched: the rejection boundary of a sequential test of
    a wrong motion (:func:`gatv.models.rigid.congruent.sequential_boundary`).
    ``slope = offset = 0`` never stops.
    """
    # Fresh empty arrays, not the module's: a global array is a read-only constant to numba, a
    # second specialisation of count_inliers_visited.
    n, _ = count_inliers_visited(R, t, source, target, start, order, origin, cell, dims, radius, need,
                                 visit, slope, offset, np.zeros(0, np.uint8), origin, cell, dims,
                                 np.zeros(0, np.int64))
    return n


@njit(cache=True)
def count_inliers_visited(R, t, source, target, start, order, origin, cell, dims, radius, need,
                          visit, slope, offset, occ, occ_origin, occ_cell, occ_dims, base):
    """:func:`count_inliers` and the number of source points it visited.

    ``occ`` (empty: none) is the target's :func:`build_occupancy` at
    ``radius`` over the grid ``occ_origin``, ``occ_cell``, ``occ_dims``: a
    moved point in an empty cell is a miss without a grid search.  The
    points ``base`` (the sample the motion was fitted to, which it brings
    onto the target by construction) count but stay out of the sequential
    test: their hits say nothing of the motion.
    """
    n = 0
    nb = 0  # hits and visits of base points, left out of the test
    vb = 0
    p = np.empty(3)
    ordered = visit.shape[0] == source.shape[0]
    m = source.shape[0]
    for v in range(m):
        if n - nb < slope * (v - vb) + offset or n + (m - v) < need:
            return n, v
        i = visit[v] if ordered else v
        in_base = False
        for b in range(base.shape[0]):
            if base[b] == i:
                in_base = True
        for r in range(3):
            p[r] = R[r, 0] * source[i, 0] + R[r, 1] * source[i, 1] + R[r, 2] * source[i, 2] + t[r]
        hit = maybe_occupied(p, occ, occ_origin, occ_cell, occ_dims) and \
            nearest_in_grid(p, target, start, order, origin, cell, dims, radius) >= 0
        if hit:
            n += 1
        if in_base:
            vb += 1
            if hit:
                nb += 1
    return n, m


# ------------------------------------------------------------ hypotheses
@njit(cache=True)
def _pair_features(p, i, j, normals):
    """Rigid invariants of an unoriented-normal pair: |n_i·u|, |n_j·u|, |n_i·n_j|."""
    ux = p[j, 0] - p[i, 0]
    uy = p[j, 1] - p[i, 1]
    uz = p[j, 2] - p[i, 2]
    nu = np.sqrt(ux * ux + uy * uy + uz * uz)
    if nu > 0:
        ux /= nu
        uy /= nu
        uz /= nu
    f1 = abs(normals[i, 0] * ux + normals[i, 1] * uy + normals[i, 2] * uz)
    f2 = abs(normals[j, 0] * ux + normals[j, 1] * uy + normals[j, 2] * uz)
    f3 = abs(normals[i, 0] * normals[j, 0] + normals[i, 1] * normals[j, 1] + normals[i, 2] * normals[j, 2])
    return f1, f2, f3


@njit(cache=True)
def _features_agree(src, i, j, sn, tgt, k, l, tn, tol):
    """Do the pair (i, j) of the source and (k, l) of the target look alike?"""
    a1, a2, a3 = _pair_features(src, i, j, sn)
    b1, b2, b3 = _pair_features(tgt, k, l, tn)
    return abs(a1 - b1) <= tol and abs(a2 - b2) <= tol and abs(a3 - b3) <= tol


@njit(cache=True)
def _grown(a, size):
    """``a`` copied into a new array of ``size`` entries."""
    b = np.empty(size, a.dtype)
    for i in range(a.shape[0]):  # not ``b[:n] = a``: see triple_hypotheses' copies
        b[i] = a[i]
    return b


@njit(cache=True)
def _match_lists(max_enumerated):
    """Empty ``(k, l, m, discrepancy)`` lists of a listing, grown by :func:`_third_points` as matches come.

    They start at 64 entries: most triples list a few matches, and allocating
    the cap (1 MB at 32,768) for each cost more than the listing.
    """
    size = min(max_enumerated, 64)
    return np.empty(size, np.int64), np.empty(size, np.int64), np.empty(size, np.int64), np.empty(size)


@njit(cache=True)
def _congruent_matches(source, target, a, b, c, offset, plen, pi, pj, ndist, nidx, eps, max_enumerated,
                       src_normals, tgt_normals, feature_tol, use_normals, by_point=-1):
    """Target triples congruent to the source triple ``(a, b, c)`` within ``eps``.

    Returns ``(k, l, m, discrepancy, probes)``: arrays of at most
    ``max_enumerated`` matches, ``discrepancy`` the sum of the three squared
    side-length differences, and the number of binary searches and
    candidate third points the listing examined (its cost).

    Two ways of listing the same matches.  By pair: each target pair of
    length ``|ab| ± eps`` (both orientations ``k, l``), then the points
    ``m`` of ``k``'s sorted neighbour list at ``|ac| ± eps``: two binary
    searches a pair.  By point (``by_point=1``; ``-1`` chooses it when the
    window holds more pairs than the target has points): for each target
    point ``k`` the neighbours ``l`` at ``|ab| ± eps`` and ``m`` at
    ``|ac| ± eps`` of its list, four binary searches a point.  Either scan
    starts at ``offset`` (modulo the window or the target) and wraps
    around, the points in a stride order the offset also draws, so that a
    capped scan is an unbiased sample rather than the shortest pairs or a
    run of neighbouring points.
    """
    dab = _dist(source, a, source, b)
    dac = _dist(source, a, source, c)
    dbc = _dist(source, b, source, c)
    lo = _lower_bound(plen, dab - eps)
    hi = _lower_bound(plen, dab + eps)
    n2 = target.shape[0]
    if by_point == 1 or (by_point < 0 and hi - lo > n2):
        return _congruent_matches_by_point(source, target, a, b, c, dab, dac, dbc, offset, ndist, nidx, eps,
                                           max_enumerated, src_normals, tgt_normals, feature_tol, use_normals)
    ks, ls, ms, disc = _match_lists(max_enumerated)
    found = np.int64(0)  # not the literal 0: one specialisation of _third_points
    probes = 2
    width = hi - lo
    for w in range(width):
        if found >= max_enumerated:
            break
        s = lo + (offset + w) % width
        for orient in range(2):
            # int64 indices everywhere (the tables hold int32): one specialisation of each callee
            if orient == 0:
                k, l = np.int64(pi[s]), np.int64(pj[s])
            else:
                k, l = np.int64(pj[s]), np.int64(pi[s])
            if use_normals and not _features_agree(source, a, b, src_normals, target, k, l,
                                                   tgt_normals, feature_tol):
                continue
            row = ndist[k]
            m0 = _lower_bound(row, dac - eps)
            m1 = _lower_bound(row, dac + eps)
            probes += 2 + (m1 - m0)
            ks, ls, ms, disc, found = _third_points(source, target, a, b, c, k, l, plen[s] - dab, row, nidx[k], m0,
                                                    m1, dac, dbc, eps, ks, ls, ms, disc, found, max_enumerated,
                                                    src_normals, tgt_normals, feature_tol, use_normals)
            if found >= max_enumerated:
                break
    return ks[:found], ls[:found], ms[:found], disc[:found], probes


@njit(cache=True)
def _third_points(source, target, a, b, c, k, l, e1, row, near, m0, m1, dac, dbc, eps, ks, ls, ms, disc, found,
                  max_enumerated, src_normals, tgt_normals, feature_tol, use_normals):
    """Append the matches ``(k, l, m)`` for ``m`` among ``near[m0:m1]`` (``k``'s neighbours at ``|ac| ± eps``).

    ``e1`` is the first side's error, ``row`` ``k``'s sorted neighbour
    distances; ``m`` must also be ``|bc| ± eps`` from ``l``.  The lists grow
    by doubling up to ``max_enumerated``.  Returns them and the new count.
    """
    for u in range(m0, m1):
        m = np.int64(near[u])
        if m == l:
            continue
        e3 = _dist(target, l, target, m) - dbc
        if abs(e3) > eps:
            continue
        if use_normals and not (
            _features_agree(source, a, c, src_normals, target, k, m, tgt_normals, feature_tol)
            and _features_agree(source, b, c, src_normals, target, l, m, tgt_normals, feature_tol)
        ):
            continue
        e2 = row[u] - dac
        if found == ks.shape[0]:
            size = min(2 * ks.shape[0], max_enumerated)
            ks = _grown(ks, size)
            ls = _grown(ls, size)
            ms = _grown(ms, size)
            disc = _grown(disc, size)
        ks[found] = k
        ls[found] = l
        ms[found] = m
        disc[found] = e1 * e1 + e2 * e2 + e3 * e3
        found += 1
        if found >= max_enumerated:
            break
    return ks, ls, ms, disc, found


@njit(cache=True)
def _gcd(a, b):
    while b:
        a, b = b, a % b
    return a


@njit(cache=True)
def _congruent_matches_by_point(source, target, a, b, c, dab, dac, dbc, offset, ndist, nidx, eps, max_enumerated,
                                src_normals, tgt_normals, feature_tol, use_normals):
    """:func:`_congruent_matches` listed point by point (see there)."""
    n2 = target.shape[0]
    ks, ls, ms, disc = _match_lists(max_enumerated)
    found = np.int64(0)
    probes = 0
    # Points in a stride order coprime to n2 from the offset: a capped scan
    # then takes points spread over the target, not a run of consecutive
    # indices (which a voxel-ordered target keeps in one region).
    stride = 1 + (offset // n2) % max(n2 - 1, 1)
    while _gcd(stride, n2) != 1:
        stride += 1
    for w in range(n2):
        if found >= max_enumerated:
            break
        k = (offset + w * stride) % n2
        row = ndist[k]
        l0 = _lower_bound(row, dab - eps)
        l1 = _lower_bound(row, dab + eps)
        probes += 2
        if l0 == l1:
            continue
        m0 = _lower_bound(row, dac - eps)
        m1 = _lower_bound(row, dac + eps)
        probes += 2
        for ul in range(l0, l1):
            if found >= max_enumerated:
                break
            l = np.int64(nidx[k, ul])
            if use_normals and not _features_agree(source, a, b, src_normals, target, k, l, tgt_normals,
                                                   feature_tol):
                continue
            probes += m1 - m0
            ks, ls, ms, disc, found = _third_points(source, target, a, b, c, k, l, row[ul] - dab, row, nidx[k], m0,
                                                    m1, dac, dbc, eps, ks, ls, ms, disc, found, max_enumerated,
                                                    src_normals, tgt_normals, feature_tol, use_normals)
    return ks[:found], ls[:found], ms[:found], disc[:found], probes


@njit(cache=True)
def scored_matches(source, target, a, b, c, offset, plen, pi, pj, ndist, nidx, eps, max_enumerated, max_matches,
                   src_normals, tgt_normals, feature_tol, use_normals, first_box=0.5):
    """The ``max_matches`` tightest of at most ``max_enumerated`` congruent matches of ``(a, b, c)``.

    Returns ``(k, l, m, n_listed, n_probes)`` (``n_probes``: the listing's
    cost, see :func:`_congruent_matches`).  When more are listed than
    scored, the matches within ``e = first_box eps`` of every side are
    listed first (``0 < first_box < 1``): if the last of their
    ``max_matches`` tightest has a discrepancy (sum of squared side
    errors) of at most ``e²``, no match outside that box can be tighter,
    and these are the tightest of all for about ``first_box²`` of the
    listing work (the listing's inner loop grows like ``eps²``); otherwise
    the box doubles, up to the full ``eps``.  ``first_box = 0`` lists the
    full box at once, for a triple whose full box holds too few matches
    for a smaller one to answer.
    """
    listed = 0
    probes = 0
    frac = first_box
    auto = np.int64(-1)  # by_point given, not omitted nor a literal: the callers' one specialisation
    while max_enumerated > max_matches and 0.0 < frac < 1.0:
        e = frac * eps
        ks, ls, ms, disc, pr = _congruent_matches(source, target, a, b, c, offset, plen, pi, pj, ndist, nidx,
                                                  e, max_enumerated, src_normals, tgt_normals, feature_tol,
                                                  use_normals, auto)
        listed += ks.shape[0]
        probes += pr
        if ks.shape[0] > max_matches:
            pick = np.argsort(disc, kind="mergesort")[:max_matches]
            if ks.shape[0] >= max_enumerated or disc[pick[-1]] <= e * e:
                return ks[pick], ls[pick], ms[pick], listed, probes
        frac *= 2.0
    ks, ls, ms, disc, pr = _congruent_matches(source, target, a, b, c, offset, plen, pi, pj, ndist, nidx, eps,
                                              max(max_enumerated, max_matches), src_normals, tgt_normals,
                                              feature_tol, use_normals, auto)
    listed += ks.shape[0]
    probes += pr
    if ks.shape[0] > max_matches:
        pick = np.argsort(disc, kind="mergesort")[:max_matches]
        return ks[pick], ls[pick], ms[pick], listed, probes
    return ks, ls, ms, listed, probes


@njit(cache=True, parallel=_prange_only())
def triple_hypotheses(
    source,
    target,
    triples,
    offsets,
    plen,
    pi,
    pj,
    ndist,
    nidx,
    eps,
    start,
    order,
    origin,
    cell,
    dims,
    radius,
    max_matches,
    src_normals,
    tgt_normals,
    feature_tol,
    max_enumerated=0,
    visit=_NO_VISIT,
    slope=0.0,
    offset=0.0,
    occ=_NO_OCC,
    occ_origin=_ORIGIN,
    occ_cell=1.0,
    occ_dims=_DIMS,
    first_box=_HALF_BOX,
):
    """Best congruent match of each source triple, scored by inlier count.

    For source triple ``(a, b, c)`` every target triple ``(k, l, m)`` with
    ``| |ab| - |kl| |, | |ac| - |km| |, | |bc| - |lm| | <= eps`` (and, when
    normals are given, the invariants of :func:`_pair_features` of all
    three sides within ``feature_tol``) gives a motion (the least-squares pose of the
    three pairs, :func:`gatv._fit_kernels.triangle_pose`) whose support is the number of source points landing within
    ``radius`` of a target point.  Up to ``max_enumerated`` congruent
    triples are listed (:func:`_congruent_matches`; default
    ``max_matches``) and the ``max_matches`` tightest of them (smallest
    side-length discrepancy) are scored: under noise a triple matches many
    target triples, and the true one is among the tightest far more often
    than among an arbitrary share.

    The source points are visited in the order ``visit`` (a permutation;
    empty: index order) and a motion's count stops, returned so far, at the
    sequential test's boundary ``slope * v + offset`` (:func:`count_inliers`;
    ``0, 0``: none): most of the many wrong motions a noisy triple yields
    are rejected after a few dozen points.  ``occ`` (the target's
    :func:`build_occupancy` at ``radius``; empty: none) answers most of
    their misses with one memory read.

    Returns ``(score, R, t, n_matches, n_listed, n_visited, n_probes)`` per
    triple (``n_matches`` counts the scored matches, ``n_listed`` the listed
    ones, ``n_visited`` the source points visited in scoring them,
    ``n_probes`` the listing's binary searches and candidates); ``score =
    -1`` when no congruent triple exists.  ``first_box`` (one a triple;
    empty: 0.5 for all) is the share of ``eps`` each triple lists first
    (:func:`scored_matches`).
    """
    nt = triples.shape[0]
    scores = np.full(nt, -1, np.int64)
    rots = np.zeros((nt, 3, 3))
    trans = np.zeros((nt, 3))
    nmatch = np.zeros(nt, np.int64)
    nlisted = np.zeros(nt, np.int64)
    nvisited = np.zeros(nt, np.int64)
    nprobes = np.zeros(nt, np.int64)
    use_normals = src_normals.shape[0] == source.shape[0] and tgt_normals.shape[0] == target.shape[0]
    n_enum = max(max_enumerated, max_matches)
    for q in prange(nt):
        a, b, c = triples[q, 0], triples[q, 1], triples[q, 2]
        box = first_box[q] if first_box.shape[0] == nt else 0.5
        ks, ls, ms, listed, probes = scored_matches(source, target, a, b, c, offsets[q], plen, pi, pj, ndist,
                                                    nidx, eps, n_enum, max_matches, src_normals, tgt_normals,
                                                    feature_tol, use_normals, box)
        src = np.empty((3, 3))
        dst = np.empty((3, 3))
        gather_rows(src, source, a, b, c)
        for v in range(ks.shape[0]):
            gather_rows(dst, target, ks[v], ls[v], ms[v])
            R, t = triangle_pose(src, dst)
            sc, nv = count_inliers_visited(R, t, source, target, start, order, origin, cell, dims, radius,
                                           scores[q] + 1, visit, slope, offset, occ, occ_origin, occ_cell,
                                           occ_dims, triples[q])
            nvisited[q] += nv
            if sc > scores[q]:
                scores[q] = sc
                # Element copies, not ``rots[q] = R``: an array assigned to a slice compiles numba's
                # shape-mismatch message (string formatting, ~1.5 CPU-s a shape) into every function
                # of the parallel loop's chain.
                for r in range(3):
                    trans[q, r] = t[r]
                    for u in range(3):
                        rots[q, r, u] = R[r, u]
        nmatch[q] = ks.shape[0]
        nlisted[q] = listed
        nprobes[q] = probes
    return scores, rots, trans, nmatch, nlisted, nvisited, nprobes


@njit(cache=True)
def count_distinct_inliers(A, t, source, target, start, order, origin, cell, dims, radius, need,
                           mark, stamp):
    """Number of distinct target points the moved source points land on (within ``radius``).

    Like :func:`count_inliers` with linear part ``A``, but a target point
    already claimed by an earlier source point does not count again: a
    similarity that shrinks the source onto a few target points (which
    :func:`count_inliers` would reward on dense data) scores low.
    ``mark`` (one int64 per target point) holds ``stamp`` for the claimed
    ones; give a new ``stamp`` per call instead of clearing it.  Gives up
    (returning a count below ``need``) once ``need`` is out of reach.
    """
    n = 0
    p = np.empty(3)
    m = source.shape[0]
    for i in range(m):
        if n + (m - i) < need:
            return n
        for r in range(3):
            p[r] = A[r, 0] * source[i, 0] + A[r, 1] * source[i, 1] + A[r, 2] * source[i, 2] + t[r]
        j = nearest_in_grid(p, target, start, order, origin, cell, dims, radius)
        if j >= 0 and mark[j] != stamp:
            mark[j] = stamp
            n += 1
    return n


@njit(cache=True, parallel=True)
def similar_triple_hypotheses(
    source,
    target,
    triples,
    starts,
    ndist,
    nidx,
    eps,
    s_min,
    s_max,
    start,
    order,
    origin,
    cell,
    dims,
    radius,
    max_matches,
):
    """Best similar match of each source triple, scored by inlier count.

    A similarity ``x' = s R x + t`` keeps a triangle's shape: target triple
    ``(k, l, m)`` matches source triple ``(a, b, c)`` when
    ``|kl| / |ab| = |km| / |ac| = |lm| / |bc| = s``.  The side ``ab`` is
    taken as the triple's longest (the caller orders the triples so), which
    conditions the scale ``s = |kl| / |ab|`` best and keeps the ratios
    ``rho1 = |ac| / |ab|``, ``rho2 = |bc| / |ab|`` at most 1.

    For every target point ``k`` (from ``starts[q]`` on, cyclically, so
    that the ``max_matches`` cap samples the target without favouring low
    indices) the neighbours ``l`` of ``k``'s sorted list with
    ``s_min |ab| - eps <= |kl| <= s_max |ab| + eps`` are walked in
    increasing distance while a second pointer into the same list keeps the
    window ``|km| = rho1 |kl| ± eps (1 + rho1)`` (both ends grow with
    ``|kl|``): a merge, ``O(M)`` per ``k``, ``O(M²)`` per source triple.
    Each ``m`` of the window with ``| |lm| - s |bc| | <= eps (1 + rho2)``
    is a similar triangle; ``eps`` is the side-length tolerance in
    **target** units (noise of ``eps`` on ``|kl|`` moves ``s |ac|`` by
    ``rho1 eps``, hence the widened windows).  Each similar triangle gives
    a motion (:func:`gatv._fit_kernels.umeyama3` on the three pairs); one
    whose fitted scale is outside ``[s_min, s_max]`` is dropped (the
    ``eps`` slack of the length window lets such triangles through, and a
    tiny scale that shrinks the whole source onto a few target points would
    win the density test on dense surfaces), the others are counted
    against ``max_matches`` and their support is the number of distinct
    target points that the motion (linear part ``s R``, translation ``t``)
    brings source points within ``radius`` of
    (:func:`count_distinct_inliers`; distinct, so that shrinking the source
    onto a few target points does not pay).  At most ``max_matches``
    similar triangles are scored per source triple.

    Returns ``(score, A, t, n_matches)`` per triple with ``A = s R`` the
    linear part; ``score = -1`` when no similar triangle exists.
    """
    nt = triples.shape[0]
    n2 = target.shape[0]
    scores = np.full(nt, -1, np.int64)
    lins = np.zeros((nt, 3, 3))
    trans = np.zeros((nt, 3))
    nmatch = np.zeros(nt, np.int64)
    for q in prange(nt):
        a, b, c = triples[q, 0], triples[q, 1], triples[q, 2]
        dab = _dist(source, a, source, b)
        dac = _dist(source, a, source, c)
        dbc = _dist(source, b, source, c)
        if dab <= 0.0:
            nmatch[q] = 0
            continue
        rho1 = dac / dab
        rho2 = dbc / dab
        tol1 = eps * (1.0 + rho1)
        tol2 = eps * (1.0 + rho2)
        len_lo = s_min * dab - eps
        len_hi = s_max * dab + eps
        src = np.empty((3, 3))
        dst = np.empty((3, 3))
        gather_rows(src, source, a, b, c)
        mark = np.full(n2, -1, np.int64)
        found = 0
        for kk in range(n2):
            if found >= max_matches:
                break
            k = (starts[q] + kk) % n2
            row = ndist[k]
            nrow = row.shape[0]
            u0 = _lower_bound(row, len_lo)
            m_lo = 0
            m_hi = 0
            for u in range(u0, nrow):
                dkl = row[u]
                if dkl > len_hi:
                    break
                want = rho1 * dkl
                while m_lo < nrow and row[m_lo] < want - tol1:
                    m_lo += 1
                m_hi = max(m_hi, m_lo)
                while m_hi < nrow and row[m_hi] <= want + tol1:
                    m_hi += 1
                if m_lo >= m_hi:
                    continue
                l = np.int64(nidx[k, u])
                s = dkl / dab
                want2 = s * dbc
                for v in range(m_lo, m_hi):
                    m = np.int64(nidx[k, v])
                    if m == l:
                        continue
                    if abs(_dist(target, l, target, m) - want2) > tol2:
                        continue
                    gather_rows(dst, target, k, l, m)
                    sc, R, t = umeyama3(src, dst)
                    if sc < s_min or sc > s_max:
                        continue
                    found += 1
                    A = sc * R
                    n_in = count_distinct_inliers(A, t, source, target, start, order, origin, cell,
                                                  dims, radius, scores[q] + 1, mark, found)
                    if n_in > scores[q]:
                        scores[q] = n_in
                        for r in range(3):  # element copies: see triple_hypotheses
                            trans[q, r] = t[r]
                            for u in range(3):
                                lins[q, r, u] = A[r, u]
                    if found >= max_matches:
                        break
                if found >= max_matches:
                    break
        nmatch[q] = found
    return scores, lins, trans, nmatch
