"""Non-rigid deformations and trials for tests, benchmarks and the gallery.

Every generator takes points as rows and returns the moved points as a new
``(N, 3)`` array; randomness comes only from ``numpy.random.default_rng(seed)``,
so the same seed gives the same result.

* :func:`sample_plane` — a square patch of the plane ``z = 0`` sampled by
  jittered-grid (stratified) sampling: even coverage without the lattice
  regularity that would make false joint-space tokens repeat the true surface.
* :func:`twist` — the paper's Fig. 13: every cross-section normal to an axis
  turns rigidly about it by an angle growing linearly along it.
* :func:`bend` — rolls a plane around a cylinder (an isometry of the plane).
* :func:`elastic` — a smooth random warp, a sum of Gaussian radial
  displacement bumps.
* :func:`piecewise_rigid` — two parts moving differently: the part beyond a
  hinge line turns about it (a jaw opening, like the chin of the paper's
  head model, section 4.2).
* :func:`rigid` — a rigid motion, to compose with the others.
* :func:`two_link_arm` — an articulated tube: two links, each turned
  rigidly about its joint (a shoulder and an elbow), with the truth.
* :func:`nonrigid_trial` — source and moved copy with outliers added to both,
  shuffled, with the true pairs.

References
----------
Reyes, Medioni & Bayro, IJCV 75(3) 2007, section 5.1 and Fig. 13.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._validation import as_points, check_nonnegative, check_positive
from .._validation import frozen_array as _frozen
from ..datasets import outlier_count
from ..errors import InputError

__all__ = [
    "NonRigidTrial",
    "bend",
    "elastic",
    "nonrigid_trial",
    "piecewise_rigid",
    "rigid",
    "sample_plane",
    "twist",
    "two_link_arm",
]


def _axis(axis, name: str = "axis") -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)) or np.linalg.norm(a) == 0:
        msg = f"Expected `{name}` to be a nonzero 3-vector, got {axis!r}."
        raise InputError(msg)
    return a / np.linalg.norm(a)


def _angle(value, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not np.isfinite(value):
        msg = f"Expected `{name}` to be a finite number of degrees, got {value!r}."
        raise InputError(msg)
    return float(np.radians(value))


def _rotate_about(points: np.ndarray, axis: np.ndarray, angles) -> np.ndarray:
    """Rodrigues' rotation of each row about ``axis`` (through 0) by its angle."""
    c = np.cos(angles)[..., None]
    s = np.sin(angles)[..., None]
    along = (points @ axis)[:, None] * axis
    return points * c + np.cross(axis, points) * s + along * (1.0 - c)


def _center(points: np.ndarray, center) -> np.ndarray:
    if center is None:
        return 0.5 * (points.min(axis=0) + points.max(axis=0))
    c = np.asarray(center, dtype=np.float64).reshape(-1)
    if c.shape != (3,) or not np.all(np.isfinite(c)):
        msg = f"Expected `center` to be 3 finite numbers, got {center!r}."
        raise InputError(msg)
    return c


def sample_plane(n: int = 400, size: float = 10.0, *, seed=0) -> np.ndarray:
    """Points on the square ``[-size/2, size/2]² × {0}`` by jittered-grid sampling.

    The square is cut into ``ceil(sqrt(n))²`` cells; ``n`` distinct cells
    (all of them when ``n`` is a square) each get one uniform point.

    Parameters
    ----------
    n : int, default: 400
        Number of points (≥ 3).
    size : float, default: 10
        Edge of the square.
    seed : int or numpy.random.Generator, default: 0

    Returns
    -------
    (n, 3) ndarray of float

    Examples
    --------
    >>> p = sample_plane(400, 10.0, seed=0)
    >>> p.shape, float(abs(p[:, 2]).max()), bool(abs(p[:, :2]).max() <= 5)
    ((400, 3), 0.0, True)
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 3:
        msg = f"Expected `n` to be an integer >= 3, got {n!r}."
        raise InputError(msg)
    size = check_positive(size, "size")
    rng = np.random.default_rng(seed)
    m = int(np.ceil(np.sqrt(n)))
    cells = np.sort(rng.choice(m * m, size=int(n), replace=False))
    iy, ix = np.divmod(cells, m)
    h = size / m
    xy = (np.stack([ix, iy], axis=1) + rng.uniform(size=(int(n), 2))) * h - 0.5 * size
    return np.column_stack([xy, np.zeros(int(n))])


def twist(points, angle: float, *, axis=(1.0, 0.0, 0.0), center=None, length=None) -> np.ndarray:
    """Twist about an axis: the paper's non-rigid example (Fig. 13).

    The cross-section at signed distance ``s`` from ``center`` along ``axis``
    turns rigidly about the axis by ``angle · s / length``, so the two ends of
    a body of that length turn by ``±angle/2`` (``angle`` in all).  Each
    cross-section moves rigidly and distances to the axis are kept; a small
    neighbourhood at distance ``r`` from the axis is sheared by
    ``α r`` (``α = angle/length`` in radians per unit), which stretches its
    lengths along the axis by at most ``sqrt(1 + α² r²) − 1``: the motion is
    locally rigid up to that strain.

    Parameters
    ----------
    points : (N, 3) array_like
    angle : float
        Total twist in **degrees** over ``length``.
    axis : (3,) array_like, default: (1, 0, 0)
        Direction of the twist axis.
    center : (3,) array_like, optional
        A point of the axis; default the centre of the bounding box.
    length : float, optional
        Length over which the twist is ``angle``; default the extent of the
        points along the axis.

    Returns
    -------
    (N, 3) ndarray of float
    """
    p = as_points(points, "points")
    a = _axis(axis)
    c = _center(p, center)
    q = p - c
    s = q @ a
    if length is None:
        length = float(np.ptp(s)) or 1.0
    length = check_positive(length, "length")
    return _rotate_about(q, a, _angle(angle, "angle") * s / length) + c


def bend(points, angle: float, *, axis=(0.0, 1.0, 0.0), direction=(1.0, 0.0, 0.0),
         center=None, length=None) -> np.ndarray:
    """Roll the points around a cylinder: a plane is bent without stretching.

    The coordinate ``u`` along ``direction`` (from ``center``) becomes arc
    length on a circle of radius ``ρ = length / angle`` whose axis is parallel
    to ``axis``; the offset ``w`` along ``direction × axis`` is kept along the
    circle's normal.  For points on the plane spanned by ``direction`` and
    ``axis`` this is an isometry: all distances measured on the surface are
    kept.

    Parameters
    ----------
    points : (N, 3) array_like
    angle : float
        Angle in **degrees** subtended by ``length`` of material (0 leaves
        the points unchanged).
    axis : (3,) array_like, default: (0, 1, 0)
        Direction of the cylinder's axis (the fold line).
    direction : (3,) array_like, default: (1, 0, 0)
        Direction that gets bent; made orthogonal to ``axis``.
    center, length
        As in :func:`twist` (``length`` along ``direction``).

    Returns
    -------
    (N, 3) ndarray of float
    """
    p = as_points(points, "points")
    a = _axis(axis)
    e = _axis(direction, "direction")
    e = e - (e @ a) * a
    if np.linalg.norm(e) < 1e-9:
        msg = "`direction` must not be parallel to `axis`."
        raise InputError(msg)
    e /= np.linalg.norm(e)
    n = np.cross(e, a)
    c = _center(p, center)
    q = p - c
    u, w = q @ e, q @ n
    if length is None:
        length = float(np.ptp(u)) or 1.0
    length = check_positive(length, "length")
    phi = _angle(angle, "angle")
    if abs(phi) < 1e-12:
        return p.copy()
    rho = length / phi
    t = u / rho
    # the circle through the centre, tangent to e, curving towards +n
    new_u = (rho - w) * np.sin(t)
    new_w = rho - (rho - w) * np.cos(t)
    return c + q - u[:, None] * e - w[:, None] * n + new_u[:, None] * e + new_w[:, None] * n


def elastic(points, amplitude: float, *, n_bumps: int = 6, width=None, seed=0) -> np.ndarray:
    """A smooth random warp: a sum of Gaussian radial displacement bumps.

    ``x ↦ x + Σ_k a_k exp(−|x − c_k|² / (2 w²))`` with ``n_bumps`` centres
    ``c_k`` drawn among the points, random directions ``a_k / |a_k|`` and
    ``|a_k| = amplitude``.

    Parameters
    ----------
    points : (N, 3) array_like
    amplitude : float
        Length of each bump's displacement vector (data units, ≥ 0).
    n_bumps : int, default: 6
    width : float, optional
        Gaussian width ``w``; default a quarter of the bounding-box diagonal.
    seed : int or numpy.random.Generator, default: 0

    Returns
    -------
    (N, 3) ndarray of float
    """
    p = as_points(points, "points")
    amplitude = check_nonnegative(amplitude, "amplitude")
    if isinstance(n_bumps, bool) or not isinstance(n_bumps, (int, np.integer)) or n_bumps < 1:
        msg = f"Expected `n_bumps` to be an integer >= 1, got {n_bumps!r}."
        raise InputError(msg)
    if width is None:
        width = 0.25 * float(np.linalg.norm(np.ptp(p, axis=0))) or 1.0
    width = check_positive(width, "width")
    rng = np.random.default_rng(seed)
    centres = p[rng.choice(p.shape[0], size=int(n_bumps), replace=p.shape[0] < n_bumps)]
    dirs = rng.normal(size=(int(n_bumps), 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    r2 = ((p[:, None, :] - centres[None]) ** 2).sum(axis=2)
    return p + np.exp(-r2 / (2.0 * width**2)) @ (float(amplitude) * dirs)


def piecewise_rigid(points, angle: float, *, hinge_point=None, hinge_axis=(0.0, 1.0, 0.0),
                    normal=(1.0, 0.0, 0.0), translation=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Two parts moving differently: the part beyond a hinge turns about it.

    Points with ``(x − hinge_point) · normal > 0`` turn by ``angle`` about
    the line through ``hinge_point`` along ``hinge_axis``, then move by
    ``translation``; the other part stays.  Like the chin of the paper's
    head model (section 4.2): each part is rigid, the whole is not.

    Parameters
    ----------
    points : (N, 3) array_like
    angle : float
        Rotation of the moving part in **degrees**.
    hinge_point : (3,) array_like, optional
        Default the centre of the bounding box.
    hinge_axis : (3,) array_like, default: (0, 1, 0)
    normal : (3,) array_like, default: (1, 0, 0)
        Normal of the plane through ``hinge_point`` splitting the two parts.
    translation : (3,) array_like, default: (0, 0, 0)

    Returns
    -------
    (N, 3) ndarray of float
    """
    p = as_points(points, "points")
    c = _center(p, hinge_point)
    a = _axis(hinge_axis, "hinge_axis")
    nrm = _axis(normal, "normal")
    t = np.asarray(translation, dtype=np.float64).reshape(-1)
    if t.shape != (3,) or not np.all(np.isfinite(t)):
        msg = f"Expected `translation` to be 3 finite numbers, got {translation!r}."
        raise InputError(msg)
    out = p.copy()
    moving = (p - c) @ nrm > 0
    q = p[moving] - c
    out[moving] = _rotate_about(q, a, np.full(q.shape[0], _angle(angle, "angle"))) + c + t
    return out


def rigid(points, angle: float, *, axis=(0.0, 0.0, 1.0), translation=(0.0, 0.0, 0.0),
          center=None) -> np.ndarray:
    """Turn by ``angle`` degrees about ``axis`` through ``center`` (default the
    bounding-box centre), then move by ``translation``."""
    p = as_points(points, "points")
    c = _center(p, center)
    a = _axis(axis)
    t = np.asarray(translation, dtype=np.float64).reshape(-1)
    if t.shape != (3,) or not np.all(np.isfinite(t)):
        msg = f"Expected `translation` to be 3 finite numbers, got {translation!r}."
        raise InputError(msg)
    return _rotate_about(p - c, a, np.full(p.shape[0], _angle(angle, "angle"))) + c + t


@dataclass(frozen=True, eq=False)
class NonRigidTrial:
    """A non-rigid registration problem with its ground truth.

    Attributes
    ----------
    source : (N, 3) ndarray of float
        Inliers and outliers of the source set, shuffled.
    target : (M, 3) ndarray of float
        Moved inliers and outliers, shuffled independently.
    true_pairs : (K, 2) ndarray of int
        ``(source index, target index)`` of the inliers, sorted by source
        index: ``target[j]`` is where ``source[i]`` moved.
    outlier_fraction : float
        Fraction of outliers in each set.
    """

    source: np.ndarray
    target: np.ndarray
    true_pairs: np.ndarray
    outlier_fraction: float

    def __post_init__(self):
        object.__setattr__(self, "source", _frozen(self.source))
        object.__setattr__(self, "target", _frozen(self.target))
        object.__setattr__(self, "true_pairs", _frozen(self.true_pairs, np.int64))
        object.__setattr__(self, "outlier_fraction", float(self.outlier_fraction))

    @property
    def n_inliers(self) -> int:
        return int(self.true_pairs.shape[0])

    def warp_error(self, warp) -> float:
        """Mean distance from ``warp(source inliers)`` to their true positions."""
        i, j = self.true_pairs[:, 0], self.true_pairs[:, 1]
        moved = np.asarray(warp(self.source[i]), dtype=np.float64)
        return float(np.mean(np.linalg.norm(moved - self.target[j], axis=1)))


def nonrigid_trial(points, moved, outlier_fraction: float = 0.0, *, noise: float = 0.0,
                   seed=0) -> NonRigidTrial:
    """Source and moved copy, outliers added to both, shuffled, with the truth.

    Outliers are uniform in each set's bounding box (the project's protocol,
    :func:`gatv.datasets.synthetic_trial`); for a flat source that box is
    flat, so its outliers lie in the plane among the inliers.

    Parameters
    ----------
    points, moved : (K, 3) array_like
        Row ``i`` of ``moved`` is where row ``i`` of ``points`` went.
    outlier_fraction : float, default: 0
        Fraction ``f`` in [0, 1) of outliers in each set
        (``round(K f / (1 − f))`` added to each).
    noise : float, default: 0
        Standard deviation of Gaussian noise added to every target point.
    seed : int or numpy.random.Generator, default: 0

    Returns
    -------
    NonRigidTrial
    """
    x = as_points(points, "points", min_points=3)
    y = as_points(moved, "moved", min_points=3)
    if x.shape != y.shape:
        msg = f"Expected `points` and `moved` to have the same shape, got {x.shape} and {y.shape}."
        raise InputError(msg)
    noise = check_nonnegative(noise, "noise")
    rng = np.random.default_rng(seed)
    n = x.shape[0]
    n_out = outlier_count(outlier_fraction, n)
    if noise > 0:
        y = y + rng.normal(scale=float(noise), size=y.shape)
    src = np.vstack([x, rng.uniform(x.min(axis=0), x.max(axis=0), (n_out, 3))])
    tgt = np.vstack([y, rng.uniform(y.min(axis=0), y.max(axis=0), (n_out, 3))])
    perm_s = rng.permutation(n + n_out)
    perm_t = rng.permutation(n + n_out)
    pairs = np.column_stack([np.argsort(perm_s)[:n], np.argsort(perm_t)[:n]])
    pairs = pairs[np.argsort(pairs[:, 0])]
    return NonRigidTrial(src[perm_s], tgt[perm_t], pairs, float(outlier_fraction))


@dataclass(frozen=True, eq=False)
class ArticulatedArm:
    """A two-link arm and its motion: ``source`` (N, 3) on the tube, ``target`` the moved rows
    (row ``i`` of one is row ``i`` of the other), ``labels`` (N,) the link of each row (0, 1),
    ``rotations`` (2, 3, 3) and ``translations`` (2, 3) of the links
    (``target ≈ source @ R.T + t``), ``joints`` (2, 3) the shoulder and the elbow (source frame),
    ``axis`` (3,) the axis both joints turn about."""

    source: np.ndarray
    target: np.ndarray
    labels: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    joints: np.ndarray
    axis: np.ndarray


def two_link_arm(n: int = 600, angles=(30.0, 45.0), *, length: float = 20.0, radius: float = 1.5,
                 axis=(0.0, 0.0, 1.0), seed=0) -> ArticulatedArm:
    """An articulated arm: a tube along x whose two halves turn about their joints.

    ``n`` points on the tube ``y² + z² = radius²``, ``0 <= x <= length``, by
    jittered-grid sampling of its unrolled surface.  The first link
    (``x < length / 2``) turns by ``angles[0]`` degrees about ``axis``
    through the shoulder (the origin); the second turns by
    ``angles[1]`` more about the same axis through the elbow
    (``(length / 2, 0, 0)``, carried by the first link).  Each link is
    rigid; the whole is piecewise rigid, with a crease at the elbow.

    Returns
    -------
    ArticulatedArm
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 8:
        raise InputError(f"Expected `n` to be an integer >= 8, got {n!r}.")
    length = check_positive(length, "length")
    radius = check_positive(radius, "radius")
    a = _axis(axis)
    if len(angles) != 2:
        raise InputError(f"Expected `angles` to be two angles in degrees, got {angles!r}.")
    a1, a2 = _angle(angles[0], "angles[0]"), _angle(angles[1], "angles[1]")
    rng = np.random.default_rng(seed)
    flat = sample_plane(int(n), 1.0, seed=rng) + 0.5  # the unit square
    x = flat[:, 0] * length
    phi = flat[:, 1] * 2.0 * np.pi
    src = np.column_stack([x, radius * np.cos(phi), radius * np.sin(phi)])
    labels = (src[:, 0] >= 0.5 * length).astype(np.int64)
    shoulder, elbow = np.zeros(3), np.array([0.5 * length, 0.0, 0.0])

    def turn(th, centre):
        K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
        R = np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K
        return R, centre - R @ centre

    R1, t1 = turn(a1, shoulder)
    R2, t2 = turn(a2, elbow)  # about the elbow, then the first link's motion
    R12, t12 = R1 @ R2, R1 @ t2 + t1
    rotations = np.stack([R1, R12])
    translations = np.stack([t1, t12])
    tgt = np.einsum("nij,nj->ni", rotations[labels], src) + translations[labels]
    return ArticulatedArm(_frozen(src), _frozen(tgt), _frozen(labels, np.int64), rotations, translations,
                          np.stack([shoulder, elbow]), a)
