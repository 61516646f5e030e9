"""Synthetic scenes with several overlapping rigid motions (paper section 5, Fig. 12)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .._validation import frozen_array as _frozen
from ..candidates import median_spacing
from ..errors import InputError
from ..ga import Rotor

__all__ = ["MotionScene", "ScanScene", "fig12_scene", "multi_motion_scene", "scan_scene"]


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


@dataclass(frozen=True, eq=False)
class ScanScene:
    """Two scenes of real scans: several objects, each moved by its own motion, clutter, a static patch.

    Attributes
    ----------
    source, target : (N, 3), (M, 3) ndarray of float
        The two scenes.
    rotations : (K, 3, 3) ndarray of float
    translations : (K, 3) ndarray of float
        Motion ``k`` takes object ``k`` of the source scene onto the target
        scene (``target = source @ R.T + t``); the static patch, when there
        is one, is motion ``K - 1`` (the identity).
    source_labels, target_labels : (N,), (M,) ndarray of int
        Motion of each point (the static patch is the last) where the other
        scene sees its surface (a counterpart within three point spacings
        under the true motion); ``-1`` for clutter and parts seen in one
        scene only.
    static : bool
        Whether the last motion is the static patch.
    """

    source: np.ndarray
    target: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    source_labels: np.ndarray
    target_labels: np.ndarray
    static: bool

    @property
    def n_motions(self) -> int:
        return int(self.rotations.shape[0])


def _random_rotation(rng) -> np.ndarray:
    axis = rng.normal(size=3)
    return Rotor.from_axis_angle(axis / np.linalg.norm(axis), rng.uniform(0.0, np.pi)).as_matrix()


def scan_scene(pairs, *, n_points: int = 40000, clutter: float = 0.2, static_patch: float = 0.1,
               seed=None) -> ScanScene:
    """Compose two scenes from real scan pairs, each object moved by its own random motion.

    Parameters
    ----------
    pairs : sequence of (target, source, rotation, translation)
        Scan pairs of one object each (as :func:`gatv.datasets.load_bunny_pair`
        returns them, in one unit): ``target ≈ source @ rotation.T + translation``.
    n_points : int, default: 40000
        Points per scene, about; each object's scans are subsampled to an
        equal share of what clutter and the patch leave.
    clutter : float, default: 0.2
        Share of each scene that is uniform clutter in the scene's bounding box.
    static_patch : float, default: 0.1
        Share of each scene on a static square plane patch below the objects
        (sampled independently in the two scenes, with the objects' point
        spacing); 0 for none.
    seed : int or numpy.random.Generator
        Required: the scene is reproducible.

    Returns
    -------
    ScanScene
        Objects side by side in the target scene; in the source scene each
        is rotated about its centroid by a random rotation (any angle) and
        shifted by up to a fifth of its size.
    """
    if seed is None:
        raise InputError("Pass `seed` so that the scene is reproducible.")
    pairs = list(pairs)
    if not pairs:
        raise InputError("Expected `pairs` to hold at least one (target, source, rotation, translation).")
    if not 0.0 <= clutter < 1.0 or not 0.0 <= static_patch < 1.0 or clutter + static_patch >= 1.0:
        raise InputError(f"Expected `clutter` and `static_patch` in [0, 1) with a sum below 1, got "
                         f"{clutter!r} and {static_patch!r}.")
    rng = np.random.default_rng(seed)
    per_object = int(n_points * (1.0 - clutter - static_patch) / len(pairs))
    src_parts, tgt_parts, src_lab, tgt_lab, rots, ts = [], [], [], [], [], []
    offset = 0.0
    spacing = []
    for k, (tgt, src, R, t) in enumerate(pairs):
        tgt = np.asarray(tgt, dtype=np.float64)
        src = np.asarray(src, dtype=np.float64) @ np.asarray(R).T + np.asarray(t)  # target frame
        tgt = tgt[rng.choice(tgt.shape[0], min(per_object, tgt.shape[0]), replace=False)]
        src = src[rng.choice(src.shape[0], min(per_object, src.shape[0]), replace=False)]
        lo, hi = tgt.min(axis=0), tgt.max(axis=0)
        size = float(np.max(hi - lo))
        shift = np.array([offset - lo[0], -0.5 * (lo[1] + hi[1]), -lo[2]])  # side by side along x
        offset += 1.3 * (hi[0] - lo[0])
        tgt, src = tgt + shift, src + shift
        c = tgt.mean(axis=0)
        Q = _random_rotation(rng)
        v = rng.uniform(-0.2, 0.2, 3) * size
        moved = (src - c) @ Q.T + c + v  # source scene = Q (p - c) + c + v
        # true motion source scene -> target scene: p = Q^T (s - c - v) + c
        rots.append(Q.T)
        ts.append(c - Q.T @ (c + v))
        src_parts.append(moved)
        tgt_parts.append(tgt)
        src_lab.append(np.full(moved.shape[0], k))
        tgt_lab.append(np.full(tgt.shape[0], k))
        spacing.append(median_spacing(tgt[: min(2000, tgt.shape[0])]))
    all_t = np.vstack(tgt_parts)
    static = static_patch > 0
    if static:
        n_patch = int(n_points * static_patch)
        lo, hi = all_t.min(axis=0), all_t.max(axis=0)
        z = lo[2] - 0.05 * (hi[2] - lo[2])
        side = np.sqrt(n_patch) * float(np.median(spacing))  # the objects' spacing
        mid = 0.5 * (lo[:2] + hi[:2])
        for parts, labs in ((src_parts, src_lab), (tgt_parts, tgt_lab)):
            xy = mid + rng.uniform(-0.5 * side, 0.5 * side, (n_patch, 2))
            zs = z + rng.normal(0.0, 0.1 * float(np.median(spacing)), n_patch)  # a noisy floor
            parts.append(np.column_stack([xy, zs]))
            labs.append(np.full(n_patch, len(pairs)))
        rots.append(np.eye(3))
        ts.append(np.zeros(3))
    out = []
    for parts, labs in ((src_parts, src_lab), (tgt_parts, tgt_lab)):
        pts, lab = np.vstack(parts), np.concatenate(labs)
        n_clutter = round(clutter / (1.0 - clutter) * pts.shape[0])
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        pts = np.vstack([pts, rng.uniform(lo, hi, (n_clutter, 3))])
        lab = np.concatenate([lab, np.full(n_clutter, -1)])
        perm = rng.permutation(pts.shape[0])
        out.append((pts[perm], lab[perm]))
    (S, ls), (T, lt) = out
    # A point is explained by its motion where the other scene sees its surface:
    # its counterpart lies within three point spacings; elsewhere -1.
    gate = 3.0 * float(np.median(spacing))
    rots_a, ts_a = np.array(rots), np.array(ts)
    for k in range(len(rots)):
        ms, mt = np.flatnonzero(ls == k), np.flatnonzero(lt == k)
        moved = S[ms] @ rots_a[k].T + ts_a[k]
        ds, _ = cKDTree(T[mt]).query(moved, k=1, distance_upper_bound=gate)
        dt, _ = cKDTree(moved).query(T[mt], k=1, distance_upper_bound=gate)
        ls[ms[~np.isfinite(ds)]] = -1
        lt[mt[~np.isfinite(dt)]] = -1
    return ScanScene(source=_frozen(S), target=_frozen(T), rotations=_frozen(np.array(rots)),
                     translations=_frozen(np.array(ts)), source_labels=_frozen(ls, np.int64),
                     target_labels=_frozen(lt, np.int64), static=static)
