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
3. **Rigid or locally rigid.** The rotation's support is compared with the
   chance level of the sphere (a wrong rotation brings a ray within the
   gate of a target ray with probability ``n2 π gate² / area``); when it
   explains nearly all rays (``rigid_share``) it is the answer; its pairs
   are kept when their posterior against a chance ray reaches
   ``MIN_POSTERIOR`` (:func:`_rigid_posterior`). With a
   camera translation the rays move non-rigidly (parallax ``t⊥ / depth``),
   only locally rigidly: each ray is moved by the rotation of its nearest
   matched neighbours, grown from the rotation's pairs or from the
   vertices of a wider cluster of triangle rotations ("local").
4. **Epipolar geometry.** True pairs satisfy ``y · (t × R x) = 0``: ``y``
   lies on the great-circle arc from ``R x`` (infinite depth) towards the
   epipole ``t`` (zero depth). An essential matrix is found by 8-point
   RANSAC on the sphere, each sample three matched local triangles (nine
   pairs; the 32 most similar target triangles of each source triangle,
   as parallax reorders their shapes) from a cluster of triangle rotations as wide as the parallax,
   scored on those pairs and the local-growth pairs. A minimal sample's
   essential matrix is rough (at 20% translation, 8-point fits to 8 or
   even 9 true pairs were off by about 10 degrees in R): the samples are
   ranked with a twice wider gate, and the best 24 are refitted on all
   their pairs and polished by least squares on the epipolar angles before
   they compete (LO-RANSAC). The rays are then matched along
   their arcs: the inverse depth ``rho = |t| / d`` of a plane is linear
   in the ray, ``rho = w · u``, so the plane that most of a ray's matched
   neighbours agree with (the best of their triples, refitted) predicts
   where on its arc the ray lands; candidates within the noise gate (along
   the arc widened by the prediction's own standard error, from the plane
   fit's covariance) are matched one-to-one, closest first, growing until the matches repeat,
   with (R, t) refitted on them. In the last round a ray is also
   predicted by every other plane that two thirds of its neighbours agree
   with (both sides of a crease), and a match is kept only when its
   posterior probability of being the true partner, against a chance ray
   of view 2 and against the other candidates of either ray, is at least
   ``MIN_POSTERIOR`` (0.8; :func:`_posterior`, probabilistic data
   association): precision first. Without parallax (a pure
   rotation, ``t`` undefined) the stage stands aside. The epipolar result is kept when it explains clearly more
   pairs than the rotation (``nonrigid_gain``) and beats the chance
   level. ``strategy="nonrigid"`` instead extracts the curved surface of
   the tokens ``y_j − R x_i`` with tensor voting and local eq. 41
   (:func:`gatv.nonrigid.register`).
5. **Ambiguity (repeated structure).** A regular pattern, such as a
   checkerboard, also matches itself shifted by one period, and the
   shifted matching is as rigid (and as epipolar: a planar board is
   degenerate for the essential matrix) as the true one. The analogue of
   Lowe's ratio test, at the level of hypotheses: the winning matches are
   shifted by the vector from a matched target ray to one of its
   neighbours (near a few anchors) and grown locally rigidly
   (:func:`_rival`); the rival's support counts its pairs that are not
   winning pairs (other partners). When it reaches ``RIVAL_RATIO`` (0.6)
   of the winner's support, and the chance level, the result is empty
   with ``info["reason"]`` "ambiguous (repeated structure) ...": nothing
   tells which of the two is right, and precision comes first. The
   threshold: a one-period shift of a pattern ``a >= 3`` periods wide
   keeps ``(a - 1) / a >= 2/3`` of the pairs (measured on the real board
   pairs: 0.9-1.6); on scattered corners the rival is a chance-level
   growth (measured: at most 0.29 of the winner in 48 synthetic trials
   of the benchmark, 0 and 50% outliers, at most 0.44 on the detected
   corners of the real corridor pairs, whose board is a real, partial
   rival).

Motion convention: a scene point seen along ray ``x`` in view 1 is seen
along ``y ≈ R x`` in view 2 (pure rotation), ``y ∝ R X + t`` in general
(``X = d x`` the point in view 1's frame, the convention of
:func:`catadioptric.synthetic_views`).
"""

from __future__ import annotations

import math
import numbers
import time
from dataclasses import dataclass, field
from itertools import combinations
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import poisson

from catadioptric.camera import UnifiedCamera
from gatv._validation import frozen_array as _frozen
from gatv.candidates import one_to_one
from gatv.errors import InputError

if TYPE_CHECKING:
    from numpy.typing import ArrayLike, NDArray

__all__ = ["SphereMatch", "match", "sphere_noise"]

#: Residual gate of a pair, in per-axis standard deviations of the pair's
#: combined noise: the norm of a 2D Gaussian stays below it with 99%.
GATE_SIGMAS = 3.03
#: Neighbours per ray for the local triangles of the rotation search.
TRIANGLE_NEIGHBOURS = 6
#: A rigid or epipolar match is kept when its posterior probability of
#: being the ray's true partner (:func:`_posterior`) reaches this. The
#: posterior is calibrated (measured, see :func:`_posterior`), and most
#: matches lie far above the floor: at 50% outliers the matches kept at
#: 0.8 were right 0.962 of the time at 20% translation, 0.980 without
#: translation (60 trials each).
MIN_POSTERIOR = 0.8


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
        Camera rotation ``R`` (view 1 rays to view 2 rays). For the
        ``"epipolar"`` strategy the rotation of the recovered motion
        ``y ∝ d R x + t``; otherwise the dominant pure rotation ``y ≈ R x``
        when its support beats the chance level of the sphere, else None
        (None too when the match is ambiguous, ``info["reason"]``).
    rotation_support : int
        Pairs within the noise gate of the pure rotation ``y ≈ R x``
        (one-to-one; 0 when no rotation beat the chance level).
    strategy : {"rigid", "local", "epipolar", "nonrigid", "none"}
        Which stage gave ``correspondences``.
    noise : float
        Median sphere noise of the rays (unit-sphere units, per axis).
    info : dict
        Diagnostics: chance level, supports of the stages, timings.
    translation : (3,) ndarray of float or None
        Unit direction of the translation ``t`` in ``X2 = R X1 + t`` (the
        epipole of view 1's centre in view 2) for the ``"epipolar"``
        strategy; None otherwise (also for a pure rotation, where ``t``
        is not defined).
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
    translation: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "correspondences",
                           _frozen(np.asarray(self.correspondences).reshape(-1, 2), np.int64))
        for name in ("rays1", "rays2"):
            object.__setattr__(self, name, _frozen(getattr(self, name)))
        for name in ("index1", "index2"):
            object.__setattr__(self, name, _frozen(getattr(self, name), np.int64))
        for name in ("rotation", "translation"):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, _frozen(getattr(self, name)))

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

    @property
    def essential(self) -> NDArray[np.float64] | None:
        """(3, 3) ndarray or None: essential matrix ``E = [t]x R``, ``y^T E x = 0`` for true pairs."""
        if self.translation is None or self.rotation is None:
            return None
        return _essential_from_motion(self.rotation, self.translation)

    def to_dict(self) -> dict:
        """JSON-serialisable summary (correspondences as lists of input rows)."""
        return {
            "strategy": self.strategy,
            "support": self.support,
            "correspondences": self.correspondences.tolist(),
            "rotation": None if self.rotation is None else self.rotation.tolist(),
            "rotation_deg": self.rotation_deg,
            "rotation_support": int(self.rotation_support),
            "translation": None if self.translation is None else self.translation.tolist(),
            "essential": None if self.translation is None else self.essential.tolist(),
            "noise": self.noise,
            "n_rays1": int(self.rays1.shape[0]),
            "n_rays2": int(self.rays2.shape[0]),
        }


# --------------------------------------------------------------- validation
def _check_pixels(pixels, name: str) -> NDArray[np.float64]:
    if pixels is None:
        msg = f"Expected `{name}` to be an (N, 2) array of pixels, got None."
        raise InputError(msg)
    try:
        arr = np.asarray(pixels, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        msg = f"Expected `{name}` to be an (N, 2) array of numbers: {exc}."
        raise InputError(msg) from exc
    if arr.ndim != 2 or arr.shape[1] != 2:
        msg = f"Expected `{name}` to have shape (N, 2), got {arr.shape}."
        raise InputError(msg)
    return np.ascontiguousarray(arr)


def _check_camera(camera, name: str) -> UnifiedCamera:
    if not isinstance(camera, UnifiedCamera):
        msg = f"Expected `{name}` to be a catadioptric.UnifiedCamera, got {type(camera).__name__}."
        raise InputError(msg)
    return camera


def _check_real(value, name: str, *, low: float = 0.0, allow_zero: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        msg = f"Expected `{name}` to be a finite number, got {value!r}."
        raise InputError(msg)
    value = float(value)
    if value < low or (value == low and not allow_zero):
        msg = f"Expected `{name}` {'>=' if allow_zero else '>'} {low}, got {value!r}."
        raise InputError(msg)
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


def _dominant_rotation(r1, r2, rel_tol, radius_deg, max_matches=8):
    """Densest cluster of trial rotations.

    Returns ``(rotation, cluster size, number of trials, vertex pairs of the
    cluster's trials)``.
    """
    Rs, verts = _trial_rotations(r1, r2, rel_tol, max_matches)
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
    members = np.unique(near % q.shape[0])
    return R, int(counts[best]), int(Rs.shape[0]), verts[members]


def _voted_seeds(vertex_pairs, min_votes=2):
    """Pairs named by at least ``min_votes`` trials of the cluster, one-to-one by votes."""
    vertex_pairs = vertex_pairs.reshape(-1, 2)
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


def _rigid_posterior(r1, tree2, s1, s2, R, pairs):
    """The pairs of a rotation whose posterior (:func:`_posterior`) reaches ``MIN_POSTERIOR``.

    The residual ``y - R x`` of a true pair is isotropic Gaussian with the
    pair's noise per axis; the rivals are the other pairs inside the noise
    gate of either ray; the prior counts the rays of view 1 that the
    rotation brings into the cap of view 2's rays (``tree2``: their
    :class:`~scipy.spatial.cKDTree`).
    """
    r2 = tree2.data
    moved = r1 @ R.T
    gmax = GATE_SIGMAS * math.sqrt(float(s1.max()) ** 2 + float(s2.max()) ** 2)
    near = cKDTree(moved).sparse_distance_matrix(tree2, gmax, output_type="ndarray")
    ci, cj = near["i"].astype(np.int64), near["j"].astype(np.int64)
    sig_c = np.sqrt(s1[ci] ** 2 + s2[cj] ** 2)
    inside = near["v"] <= GATE_SIGMAS * sig_c
    cand = np.column_stack([ci[inside], cj[inside]])
    like_c = _likelihood(near["v"][inside] / sig_c[inside], sig_c[inside], sig_c[inside])
    sig = np.sqrt(s1[pairs[:, 0]] ** 2 + s2[pairs[:, 1]] ** 2)
    e = np.linalg.norm(r2[pairs[:, 1]] - moved[pairs[:, 0]], axis=1) / sig
    like = _likelihood(e, sig, sig)
    rivals = _rival_likelihood(pairs, np.where(e <= GATE_SIGMAS, like, 0.0), cand, like_c, r1.shape[0], r2.shape[0])
    cap = _cap(r2)
    n1 = r1.shape[0] if cap is None else int(np.count_nonzero(moved @ cap[0] >= cap[1]))
    return pairs[_posterior(pairs, like, tree2, max(n1, pairs.shape[0]), rivals) >= MIN_POSTERIOR]


def _cap(rays: NDArray[np.float64]):
    """``(axis, cos)`` of the smallest cap around the mean direction holding 99% of the rays.

    None when the mean direction vanishes (rays all around the sphere).
    """
    m = rays.mean(axis=0)
    nm = np.linalg.norm(m)
    if nm < 1e-9:
        return None
    return m / nm, float(np.quantile(rays @ (m / nm), 0.01))


def _cap_area(rays: NDArray[np.float64]) -> float:
    """Area of the smallest cap around the mean direction holding 99% of the rays."""
    cap = _cap(rays)
    if cap is None:
        return 4.0 * math.pi
    return max(2.0 * math.pi * (1.0 - cap[1]), 1e-6)


def _chance(n1, n2, area, gate, alpha=1e-6):
    """Support a wrong rotation reaches by chance on the sphere (+3 seed points)."""
    p = min(1.0, n2 * math.pi * gate * gate / area)
    return int(poisson.isf(alpha, n1 * p)) + 3



#: Ambiguity test against repeated structure (a checkerboard matches itself
#: shifted by one square). A rival that explains at least this share of the
#: winner's pairs with different partners (and the chance level) makes the
#: answer ambiguous: below the (a - 1) / a >= 2/3 a one-period shift keeps
#: of a pattern 3 or more periods wide, above the chance-level rivals of
#: scattered corners (<= 0.29 synthetic, <= 0.44 real corridor; module
#: docstring, step 5).
RIVAL_RATIO = 0.6
#: Winner pairs (nearest the anchor) shifted to seed a rival, and anchors.
RIVAL_SEEDS = 8
RIVAL_ANCHORS = 3


def _rival(r1, r2, tree2, s1, s2, pairs):
    """Best rival of the matches ``pairs``: a locally rigid matching with other partners.

    The analogue of Lowe's ratio test at the level of hypotheses. A regular
    pattern also matches itself shifted by one period; the shift moves
    every partner ``y_j`` by about the same vector (on a small patch) as
    the one from a matched target ray to one of its neighbours. For a few
    anchors among the matches (spread over the matched rays) and each of
    the anchor's ``TRIANGLE_NEIGHBOURS`` target neighbours, the
    ``RIVAL_SEEDS`` matches nearest the anchor are moved by that vector onto
    the nearest target rays (within two noise gates) and grown by
    :func:`_grow_local`. A rival's support is the number of its pairs that
    are not matches (different partners; a rival that snaps back onto the
    matches counts nothing). On scattered corners a shifted seed is a set
    of chance pairs and grows to about the chance level; on a grid it
    grows over the whole overlap (``(a - 1) / a`` of an ``a``-square-wide
    board). Returns ``(support, rival pairs not among the matches)``.
    """
    m = pairs.shape[0]
    empty = (0, np.empty((0, 2), np.int64))
    if m < 4 or r2.shape[0] < 2:
        return empty
    xs = r1[pairs[:, 0]]
    # anchors: the match nearest the centroid, then farthest-point spread
    c = xs.mean(axis=0)
    anchors = [int(np.argmin(np.linalg.norm(xs - c, axis=1)))]
    dmin = np.linalg.norm(xs - xs[anchors[0]], axis=1)
    while len(anchors) < min(RIVAL_ANCHORS, m):
        # half-way out: far enough to see another part, with neighbours around
        far = np.flatnonzero(dmin >= 0.5 * dmin.max())
        a = int(far[np.argmin(dmin[far])])
        anchors.append(a)
        dmin = np.minimum(dmin, np.linalg.norm(xs - xs[a], axis=1))
    tree1 = cKDTree(xs)
    known = set(map(tuple, pairs.tolist()))
    k = min(TRIANGLE_NEIGHBOURS + 1, r2.shape[0])
    best = empty
    for a in anchors:
        j0 = pairs[a, 1]
        _, nbj = tree2.query(r2[j0], k=k)
        _, near = tree1.query(xs[a], k=min(RIVAL_SEEDS, m))
        near = np.atleast_1d(near)
        for jn in np.atleast_1d(nbj)[1:]:
            d = r2[jn] - r2[j0]
            moved = np.full((r1.shape[0], 3), np.inf)
            moved[pairs[near, 0]] = r2[pairs[near, 1]] + d
            seeds = _gated_pairs(moved, r2, tree2, s1, s2, 2.0)
            if seeds.shape[0] < 3:
                continue
            grown = _grow_local(r1, r2, tree2, s1, s2, seeds)
            other = np.array([p for p in grown.tolist() if tuple(p) not in known], np.int64).reshape(-1, 2)
            if other.shape[0] > best[0]:
                best = (int(other.shape[0]), other)
    return best


# --------------------------------------------------------------- entry point
def match(
    pixels1: ArrayLike,
    pixels2: ArrayLike,
    camera1: UnifiedCamera,
    camera2: UnifiedCamera | None = None,
    *,
    noise_px: float = 1.0,
    strategy: str = "auto",
    max_parallax: float = 0.5,
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
    strategy : {"auto", "rigid", "local", "epipolar", "nonrigid"}, default: "auto"
        ``"rigid"``: pure camera rotation only; ``"local"``: locally rigid
        growth after the rotation; ``"epipolar"``: matching along the
        epipolar arcs of a recovered motion (R, t); ``"nonrigid"``: the
        local-constraint mode of :func:`gatv.nonrigid.register` after the
        rotation; ``"auto"``: the rotation when it explains nearly all
        rays, else the epipolar result when it has at least
        ``nonrigid_gain`` times the rotation's support, else the local
        one under the same rule, else the rotation.
    max_parallax : float, default: 0.5
        Largest displacement of a ray left after the camera rotation
        (chord on the unit sphere, ~radians): the camera translation over
        the nearest depth. Bounds the candidate pairs of the epipolar and
        non-rigid stages.
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
        Falsy, with ``info["reason"]``, when nothing was matched, also when
        a rival matching with other partners explains nearly as many rays
        (a repeated pattern, ``info["rival_support"]``; see the module
        docstring, step 5).

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
    if strategy not in ("auto", "rigid", "local", "nonrigid", "epipolar"):
        msg = f"Expected `strategy` to be 'auto', 'rigid', 'local' or 'nonrigid', got {strategy!r}."
        raise InputError(msg)
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
        msg = f"Expected `seed` to be an integer >= 0, got {seed!r}."
        raise InputError(msg)

    r1, index1 = _lift(camera1, p1)
    r2, index2 = _lift(camera2, p2)
    info: dict = {"n_pixels1": int(p1.shape[0]), "n_pixels2": int(p2.shape[0]),
                  "n_rays1": int(r1.shape[0]), "n_rays2": int(r2.shape[0])}
    s1 = sphere_noise(camera1, p1[index1], noise_px) if index1.size else np.empty(0)
    s2 = sphere_noise(camera2, p2[index2], noise_px) if index2.size else np.empty(0)
    noise = float(np.median(np.concatenate([s1, s2]))) if s1.size + s2.size else float("nan")

    def result(pairs, rotation, rot_support, used, reason=None, motion=None):
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        if used == "rigid" and pairs.shape[0]:
            pairs = _rigid_posterior(r1, tree2, s1, s2, rotation, pairs)
        if pairs.shape[0] and reason is None:
            t_r = time.perf_counter()
            rival, _ = _rival(r1, r2, tree2, s1, s2, pairs)
            info.update(rival_support=rival, time_rival_s=time.perf_counter() - t_r)
            if rival >= max(chance, RIVAL_RATIO * pairs.shape[0]):
                info.update(ambiguous_strategy=used, ambiguous_support=int(pairs.shape[0]))
                used, reason = "none", (
                    f"ambiguous (repeated structure): the {used} match of {pairs.shape[0]} pairs has a "
                    f"rival with other partners for {rival} rays")
                # the motion is as ambiguous as the pairs
                pairs, rotation, rot_support, motion = np.empty((0, 2), np.int64), None, 0, None
        out = np.column_stack([index1[pairs[:, 0]], index2[pairs[:, 1]]]) if pairs.size else pairs
        out = out[np.argsort(out[:, 0], kind="stable")]
        if reason is not None:
            info["reason"] = reason
        info["time_s"] = time.perf_counter() - t_start
        return SphereMatch(out, r1, r2, index1, index2, rotation, rot_support, used, noise, info,
                           translation=motion)

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
    if strategy in ("auto", "epipolar"):
        # Stage 4: epipolar geometry (camera translation).
        t0 = time.perf_counter()
        seeds_e = local if local.shape[0] >= rigid.shape[0] else rigid
        epi = _epipolar_stage(r1, r2, tree2, s1, s2, seeds_e, noise, max_parallax, seed, info)
        info["time_epipolar_s"] = time.perf_counter() - t0
        if epi is not None:
            Re, te, pe = epi
            info["epipolar_support"] = int(pe.shape[0])
            if pe.shape[0] >= max(nonrigid_gain * rigid.shape[0], chance):
                return result(pe, Re, rot_support, "epipolar", motion=te)
            info.setdefault("epipolar_reason", "fewer pairs than the rotation or the chance level")
        if strategy == "epipolar":
            return result([], R, rot_support, "none", info.get("epipolar_reason", "nothing matched"))
    if strategy != "auto" or local.shape[0] >= max(nonrigid_gain * rigid.shape[0], chance):
        if local.shape[0] == 0:
            return result([], R, rot_support, "none", info.get("nonrigid_reason", "nothing matched"))
        return result(local, R, rot_support, "local" if strategy != "nonrigid" else "nonrigid")
    if R is None:
        return result([], None, 0, "none", "no rotation and no locally rigid match beat the chance level")
    return result(rigid, R, rot_support, "rigid")


#: Epipolar stage. Radius (degrees) of the cluster of triangle rotations
#: whose triangles feed the RANSAC (as wide as the parallax turns them) and
#: its shape tolerance on log side lengths.
EPI_CLUSTER_DEG = 15.0
EPI_SHAPE_TOL = 0.25
#: RANSAC samples (three triangles each), motions grown at most, and the
#: share of the best sample's support a rival needs to be grown too.
EPI_RANSAC = 2000
EPI_HYPOTHESES = 6
EPI_RIVAL = 0.5
#: LO-RANSAC: samples polished on all the pairs within EPI_LO_GATE noise gates
#: of their essential matrix (the best EPI_LO by that wider score).
EPI_LO = 24
EPI_LO_GATE = 2.0
#: Growth rounds with (R, t) refitted between them.
EPI_OUTER = 6
#: Final gate, in noise gates.
EPI_FINAL = 1.0
#: Median arc angle of the matches, in sphere noise, below which the views
#: differ by a rotation only (t undefined).
EPI_MIN_PARALLAX = 3.0
#: Target triangles retrieved per source triangle for the RANSAC pool (the
#: nearest in log side lengths). Parallax and noise change a small
#: triangle's sides by 0.15-0.3 in log units (median, measured at 10-20%
#: translation), where thousands of triangles crowd: the true partner's
#: rank among the targets has a median of 17-90, and with the 8 of the
#: rotation search only 20-40 true triangles entered the pool in the trials
#: whose motion was lost (held-out seeds, 90 degrees, 20%, 50% outliers).
EPI_MATCHES = 32
#: Last round: a ray is also predicted by every plane of its neighbours that
#: at least this share of them agree with (both sides of a crease of the
#: scene; see :func:`_supported_planes`).
EPI_SHARE = 2.0 / 3.0


# --------------------------------------------------------------- epipolar stage
def _essential_from_motion(R, t):
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    return tx @ R


def _epipolar_distance(E, x, y):
    """Angular distance of ``y`` from the epipolar great circle of ``x`` and vice versa (the larger)."""
    ex = x @ E.T
    ey = y @ E
    num = np.abs(np.einsum("ij,ij->i", y, ex))
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.maximum(num / np.linalg.norm(ex, axis=1), num / np.linalg.norm(ey, axis=1))
    return np.nan_to_num(d, nan=np.inf)


def _batched_essentials(X, Y):
    """Essential matrices of stacks of 8 ray pairs (K, 8, 3) by the linear 8-point method."""
    A = np.einsum("kni,knj->knij", Y, X).reshape(X.shape[0], X.shape[1], 9)
    if A.shape[1] < 9:
        A = np.concatenate([A, np.zeros((A.shape[0], 9 - A.shape[1], 9))], axis=1)
    _, _, Vt = np.linalg.svd(A)
    E = Vt[:, -1, :].reshape(-1, 3, 3)
    U, _, Vt = np.linalg.svd(E)
    return U @ np.diag([1.0, 1.0, 0.0]) @ Vt


def _motions(E):
    """The four (R, t) of an essential matrix."""
    U, _, Vt = np.linalg.svd(E)
    if np.linalg.det(U) < 0:
        U = -U
    if np.linalg.det(Vt) < 0:
        Vt = -Vt
    W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    out = []
    for Rm in (U @ W @ Vt, U @ W.T @ Vt):
        for s in (1.0, -1.0):
            out.append((Rm, s * U[:, 2]))
    return out


def _arc_coordinates(Rx, t, y):
    """Epipolar coordinates of ``y`` against the rays ``Rx`` for the translation direction ``t``.

    Returns ``(phi, alpha, across)``: ``phi`` the angle from ``Rx`` to the
    projection of ``y`` on the epipolar great circle, positive towards
    ``t``; ``alpha`` the angle from ``Rx`` to ``t``; ``across`` the signed
    angular distance of ``y`` from the circle.
    """
    c = Rx @ t
    e2 = t[None, :] - c[:, None] * Rx
    s = np.linalg.norm(e2, axis=1)
    e2 = e2 / np.maximum(s, 1e-12)[:, None]
    nrm = np.cross(Rx, e2)
    a, b = np.einsum("ij,ij->i", y, Rx), np.einsum("ij,ij->i", y, e2)
    phi = np.arctan2(b, a)
    alpha = np.arctan2(s, c)
    across = np.arcsin(np.clip(np.einsum("ij,ij->i", y, nrm), -1.0, 1.0))
    return phi, alpha, across


def _inverse_depth(phi, alpha):
    """Inverse depth ``|t| / d`` of the arc angle ``phi`` (``alpha``: angle to the epipole)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.sin(phi) / np.sin(alpha - phi)


def _arc_angle(rho, alpha):
    """Arc angle of the inverse depth ``rho`` (inverse of :func:`_inverse_depth`)."""
    return np.arctan2(rho * np.sin(alpha), 1.0 + rho * np.cos(alpha))


def _cheirality(R, t, x, y):
    """Pairs in front of both cameras (inverse depth above a small negative bound)."""
    phi, alpha, _ = _arc_coordinates(x @ R.T, t, y)
    return (phi > -0.02) & (phi < alpha)


def _refine_motion(R, t, x, y, sig):
    """Least squares (R, t) on the sphere: signed epipolar distances, 5 parameters."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    def unpack(p):
        Rm = Rotation.from_rotvec(p[:3]).as_matrix() @ R
        # t on the sphere: tangent coordinates about the current t
        b1 = np.cross(t, [1.0, 0.0, 0.0] if abs(t[0]) < 0.9 else [0.0, 1.0, 0.0])
        b1 /= np.linalg.norm(b1)
        b2 = np.cross(t, b1)
        tv = t + p[3] * b1 + p[4] * b2
        return Rm, tv / np.linalg.norm(tv)

    def res(p):
        Rm, tv = unpack(p)
        n = np.cross(tv[None, :], x @ Rm.T)
        nn = np.linalg.norm(n, axis=1)
        return np.einsum("ij,ij->i", y, n) / np.maximum(nn, 1e-9) / sig

    sol = least_squares(res, np.zeros(5), loss="soft_l1", f_scale=GATE_SIGMAS)
    return unpack(sol.x)


def _estimate_motions(x, y, sig, rng, groups=None, iterations=None, hypotheses=None):
    """Robust motions (R, t) from candidate pairs: 8-point RANSAC on the sphere, then least squares.

    ``groups`` (G, 3) rows of ``x, y``: the vertex pairs of matched local
    triangles; a sample is then three triangles (nine pairs), all right
    far more often than eight independent pairs. Returns up to
    ``hypotheses`` distinct ``(R, t, inlier mask)``, best supported first
    (the caller keeps the one that explains most rays).
    """
    iterations = EPI_RANSAC if iterations is None else iterations
    hypotheses = EPI_HYPOTHESES if hypotheses is None else hypotheses
    k = x.shape[0]
    if k < 12:
        return []
    if groups is not None and groups.shape[0] >= 3:
        pick = np.argsort(rng.random((iterations, groups.shape[0])), axis=1)[:, :3]
        samples = groups[pick].reshape(iterations, 9)
    else:
        samples = np.argsort(rng.random((iterations, k)), axis=1)[:, :8]
    Es = _batched_essentials(x[samples], y[samples])
    gate = GATE_SIGMAS * sig
    ex = np.einsum("kij,nj->kni", Es, x)
    ey = np.einsum("kij,ni->knj", Es, y)
    num = np.abs(np.einsum("ni,kni->kn", y, ex))
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.maximum(num / np.linalg.norm(ex, axis=2), num / np.linalg.norm(ey, axis=2))
    # a minimal sample's E is rough (the problem is ill-conditioned at small
    # parallax): samples are ranked with a wider gate, and the best are
    # polished on all their pairs before they compete (LO-RANSAC)
    inl_wide = np.nan_to_num(d, nan=np.inf) <= EPI_LO_GATE * gate
    whole = groups is not None and groups.shape[0] >= 3

    def score_of(inl):
        # whole triangles consistent with the motion: a wrong E gathers
        # single near-miss pairs along its epipolar circles more easily
        s = np.count_nonzero(inl, axis=-1)
        return np.all(inl[..., groups], axis=-1).sum(axis=-1) * (k + 1) + s if whole else s

    score = score_of(inl_wide)
    polished = []
    for h in np.argsort(-score, kind="stable")[:EPI_LO]:
        inl = inl_wide[h]
        if np.count_nonzero(inl) < 8:
            continue
        E = _batched_essentials(x[inl][None], y[inl][None])[0]
        cands = [(int(np.count_nonzero(_cheirality(Rm, tv, x[inl], y[inl]))), i, Rm, tv)
                 for i, (Rm, tv) in enumerate(_motions(E))]
        _, _, R, t = max(cands, key=lambda c: (c[0], -c[1]))
        ok = True
        for _ in range(3):
            R, t = _refine_motion(R, t, x[inl], y[inl], sig[inl])
            E = _essential_from_motion(R, t)
            inl = (_epipolar_distance(E, x, y) <= gate) & _cheirality(R, t, x, y)
            if np.count_nonzero(inl) < 8:
                ok = False
                break
        if ok:
            polished.append((R, t, inl, score_of(inl)))
    out = []
    for R, t, inl, sc in sorted(polished, key=lambda o: -o[3]):
        if out and (len(out) >= hypotheses or sc < EPI_RIVAL * out[0][3]):
            break
        if any(np.count_nonzero(inl & o[2]) > 0.5 * np.count_nonzero(inl) for o in out):
            continue
        out.append((R, t, inl, sc))
    return [o[:3] for o in out]


def _epipolar_candidates(r1, r2, tree2, s1, s2, R, t, max_parallax):
    """Candidate pairs near the epipolar arcs of the motion (R, t).

    Returns ``(i, j, phi, across, sigma, alpha)``: per candidate the rows,
    the arc angle and the distance from the arc (:func:`_arc_coordinates`)
    and the pair's noise; ``alpha`` per ray of view 1 (angle to the epipole).
    A candidate lies within the noise gate of the arc from ``R x`` to the
    epipole and within ``max_parallax`` (chord) of ``R x``.
    """
    Rx = r1 @ R.T
    lists = tree2.query_ball_point(Rx, max_parallax)
    lens = np.fromiter((len(a) for a in lists), np.int64, len(lists))
    ii = np.repeat(np.arange(r1.shape[0]), lens)
    jj = np.fromiter((j for a in lists for j in a), np.int64, int(lens.sum()))
    if ii.size == 0:
        e = np.empty(0)
        return ii, jj, e, e, e, np.arctan2(np.linalg.norm(np.cross(Rx, t), axis=1), Rx @ t)
    phi, alpha, across = _arc_coordinates(Rx[ii], t, r2[jj])
    sig = np.sqrt(s1[ii] ** 2 + s2[jj] ** 2)
    gate = GATE_SIGMAS * sig
    ok = (np.abs(across) <= gate) & (phi >= -gate) & (phi <= alpha + gate)
    alpha_all = np.arctan2(np.linalg.norm(np.cross(Rx, t), axis=1), Rx @ t)
    return ii[ok], jj[ok], phi[ok], across[ok], sig[ok], alpha_all


def _triple_planes(A, rn, wts, keep, support_gate):
    """The exact plane through each triple of a ray's neighbours, and who agrees with it.

    ``A, rn, wts, keep`` as in :func:`_local_planes` (k >= 3 neighbours).
    Returns ``usable (n, T)`` (three usable, independent neighbours),
    ``res (n, T, k)`` the neighbours' residuals from each triple's plane in
    noise units, and ``inl (n, T, k)`` those within ``support_gate``; the
    T triples in :func:`itertools.combinations` order.
    """
    k = A.shape[1]
    trip = np.array(list(combinations(range(k), 3)), dtype=np.int64)
    a0, a1, a2 = A[:, trip[:, 0]], A[:, trip[:, 1]], A[:, trip[:, 2]]   # (n, T, 3)
    c0, c1, c2 = np.cross(a1, a2), np.cross(a2, a0), np.cross(a0, a1)
    det = np.einsum("nti,nti->nt", a0, c0)
    usable = np.all(keep[:, trip], axis=2) & (np.abs(det) > 1e-12)
    bt = rn[:, trip]                                  # (n, T, 3)
    # Cramer's rule: the plane through the three neighbours' (ray, rho)
    wt = (bt[..., 0:1] * c0 + bt[..., 1:2] * c1 + bt[..., 2:3] * c2) / np.where(usable, det, 1.0)[..., None]
    res = (rn[:, None, :] - np.einsum("nki,nti->ntk", A, wt)) * np.sqrt(wts)[:, None, :]
    inl = (np.abs(res) <= support_gate) & keep[:, None, :]
    return usable, res, inl


def _local_planes(A, rn, wts, keep, ridge, support_gate=GATE_SIGMAS):
    """Inverse-depth planes ``rho = w . u`` of each ray's neighbours, robust to a second plane.

    Every triple of a ray's neighbours gives an exact plane; the plane that
    the most neighbours agree with (within ``support_gate`` noise units of
    arc angle) is refitted by weighted least squares on those neighbours,
    so a ray near a crease of the scene is predicted by one side of it
    rather than by a blend of both.

    ``A``: (n, k, 3) neighbour rays; ``rn``: (n, k) their inverse depths;
    ``wts``: (n, k) weights (arc-angle sensitivity over noise, squared);
    ``keep``: (n, k) bool mask of usable neighbours. Returns the planes
    (n, 3) and the normal matrices ``M`` (n, 3, 3) of their weighted least
    squares: the weights are inverse variances of the neighbours' inverse
    depths, so ``M^-1`` is the covariance of ``w`` and ``u . M^-1 u`` the
    variance of the plane's inverse depth at the ray ``u``.
    """
    n, k, _ = A.shape
    if k >= 3:
        usable, res, inl = _triple_planes(A, rn, wts, keep, support_gate)
        score = inl.sum(axis=2) - np.minimum(np.where(inl, res * res, 0.0).sum(axis=2) / (support_gate ** 2 * k), 0.99)
        score = np.where(usable, score, -1.0)
        best = np.argmax(score, axis=1)
        w = wts * inl[np.arange(n), best]
        w = np.where(np.any(usable, axis=1)[:, None], w, wts * keep)
    else:
        w = wts * keep
    AtW = A * w[..., None]
    Mt = np.einsum("nki,nkj->nij", AtW, A) + ridge * (wts * keep).sum(axis=1)[:, None, None] * np.eye(3)
    b = np.einsum("nki,nk->ni", AtW, rn)
    return _solve3(Mt, b), Mt


def _supported_planes(A, rn, wts, keep, ridge, share, support_gate=GATE_SIGMAS):
    """Every well-supported inverse-depth plane of each ray's neighbours (a crease has two).

    Each triple of usable neighbours gives an exact plane; those that at
    least ``share`` of the ray's usable neighbours agree with (within
    ``support_gate`` noise units, as in :func:`_local_planes`) are refitted
    by weighted least squares on their agreeing neighbours. Returns the
    planes ``(n, T, 3)``, their normal matrices ``(n, T, 3, 3)`` and the
    mask ``(n, T)`` of the well-supported ones (T triples).
    """
    n, k, _ = A.shape
    if k < 3:
        return np.zeros((n, 0, 3)), np.zeros((n, 0, 3, 3)), np.zeros((n, 0), bool)
    usable, _, inl = _triple_planes(A, rn, wts, keep, support_gate)
    ok = usable & (inl.sum(axis=2) >= share * keep.sum(axis=1)[:, None] - 1e-9)
    w = wts[:, None, :] * inl
    Mt = (np.einsum("ntk,nki,nkj->ntij", w, A, A)
          + ridge * (wts * keep).sum(axis=1)[:, None, None, None] * np.eye(3))
    b = np.einsum("ntk,nki,nk->nti", w, A, rn)
    T = inl.shape[1]
    wv = _solve3(Mt.reshape(n * T, 3, 3), b.reshape(n * T, 3)).reshape(n, T, 3)
    return wv, Mt, ok


def _solve3(M, b):
    """Solutions of stacks of 3x3 systems ``M w = b`` by Cramer's rule."""
    m0, m1, m2 = M[:, :, 0], M[:, :, 1], M[:, :, 2]
    c0, c1, c2 = np.cross(m1, m2), np.cross(m2, m0), np.cross(m0, m1)
    det = np.einsum("ni,ni->n", m0, c0)
    det = np.where(np.abs(det) > 1e-300, det, 1e-300)
    return np.column_stack([np.einsum("ni,ni->n", b, c0), np.einsum("ni,ni->n", b, c1),
                            np.einsum("ni,ni->n", b, c2)]) / det[:, None]


def _likelihood(e, s_across, s_along):
    """Density per steradian of a true pair's residual: ``exp(-e^2/2) / (2 pi s_across s_along)``.

    ``e``: the residual's Mahalanobis norm; ``s_across``, ``s_along``: its
    standard deviations across and along the arc, on the unit sphere.
    """
    return np.exp(-0.5 * np.asarray(e, dtype=np.float64) ** 2) / (2.0 * np.pi * s_across * s_along)


def _rival_likelihood(pairs, own, cand, like, n1, n2):
    """Summed likelihood of each match's rivals: the other candidates of either of its rays.

    ``cand`` (C, 2) are the candidate pairs inside the gate and ``like``
    their likelihoods (:func:`_likelihood`); ``own`` is each match's own
    likelihood as counted among them (0 for a match that is not a
    candidate).
    """
    per1 = np.bincount(cand[:, 0], like, minlength=n1)
    per2 = np.bincount(cand[:, 1], like, minlength=n2)
    return np.maximum(per1[pairs[:, 0]] + per2[pairs[:, 1]] - 2.0 * own, 0.0)


def _posterior(pairs, like, tree2, n1, rivals=0.0, k=16):
    """Posterior probability that each match is its ray's true partner.

    Probabilistic data association (Bar-Shalom), one view-1 ray at a time:
    a true partner's residual has the density ``like`` (:func:`_likelihood`);
    every other ray of view 2 lands there like clutter, with the local
    density ``lam`` of view 2's rays (all of them, the match's own left
    out: under "no partner" any ray may be the chance one; from the ``k``
    nearest in ``tree2``, their :class:`~scipy.spatial.cKDTree`); the prior that a ray of view 1 has a partner is the share
    ``p`` of the ``n1`` predicted rays matched. The match's ``rivals``
    (:func:`_rival_likelihood`: the other candidates of either ray, any of
    which may be the true pair instead) share the evidence::

        P = like / (lam (1 - p) / p + like + rivals)

    Calibration, measured on the benchmark's scenes at 50% outliers (seeds
    0-2, 60 trials for each translation): at 20% translation (epipolar,
    10,309 matches of the last round) matches with P in [0.8, 0.9) were
    right 0.88 of the time, in [0.9, 0.95) 0.94, in [0.95, 0.99) 0.98;
    without translation (rigid, 10,237) 0.93, 0.97 and 0.99: calibrated,
    or conservative.
    (Without the rivals and with the density of the unmatched rays only,
    the odds were about twice too high.)
    """
    if pairs.shape[0] == 0:
        return np.empty(0)
    r2 = tree2.data
    kk = min(k + 1, r2.shape[0])
    if kk < 2:
        return np.ones(pairs.shape[0])
    dk = tree2.query(r2[pairs[:, 1]], k=kk)[0][:, -1]
    lam = (kk - 1) / (np.pi * np.maximum(dk, 1e-12) ** 2)
    p = min(max(pairs.shape[0] / max(n1, 1), 1e-3), 1.0 - 1e-3)
    return like / (lam * (1.0 - p) / p + like + rivals)


def _grow_epipolar(r1, cand, n2, seeds, neighbours=6, scale=2.0, rounds=15, final_scale=EPI_FINAL, ridge=1e-3,
                   tree2=None):
    """Match along the epipolar arcs, each ray at the inverse depth of its matched neighbours.

    The inverse depth of a plane is linear in the ray, ``rho(u) = w . u``:
    ``w`` is fitted (weighted least squares in arc angle) on the
    ``neighbours`` matched rays nearest to each ray, and predicts where on
    its epipolar arc the ray lands; candidates within ``scale`` noise gates
    of the prediction are matched one-to-one, closest first, until the
    matches repeat; the last round uses ``final_scale``. A ray farther than
    4 match spacings from every match is not predicted.

    In the last round the distance along the arc is measured against the
    pair's noise plus the prediction's own variance (the fitted plane's
    covariance carried to the ray, :func:`_local_planes`, times the squared
    arc-angle sensitivity ``d phi / d rho = sin alpha / (1 + 2 rho cos alpha
    + rho^2)``): a ray predicted by few or one-sided neighbours gets a
    longer window along its arc, one inside many neighbours a tight one.
    Across the arc the test stays the pair's noise. (Measured with all true
    pairs as neighbours, 20% translation: 10-18% of the true pairs lay
    beyond the plain noise gate, 6-13% beyond this one. The growth rounds
    keep the plain distance: their wider gates with the longer windows let
    a growth drift onto chance pairs.) The last round also measures each
    candidate against every plane that ``EPI_SHARE`` of the ray's
    neighbours agree with (:func:`_supported_planes`), keeping the nearest
    prediction, and, given the tree ``tree2`` of view 2's rays, keeps the matches
    whose posterior (:func:`_posterior`) reaches ``MIN_POSTERIOR``: the
    other candidates of either ray inside the gate are its rivals (this
    replaces a ratio test, which dropped a true pair for a rival at 1.67
    times its distance; recomputed on the last rounds of 60 trials at 20%
    translation, at equal precision 0.962 the posterior with rivals kept a
    recall of 0.835, the ratio test with the one-candidate posterior 0.783).
    """
    ii, jj, phi, across, sig, alpha = cand
    n1 = r1.shape[0]
    # each candidate's inverse depth
    rho_c = _inverse_depth(np.minimum(phi, alpha[ii] - 1e-6), alpha[ii])
    order = np.lexsort((jj, ii))
    ii, jj, phi, across, sig, rho_c = ii[order], jj[order], phi[order], across[order], sig[order], rho_c[order]
    # the seeds that are candidates, and their rows among the candidates
    pair_id = ii * n2 + jj
    pid = seeds[:, 0] * n2 + seeds[:, 1]
    pos = np.minimum(np.searchsorted(pair_id, pid), max(pair_id.size - 1, 0))
    ok = (pair_id[pos] == pid) if pair_id.size else np.zeros(len(pid), bool)
    pairs = seeds[ok]
    k_of = pos[ok]
    sa = np.sin(alpha)
    for r in range(rounds + 1):
        last = r == rounds
        m = pairs.shape[0]
        if m < 4:
            return np.empty((0, 2), np.int64)
        xs = r1[pairs[:, 0]]
        rho_m = rho_c[k_of]
        D = 1.0 + 2.0 * rho_m * np.cos(alpha[pairs[:, 0]]) + rho_m ** 2
        wts = (sa[pairs[:, 0]] / D) ** 2 / sig[k_of] ** 2
        k = min(neighbours + 1, m)
        tree = cKDTree(xs)
        dist, nb = tree.query(r1, k=k)
        dist, nb = dist.reshape(n1, k), nb.reshape(n1, k)
        # leave the ray itself out of its own prediction
        self_hit = pairs[nb, 0] == np.arange(n1)[:, None]
        keep = ~self_hit
        keep &= np.cumsum(keep, axis=1) <= k - 1
        A = xs[nb]                                        # (n1, k, 3)
        wv, Mt = _local_planes(A, rho_m[nb], wts[nb], keep, ridge)
        spacing = float(np.median(tree.query(xs, k=2)[0][:, 1])) if m > 1 else 1.0
        reach = np.where(keep, dist, np.inf).min(axis=1)
        valid = reach <= 4.0 * spacing
        s = final_scale if last else scale
        if last:
            # along the arc the prediction's own error adds to the pair's
            # noise (a Mahalanobis distance in units of the pair's noise):
            # the plane's covariance (its weights are inverse variances)
            # carried to the ray, times (d phi / d rho)^2; every
            # well-supported plane predicts too, the nearest counts
            wv, Mt, okp = wv[:, None], Mt[:, None], np.ones((n1, 1), bool)
            if EPI_SHARE < 1.0:
                wvt, Mtt, okt = _supported_planes(A, rho_m[nb], wts[nb], keep, ridge, EPI_SHARE)
                wv, Mt, okp = np.concatenate([wv, wvt], 1), np.concatenate([Mt, Mtt], 1), np.hstack([okp, okt])
            P = wv.shape[1]
            rho_pred = np.einsum("npi,ni->np", wv, r1)
            phi_pred = _arc_angle(rho_pred, alpha[:, None])
            rr = np.broadcast_to(r1[:, None, :], (n1, P, 3)).reshape(-1, 3)
            var_rho = np.maximum(np.einsum("ni,ni->n", rr, _solve3(Mt.reshape(-1, 3, 3), rr)).reshape(n1, P), 0.0)
            dpred = sa[:, None] / (1.0 + 2.0 * rho_pred * np.cos(alpha)[:, None] + rho_pred ** 2)
            var_pred = np.nan_to_num(var_rho * dpred ** 2, nan=np.inf)
            st = np.sqrt(sig[:, None] ** 2 + var_pred[ii])
            dt = np.hypot((phi[:, None] - phi_pred[ii]) * sig[:, None] / st, across[:, None])
            near = np.argmin(np.where(okp[ii], dt, np.inf), axis=1)[:, None]
            dd = np.take_along_axis(dt, near, axis=1)[:, 0]
            s_along = np.take_along_axis(st, near, axis=1)[:, 0]
        else:
            phi_pred = _arc_angle(np.einsum("ni,ni->n", wv, r1), alpha)
            dd = np.hypot(phi - phi_pred[ii], across)
        okc = valid[ii] & (dd <= s * GATE_SIGMAS * sig)
        cp = np.column_stack([ii[okc], jj[okc]])
        if cp.shape[0] == 0:
            return cp
        sel = one_to_one(cp, dd[okc])
        new = cp[sel]
        new_k = np.flatnonzero(okc)[sel]
        o = np.argsort(new[:, 0], kind="stable")
        new, new_k = new[o], new_k[o]
        if last:
            if tree2 is not None and MIN_POSTERIOR > 0.0 and new.shape[0]:
                # every candidate inside the gate is a possible partner
                like = _likelihood(dd / sig, sig, s_along)
                rivals = _rival_likelihood(new, like[new_k], cp, like[okc], n1, n2)
                post = _posterior(new, like[new_k], tree2, np.count_nonzero(valid), rivals)
                new = new[post >= MIN_POSTERIOR]
            return new
        if new.shape == pairs.shape and np.array_equal(new, pairs):
            rounds = r + 1
        pairs, k_of = new, new_k
    return pairs


def _epipolar_stage(r1, r2, tree2, s1, s2, seeds, noise, max_parallax, seed, info):
    """Motion (R, t) and the pairs matched along its epipolar arcs, or None (``info["epipolar_reason"]``).

    The RANSAC pool: local-triangle matches whose rotation lies within the
    parallax spread of the densest cluster (three pairs each, sampled as
    a unit), plus the pairs of the earlier stages.
    """
    Rd, _, _, tri = _dominant_rotation(r1, r2, EPI_SHAPE_TOL, EPI_CLUSTER_DEG, EPI_MATCHES)
    sets = [tri]
    # the deeper retrieval brings more true triangles but also more chance
    # ones, which can form a denser wrong cluster: when the densest cluster
    # of the 8 most similar triangles (the rotation search's retrieval)
    # lies elsewhere, its triangles give hypotheses too, and growth decides
    R8, _, _, tri8 = _dominant_rotation(r1, r2, EPI_SHAPE_TOL, EPI_CLUSTER_DEG)
    if Rd is not None and R8 is not None and tri8.shape[0]:
        c = (float(np.trace(Rd.T @ R8)) - 1.0) / 2.0
        if math.degrees(math.acos(min(1.0, max(-1.0, c)))) > EPI_CLUSTER_DEG:
            sets.append(tri8)
    info["epipolar_clusters"] = len(sets)
    pool = np.vstack([seeds.reshape(-1, 2)] + [t.reshape(-1, 2) for t in sets])
    pool, inverse = np.unique(pool, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    group_sets, start = [], seeds.shape[0]
    for t in sets:
        n = t.shape[0] * 3
        group_sets.append(inverse[start:start + n].reshape(-1, 3) if n else None)
        start += n
    info["epipolar_pool"] = int(pool.shape[0])
    seeds = pool
    if seeds.shape[0] < 12:
        info["epipolar_reason"] = "fewer than 12 candidate pairs for the essential matrix"
        return None
    x, y = r1[seeds[:, 0]], r2[seeds[:, 1]]
    sig = np.sqrt(s1[seeds[:, 0]] ** 2 + s2[seeds[:, 1]] ** 2)
    rng = np.random.default_rng(seed)
    ests = [e for groups in group_sets for e in _estimate_motions(x, y, sig, rng, groups)]
    if not ests:
        info["epipolar_reason"] = "no essential matrix with 8 or more supporting pairs"
        return None
    best = None
    for R, t, inl in ests:
        pairs, grown = seeds[inl], np.empty((0, 2), np.int64)
        for it in range(EPI_OUTER):
            cand = _epipolar_candidates(r1, r2, tree2, s1, s2, R, t, max_parallax)
            new = _grow_epipolar(r1, cand, r2.shape[0], pairs, tree2=tree2)
            if new.shape[0] < 12:
                break
            converged = it > 0 and np.array_equal(new, grown)
            grown = pairs = new
            if converged or it + 1 == EPI_OUTER:
                break
            sig_p = np.sqrt(s1[pairs[:, 0]] ** 2 + s2[pairs[:, 1]] ** 2)
            R, t = _refine_motion(R, t, r1[pairs[:, 0]], r2[pairs[:, 1]], sig_p)
        info.setdefault("epipolar_hypotheses", []).append((int(np.count_nonzero(inl)), int(grown.shape[0])))
        if grown.shape[0] and (best is None or grown.shape[0] > best[2].shape[0]):
            best = (R, t, grown)
    if best is None:
        info["epipolar_reason"] = "growth along the epipolar arcs found fewer than 12 pairs"
        return None
    R, t, pairs = best
    sig_p = np.sqrt(s1[pairs[:, 0]] ** 2 + s2[pairs[:, 1]] ** 2)
    R, t = _refine_motion(R, t, r1[pairs[:, 0]], r2[pairs[:, 1]], sig_p)
    # growth cannot jump gaps wider than its reach: grow once more from the
    # matches and every pool pair consistent with the final motion
    consistent = (_epipolar_distance(_essential_from_motion(R, t), x, y) <= GATE_SIGMAS * sig) & _cheirality(R, t, x, y)
    cand = _epipolar_candidates(r1, r2, tree2, s1, s2, R, t, max_parallax)
    again = _grow_epipolar(r1, cand, r2.shape[0], np.unique(np.vstack([pairs, seeds[consistent]]), axis=0), tree2=tree2)
    info["epipolar_regrown"] = int(again.shape[0])
    if again.shape[0] > pairs.shape[0]:
        pairs = again
    # no parallax: a pure rotation, whose t is arbitrary (the rigid stage's case)
    phi, _, _ = _arc_coordinates(r1[pairs[:, 0]] @ R.T, t, r2[pairs[:, 1]]) if pairs.size else (np.zeros(1),) * 3
    info["epipolar_median_parallax"] = float(np.median(phi))
    if not np.median(phi) > EPI_MIN_PARALLAX * noise:
        info["epipolar_reason"] = "no parallax: the views differ by a rotation only"
        return None
    return R, t, pairs


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
