"""Synthetic scenes with several overlapping rigid motions (paper section 5, Fig. 12)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._validation import frozen_array as _frozen
from ..errors import InputError
from ..ga import Rotor

__all__ = ["MotionScene", "multi_motion_scene", "fig12_scene"]


@dataclass(frozen=True, eq=False)
class MotionScene:
    """Source and target with ``K`` known motions, outliers and ground truth.

    Attributes
    ----------
    source, target : (N, 3) ndarray of float
        Shuffled point sets (outliers included).
    rotations : (K, 3, 3) ndarray of float
    translations : (K, 3) ndarray of float
        Motion ``k`` maps its source points: ``target = source @ R.T + t``.
    true_pairs : tuple of (M_k, 2) ndarray of int
        One-to-one ``(source, target)`` pairs of each motion.
    source_labels, target_labels : (N,) ndarray of int
        Motion of each point, ``-1`` for outliers.
    """

    source: np.ndarray
    target: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    true_pairs: tuple
    source_labels: np.ndarray
    target_labels: np.ndarray

    @property
    def n_motions(self) -> int:
        return int(self.rotations.shape[0])


def multi_motion_scene(rotations, translations, sizes, *, n_outliers: int = 0, cube_size: float = 10.0,
                       noise: float = 0.0, seed=None) -> MotionScene:
    """Points of ``K`` motions drawn uniformly in one cube, plus uniform outliers.

    Parameters
    ----------
    rotations : (K, 3, 3) array_like
    translations : (K, 3) array_like
    sizes : sequence of K int
        Points moved by each motion.
    n_outliers : int, default: 0
        Uniform outliers added to each set (inside its bounding box).
    cube_size : float, default: 10
        Edge of the cube, centred at the origin, holding the source points.
    noise : float, default: 0
        Standard deviation of Gaussian noise added to the target points.
    seed : int or numpy.random.Generator
    """
    if seed is None:
        raise InputError("Pass `seed` so that the scene is reproducible.")
    rng = np.random.default_rng(seed)
    rots = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    ts = np.asarray(translations, dtype=np.float64).reshape(-1, 3)
    sizes = [int(s) for s in sizes]
    if not (len(rots) == len(ts) == len(sizes)):
        raise InputError("Expected one rotation, translation and size per motion.")
    half = 0.5 * float(cube_size)
    src, dst, lab = [], [], []
    for k, (R, t, m) in enumerate(zip(rots, ts, sizes)):
        x = rng.uniform(-half, half, size=(m, 3))
        src.append(x)
        dst.append(x @ R.T + t + (rng.normal(0.0, noise, size=(m, 3)) if noise > 0 else 0.0))
        lab.append(np.full(m, k))
    src = np.vstack(src)
    dst = np.vstack(dst)
    lab = np.concatenate(lab)
    n_in = src.shape[0]
    n_out = int(n_outliers)
    out_s = rng.uniform(src.min(axis=0), src.max(axis=0), size=(n_out, 3))
    out_t = rng.uniform(dst.min(axis=0), dst.max(axis=0), size=(n_out, 3))
    source = np.vstack([src, out_s])
    target = np.vstack([dst, out_t])
    labels = np.concatenate([lab, np.full(n_out, -1)])
    ps = rng.permutation(n_in + n_out)
    pt = rng.permutation(n_in + n_out)
    ws, wt = np.argsort(ps)[:n_in], np.argsort(pt)[:n_in]  # old row i is now at ws[i]
    pairs = []
    for k in range(len(sizes)):
        pk = np.column_stack([ws[lab == k], wt[lab == k]])
        pairs.append(_frozen(pk[np.argsort(pk[:, 0])], np.int64))
    pairs = tuple(pairs)
    return MotionScene(
        source=_frozen(source[ps]), target=_frozen(target[pt]), rotations=_frozen(rots),
        translations=_frozen(ts), true_pairs=pairs, source_labels=_frozen(labels[ps], np.int64),
        target_labels=_frozen(labels[pt], np.int64),
    )


def fig12_scene(*, n_per_motion: int = 40, n_outliers: int = 0, noise: float = 0.0, seed=0) -> MotionScene:
    """The paper's Fig. 12: three overlapping motions with different axes,
    angles and translations, points in a 10×10×10 cube centred at the origin."""
    rots = [
        Rotor.from_axis_angle([0.0, 0.0, 1.0], np.radians(30.0)).as_matrix(),
        Rotor.from_axis_angle([1.0, 1.0, 0.0], np.radians(-45.0)).as_matrix(),
        Rotor.from_axis_angle([1.0, -2.0, 2.0], np.radians(75.0)).as_matrix(),
    ]
    ts = [[2.0, 1.0, 0.0], [-3.0, 2.0, 1.5], [1.0, -2.0, -3.0]]
    return multi_motion_scene(rots, ts, [n_per_motion] * 3, n_outliers=n_outliers, noise=noise, seed=seed)
