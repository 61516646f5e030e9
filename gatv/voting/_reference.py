"""Pure-numpy brute-force O(N²) tensor voting, the reference for the kernels' tests."""

from __future__ import annotations

import numpy as np

from gatv.voting._fields import RADIUS_FACTOR, ball_vote, stick_vote

__all__ = ["ball_pass", "stick_pass", "components"]


def components(t: np.ndarray) -> np.ndarray:
    """(N, 3, 3) tensors → (N, 6) components ``(xx, xy, xz, yy, yz, zz)``."""
    return t[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]]


def ball_pass(points: np.ndarray, sigma: float) -> np.ndarray:
    """Sum of the ball votes of all tokens (self included) within ``2σ``: (N, 3, 3)."""
    p = np.asarray(points, dtype=np.float64)
    v = p[:, None, :] - p[None, :, :]  # votee − voter
    return ball_vote(v, sigma).sum(axis=1)


def stick_pass(points, normals, saliency, sigma: float) -> np.ndarray:
    """Sum of the stick votes ``saliency_j · S(n_j, x_i − p_j)`` within ``2σ``: (N, 3, 3)."""
    p = np.asarray(points, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    w = np.asarray(saliency, dtype=np.float64)
    v = p[:, None, :] - p[None, :, :]
    l2 = np.einsum("ijk,ijk->ij", v, v)
    inside = (l2 < (RADIUS_FACTOR * sigma) ** 2) & (w[None, :] > 0)
    t = stick_vote(np.broadcast_to(n[None, :, :], v.shape), v, sigma)
    t = t * (w[None, :] * inside)[..., None, None]
    return t.sum(axis=1)
