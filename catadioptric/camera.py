"""Unified sphere model of a central catadioptric camera.

The model (Geyer & Daniilidis 2000; Mei & Rives 2007, with the
radial–tangential distortion of OpenCV's ``cv2.omnidir``) maps a 3D point
``X`` in the camera frame to a pixel in four steps:

1. ``Xs = X / |X|`` (projection onto the unit sphere);
2. ``x = Xs_x / (Xs_z + xi)``, ``y = Xs_y / (Xs_z + xi)`` (perspective
   projection from the point ``(0, 0, -xi)``);
3. radial–tangential distortion, with ``r2 = x**2 + y**2``::

       xd = x (1 + k1 r2 + k2 r2**2) + 2 p1 x y + p2 (r2 + 2 x**2)
       yd = y (1 + k1 r2 + k2 r2**2) + p1 (r2 + 2 y**2) + 2 p2 x y

4. ``u = fx xd + skew yd + cx``, ``v = fy yd + cy``.

``xi = 0`` is a pinhole camera, ``xi = 1`` a para-catadioptric camera
(parabolic mirror + orthographic lens: the map is the stereographic
projection from the sphere's south pole) and ``0 < xi < 1`` a
hyper-catadioptric one. Lifting inverts the chain: undistort, then::

    r2 = x**2 + y**2
    fac = (xi + sqrt(1 + (1 - xi**2) r2)) / (r2 + 1)
    Xs = (fac x, fac y, fac - xi)

These are the formulas stored in the ``projection`` and ``lifting`` fields
of the shared ``calibration_mei_opencv.json``.

Invalid input policy
--------------------
A sphere point ``Xs`` can be projected and lifted back to itself only when
``Xs_z > -min(xi, 1/xi)`` (for ``xi <= 1`` the projection centre must see
it in front; for ``xi > 1`` the other intersection of the projection ray
with the sphere is the one lifted back). A pixel can be lifted only when
the undistortion converges inside the monotone part of the distortion and
``1 + (1 - xi**2) r2 >= 0`` (for ``xi > 1`` this is the image disc of the
mirror's rim). :meth:`UnifiedCamera.project` and
:meth:`UnifiedCamera.lift` raise a ``ValueError`` that counts the invalid
rows by default; with ``return_mask=True`` they return NaN rows plus a
boolean mask of valid rows instead.
"""

from __future__ import annotations

import json
import math
import numbers
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from gatv.validation import as_points
from gatv.errors import InputError

if TYPE_CHECKING:
    from numpy.typing import ArrayLike, NDArray

__all__ = ["UnifiedCamera"]

#: Tolerance of the iterative undistortion, in normalised image coordinates.
UNDISTORT_TOL = 1e-12
#: Maximum number of Newton steps of the undistortion.
UNDISTORT_MAX_ITER = 50

_OPENCV_D_KEYS = ("D_k1_k2_p1_p2", "D", "distortion_coefficients", "dist_coeffs", "distortion")
_OPENCV_K_KEYS = ("K", "camera_matrix", "cameraMatrix")


def _finite_real(value, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        msg = f"Expected `{name}` to be a real number, got {value!r}."
        raise InputError(msg)
    value = float(value)
    if not math.isfinite(value):
        msg = f"Expected `{name}` to be finite, got {value!r}."
        raise InputError(msg)
    return value


def _distortion_tuple(distortion) -> tuple[float, float, float, float]:
    if distortion is None:
        return (0.0, 0.0, 0.0, 0.0)
    try:
        arr = np.asarray(distortion, dtype=np.float64).ravel()
    except (TypeError, ValueError) as exc:
        msg = f"Expected `distortion` to be 4 numbers (k1, k2, p1, p2): {exc}."
        raise InputError(msg) from exc
    if arr.size == 5 and arr[4] == 0.0:
        # OpenCV's pinhole (k1, k2, p1, p2, k3) with k3 = 0 is the same model.
        arr = arr[:4]
    if arr.size != 4:
        msg = (
            "Expected `distortion` to have 4 coefficients (k1, k2, p1, p2) as in "
            f"cv2.omnidir, got {arr.size}."
        )
        raise InputError(msg)
    if not np.all(np.isfinite(arr)):
        msg = f"Expected `distortion` to be finite, got {arr.tolist()}."
        raise InputError(msg)
    return tuple(float(a) for a in arr)  # type: ignore[return-value]


def _radial_limit(k1: float, k2: float) -> float:
    """Return ``r2`` where ``r (1 + k1 r2 + k2 r2^2)`` stops increasing.

    The radial part of the distortion is invertible on ``r2 < limit``
    (``inf`` when the derivative ``1 + 3 k1 s + 5 k2 s^2`` never vanishes
    for ``s = r2 > 0``).
    """
    roots = np.roots([5.0 * k2, 3.0 * k1, 1.0]) if (k1 or k2) else np.array([])
    roots = [r.real for r in np.atleast_1d(roots) if abs(r.imag) < 1e-12 and r.real > 0]
    return float(min(roots)) if roots else math.inf


def _atomic_write_text(path: Path, text: str) -> None:
    path = Path(path)
    directory = path.parent if str(path.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=directory)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


@dataclass(frozen=True)
class UnifiedCamera:
    """Central catadioptric camera in the unified sphere model.

    Parameters
    ----------
    xi : float
        Mirror parameter, ``>= 0``: 0 pinhole, 1 parabolic mirror,
        between 0 and 1 hyperbolic/elliptic mirror. Values above 1 (as
        returned by calibrations of fisheye-like or slightly misfitted
        para-catadioptric cameras) are accepted.
    fx, fy : float
        Generalised focal lengths in pixels, ``> 0``.
    cx, cy : float
        Principal point in pixels (origin at the centre of the top-left
        pixel, ``u`` to the right, ``v`` down).
    skew : float, default: 0.0
        Skew ``s`` in ``u = fx xd + s yd + cx`` (OpenCV's ``K[0, 1]``).
    distortion : sequence of 4 float, optional
        ``(k1, k2, p1, p2)`` radial–tangential coefficients of
        ``cv2.omnidir``; default: no distortion. Stored as a tuple of 4
        floats (zeros for ``None``). A 5-vector with ``k3 = 0`` (OpenCV's
        pinhole layout) is accepted; any other length raises.
    image_size : (int, int), optional
        Image ``(width, height)`` in pixels; metadata only (kept by the
        JSON round trip, used by :func:`catadioptric.synthetic_views` to
        drop points outside the image).

    Notes
    -----
    The module docstring gives the projection and lifting formulas and the
    policy for points and pixels outside the model's domain. Instances are
    immutable and hashable.

    References
    ----------
    C. Geyer and K. Daniilidis, "A unifying theory for central panoramic
    systems and practical implications", ECCV 2000. C. Mei and P. Rives,
    "Single view point omnidirectional camera calibration from planar
    grids", ICRA 2007.

    Examples
    --------
    >>> import numpy as np
    >>> cam = UnifiedCamera(xi=1.0, fx=300.0, fy=300.0, cx=640.0, cy=512.0)
    >>> cam.project([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    array([[640., 512.],
           [940., 512.]])
    >>> cam.lift([[940.0, 512.0]]).round(12)
    array([[1., 0., 0.]])
    """

    xi: float
    fx: float
    fy: float
    cx: float
    cy: float
    skew: float = 0.0
    distortion: tuple[float, float, float, float] | None = None
    image_size: tuple[int, int] | None = field(default=None, kw_only=True)

    def __post_init__(self) -> None:
        xi = _finite_real(self.xi, "xi")
        if xi < 0:
            msg = f"Expected `xi` >= 0 (0 pinhole, 1 parabolic mirror), got {xi!r}."
            raise InputError(msg)
        values = {"xi": xi}
        for name in ("fx", "fy"):
            value = _finite_real(getattr(self, name), name)
            if value <= 0:
                msg = f"Expected `{name}` to be a focal length > 0 in pixels, got {value!r}."
                raise InputError(msg)
            values[name] = value
        for name in ("cx", "cy", "skew"):
            values[name] = _finite_real(getattr(self, name), name)
        values["distortion"] = _distortion_tuple(self.distortion)
        size = self.image_size
        if size is not None:
            try:
                w, h = (int(s) for s in size)
                ok = all(float(s) == int(s) for s in size) and w > 0 and h > 0
            except (TypeError, ValueError):
                ok = False
            if not ok:
                msg = f"Expected `image_size` to be (width, height) positive integers, got {size!r}."
                raise InputError(msg)
            values["image_size"] = (w, h)
        for name, value in values.items():
            object.__setattr__(self, name, value)
        object.__setattr__(self, "_r2_limit", _radial_limit(*values["distortion"][:2]))

    # ------------------------------------------------------------------ #
    # Properties and constructors
    # ------------------------------------------------------------------ #
    @property
    def K(self) -> NDArray[np.float64]:
        """(3, 3) ndarray of float: the generalised camera matrix."""
        return np.array(
            [[self.fx, self.skew, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]]
        )

    @property
    def has_distortion(self) -> bool:
        """bool: whether any of ``k1, k2, p1, p2`` is non-zero."""
        return any(self.distortion)

    @classmethod
    def from_opencv(cls, K, xi, D=None, *, image_size=None) -> UnifiedCamera:
        """Build a camera from ``cv2.omnidir`` parameters.

        Parameters
        ----------
        K : (3, 3) array_like
            Camera matrix ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``.
        xi : float
            Mirror parameter.
        D : sequence of 4 float, optional
            ``(k1, k2, p1, p2)``.
        image_size : (int, int), optional
            ``(width, height)``.
        """
        try:
            K = np.asarray(K, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            msg = f"Expected `K` to be a (3, 3) array of numbers: {exc}."
            raise InputError(msg) from exc
        if K.shape != (3, 3):
            msg = f"Expected `K` to have shape (3, 3), got {K.shape}."
            raise InputError(msg)
        if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0.0:
            msg = f"Expected `K` to be upper triangular with last row [0, 0, 1], got {K.tolist()}."
            raise InputError(msg)
        xi = _scalar(xi)
        return cls(
            xi, K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1], D, image_size=image_size
        )

    @classmethod
    def from_dict(cls, data: dict) -> UnifiedCamera:
        """Build a camera from a mapping in either supported layout.

        Two layouts are recognised: the one written by :meth:`to_dict`
        (keys ``xi, fx, fy, cx, cy, skew, distortion, image_size``) and the
        OpenCV one (``K`` or ``camera_matrix``, ``xi``, and ``D`` or
        ``D_k1_k2_p1_p2``; ``image_size_wh`` or ``image_size``), as in the
        shared ``calibration_mei_opencv.json``.
        """
        if not isinstance(data, dict):
            msg = f"Expected a mapping of camera parameters, got {type(data).__name__}."
            raise InputError(msg)
        if "xi" not in data:
            msg = f"Camera parameters lack the key 'xi'; keys found: {sorted(data)}."
            raise InputError(msg)
        size = data.get("image_size_wh", data.get("image_size"))
        k_key = next((k for k in _OPENCV_K_KEYS if k in data), None)
        if k_key is not None:
            d_key = next((k for k in _OPENCV_D_KEYS if k in data), None)
            D = data[d_key] if d_key is not None else None
            return cls.from_opencv(data[k_key], _scalar(data["xi"]), D, image_size=size)
        missing = [k for k in ("fx", "fy", "cx", "cy") if k not in data]
        if missing:
            msg = (
                f"Camera parameters lack {missing}; expected either fx, fy, cx, cy "
                f"or an OpenCV camera matrix 'K'. Keys found: {sorted(data)}."
            )
            raise InputError(msg)
        return cls(
            _scalar(data["xi"]),
            data["fx"],
            data["fy"],
            data["cx"],
            data["cy"],
            data.get("skew", 0.0),
            data.get("distortion"),
            image_size=size,
        )

    def to_dict(self) -> dict:
        """Return the parameters as a JSON-serialisable ``dict``."""
        return {
            "model": "unified (Mei & Rives), radial-tangential distortion as cv2.omnidir",
            "xi": self.xi,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "skew": self.skew,
            "distortion": list(self.distortion),
            "distortion_order": ["k1", "k2", "p1", "p2"],
            "image_size": list(self.image_size) if self.image_size else None,
        }

    @classmethod
    def from_json(cls, path) -> UnifiedCamera:
        """Read a camera from a JSON file (either layout of :meth:`from_dict`)."""
        path = Path(path)
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            msg = f"`path` {str(path)!r} is not valid JSON: {exc}."
            raise InputError(msg) from exc
        return cls.from_dict(data)

    #: Alias of :meth:`from_json`; the layout is detected from the keys.
    from_opencv_json = from_json

    def to_json(self, path) -> None:
        """Write the camera to ``path`` as JSON, atomically.

        The text goes to a temporary file in the same folder, which then
        replaces ``path`` with :func:`os.replace`; a crash never leaves a
        half-written file.
        """
        _atomic_write_text(Path(path), json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def from_yaml(cls, path) -> UnifiedCamera:
        """Read a camera from YAML (needs PyYAML, an optional dependency).

        OpenCV ``FileStorage`` files (``%YAML:1.0`` header, ``!!opencv-matrix``
        nodes) are accepted. Keys as in :meth:`from_dict`.

        Raises
        ------
        ImportError
            PyYAML is not installed.
        """
        try:
            import yaml
        except ImportError as exc:
            msg = (
                "Reading YAML camera files needs PyYAML, which is not installed; "
                "install it with `pip install pyyaml`, or use JSON (UnifiedCamera.from_json)."
            )
            raise ImportError(msg) from exc
        text = Path(path).read_text(encoding="utf-8")
        if text.startswith("%YAML:"):
            text = text.split("\n", 1)[1] if "\n" in text else ""

        class _Loader(yaml.SafeLoader):
            pass

        def _matrix(loader, node):
            m = loader.construct_mapping(node, deep=True)
            return np.asarray(m["data"], dtype=np.float64).reshape(m["rows"], m["cols"]).tolist()

        _Loader.add_constructor("tag:yaml.org,2002:opencv-matrix", _matrix)
        data = yaml.load(text, Loader=_Loader)  # noqa: S506 - SafeLoader subclass
        return cls.from_dict(data)

    @classmethod
    def from_file(cls, path) -> UnifiedCamera:
        """Read a camera from ``.json``, ``.yaml`` or ``.yml``, by suffix."""
        suffix = Path(path).suffix.lower()
        if suffix in (".yaml", ".yml"):
            return cls.from_yaml(path)
        return cls.from_json(path)

    # ------------------------------------------------------------------ #
    # Distortion
    # ------------------------------------------------------------------ #
    def distort(self, xy: NDArray[np.float64]) -> NDArray[np.float64]:
        """Apply the radial–tangential distortion to normalised points.

        Parameters
        ----------
        xy : (N, 2) ndarray of float
            Undistorted normalised coordinates ``(x, y)``.

        Returns
        -------
        (N, 2) ndarray of float
        """
        k1, k2, p1, p2 = self.distortion
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + k2 * r2)
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return np.column_stack([xd, yd])

    def _distortion_jacobian(self, x, y):
        k1, k2, p1, p2 = self.distortion
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + k2 * r2)
        dr = 2.0 * (k1 + 2.0 * k2 * r2)  # d radial / d(x or y) divided by x or y
        jxx = radial + dr * x * x + 2.0 * p1 * y + 6.0 * p2 * x
        jyy = radial + dr * y * y + 6.0 * p1 * y + 2.0 * p2 * x
        jxy = dr * x * y + 2.0 * p1 * x + 2.0 * p2 * y  # symmetric
        return jxx, jxy, jyy

    def _distortion_ok(self, x, y) -> NDArray[np.bool_]:
        """Points in the monotone (invertible) part of the distortion."""
        if not self.has_distortion:
            return np.ones(x.shape, dtype=bool)
        jxx, jxy, jyy = self._distortion_jacobian(x, y)
        return ((x * x + y * y) < self._r2_limit) & (jxx * jyy - jxy * jxy > 0)

    def undistort(self, xy_d: NDArray[np.float64]):
        """Invert :meth:`distort` by Newton's method.

        Parameters
        ----------
        xy_d : (N, 2) ndarray of float
            Distorted normalised coordinates.

        Returns
        -------
        xy : (N, 2) ndarray of float
            Undistorted coordinates; ``|distort(xy) - xy_d| <= 1e-12`` where
            converged.
        converged : (N,) ndarray of bool
            False where Newton did not converge or ended outside the
            monotone part of the distortion (see :meth:`project`).
        """
        xy = np.array(xy_d, dtype=np.float64, copy=True)
        n = xy.shape[0]
        if not self.has_distortion:
            return xy, np.ones(n, dtype=bool)
        converged = np.zeros(n, dtype=bool)
        active = np.arange(n)
        for _ in range(UNDISTORT_MAX_ITER):
            cur = xy[active]
            res = self.distort(cur) - xy_d[active]
            err = np.max(np.abs(res), axis=1)
            done = err <= UNDISTORT_TOL
            converged[active[done]] = True
            keep = ~done & np.isfinite(err)
            active, cur, res = active[keep], cur[keep], res[keep]
            if active.size == 0:
                break
            jxx, jxy, jyy = self._distortion_jacobian(cur[:, 0], cur[:, 1])
            det = jxx * jyy - jxy * jxy
            with np.errstate(divide="ignore", invalid="ignore"):
                dx = (jyy * res[:, 0] - jxy * res[:, 1]) / det
                dy = (jxx * res[:, 1] - jxy * res[:, 0]) / det
            xy[active, 0] = cur[:, 0] - dx
            xy[active, 1] = cur[:, 1] - dy
        # One more Newton step polishes the converged points to round-off.
        idx = np.flatnonzero(converged)
        if idx.size:
            cur = xy[idx]
            res = self.distort(cur) - xy_d[idx]
            jxx, jxy, jyy = self._distortion_jacobian(cur[:, 0], cur[:, 1])
            det = jxx * jyy - jxy * jxy
            with np.errstate(divide="ignore", invalid="ignore"):
                step = np.column_stack(
                    [(jyy * res[:, 0] - jxy * res[:, 1]) / det, (jxx * res[:, 1] - jxy * res[:, 0]) / det]
                )
            ok = np.all(np.isfinite(step), axis=1)
            xy[idx[ok]] = cur[ok] - step[ok]
        converged &= self._distortion_ok(xy[:, 0], xy[:, 1])
        return xy, converged

    # ------------------------------------------------------------------ #
    # Projection and lifting
    # ------------------------------------------------------------------ #
    def sphere_limit(self) -> float:
        """Return ``-min(xi, 1/xi)``: sphere points need ``Xs_z`` above it."""
        if self.xi == 0.0:
            return 0.0
        return -min(self.xi, 1.0 / self.xi)

    def project(self, points: ArrayLike, *, return_mask: bool = False):
        """Project 3D points in the camera frame to pixels.

        Parameters
        ----------
        points : (N, 3) array_like of float
            Points in the camera frame (any norm; only the direction counts).
        return_mask : bool, default: False
            If True, return ``(pixels, valid)`` with NaN rows where a point
            cannot be projected; otherwise raise on such points.

        Returns
        -------
        pixels : (N, 2) ndarray of float
            ``(u, v)`` pixel coordinates.
        valid : (N,) ndarray of bool
            Only with ``return_mask=True``.

        Raises
        ------
        ValueError
            Malformed ``points`` or, without ``return_mask``, points that
            cannot be projected: the zero vector, sphere points with
            ``Xs_z <= -min(xi, 1/xi)`` (behind the projection centre or on
            the far side of the mirror) and points whose normalised
            coordinates fall outside the invertible part of the distortion.
        """
        pts = as_points(points, "points", min_points=0, dim=3)
        norm = np.linalg.norm(pts, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            xs = pts / norm[:, None]
            denom = xs[:, 2] + self.xi
            valid = (norm > 0) & (xs[:, 2] > self.sphere_limit())
            x = xs[:, 0] / denom
            y = xs[:, 1] / denom
        valid &= np.isfinite(x) & np.isfinite(y)
        x = np.where(valid, x, np.nan)
        y = np.where(valid, y, np.nan)
        if self.has_distortion:
            ok = self._distortion_ok(x, y)
            valid &= ok
            xy = self.distort(np.column_stack([x, y]))
        else:
            xy = np.column_stack([x, y])
        xy[~valid] = np.nan
        u = self.fx * xy[:, 0] + self.skew * xy[:, 1] + self.cx
        v = self.fy * xy[:, 1] + self.cy
        pixels = np.column_stack([u, v])
        if return_mask:
            return pixels, valid
        bad = int(np.count_nonzero(~valid))
        if bad:
            msg = (
                f"{bad} of {len(valid)} rows of `points` cannot be projected by this camera "
                f"(zero vector, or sphere z <= {self.sphere_limit():.6g}, or outside the "
                "invertible part of the distortion); pass return_mask=True to get NaN rows "
                "and a validity mask instead."
            )
            raise InputError(msg)
        return pixels

    def lift(self, pixels: ArrayLike, *, return_mask: bool = False):
        """Lift pixels to unit rays on the sphere (inverse of :meth:`project`).

        Parameters
        ----------
        pixels : (N, 2) array_like of float
            ``(u, v)`` pixel coordinates.
        return_mask : bool, default: False
            If True, return ``(rays, valid)`` with NaN rows for pixels that
            cannot be lifted; otherwise raise on such pixels.

        Returns
        -------
        rays : (N, 3) ndarray of float
            Unit vectors in the camera frame.
        valid : (N,) ndarray of bool
            Only with ``return_mask=True``.

        Raises
        ------
        ValueError
            Malformed ``pixels`` or, without ``return_mask``, pixels outside
            the domain: for ``xi > 1``, outside the disc where
            ``1 + (1 - xi**2) r2 >= 0``; with distortion, where the
            undistortion does not converge to 1e-12 inside the invertible
            part of the distortion; for ``xi = 0``, never.
        """
        pix = as_points(pixels, "pixels", min_points=0, dim=2)
        y_d = (pix[:, 1] - self.cy) / self.fy
        x_d = (pix[:, 0] - self.cx - self.skew * y_d) / self.fx
        xy, valid = self.undistort(np.column_stack([x_d, y_d]))
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        disc = 1.0 + (1.0 - self.xi * self.xi) * r2
        valid &= disc >= 0
        with np.errstate(invalid="ignore"):
            fac = (self.xi + np.sqrt(np.where(valid, disc, np.nan))) / (r2 + 1.0)
        rays = np.column_stack([fac * x, fac * y, fac - self.xi])
        rays[~valid] = np.nan
        if return_mask:
            return rays, valid
        bad = int(np.count_nonzero(~valid))
        if bad:
            msg = (
                f"{bad} of {len(valid)} rows of `pixels` cannot be lifted by this camera "
                "(outside the mirror's image disc, where 1 + (1 - xi^2) r^2 < 0, or where "
                "the undistortion fails); pass return_mask=True to get NaN rows and a "
                "validity mask instead."
            )
            raise InputError(msg)
        return rays


def _scalar(value):
    """Unwrap 1-element lists such as OpenCV's ``xi: [[1.02]]``."""
    arr = np.asarray(value)
    if arr.size == 1 and arr.ndim > 0:
        return arr.ravel()[0].item()
    return value
