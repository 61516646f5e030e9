"""Numba kernels for 2D affine trial motions from area-ratio invariants.

An affine map keeps ratios of areas, so the barycentric coordinates
``(l1, l2)`` of a fourth point ``c = j + l1 (a - j) + l2 (b - j)`` with
respect to a triangle ``(j, a, b)`` survive any affine map.  The target is
indexed by the signatures of *local* quadruples (an anchor and three of its
``K`` nearest neighbours, :func:`quad_table`), bucketed on a grid of the
signature plane; a source sample (an anchor and three of its neighbours,
in each of its 6 orders) looks up target quadruples of the same signature,
and the triangle's affine map, verified on the fourth point, is scored by
a density test (:func:`quad_hypotheses`).

Pure functions: arrays and scalars in, arrays out.  :mod:`gatv.models.affine2d`
drives them; :func:`quad_hypotheses_reference` is the numpy reference the
tests check :func:`quad_hypotheses` against.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["quad_table", "bucket", "build_grid", "count_inliers", "quad_hypotheses",
           "quad_hypotheses_reference", "ORDERS", "LMAX", "WMAX"]

#: Signatures beyond ``|l| <= LMAX`` are not indexed (the 4th point is far outside the triangle).
LMAX = 4.0

#: Widest signature window searched (signatures differing by more carry no information).
WMAX = 1.0

#: The 6 orders ``(p, q, r)`` of a sample's three neighbours: base ``(anchor, p, q)``, 4th ``r``.
ORDERS = np.array([[1, 2, 3], [2, 1, 3], [1, 3, 2], [3, 1, 2], [2, 3, 1], [3, 2, 1]], np.int64)


@njit(cache=True)
def _smin(m00, m01, m10, m11):
    """Smallest and largest singular values of a 2x2 matrix."""
    f = m00 * m00 + m01 * m01 + m10 * m10 + m11 * m11
    det = m00 * m11 - m01 * m10
    disc = max(f * f - 4.0 * det * det, 0.0)
    r = np.sqrt(disc)
    return np.sqrt(max(0.5 * (f - r), 0.0)), np.sqrt(0.5 * (f + r))


@njit(cache=True)
def _signature(p, j, a, b, c):
    """``(l1, l2, sigma_min, sigma_max)`` of ``c`` in the frame ``(j; a - j, b - j)`` of ``p``."""
    b00 = p[a, 0] - p[j, 0]
    b10 = p[a, 1] - p[j, 1]
    b01 = p[b, 0] - p[j, 0]
    b11 = p[b, 1] - p[j, 1]
    det = b00 * b11 - b01 * b10
    smin, smax = _smin(b00, b01, b10, b11)
    if smin <= 1e-12 * max(smax, 1e-300):
        return 0.0, 0.0, 0.0, smax
    vx = p[c, 0] - p[j, 0]
    vy = p[c, 1] - p[j, 1]
    l1 = (b11 * vx - b01 * vy) / det
    l2 = (-b10 * vx + b00 * vy) / det
    return l1, l2, smin, smax


@njit(cache=True)
def quad_table(points, nbr, max_cond):
    """Signatures of every local quadruple ``(j; a, b, c)``, ``a < b < c`` in ``j``'s neighbour row.

    Returns ``(sig (E, 2), quad (E, 4) int32, scale (E,))``: ``scale`` is
    ``(2 + |l1| + |l2|) / sigma_min`` of the base triangle, the factor that
    turns a point displacement into a signature error.  Triangles with a
    condition number above ``max_cond`` and signatures beyond ``LMAX`` are
    left out.
    """
    n, k = nbr.shape
    cap = n * (k * (k - 1) * (k - 2) // 6)
    sig = np.empty((cap, 2))
    quad = np.empty((cap, 4), np.int32)
    scale = np.empty(cap)
    e = 0
    for j in range(n):
        for x in range(k):
            a = nbr[j, x]
            for y in range(x + 1, k):
                b = nbr[j, y]
                for z in range(y + 1, k):
                    c = nbr[j, z]
                    l1, l2, smin, smax = _signature(points, j, a, b, c)
                    if smin <= 0.0 or smax > max_cond * smin:
                        continue
                    if abs(l1) > LMAX or abs(l2) > LMAX:
                        continue
                    sig[e, 0] = l1
                    sig[e, 1] = l2
                    quad[e, 0] = j
                    quad[e, 1] = a
                    quad[e, 2] = b
                    quad[e, 3] = c
                    scale[e] = (2.0 + abs(l1) + abs(l2)) / smin
                    e += 1
    return sig[:e].copy(), quad[:e].copy(), scale[:e].copy()


@njit(cache=True)
def bucket(sig, g):
    """CSR buckets of signatures on a ``g x g`` grid of ``[-LMAX, LMAX]^2``: ``(start, order)``."""
    h = 2.0 * LMAX / g
    m = sig.shape[0]
    cell = np.empty(m, np.int64)
    for e in range(m):
        cx = min(max(int((sig[e, 0] + LMAX) / h), 0), g - 1)
        cy = min(max(int((sig[e, 1] + LMAX) / h), 0), g - 1)
        cell[e] = cx * g + cy
    order = np.argsort(cell, kind="mergesort")
    start = np.zeros(g * g + 1, np.int64)
    for e in range(m):
        start[cell[e] + 1] += 1
    for c in range(g * g):
        start[c + 1] += start[c]
    return start, order.astype(np.int64)


@njit(cache=True)
def build_grid(points, origin, cell, dims):
    """CSR grid of 2D ``points``: ``(start, order)`` over ``dims[0] * dims[1]`` cells."""
    n = points.shape[0]
    ids = np.empty(n, np.int64)
    for i in range(n):
        cx = min(max(int((points[i, 0] - origin[0]) / cell), 0), dims[0] - 1)
        cy = min(max(int((points[i, 1] - origin[1]) / cell), 0), dims[1] - 1)
        ids[i] = cx * dims[1] + cy
    order = np.argsort(ids, kind="mergesort")
    start = np.zeros(dims[0] * dims[1] + 1, np.int64)
    for i in range(n):
        start[ids[i] + 1] += 1
    for c in range(dims[0] * dims[1]):
        start[c + 1] += start[c]
    return start, order.astype(np.int64)


@njit(cache=True)
def _has_near(x, y, target, start, order, origin, cell, dims, r2):
    cx = int(np.floor((x - origin[0]) / cell))
    cy = int(np.floor((y - origin[1]) / cell))
    for gx in range(max(cx - 1, 0), min(cx + 2, dims[0])):
        for gy in range(max(cy - 1, 0), min(cy + 2, dims[1])):
            c = gx * dims[1] + gy
            for s in range(start[c], start[c + 1]):
                q = order[s]
                dx = target[q, 0] - x
                dy = target[q, 1] - y
                if dx * dx + dy * dy <= r2:
                    return True
    return False


@njit(cache=True)
def count_inliers(source, a00, a01, a10, a11, tx, ty, target, start, order, origin, cell, dims,
                  radius):
    """Source points moved by ``A x + t`` that land within ``radius`` of a target point."""
    r2 = radius * radius
    cnt = 0
    for i in range(source.shape[0]):
        x = a00 * source[i, 0] + a01 * source[i, 1] + tx
        y = a10 * source[i, 0] + a11 * source[i, 1] + ty
        if _has_near(x, y, target, start, order, origin, cell, dims, r2):
            cnt += 1
    return cnt


@njit(cache=True)
def _triangle_map(src, i, p, q, dst, j, a, b):
    """Affine map of the triangle ``(i, p, q)`` of ``src`` onto ``(j, a, b)`` of ``dst``."""
    s00 = src[p, 0] - src[i, 0]
    s10 = src[p, 1] - src[i, 1]
    s01 = src[q, 0] - src[i, 0]
    s11 = src[q, 1] - src[i, 1]
    det = s00 * s11 - s01 * s10
    t00 = dst[a, 0] - dst[j, 0]
    t10 = dst[a, 1] - dst[j, 1]
    t01 = dst[b, 0] - dst[j, 0]
    t11 = dst[b, 1] - dst[j, 1]
    # A = T S^-1
    i00 = s11 / det
    i01 = -s01 / det
    i10 = -s10 / det
    i11 = s00 / det
    a00 = t00 * i00 + t01 * i10
    a01 = t00 * i01 + t01 * i11
    a10 = t10 * i00 + t11 * i10
    a11 = t10 * i01 + t11 * i11
    tx = dst[j, 0] - (a00 * src[i, 0] + a01 * src[i, 1])
    ty = dst[j, 1] - (a10 * src[i, 0] + a11 * src[i, 1])
    return a00, a01, a10, a11, tx, ty


@njit(cache=True)
def quad_hypotheses(source, samples, target, sig, quad, scale, s_cap, bstart, border, g, eps,
                    gstart, gorder, origin, cell, dims, radius, max_matches, max_cond):
    """Best affine trial of each source sample ``(anchor, n1, n2, n3)``.

    For each of the 6 orders of the neighbours whose scale is at most
    ``s_cap`` (the table's largest), target quadruples whose signature is
    within ``min(eps * (scale_source + scale_target), eps * (scale_source +
    s_cap), WMAX)`` are looked up;
    the base triangles' affine map must bring the source's 4th point within
    ``eps`` of the target's and have a condition number of at most
    ``max_cond``; it is then scored by :func:`count_inliers`.  Ties go to
    the smaller ``order * E + entry``.  At most ``max_matches`` verified
    matches are scored per sample.

    Returns ``(scores (S,), A (S, 2, 2), t (S, 2), n_matches (S,))``; a score
    of 0 means no verified match.
    """
    S = samples.shape[0]
    E = sig.shape[0]
    h = 2.0 * LMAX / g
    scores = np.zeros(S, np.int64)
    A = np.zeros((S, 2, 2))
    t = np.zeros((S, 2))
    nm = np.zeros(S, np.int64)
    for s in range(S):
        best = -1
        best_key = -1
        done = False
        for o in range(6):
            if done:
                break
            i = samples[s, 0]
            p = samples[s, ORDERS[o, 0]]
            q = samples[s, ORDERS[o, 1]]
            r = samples[s, ORDERS[o, 2]]
            l1, l2, smin, smax = _signature(source, i, p, q, r)
            if smin <= 0.0:
                continue
            ss = (2.0 + abs(l1) + abs(l2)) / smin
            if ss > s_cap:
                continue
            w = min(eps * (ss + s_cap), WMAX)
            if abs(l1) > LMAX + w or abs(l2) > LMAX + w:
                continue
            x0 = min(max(int((l1 - w + LMAX) / h), 0), g - 1)
            x1 = min(max(int((l1 + w + LMAX) / h), 0), g - 1)
            y0 = min(max(int((l2 - w + LMAX) / h), 0), g - 1)
            y1 = min(max(int((l2 + w + LMAX) / h), 0), g - 1)
            for cx in range(x0, x1 + 1):
                if done:
                    break
                for cy in range(y0, y1 + 1):
                    if done:
                        break
                    c = cx * g + cy
                    for k in range(bstart[c], bstart[c + 1]):
                        e = border[k]
                        tol = min(eps * (ss + scale[e]), w)
                        if abs(sig[e, 0] - l1) > tol or abs(sig[e, 1] - l2) > tol:
                            continue
                        j = quad[e, 0]
                        a = quad[e, 1]
                        b = quad[e, 2]
                        cc = quad[e, 3]
                        a00, a01, a10, a11, tx, ty = _triangle_map(source, i, p, q, target, j, a, b)
                        dx = a00 * source[r, 0] + a01 * source[r, 1] + tx - target[cc, 0]
                        dy = a10 * source[r, 0] + a11 * source[r, 1] + ty - target[cc, 1]
                        if dx * dx + dy * dy > eps * eps:
                            continue
                        mn, mx = _smin(a00, a01, a10, a11)
                        if mn <= 0.0 or mx > max_cond * mn:
                            continue
                        nm[s] += 1
                        sc = count_inliers(source, a00, a01, a10, a11, tx, ty, target, gstart, gorder,
                                           origin, cell, dims, radius)
                        key = o * E + e
                        if sc > best or (sc == best and key < best_key):
                            best = sc
                            best_key = key
                            A[s, 0, 0] = a00
                            A[s, 0, 1] = a01
                            A[s, 1, 0] = a10
                            A[s, 1, 1] = a11
                            t[s, 0] = tx
                            t[s, 1] = ty
                        if nm[s] >= max_matches:
                            done = True
                            break
        scores[s] = max(best, 0)
    return scores, A, t, nm


# ------------------------------------------------------------- numpy reference
def _signature_np(p, j, a, b, c):
    B = np.stack([p[a] - p[j], p[b] - p[j]], axis=1)
    sv = np.linalg.svd(B, compute_uv=False)
    if sv[1] <= 1e-12 * max(sv[0], 1e-300):
        return None
    lam = np.linalg.solve(B, p[c] - p[j])
    return lam, sv[1], sv[0]


def quad_hypotheses_reference(source, samples, target, sig, quad, scale, s_cap, eps, radius, max_cond):
    """Numpy twin of :func:`quad_hypotheses` with no cap on matches (full table scans).

    The same candidates are verified and scored, the same tie rule picks
    the best; returns the same four arrays.
    """
    S, E = samples.shape[0], sig.shape[0]
    scores = np.zeros(S, np.int64)
    A = np.zeros((S, 2, 2))
    t = np.zeros((S, 2))
    nm = np.zeros(S, np.int64)
    for s in range(S):
        best, best_key = -1, -1
        for o in range(6):
            i = samples[s, 0]
            p, q, r = samples[s, ORDERS[o]]
            out = _signature_np(source, i, p, q, r)
            if out is None:
                continue
            lam, smin, _ = out
            ss = (2.0 + np.abs(lam).sum()) / smin
            if ss > s_cap:
                continue
            tol = np.minimum(eps * (ss + scale), min(eps * (ss + s_cap), WMAX))
            hit = np.flatnonzero((np.abs(sig - lam) <= tol[:, None]).all(axis=1))
            for e in hit:
                j, a, b, c = quad[e]
                S_ = np.stack([source[p] - source[i], source[q] - source[i]], axis=1)
                T_ = np.stack([target[a] - target[j], target[b] - target[j]], axis=1)
                Am = T_ @ np.linalg.inv(S_)
                tv = target[j] - Am @ source[i]
                if np.linalg.norm(Am @ source[r] + tv - target[c]) > eps:
                    continue
                sv = np.linalg.svd(Am, compute_uv=False)
                if sv[1] <= 0 or sv[0] > max_cond * sv[1]:
                    continue
                nm[s] += 1
                moved = source @ Am.T + tv
                d2 = ((moved[:, None, :] - target[None, :, :]) ** 2).sum(axis=2)
                sc = int(np.count_nonzero((d2 <= radius * radius).any(axis=1)))
                key = o * E + int(e)
                if sc > best or (sc == best and key < best_key):
                    best, best_key = sc, key
                    A[s], t[s] = Am, tv
        scores[s] = max(best, 0)
    return scores, A, t, nm
