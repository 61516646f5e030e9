"""Numba twins of :mod:`gatv.fitting` for the hypothesis kernels, and the scatter of neighbourhoods.

Pure functions over small contiguous float64 arrays; each is checked
against its numpy reference in ``tests/test_fitting.py``
(:func:`neighbourhood_scatter` through :func:`gatv._icp_kernels.neighbourhood_axes`
in ``tests/test_scans_kernels.py``).  Nothing here imports gatv, so the
models' input checks (:func:`gatv.models.rigid.check_spread`) and the scans
kernels alike can use it.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True)
def _centred_cov(src, dst):
    n = src.shape[0]
    d = src.shape[1]
    cs = np.zeros(d)
    cd = np.zeros(d)
    for i in range(n):
        for k in range(d):
            cs[k] += src[i, k]
            cd[k] += dst[i, k]
    cs /= n
    cd /= n
    H = np.zeros((d, d))
    var = 0.0
    for i in range(n):
        for r in range(d):
            a = src[i, r] - cs[r]
            var += a * a
            for c in range(d):
                H[r, c] += a * (dst[i, c] - cd[c])
    return cs, cd, H, var / n


@njit(cache=True, parallel=True)
def neighbourhood_scatter(points, neighbours, m):
    """``(centroids, scatter)``: ``(N, 3)`` the mean of each row's first ``m`` ``neighbours`` (rows of
    ``points``) and ``(N, 6)`` the upper triangle ``(xx, xy, xz, yy, yz, zz)`` of their scatter matrix
    about it: :func:`gatv.scans.local_scatter`'s centroids and matrix, without gathering the neighbours (and the
    input check's spread, :func:`gatv.models.rigid.check_spread`: one neighbourhood of every point)."""
    n = neighbours.shape[0]
    centroids = np.empty((n, 3))
    out = np.empty((n, 6))
    for i in prange(n):
        cx = cy = cz = 0.0
        for a in range(m):
            q = neighbours[i, a]
            cx += points[q, 0]
            cy += points[q, 1]
            cz += points[q, 2]
        cx /= m
        cy /= m
        cz /= m
        s0 = s1 = s2 = s3 = s4 = s5 = 0.0
        for a in range(m):
            q = neighbours[i, a]
            x = points[q, 0] - cx
            y = points[q, 1] - cy
            z = points[q, 2] - cz
            s0 += x * x
            s1 += x * y
            s2 += x * z
            s3 += y * y
            s4 += y * z
            s5 += z * z
        centroids[i, 0], centroids[i, 1], centroids[i, 2] = cx, cy, cz
        out[i, 0], out[i, 1], out[i, 2], out[i, 3], out[i, 4], out[i, 5] = s0, s1, s2, s3, s4, s5
    return centroids, out


@njit(cache=True)
def kabsch3(src, dst):
    """Least-squares rotation and translation with ``dst ≈ R src + t`` (equal weights)."""
    cs, cd, H, _ = _centred_cov(src, dst)
    U, S, Vt = np.linalg.svd(H)
    R = Vt.T @ U.T
    if np.linalg.det(R) < 0:
        for r in range(3):
            Vt[2, r] = -Vt[2, r]
        R = Vt.T @ U.T
    t = cd - R @ cs
    return R, t


@njit(cache=True)
def umeyama3(src, dst):
    """Least-squares similarity ``dst ≈ s R src + t`` (equal weights); returns ``(s, R, t)``."""
    cs, cd, H, var = _centred_cov(src, dst)
    n = src.shape[0]
    U, S, Vt = np.linalg.svd(H)
    R = Vt.T @ U.T
    last = S[2]
    if np.linalg.det(R) < 0:
        for r in range(3):
            Vt[2, r] = -Vt[2, r]
        R = Vt.T @ U.T
        last = -last
    s = (S[0] + S[1] + last) / n / var if var > 0 else 1.0
    t = cd - s * (R @ cs)
    return s, R, t


@njit(cache=True)
def triangle_pose(src, dst):
    """:func:`kabsch3` of two labelled triangles in closed form (no SVD).

    Three points are coplanar, so the least-squares rotation maps the
    source triangle's plane onto the target's, normal ``(b - a) × (c - a)``
    onto normal, and turns in that plane by the angle of the 2D
    least-squares fit, ``atan2(Σ x_i × y_i, Σ x_i · y_i)`` of the centred
    in-plane coordinates.  Equal to :func:`kabsch3` whenever the two
    labelled triangles have the same orientation in their planes (always
    for congruent ones that are not nearly collinear), at a tenth of its
    cost; nearly collinear triangles go to :func:`kabsch3`.
    """
    cs = np.empty(3)
    cd = np.empty(3)
    for k in range(3):
        cs[k] = (src[0, k] + src[1, k] + src[2, k]) / 3.0
        cd[k] = (dst[0, k] + dst[1, k] + dst[2, k]) / 3.0
    fs = _triangle_frame(src)
    fd = _triangle_frame(dst)
    if fs[0, 0] != fs[0, 0] or fd[0, 0] != fd[0, 0]:  # NaN: nearly collinear
        return kabsch3(src, dst)
    # In-plane least-squares angle from the source's (u, v) to the target's.
    dot = 0.0
    crs = 0.0
    for i in range(3):
        xu = xv = yu = yv = 0.0
        for k in range(3):
            xs = src[i, k] - cs[k]
            yd = dst[i, k] - cd[k]
            xu += xs * fs[0, k]
            xv += xs * fs[1, k]
            yu += yd * fd[0, k]
            yv += yd * fd[1, k]
        dot += xu * yu + xv * yv
        crs += xu * yv - xv * yu
    h = np.hypot(dot, crs)
    c, s = (dot / h, crs / h) if h > 0 else (1.0, 0.0)
    R = np.zeros((3, 3))
    for r in range(3):
        ur = c * fd[0, r] + s * fd[1, r]  # image of the source's u
        vr = -s * fd[0, r] + c * fd[1, r]  # image of the source's v
        for k in range(3):
            R[r, k] = ur * fs[0, k] + vr * fs[1, k] + fd[2, r] * fs[2, k]
    t = cd - R @ cs
    return R, t


@njit(cache=True)
def _triangle_frame(p):
    """Rows ``u, v, n``: ``u`` along ``b - a``, ``n`` along ``(b - a) × (c - a)``; NaN when nearly collinear."""
    # Element by element: an array assigned to a slice compiles numba's shape-mismatch message (seconds).
    f = np.empty((3, 3))
    e1 = p[1] - p[0]
    e2 = p[2] - p[0]
    n = np.empty(3)
    _cross(e1, e2, n)
    l1 = np.sqrt(e1 @ e1)
    ln = np.sqrt(n @ n)
    if not (ln > 1e-12 * l1 * np.sqrt(e2 @ e2)):
        for r in range(3):
            for k in range(3):
                f[r, k] = np.nan
        return f
    for k in range(3):
        f[0, k] = e1[k] / l1
        f[2, k] = n[k] / ln
    _cross(f[2], f[0], f[1])  # n × u
    return f


@njit(cache=True)
def _cross(a, b, out):
    """``out = a × b`` for 3-vectors, as ``np.cross`` computes it, without its general machinery."""
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]
