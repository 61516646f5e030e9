"""Synthetic two-view catadioptric scenes with known correspondences.

A camera stands inside a box-shaped room; corner points lie on the walls,
floor and ceiling, a few metres away. A second camera, related to the
first by a rigid motion, sees the same room. Each view gets pixel noise
and outlier corners, and its rows are shuffled, so that recovering the
correspondences is the problem of the catadioptric example of Reyes,
Medioni & Bayro (IJCV 2007, end of section 5.1, Fig. 15).

Motion convention: a scene point with coordinates ``X1`` in the frame of
camera 1 has coordinates ``X2 = R @ X1 + t`` in the frame of camera 2.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from catadioptric.camera import UnifiedCamera
from gatv.errors import InputError

if TYPE_CHECKING:
    from numpy.typing import ArrayLike, NDArray

__all__ = ["SyntheticViews", "synthetic_views"]


@dataclass(frozen=True, eq=False)
class SyntheticViews:
    """Two catadioptric views of a synthetic room, with ground truth.

    All arrays are read-only.

    Attributes
    ----------
    pixels1, pixels2 : (N1, 2), (N2, 2) ndarray of float
        Noisy, shuffled corner pixels of views 1 and 2, outliers included.
    camera1, camera2 : UnifiedCamera
        The cameras of the two views (the same object unless a second
        camera was given).
    rotation : (3, 3) ndarray of float
        ``R`` in ``X2 = R @ X1 + t``.
    translation : (3,) ndarray of float
        ``t`` in ``X2 = R @ X1 + t`` (metres).
    pairs : (K, 2) ndarray of int
        Ground-truth correspondences ``(i, j)``: ``pixels1[i]`` and
        ``pixels2[j]`` are the same scene point. Sorted by ``i``.
    points : (M, 3) ndarray of float
        Scene points in the frame of camera 1 (metres), all of them,
        including those seen in one view only.
    ids1, ids2 : (N1,), (N2,) ndarray of int
        Row of ``points`` seen by each pixel; ``-1`` for outliers.
    noise_px : float
        Standard deviation of the pixel noise, per coordinate.
    """

    pixels1: NDArray[np.float64]
    pixels2: NDArray[np.float64]
    camera1: UnifiedCamera
    camera2: UnifiedCamera
    rotation: NDArray[np.float64]
    translation: NDArray[np.float64]
    pairs: NDArray[np.intp]
    points: NDArray[np.float64]
    ids1: NDArray[np.intp]
    ids2: NDArray[np.intp]
    noise_px: float

    def __post_init__(self) -> None:
        for name in ("pixels1", "pixels2", "rotation", "translation", "pairs", "points", "ids1", "ids2"):
            arr = np.array(getattr(self, name))
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    @property
    def outliers1(self) -> NDArray[np.bool_]:
        """(N1,) ndarray of bool: rows of ``pixels1`` that are outliers."""
        return self.ids1 < 0

    @property
    def outliers2(self) -> NDArray[np.bool_]:
        """(N2,) ndarray of bool: rows of ``pixels2`` that are outliers."""
        return self.ids2 < 0

    def rays(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Lift both views to unit rays: ``(rays1, rays2)``, (N1, 3) and (N2, 3)."""
        return self.camera1.lift(self.pixels1), self.camera2.lift(self.pixels2)


def _int_at_least(value, name, low):
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < low:
        msg = f"Expected `{name}` to be an integer >= {low}, got {value!r}."
        raise InputError(msg)
    return int(value)


def _real(value, name, low=-math.inf, high=math.inf, *, low_open=False, high_open=False):
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        msg = f"Expected `{name}` to be a finite number, got {value!r}."
        raise InputError(msg)
    value = float(value)
    bad_low = value <= low if low_open else value < low
    bad_high = value >= high if high_open else value > high
    if bad_low or bad_high:
        lo = "(" if low_open else "["
        hi = ")" if high_open else "]"
        msg = f"Expected `{name}` in {lo}{low}, {high}{hi}, got {value!r}."
        raise InputError(msg)
    return value


def _vector3(value, name):
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        msg = f"Expected `{name}` to be 3 numbers: {exc}."
        raise InputError(msg) from exc
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        msg = f"Expected `{name}` to be 3 finite numbers, got {value!r}."
        raise InputError(msg)
    return arr


def _max_angle(camera: UnifiedCamera, requested: float) -> float:
    """Largest angle from +z (radians) both asked for and projectable."""
    limit = math.acos(max(-1.0, camera.sphere_limit()))
    return min(requested, limit - math.radians(5.0))


def _default_camera(xi: float, max_angle: float) -> UnifiedCamera:
    """A 1280x1024 camera whose image holds the cone of half-angle ``max_angle``."""
    probe = UnifiedCamera(xi, 1.0, 1.0, 0.0, 0.0)
    theta = _max_angle(probe, max_angle)
    # Hyperbolic mirrors (xi < 1) see close to their limit only at huge
    # normalised radii: cap the radius fitted in the image at 2 (the
    # parabolic mirror's 127 degrees); farther points leave the image.
    r_max = min(math.sin(theta) / (math.cos(theta) + xi), 2.0)
    f = 0.95 * 512.0 / r_max
    return UnifiedCamera(xi, f, f, 639.5, 511.5, image_size=(1280, 1024))


def _in_image(camera: UnifiedCamera, pixels: NDArray[np.float64]) -> NDArray[np.bool_]:
    ok = np.all(np.isfinite(pixels), axis=1)
    if camera.image_size is not None:
        w, h = camera.image_size
        with np.errstate(invalid="ignore"):
            ok &= (pixels[:, 0] >= -0.5) & (pixels[:, 0] <= w - 0.5)
            ok &= (pixels[:, 1] >= -0.5) & (pixels[:, 1] <= h - 0.5)
    return ok


def _visible(camera, points, max_angle, rng, noise_px):
    """Noisy pixels of ``points`` and the mask of those kept in this view."""
    norm = np.linalg.norm(points, axis=1)
    keep = points[:, 2] >= norm * math.cos(_max_angle(camera, max_angle))
    pixels, ok = camera.project(points, return_mask=True)
    keep &= ok & _in_image(camera, pixels)
    pixels = pixels + rng.normal(0.0, noise_px, size=pixels.shape) if noise_px > 0 else pixels
    keep &= _in_image(camera, pixels)
    if keep.any():
        _, liftable = camera.lift(np.where(keep[:, None], pixels, 0.0), return_mask=True)
        keep &= liftable
    return pixels, keep


def _cap_directions(rng, n, max_angle):
    """``n`` directions uniform on the cap of half-angle ``max_angle`` around +z."""
    z = rng.uniform(math.cos(max_angle), 1.0, n)
    phi = rng.uniform(0.0, 2.0 * math.pi, n)
    s = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    return np.column_stack([s * np.cos(phi), s * np.sin(phi), z])


def _outlier_pixels(camera, rng, n, max_angle):
    theta = _max_angle(camera, max_angle)
    out = np.empty((0, 2))
    for _ in range(100):
        if len(out) >= n:
            break
        pix, ok = camera.project(_cap_directions(rng, 2 * (n - len(out)) + 8, theta), return_mask=True)
        ok &= _in_image(camera, pix)
        out = np.vstack([out, pix[ok]])
    return out[:n]


def synthetic_views(
    n_points: int = 200,
    *,
    xi: float = 1.0,
    rotation_deg: float = 10.0,
    axis: ArrayLike | None = None,
    translation: ArrayLike = (0.3, 0.1, 0.05),
    noise_px: float = 1.0,
    outlier_fraction: float = 0.0,
    camera: UnifiedCamera | None = None,
    camera2: UnifiedCamera | None = None,
    room: ArrayLike = (4.0, 3.0, 1.5, 2.0),
    max_angle_deg: float = 120.0,
    seed: int | np.random.Generator | None = 0,
) -> SyntheticViews:
    """Simulate two catadioptric views of corners on the walls of a room.

    Parameters
    ----------
    n_points : int, default: 200
        Scene corners, drawn along directions uniform over the field of
        view of camera 1 and placed where those rays meet the room.
    xi : float, default: 1.0
        Mirror parameter of the default camera (1: parabolic mirror).
        Ignored when ``camera`` is given.
    rotation_deg : float, default: 10.0
        Rotation angle of the motion, in degrees.
    axis : (3,) array_like of float, optional
        Rotation axis; default: a random unit axis drawn from ``seed``.
    translation : (3,) array_like of float, default: (0.3, 0.1, 0.05)
        ``t`` in ``X2 = R @ X1 + t`` (metres). Camera 2's centre,
        ``-R.T @ t``, must lie inside the room.
    noise_px : float, default: 1.0
        Standard deviation of the Gaussian pixel noise, per coordinate,
        added independently to both views.
    outlier_fraction : float, default: 0.0
        Fraction, in ``[0, 1)``, of each view's rows that are outlier
        corners (random pixels in the image disc, matching nothing).
    camera : UnifiedCamera, optional
        Camera of view 1 (and of view 2 unless ``camera2`` is given).
        Default: a 1280x1024 camera with mirror parameter ``xi`` whose
        focal length fits the field of view into the image.
    camera2 : UnifiedCamera, optional
        Camera of view 2; default: ``camera``.
    room : (4,) array_like of float, default: (4.0, 3.0, 1.5, 2.0)
        The room around camera 1: ``|x| <= a``, ``|y| <= b``,
        ``-floor <= z <= ceiling`` for ``(a, b, floor, ceiling)`` in metres
        (``z`` is the mirror axis).
    max_angle_deg : float, default: 120.0
        Field of view: a point is seen when its angle from the mirror axis
        ``+z`` is at most this (the image disc), and the camera can project
        it (5 degrees inside the model's limit ``Xs_z > -min(xi, 1/xi)``).
    seed : int or numpy.random.Generator, default: 0
        Seed of the random generator.

    Returns
    -------
    SyntheticViews
        Pixels, cameras, motion, ground-truth pairs and scene points.
        Points outside either view's image disc, outside the image or
        not projectable in a view are left out of that view only; the
        pairs hold the points seen in both.

    Raises
    ------
    ValueError
        Invalid argument (named in the message), or camera 2 outside the
        room.

    Examples
    --------
    >>> views = synthetic_views(50, noise_px=0.0, outlier_fraction=0.2, seed=1)
    >>> views.pixels1.shape[1], views.pairs.shape[1]
    (2, 2)
    >>> bool(np.all(views.ids1[views.pairs[:, 0]] == views.ids2[views.pairs[:, 1]]))
    True
    """
    n_points = _int_at_least(n_points, "n_points", 1)
    rotation_deg = _real(rotation_deg, "rotation_deg")
    t = _vector3(translation, "translation")
    noise_px = _real(noise_px, "noise_px", 0.0)
    outlier_fraction = _real(outlier_fraction, "outlier_fraction", 0.0, 1.0, high_open=True)
    max_angle = math.radians(_real(max_angle_deg, "max_angle_deg", 0.0, 180.0, low_open=True))
    try:
        a, b, floor, ceiling = (float(v) for v in np.asarray(room, dtype=np.float64).ravel())
    except (TypeError, ValueError) as exc:
        msg = f"Expected `room` to be 4 positive numbers (a, b, floor, ceiling), got {room!r}."
        raise InputError(msg) from exc
    if not all(math.isfinite(v) and v > 0 for v in (a, b, floor, ceiling)):
        msg = f"Expected `room` to be 4 positive numbers (a, b, floor, ceiling), got {room!r}."
        raise InputError(msg)
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    if camera is None:
        camera = _default_camera(_real(xi, "xi", 0.0), max_angle)
    elif not isinstance(camera, UnifiedCamera):
        msg = f"Expected `camera` to be a UnifiedCamera, got {type(camera).__name__}."
        raise InputError(msg)
    if camera2 is None:
        camera2 = camera
    elif not isinstance(camera2, UnifiedCamera):
        msg = f"Expected `camera2` to be a UnifiedCamera, got {type(camera2).__name__}."
        raise InputError(msg)

    if axis is None:
        axis_v = rng.normal(size=3)
    else:
        axis_v = _vector3(axis, "axis")
    if not np.linalg.norm(axis_v) > 0:
        msg = f"Expected `axis` to be a non-zero vector, got {axis!r}."
        raise InputError(msg)
    axis_v = axis_v / np.linalg.norm(axis_v)
    R = Rotation.from_rotvec(math.radians(rotation_deg) * axis_v).as_matrix()
    centre2 = -R.T @ t
    lo = np.array([-a, -b, -floor])
    hi = np.array([a, b, ceiling])
    if not (np.all(centre2 > lo) and np.all(centre2 < hi)):
        msg = (
            f"Camera 2's centre -R.T @ t = {np.round(centre2, 3).tolist()} lies outside the "
            f"room {room!r}; use a smaller `translation` or a larger `room`."
        )
        raise InputError(msg)

    # Scene: rays of camera 1 hit the walls of the (convex) room, which both
    # cameras are inside of, so every point is unoccluded in both views.
    dirs = _cap_directions(rng, n_points, _max_angle(camera, max_angle))
    with np.errstate(divide="ignore", invalid="ignore"):
        hits = np.where(dirs > 0, hi / dirs, np.where(dirs < 0, lo / dirs, np.inf))
    points = dirs * hits.min(axis=1)[:, None]

    pix1, keep1 = _visible(camera, points, max_angle, rng, noise_px)
    pix2, keep2 = _visible(camera2, points @ R.T + t, max_angle, rng, noise_px)

    def _view(pix, keep, cam):
        ids = np.flatnonzero(keep)
        n_out = int(round(outlier_fraction / (1.0 - outlier_fraction) * len(ids)))
        out = _outlier_pixels(cam, rng, n_out, max_angle)
        all_pix = np.vstack([pix[ids], out])
        all_ids = np.concatenate([ids, np.full(len(out), -1, dtype=np.intp)])
        perm = rng.permutation(len(all_ids))
        return all_pix[perm], all_ids[perm]

    pixels1, ids1 = _view(pix1, keep1, camera)
    pixels2, ids2 = _view(pix2, keep2, camera2)
    row2 = np.full(n_points, -1, dtype=np.intp)
    row2[ids2[ids2 >= 0]] = np.flatnonzero(ids2 >= 0)
    i1 = np.flatnonzero((ids1 >= 0) & (row2[np.maximum(ids1, 0)] >= 0))
    pairs = np.column_stack([i1, row2[ids1[i1]]]).astype(np.intp).reshape(-1, 2)
    return SyntheticViews(
        pixels1=pixels1,
        pixels2=pixels2,
        camera1=camera,
        camera2=camera2,
        rotation=R,
        translation=t,
        pairs=pairs,
        points=points,
        ids1=ids1,
        ids2=ids2,
        noise_px=noise_px,
    )
