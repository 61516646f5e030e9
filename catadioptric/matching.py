"""Corner correspondences between two catadioptric images, on the unit sphere.

The catadioptric example of Reyes, Medioni & Bayro (IJCV 2007, end of
section 5.1, Fig. 15): the corners of both images are lifted to the unit
sphere of the unified camera model, and the corresponding corners are found
as a structure in the joint space of candidate pairs.

How it works
------------
1. **Lift.** Both pixel sets are lifted to unit rays; pixels the camera
   cannot lift (outside the mirror's disc, NaN rows) are dropped, and the
   index maps back to the input rows are kept. Each ray gets its own noise
   level, ``noise_px`` times the lifting's Jacobian at that pixel (the
   sphere noise of a 1-pixel error is largest at the image centre,
   ``(1 + xi) / f``, and falls towards the rim).
2. **Dominant rotation.** A pure camera rotation moves the rays rigidly
   about the centre of the sphere, ``y = R x``. Local oriented triangles
   (each ray with two of its nearest neighbours, counter-clockwise) are
   matched between the views by their side lengths, each match gives a
   trial rotation (three rays suffice, the sphere's centre is the fourth,
   fixed point), and the densest cluster of trial rotations, found by
   counting neighbours in quaternion space, is the dominant rotation. It is
   polished by rotation-only ICP inside the per-pair noise gate. The
   congruent-triple search of :func:`gatv.register` is not used here: on a
   sphere every wrong rotation maps the points onto the same surface, so
   its volumetric chance level accepts wrong trials, and a triangle has
   more congruent partners than the search keeps.
3. **Rigid or non-rigid.** The rotation's support is compared with the
   chance level of the sphere (a wrong rotation brings a ray within the
   gate of a target ray with probability ``n2 π gate² / area``). With a
   camera translation the rays move non-rigidly (parallax ``t⊥ / depth``),
   only locally rigidly: after turning the first view by the dominant
   rotation, the tokens ``y_j − R x_i`` of the true pairs form a curved
   surface in the joint space, which the local-constraint mode
   :func:`gatv.nonrigid.register` extracts with tensor voting and local
   eq. 41. The non-rigid result is kept when it explains clearly more
   pairs than the rotation (``nonrigid_gain``), else the rigid one.

Motion convention: a scene point seen along ray ``x`` in view 1 is seen
along ``y ≈ R x`` in view 2 (pure rotation), ``y ∝ R X + t`` in general.
"""

from __future__ import annotations

import math
import numbers
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import poisson

from catadioptric.camera import UnifiedCamera
from gatv.candidates import one_to_one
from gatv._validation import frozen_array as _frozen

if TYPE_CHECKING:
    from numpy.typing import ArrayLike, NDArray

__all__ = ["SphereMatch", "match", "sphere_noise"]

#: Residual gate of a pair, in per-axis standard deviations of the pair's
#: combined noise: the norm of a 2D Gaussian stays below it with 99%.
GATE_SIGMAS = 3.03
#: Neighbours per ray for the local triangles of the rotation search.
TRIANGLE_NEIGHBOURS = 6


@dataclass(frozen=True, eq=False)
class SphereMatch:
    """Corner correspondences between two catadioptric views.

    All arrays are read-only. The result is falsy when nothing was matched
    (``info["reason"]`` says why).

    Attributes
    ----------
    correspondences : (K, 2) ndarray of int
        One-to-one pairs ``(i, j)`` of rows of ``pixels1`` and ``pixels2``
        (the input rows), sorted by ``i``.
    rays1, rays2 : (M1, 3), (M2, 3) ndarray of float
        Unit rays of the pixels that could be lifted.
    index1, index2 : (M1,), (M2,) ndarray of int
        Input row of each ray: ``rays1[k]`` is ``pixels1[index1[k]]``.
    rotation : (3, 3) ndarray of float or None
        Dominant rotation ``y ≈ R x`` (view 1 rays to view 2 rays) when its
        support beats the chance level of the sphere, else None.
    rotation_support : int
        Pairs within the noise gate of ``rotation`` (one-to-one).
    strategy : {"rigid", "nonrigid", "none"}
        Which stage gave ``correspondences``.
    noise : float
        Median sphere noise of the rays (unit-sphere units, per axis).
    info : dict
        Diagnostics: chance level, supports of both stages, timings.
    """

    correspondences: NDArray[np.int64]
    rays1: NDArray[np.float64]
    rays2: NDArray[np.float64]
    index1: NDArray[np.int64]
    index2: NDArray[np.int64]
    rotation: NDArray[np.float64] | None
    rotation_support: int
    strategy: str
    noise: float
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "correspondences",
                           _frozen(np.asarray(self.correspondences).reshape(-1, 2), np.int64))
        for name in ("rays1", "rays2"):
            object.__setattr__(self, name, _frozen(getattr(self, name)))
        for name in ("index1", "index2"):
            object.__setattr__(self, name, _frozen(getattr(self, name), np.int64))
        if self.rotation is not None:
            object.__setattr__(self, "rotation", _frozen(self.rotation))

    @property
    def support(self) -> int:
        """int: number of correspondences."""
        return int(self.correspondences.shape[0])

    def __bool__(self) -> bool:
        return self.support > 0

    @property
    def rotation_deg(self) -> float | None:
        """float or None: angle of :attr:`rotation` in degrees."""
        if self.rotation is None:
            return None
        c = (float(np.trace(self.rotation)) - 1.0) / 2.0
        return math.degrees(math.acos(min(1.0, max(-1.0, c))))

    def to_dict(self) -> dict:
        """JSON-serialisable summary (correspondences as lists of input rows)."""
        return {
            "strategy": self.strategy,
            "support": self.support,
            "correspondences": self.correspondences.tolist(),
            "rotation": None if self.rotation is None else self.rotation.tolist(),
            "rotation_deg": self.rotation_deg,
            "rotation_support": int(self.rotation_support),
            "noise": self.noise,
            "n_rays1": int(self.rays1.shape[0]),
            "n_rays2": int(self.rays2.shape[0]),
        }


# --------------------------------------------------------------- validation
def _check_pixels(pixels, name: str) -> NDArray[np.float64]:
    if pixels is None:
        msg = f"Expected `{name}` to be an (N, 2) array of pixels, got None."
        raise ValueError(msg)
    try:
        arr = np.asarray(pixels, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        msg = f"Expected `{name}` to be an (N, 2) array of numbers: {exc}."
        raise ValueError(msg) from exc
    if arr.ndim != 2 or arr.shape[1] != 2:
        msg = f"Expected `{name}` to have shape (N, 2), got {arr.shape}."
        raise ValueError(msg)
    return np.ascontiguousarray(arr)


def _check_camera(camera, name: str) -> UnifiedCamera:
    if not isinstance(camera, UnifiedCamera):
        msg = f"Expected `{name}` to be a catadioptric.UnifiedCamera, got {type(camera).__name__}."
        raise ValueError(msg)
    return camera


def _check_real(value, name: str, *, low: float = 0.0, allow_zero: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        msg = f"Expected `{name}` to be a finite number, got {value!r}."
        raise ValueError(msg)
    value = float(value)
    if value < low or (value == low and not allow_zero):
        msg = f"Expected `{name}` {'>=' if allow_zero else '>'} {low}, got {value!r}."
        raise ValueError(msg)
    return value


# --------------------------------------------------------------- lifting
def _lift(camera: UnifiedCamera, pixels: NDArray[np.float64]):
    finite = np.all(np.isfinite(pixels), axis=1)
    rays = np.full((pixels.shape[0], 3), np.nan)
    valid = np.zeros(pixels.shape[0], dtype=bool)
    if finite.any():
        r, ok = camera.lift(pixels[finite], return_mask=True)
        rays[finite] = r
        valid[finite] = ok
    index = np.flatnonzero(valid)
    return rays[index], index


def sphere_noise(camera: UnifiedCamera, pixels: ArrayLike, noise_px: float = 1.0) -> NDArray[np.float64]:
    """Per-axis sphere noise of rays lifted from pixels with ``noise_px`` noise.

    The lifting's Jacobian is taken by central differences (0.5 px); the
    result is ``noise_px`` times the root-mean-square of its two columns
    (the ray's displacement per pixel along ``u`` and ``v``).

    Parameters
    ----------
    camera : UnifiedCamera
    pixels : (N, 2) array_like of float
        Pixels that the camera can lift.
    noise_px : float, default: 1.0
        Pixel noise, standard deviation per coordinate.

    Returns
    -------
    (N,) ndarray of float
        At the image centre ``noise_px (1 + xi) / f`` for an undistorted
        camera.

    Examples
    --------
    >>> cam = UnifiedCamera(1.0, 300.0, 300.0, 640.0, 512.0)
    >>> round(float(sphere_noise(cam, [[640.0, 512.0]])[0] * 300.0), 3)
    2.0
    """
    pix = _check_pixels(pixels, "pixels")
    h = 0.5
    cols = []
    for du, dv in ((h, 0.0), (0.0, h)):
        plus, ok1 = camera.lift(pix + [du, dv], return_mask=True)
        minus, ok2 = camera.lift(pix - [du, dv], return_mask=True)
        d = np.linalg.norm(plus - minus, axis=1) / (2.0 * h)
        fallback = (1.0 + camera.xi) / min(camera.fx, camera.fy)
        cols.append(np.where(ok1 & ok2 & np.isfinite(d), d, fallback))
    return noise_px * np.sqrt(0.5 * (cols[0] ** 2 + cols[1] ** 2))


# --------------------------------------------------------------- rotation search
def _rotation_fit(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation ``R`` minimising ``sum |b - a R^T|^2`` (about the origin)."""
    H = a.T @ b
    U, _, Vt = np.linalg.svd(H)
    d = 1.0 if np.linalg.det(Vt.T @ U.T) >= 0 else -1.0
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T


def _batched_rotation_fit(A, B):
    """Rotations for stacks ``A, B`` of shape (K, m, 3), about the origin."""
    H = np.einsum("kmi,kmj->kij", A, B)
    U, _, Vt = np.linalg.svd(H)
    V = np.transpose(Vt, (0, 2, 1))
    Ut = np.transpose(U, (0, 2, 1))
    d = np.sign(np.linalg.det(V @ Ut))
    d = np.where(d == 0, 1.0, d)
    D = np.zeros_like(H)
    D[:, 0, 0] = 1.0
    D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    return V @ D @ Ut


def _quaternions(R):
    """Unit quaternions ``(w, x, y, z)`` with ``w >= 0`` of rotation stacks."""
    tr = np.trace(R, axis1=1, axis2=2)
    w = 0.5 * np.sqrt(np.maximum(0.0, 1.0 + tr))
    x = 0.5 * np.sqrt(np.maximum(0.0, 1.0 + R[:, 0, 0] - R[:, 1, 1] - R[:, 2, 2]))
    y = 0.5 * np.sqrt(np.maximum(0.0, 1.0 - R[:, 0, 0] + R[:, 1, 1] - R[:, 2, 2]))
    z = 0.5 * np.sqrt(np.maximum(0.0, 1.0 - R[:, 0, 0] - R[:, 1, 1] + R[:, 2, 2]))
    x = np.copysign(x, R[:, 2, 1] - R[:, 1, 2])
    y = np.copysign(y, R[:, 0, 2] - R[:, 2, 0])
    z = np.copysign(z, R[:, 1, 0] - R[:, 0, 1])
    q = np.column_stack([w, x, y, z])
    return q / np.linalg.norm(q, axis=1)[:, None]


def _triangles(rays: NDArray[np.float64], k: int):
    """Oriented local triangles ``(a, b, c)`` and their side lengths.

    ``b, c`` are two of the ``k`` nearest neighbours of ``a`` with
    ``det(a, b, c) > 0`` (counter-clockwise seen from outside the sphere;
    a rotation keeps the orientation, a mirror would not).
    """
    n = rays.shape[0]
    k = min(k, n - 1)
    if k < 2:
        return np.empty((0, 3), np.int64), np.empty((0, 3))
    _, nb = cKDTree(rays).query(rays, k=k + 1)
    nb = nb[:, 1:]
    p, q = np.triu_indices(k, 1)
    a = np.repeat(np.arange(n), p.size)
    b = nb[:, p].ravel()
    c = nb[:, q].ravel()
    det = np.einsum("ij,ij->i", rays[a], np.cross(rays[b], rays[c]))
    swap = det < 0
    b, c = np.where(swap, c, b), np.where(swap, b, c)
    tri = np.column_stack([a, b, c])
    sides = np.column_stack([
        np.linalg.norm(rays[a] - rays[b], axis=1),
        np.linalg.norm(rays[a] - rays[c], axis=1),
        np.linalg.norm(rays[b] - rays[c], axis=1),
    ])
    return tri, sides


def _trial_rotations(r1, r2, rel_tol, max_matches=8):
    """Rotations of source triangles onto target triangles of the same shape.

    Returns the rotations (K, 3, 3) and the triangles' vertex pairs
    (K, 3, 2) ``(source ray, target ray)``.
    """
    t1, s1 = _triangles(r1, TRIANGLE_NEIGHBOURS)
    t2, s2 = _triangles(r2, TRIANGLE_NEIGHBOURS)
    empty = np.empty((0, 3, 3)), np.empty((0, 3, 2), np.int64)
    if t1.shape[0] == 0 or t2.shape[0] == 0:
        return empty
    l1, l2 = np.log(np.maximum(s1, 1e-12)), np.log(np.maximum(s2, 1e-12))
    k = min(max_matches, t2.shape[0])
    dist, j = cKDTree(l2).query(l1, k=k, distance_upper_bound=rel_tol)
    dist, j = dist.reshape(len(l1), -1), j.reshape(len(l1), -1)
    ii, kk = np.nonzero(np.isfinite(dist))
    if ii.size == 0:
        return empty
    a, b = t1[ii], t2[j[ii, kk]]
    return _batched_rotation_fit(r1[a], r2[b]), np.stack([a, b], axis=2)


def _dominant_rotation(r1, r2, rel_tol, radius_deg):
    """Densest cluster of trial rotations.

    Returns ``(rotation, cluster size, number of trials, vertex pairs of the
    cluster's trials)``.
    """
    Rs, verts = _trial_rotations(r1, r2, rel_tol)
    if Rs.shape[0] == 0:
        return None, 0, 0, np.empty((0, 2), np.int64)
    q = _quaternions(Rs)
    both = np.vstack([q, -q])
    tree = cKDTree(both)
    rad = 2.0 * math.sin(math.radians(radius_deg) / 4.0)  # chord for a rotation angle
    sample = q if q.shape[0] <= 20000 else q[np.random.default_rng(0).choice(q.shape[0], 20000, replace=False)]
    counts = tree.query_ball_point(sample, rad, return_length=True)
    best = int(np.argmax(counts))
    near = np.asarray(tree.query_ball_point(sample[best], rad), dtype=np.int64)
    qs = both[near]
    qs = qs * np.sign(qs @ sample[best])[:, None]
    m = qs.mean(axis=0)
    m /= np.linalg.norm(m)
    w, x, y, z = m
    R = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])
    members = near % q.shape[0]
    return R, int(counts[best]), int(Rs.shape[0]), verts[members].reshape(-1, 2)


def _voted_seeds(vertex_pairs, min_votes=2):
    """Pairs named by at least ``min_votes`` trials of the cluster, one-to-one by votes."""
    if vertex_pairs.shape[0] == 0:
        return vertex_pairs
    pairs, votes = np.unique(vertex_pairs, axis=0, return_counts=True)
    ok = votes >= min_votes
    pairs, votes = pairs[ok], votes[ok]
    if pairs.shape[0] == 0:
        return pairs
    return pairs[one_to_one(pairs, -votes.astype(np.float64))]


def _grow_local(r1, r2, tree2, s1, s2, seeds, neighbours=6, scale=2.0, rounds=15, final_scale=1.0):
    """Locally rigid growth: each ray moves by the rotation of its nearest matches.

    The rotation (about the sphere's centre) fitted on the ``neighbours``
    matched rays nearest to a source ray predicts where it lands; target
    rays within ``scale`` noise gates of the prediction are matched
    one-to-one, closest first, and the matches are recomputed from the
    previous round's until they repeat (the local constraint of section
    5.1: rigid only between neighbours).
    """
    pairs = seeds
    for r in range(rounds + 1):
        if pairs.shape[0] < 3:
            return pairs
        last = r == rounds
        xs, ys = r1[pairs[:, 0]], r2[pairs[:, 1]]
        k = min(neighbours, pairs.shape[0])
        _, nb = cKDTree(xs).query(r1, k=k)
        nb = nb.reshape(r1.shape[0], k)
        Rl = _batched_rotation_fit(xs[nb], ys[nb])
        pred = np.einsum("kij,kj->ki", Rl, r1)
        # a ray far from every match is not predicted
        reach = np.linalg.norm(r1 - xs[nb[:, 0]], axis=1)
        spacing = float(np.median(cKDTree(xs).query(xs, k=2)[0][:, 1])) if xs.shape[0] > 1 else 1.0
        pred[reach > 4.0 * spacing] = np.inf
        new = _gated_pairs(pred, r2, tree2, s1, s2, final_scale if last else scale)
        if last:
            return new
        if new.shape == pairs.shape and np.array_equal(new, pairs):
            rounds = r + 1
        pairs = new
    return pairs


def _gated_pairs(moved, r2, tree2, s1, s2, scale=1.0, k=4):
    """One-to-one pairs within the per-pair noise gate, closest first."""
    gmax = scale * GATE_SIGMAS * math.sqrt(float(s1.max()) ** 2 + float(s2.max()) ** 2)
    rows = np.flatnonzero(np.all(np.isfinite(moved), axis=1))
    d, j = tree2.query(moved[rows], k=min(k, r2.shape[0]), distance_upper_bound=gmax)
    d, j = d.reshape(len(rows), -1), j.reshape(len(rows), -1)
    ii, kk = np.nonzero(np.isfinite(d))
    jj, dd = j[ii, kk], d[ii, kk]
    ii = rows[ii]
    ok = dd <= scale * GATE_SIGMAS * np.sqrt(s1[ii] ** 2 + s2[jj] ** 2)
    pairs = np.column_stack([ii[ok], jj[ok]]).astype(np.int64)
    if pairs.shape[0] == 0:
        return pairs
    return pairs[one_to_one(pairs, dd[ok])]


def _rotation_icp(r1, r2, tree2, s1, s2, R, iterations=30):
    """Rotation-only ICP: wide gate first (the trial is a few degrees off), then the noise gate."""
    kept = np.empty((0, 2), np.int64)
    for scale in (4.0, 2.0, 1.0):
        for _ in range(iterations):
            new = _gated_pairs(r1 @ R.T, r2, tree2, s1, s2, scale)
            if new.shape[0] < 3:
                break
            R = _rotation_fit(r1[new[:, 0]], r2[new[:, 1]])
            if new.shape == kept.shape and np.array_equal(new, kept):
                break
            kept = new
    kept = _gated_pairs(r1 @ R.T, r2, tree2, s1, s2)
    return R, kept


def _cap_area(rays: NDArray[np.float64]) -> float:
    """Area of the smallest cap around the mean direction holding 99% of the rays."""
    m = rays.mean(axis=0)
    nm = np.linalg.norm(m)
    if nm < 1e-9:
        return 4.0 * math.pi
    c = float(np.quantile(rays @ (m / nm), 0.01))
    return max(2.0 * math.pi * (1.0 - c), 1e-6)


def _chance(n1, n2, area, gate, alpha=1e-6):
    """Support a wrong rotation reaches by chance on the sphere (+3 seed points)."""
    p = min(1.0, n2 * math.pi * gate * gate / area)
    return int(poisson.isf(alpha, n1 * p)) + 3


# --------------------------------------------------------------- entry point
def match(
    pixels1: ArrayLike,
    pixels2: ArrayLike,
    camera1: UnifiedCamera,
    camera2: UnifiedCamera | None = None,
    *,
    noise_px: float = 1.0,
    strategy: str = "auto",
    max_parallax: float = 0.35,
    nonrigid_gain: float = 1.15,
    rigid_share: float = 0.9,
    shape_tolerance: float = 0.15,
    cluster_deg: float = 4.0,
    seed: int = 0,
) -> SphereMatch:
    """Match the corners of two catadioptric images on the unit sphere.

    Parameters
    ----------
    pixels1, pixels2 : (N1, 2), (N2, 2) array_like of float
        Corner pixels ``(u, v)`` of the two images, in any order, with any
        share of unmatched corners. Rows that are NaN or that the camera
        cannot lift are dropped (see :attr:`SphereMatch.index1`).
    camera1 : UnifiedCamera
        Camera of image 1.
    camera2 : UnifiedCamera, optional
        Camera of image 2; default: ``camera1``.
    noise_px : float, default: 1.0
        Assumed corner noise in pixels (standard deviation per
        coordinate); sets every gate through :func:`sphere_noise`.
    strategy : {"auto", "rigid", "nonrigid"}, default: "auto"
        ``"rigid"``: pure camera rotation only; ``"nonrigid"``: always the
        local-constraint mode after the rotation; ``"auto"``: the
        non-rigid result when it has at least ``nonrigid_gain`` times the
        rotation's support, else the rigid one.
    max_parallax : float, default: 0.35
        Largest displacement of a ray left after the dominant rotation
        (chord on the unit sphere, ~radians): the camera translation over
        the nearest depth. Bounds the candidate pairs of the non-rigid
        stage.
    nonrigid_gain : float, default: 1.15
        See ``strategy``.
    shape_tolerance : float, default: 0.15
        Tolerance on the log side lengths of matched local triangles (the
        relative change of a triangle's sides that parallax may cause).
    cluster_deg : float, default: 4.0
        Radius of the cluster of trial rotations, degrees.
    seed : int, default: 0
        Seed of the non-rigid stage.

    Returns
    -------
    SphereMatch
        Falsy, with ``info["reason"]``, when nothing was matched.

    Raises
    ------
    ValueError
        Pixels not an (N, 2) array of numbers, a camera that is not a
        :class:`UnifiedCamera`, or a bad option.

    References
    ----------
    Reyes, Medioni & Bayro, IJCV 75(3) 2007, section 5.1 and Fig. 15.

    Examples
    --------
    >>> from catadioptric import synthetic_views
    >>> v = synthetic_views(120, rotation_deg=40.0, translation=(0, 0, 0), seed=2)
    >>> m = match(v.pixels1, v.pixels2, v.camera1)
    >>> m.strategy, round(m.rotation_deg), m.support == len(v.pairs)
    ('rigid', 40, True)
    """
    t_start = time.perf_counter()
    p1 = _check_pixels(pixels1, "pixels1")
    p2 = _check_pixels(pixels2, "pixels2")
    camera1 = _check_camera(camera1, "camera1")
    camera2 = camera1 if camera2 is None else _check_camera(camera2, "camera2")
    noise_px = _check_real(noise_px, "noise_px")
    max_parallax = _check_real(max_parallax, "max_parallax")
    nonrigid_gain = _check_real(nonrigid_gain, "nonrigid_gain")
    shape_tolerance = _check_real(shape_tolerance, "shape_tolerance")
    cluster_deg = _check_real(cluster_deg, "cluster_deg")
    rigid_share = _check_real(rigid_share, "rigid_share")
    if strategy not in ("auto", "rigid", "local", "nonrigid"):
        msg = f"Expected `strategy` to be 'auto', 'rigid', 'local' or 'nonrigid', got {strategy!r}."
        raise ValueError(msg)
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
        msg = f"Expected `seed` to be an integer >= 0, got {seed!r}."
        raise ValueError(msg)

    r1, index1 = _lift(camera1, p1)
    r2, index2 = _lift(camera2, p2)
    info: dict = {"n_pixels1": int(p1.shape[0]), "n_pixels2": int(p2.shape[0]),
                  "n_rays1": int(r1.shape[0]), "n_rays2": int(r2.shape[0])}
    s1 = sphere_noise(camera1, p1[index1], noise_px) if index1.size else np.empty(0)
    s2 = sphere_noise(camera2, p2[index2], noise_px) if index2.size else np.empty(0)
    noise = float(np.median(np.concatenate([s1, s2]))) if s1.size + s2.size else float("nan")

    def result(pairs, rotation, rot_support, used, reason=None):
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        out = np.column_stack([index1[pairs[:, 0]], index2[pairs[:, 1]]]) if pairs.size else pairs
        out = out[np.argsort(out[:, 0], kind="stable")]
        if reason is not None:
            info["reason"] = reason
        info["time_s"] = time.perf_counter() - t_start
        return SphereMatch(out, r1, r2, index1, index2, rotation, rot_support, used, noise, info)

    if r1.shape[0] < 3 or r2.shape[0] < 3:
        return result([], None, 0, "none", "fewer than 3 liftable pixels in a view")

    # Stage 2: the dominant rotation.
    t0 = time.perf_counter()
    tree2 = cKDTree(r2)
    R0, cluster, n_trials, votes = _dominant_rotation(r1, r2, shape_tolerance, cluster_deg)
    gate = GATE_SIGMAS * math.sqrt(2.0) * noise
    chance = _chance(r1.shape[0], r2.shape[0], _cap_area(r2), gate)
    info.update(n_trial_rotations=n_trials, cluster_size=cluster, chance_support=chance)
    rigid = np.empty((0, 2), np.int64)
    R = None
    if R0 is not None:
        R, rigid = _rotation_icp(r1, r2, tree2, s1, s2, R0)
        if rigid.shape[0] < chance:
            R, rigid = None, np.empty((0, 2), np.int64)
    info.update(rigid_support=int(rigid.shape[0]), time_rotation_s=time.perf_counter() - t0)
    if strategy == "rigid":
        if R is None:
            return result([], None, 0, "none", "no rotation beat the chance level of the sphere")
        return result(rigid, R, rigid.shape[0], "rigid")

    # Stage 3: locally rigid matching (translation: parallax).
    rot_support = int(rigid.shape[0])
    if strategy == "auto" and R is not None and rigid.shape[0] >= rigid_share * min(r1.shape[0], r2.shape[0]):
        return result(rigid, R, rot_support, "rigid")
    t0 = time.perf_counter()
    if strategy == "nonrigid":
        local = _nonrigid(r1, r2, R, noise, max_parallax, seed, info)
    else:
        if R is not None and rigid.shape[0] >= 3:
            seeds = rigid
        else:
            # parallax spreads the triangles' rotations: a wider cluster,
            # whose triangles' vertices are the seeds
            _, wide, _, votes = _dominant_rotation(r1, r2, shape_tolerance, 2.5 * cluster_deg)
            info["wide_cluster_size"] = wide
            seeds = _voted_seeds(votes)
        info["n_seeds"] = int(seeds.shape[0])
        local = _grow_local(r1, r2, tree2, s1, s2, seeds)
    info["time_local_s"] = time.perf_counter() - t0
    info["local_support"] = int(local.shape[0])
    if strategy != "auto" or local.shape[0] >= max(nonrigid_gain * rigid.shape[0], chance):
        if local.shape[0] == 0:
            return result([], R, rot_support, "none", info.get("nonrigid_reason", "nothing matched"))
        return result(local, R, rot_support, "local" if strategy != "nonrigid" else "nonrigid")
    if R is None:
        return result([], None, 0, "none", "no rotation and no locally rigid match beat the chance level")
    return result(rigid, R, rot_support, "rigid")


def _nonrigid(r1, r2, R, noise, max_parallax, seed, info):
    from gatv.nonrigid import register as nonrigid_register

    x = r1 if R is None else r1 @ R.T
    if x.shape[0] < 4 or r2.shape[0] < 4:
        info["nonrigid_reason"] = "fewer than 4 rays"
        return np.empty((0, 2), np.int64)
    try:
        m = nonrigid_register(x, r2, seed=seed, noise=noise, max_displacement=max_parallax)
    except ValueError as exc:
        info["nonrigid_reason"] = str(exc)
        return np.empty((0, 2), np.int64)
    info["nonrigid"] = {k: m.info[k] for k in ("structure", "n_candidates", "n_seeds", "gate")
                        if k in m.info}
    if not m:
        info["nonrigid_reason"] = m.info.get("reason", "nothing found")
    return np.asarray(m.correspondences, dtype=np.int64).reshape(-1, 2)
