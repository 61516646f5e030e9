"""Numba twins of :mod:`gatv.fitting` for the hypothesis kernels.

Pure functions over small contiguous float64 arrays; each is checked
against its numpy reference in ``tests/test_fitting.py``.
"""

from __future__ import annotations

import numpy as np
from numba import njit


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
