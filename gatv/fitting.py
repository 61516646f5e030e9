"""Least-squares fits of paired points: Kabsch/Horn and Umeyama.

One numpy implementation serves every caller (the rigid and similarity
models, the sequential-RANSAC baseline, the local rigid motions of the
non-rigid mode, the rotations of the catadioptric matcher); its numba twin
for the congruent-triple kernels is :mod:`gatv._fit_kernels`, tested
against it.

Conventions: rows are points, ``target ≈ source @ R.T + t`` (with a scale
``s``: ``target ≈ s source @ R.T + t``), ``R`` a proper rotation
(``det R = +1``, the reflection of the SVD solution is turned away).
"""

from __future__ import annotations

import numpy as np

from ._validation import as_points
from .errors import InputError

__all__ = ["kabsch", "umeyama", "fit_rigid"]


def _weights(w, m: int, batch_shape) -> np.ndarray:
    if w is None:
        return np.full(batch_shape + (m,), 1.0 / m)
    w = np.asarray(w, dtype=np.float64)
    return w / w.sum(axis=-1, keepdims=True)


def _rotation_from_cov(H: np.ndarray):
    """Proper rotation ``R`` maximising ``tr(R H)`` and the SVD's singular values, sign-corrected."""
    U, S, Vt = np.linalg.svd(H)
    V = np.swapaxes(Vt, -1, -2)
    Ut = np.swapaxes(U, -1, -2)
    d = np.sign(np.linalg.det(V @ Ut))
    d = np.where(d == 0, 1.0, d)
    dim = H.shape[-1]
    D = np.broadcast_to(np.eye(dim), H.shape).copy()
    D[..., dim - 1, dim - 1] = d
    S = S.copy()
    S[..., dim - 1] *= d
    return V @ D @ Ut, S


def _fit(x, y, weights, translation: bool, scale: bool):
    m = x.shape[-2]
    if weights is None and not translation:
        cx = np.zeros(x.shape[:-2] + x.shape[-1:])
        cy = cx
        H = np.swapaxes(x, -1, -2) @ y
        var = np.sum(x * x, axis=(-2, -1))
    else:
        w = _weights(weights, m, x.shape[:-2])
        if translation:
            if x.ndim == 2:
                cx, cy = w @ x, w @ y
            else:
                cx = np.einsum("...m,...md->...d", w, x)
                cy = np.einsum("...m,...md->...d", w, y)
        else:
            cx = np.zeros(x.shape[:-2] + x.shape[-1:])
            cy = cx
        xc = x - cx[..., None, :]
        H = np.swapaxes(xc, -1, -2) @ ((y - cy[..., None, :]) * w[..., :, None])
        var = np.einsum("...m,...md,...md->...", w, xc, xc)
    R, S = _rotation_from_cov(H)
    s = np.ones(x.shape[:-2])
    if scale:
        s = S.sum(axis=-1) / np.where(var > 0, var, 1.0)
    if x.ndim == 2:
        t = cy - s * (R @ cx)
    else:
        t = cy - s[..., None] * np.einsum("...ij,...j->...i", R, cx)
    return R, s, t


def _check_pairs(source, target, weights):
    x = np.asarray(source, dtype=np.float64)
    y = np.asarray(target, dtype=np.float64)
    if x.ndim < 2 or x.shape != y.shape:
        msg = f"Expected `source` and `target` to be paired (..., K, d) arrays, got {x.shape} and {y.shape}."
        raise InputError(msg)
    if x.shape[-2] < 1:
        raise InputError("Expected at least one pair in `source` and `target`.")
    if weights is not None:
        w = np.asarray(weights, dtype=np.float64)
        if (w.shape != x.shape[:-1] or np.any(w < 0) or not np.all(np.isfinite(w))
                or np.any(w.sum(axis=-1) <= 0)):
            msg = "Expected `weights` to be non-negative, finite, not all zero, one per pair."
            raise InputError(msg)
    return x, y


def kabsch(source, target, weights=None, *, translation: bool = True):
    """Least-squares rotation (and translation) between paired rows (Kabsch/Horn).

    Parameters
    ----------
    source, target : (K, d) or (..., K, d) array_like
        Paired points (a stack of problems when more than 2-D).
    weights : (K,) or (..., K) array_like, optional
        Non-negative weights; default equal.
    translation : bool, default: True
        Fit ``t`` as well; ``False`` fits a rotation about the origin (as for
        rays on the unit sphere).

    Returns
    -------
    rotation : (d, d) or (..., d, d) ndarray
    translation : (d,) or (..., d) ndarray
        Minimisers of ``sum w |R x + t - y|^2`` (``t = 0`` when not fitted).

    Examples
    --------
    >>> import numpy as np
    >>> from gatv.ga import Rotor
    >>> x = np.random.default_rng(0).normal(size=(10, 3))
    >>> R0 = Rotor.from_axis_angle([0, 0, 1], 0.5).as_matrix()
    >>> R, t = kabsch(x, x @ R0.T + [1, 2, 3])
    >>> bool(np.allclose(R, R0) and np.allclose(t, [1, 2, 3]))
    True
    """
    x, y = _check_pairs(source, target, weights)
    R, _, t = _fit(x, y, weights, translation, scale=False)
    return R, t


def umeyama(source, target, weights=None):
    """Least-squares similarity between paired rows (Umeyama 1991).

    Minimises ``sum w |s R x + t - y|^2`` over a proper rotation ``R``, a
    scale ``s > 0`` and ``t``; shapes as :func:`kabsch`.

    Returns
    -------
    scale : float or (...,) ndarray
    rotation : (d, d) or (..., d, d) ndarray
    translation : (d,) or (..., d) ndarray

    Examples
    --------
    >>> import numpy as np
    >>> x = np.random.default_rng(1).normal(size=(8, 3))
    >>> s, R, t = umeyama(x, 2.5 * x + 1.0)
    >>> round(float(s), 12), bool(np.allclose(R, np.eye(3))), bool(np.allclose(t, 1.0))
    (2.5, True, True)
    """
    x, y = _check_pairs(source, target, weights)
    R, s, t = _fit(x, y, weights, translation=True, scale=True)
    return (float(s) if np.ndim(s) == 0 else s), R, t


def fit_rigid(source, target, weights=None) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid motion between paired (K, 3) rows (Kabsch/Horn).

    :func:`kabsch` on validated (K, 3) points.

    Returns
    -------
    rotation : (3, 3) ndarray
    translation : (3,) ndarray
        Minimisers of ``sum w |R x + t - x'|^2``.
    """
    x = as_points(source, "source", min_points=1)
    y = as_points(target, "target", min_points=1)
    return kabsch(x, y, weights)
