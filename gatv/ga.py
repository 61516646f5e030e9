"""Geometric algebra of 3D space G(3,0,0): rotors, joint spaces and eq. 41.

Conventions
-----------
* Basis vectors ``e1, e2, e3`` (the paper's σ1, σ2, σ3); bivectors
  ``e23, e31, e12``; pseudoscalar ``I = e123``.
* A rotor is stored scalar first, ``R = q0 + qx e23 + qy e31 + qz e12``
  (paper eq. 19), normalised so that ``R ~R = 1`` and canonicalised to
  ``q0 >= 0``.
* Rotation by the angle θ about the unit axis ``a`` (right-handed,
  counter-clockwise seen from the tip of ``a``) is
  ``R = exp(-θ I a / 2) = cos(θ/2) - sin(θ/2) (ax e23 + ay e31 + az e12)``,
  acting on vectors by the sandwich ``x' = R x ~R`` (``R >> x``).
  Hence ``(qx, qy, qz) = -sin(θ/2) a``: the Hamilton quaternion of the same
  rotation is ``(q0, -qx, -qy, -qz)``.
* A rigid motion is ``x' = R x ~R + t`` (paper eq. 18); with rotation matrix
  ``M`` this is ``x' = M x + t``, i.e. ``target = source @ M.T + t`` for
  points stored as rows.

Joint spaces (paper eqs. 27–30)
-------------------------------
Left-multiplying ``x' = R x ~R + t`` by ``~R`` gives ``~R x' = x ~R + ~R t``;
its e1, e2, e3 and e123 parts are four linear equations. With
``d = x' - x``, ``s = x' + x`` and ``P = ~R = (p0, px, py, pz) =
(q0, -qx, -qy, -qz)`` they read (the paper writes them for ``P``)::

    e1   : p0 dx - py sz + pz sy + (py tz - p0 tx - pz ty) = 0      (27)
    e2   : p0 dy + px sz - pz sx + (pz tx - p0 ty - px tz) = 0      (28)
    e3   : p0 dz - px sy + py sx + (px ty - p0 tz - py tx) = 0      (29)
    e123 : px dx + py dy + pz dz - (px tx + py ty + pz tz) = 0      (30)

so every true pair lies on one plane in each of the joint spaces
``{dx, sz, sy}``, ``{dy, sz, sx}``, ``{dz, sy, sx}`` and ``{dx, dy, dz}``
(the paper's order of coordinates).  The normal of the last plane is the
rotation axis.

References
----------
L. Reyes, G. Medioni, E. Bayro, "Registration of 3D Points Using Geometric
Algebra and Tensor Voting", IJCV 75(3):351–369, 2007.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._validation import as_points
from .errors import InputError

__all__ = [
    "Rotor",
    "rotor_product",
    "sandwich",
    "joint_space_coordinates",
    "joint_space_planes",
    "JOINT_SPACE_NAMES",
    "pair_differences",
    "eq41",
    "eq41_length_residual",
    "rotation_angle_deg",
    "turn_about",
    "eq41_residual",
]

#: Names of the four joint spaces, in the paper's order (eqs. 27, 28, 29, 30).
JOINT_SPACE_NAMES = (
    ("dx", "sz", "sy"),
    ("dy", "sz", "sx"),
    ("dz", "sy", "sx"),
    ("dx", "dy", "dz"),
)


def rotor_product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Geometric product of even multivectors ``a b`` stored as (..., 4).

    Each operand is ``(s, b23, b31, b12)``. In this basis
    ``e23 e31 = -e12`` (cyclic), so the vector part is
    ``a0 b + b0 a - a × b``.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    a0, av = a[..., 0], a[..., 1:]
    b0, bv = b[..., 0], b[..., 1:]
    s = a0 * b0 - np.sum(av * bv, axis=-1)
    v = a0[..., None] * bv + b0[..., None] * av - np.cross(av, bv)
    return np.concatenate([s[..., None], v], axis=-1)


def sandwich(q: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Rotate row vectors by the rotor ``q``: ``R x ~R`` for each row.

    Parameters
    ----------
    q : (4,) array_like
        Unit rotor ``(q0, qx, qy, qz)``.
    points : (N, 3) ndarray

    Returns
    -------
    (N, 3) ndarray
    """
    q = np.asarray(q, dtype=np.float64)
    w = q[0]
    v = -q[1:]  # Hamilton quaternion vector part
    x = np.asarray(points, dtype=np.float64)
    t = 2.0 * np.cross(v, x)
    return x + w * t + np.cross(v, t)


def _normalise(q: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(q))
    if not np.isfinite(n) or n < 1e-12:
        msg = f"A rotor needs a non-zero finite norm, got |q| = {n!r}."
        raise InputError(msg)
    q = q / n
    # Canonical sign: q0 > 0; for half-turns (q0 ~ 0) the first clearly
    # non-zero bivector coefficient is made positive.
    key = q[0] if abs(q[0]) > 1e-12 else _first_clear(q[1:])
    return -q if key < 0 else q


def _first_clear(v: np.ndarray) -> float:
    nz = np.flatnonzero(np.abs(v) > 1e-12)
    return float(v[nz[0]]) if nz.size else 0.0


@dataclass(frozen=True, eq=False)
class Rotor:
    """A unit rotor of G(3,0,0), ``R = q0 + qx e23 + qy e31 + qz e12``.

    Build one with :meth:`from_axis_angle`, :meth:`from_matrix`,
    :meth:`from_scipy`, :meth:`from_quaternion` or :meth:`identity`; compose
    with ``R1 * R2`` (apply ``R2`` first), reverse with ``~R`` and rotate
    points (rows of an (N, 3) array) with ``R >> x`` or :meth:`apply`.

    ``R`` and ``-R`` give the same rotation; the stored rotor has
    ``q0 >= 0``.

    Examples
    --------
    >>> import numpy as np
    >>> R = Rotor.from_axis_angle([0, 0, 1], np.pi / 2)
    >>> np.round(R >> np.array([[1.0, 0.0, 0.0]]), 12) + 0.0
    array([[0., 1., 0.]])
    >>> np.allclose((R * ~R).q, [1, 0, 0, 0])
    True
    """

    q: np.ndarray

    def __post_init__(self):
        q = np.array(self.q, dtype=np.float64).reshape(-1)
        if q.shape != (4,):
            msg = f"Expected `q` to have 4 components (q0, qx, qy, qz), got {q.shape}."
            raise InputError(msg)
        if not np.all(np.isfinite(q)):
            raise InputError("`q` contains NaN or infinite values.")
        q = _normalise(q)
        q.setflags(write=False)
        object.__setattr__(self, "q", q)

    # ----------------------------------------------------------------- build
    @classmethod
    def identity(cls) -> Rotor:
        """The identity rotor ``R = 1``."""
        return cls(np.array([1.0, 0.0, 0.0, 0.0]))

    @classmethod
    def from_axis_angle(cls, axis, angle: float) -> Rotor:
        """Rotation by ``angle`` radians about ``axis``: ``exp(-angle I a / 2)``.

        Parameters
        ----------
        axis : (3,) array_like
            Rotation axis; normalised here, must be non-zero.
        angle : float
            Angle in radians, right-handed about ``axis``.
        """
        a = np.asarray(axis, dtype=np.float64).reshape(-1)
        if a.shape != (3,) or not np.all(np.isfinite(a)):
            msg = f"Expected `axis` to be 3 finite numbers, got {np.asarray(axis)!r}."
            raise InputError(msg)
        n = np.linalg.norm(a)
        if n < 1e-15:
            raise InputError("Expected `axis` to be non-zero.")
        angle = float(angle)
        if not np.isfinite(angle):
            raise InputError(f"Expected `angle` to be finite, got {angle!r}.")
        a = a / n
        return cls(np.concatenate([[np.cos(angle / 2)], -np.sin(angle / 2) * a]))

    @classmethod
    def from_rotvec(cls, rotvec) -> Rotor:
        """Rotation vector ``θ a`` (radians), as :meth:`from_axis_angle`."""
        r = np.asarray(rotvec, dtype=np.float64).reshape(-1)
        theta = float(np.linalg.norm(r))
        if theta < 1e-300:
            return cls.identity()
        return cls.from_axis_angle(r / theta, theta)

    @classmethod
    def from_quaternion(cls, quat, *, scalar_first: bool = True) -> Rotor:
        """From a Hamilton unit quaternion of the same rotation.

        ``scalar_first=False`` takes scipy's ``(x, y, z, w)`` order.
        """
        h = np.asarray(quat, dtype=np.float64).reshape(-1)
        if h.shape != (4,):
            msg = f"Expected `quat` to have 4 components, got {h.shape}."
            raise InputError(msg)
        if not scalar_first:
            h = np.array([h[3], h[0], h[1], h[2]])
        return cls(np.array([h[0], -h[1], -h[2], -h[3]]))

    @classmethod
    def from_matrix(cls, matrix) -> Rotor:
        """From a proper rotation matrix (3, 3) acting on column vectors."""
        from scipy.spatial.transform import Rotation

        m = np.asarray(matrix, dtype=np.float64)
        if m.shape != (3, 3) or not np.all(np.isfinite(m)):
            msg = f"Expected `matrix` to be a finite (3, 3) array, got shape {m.shape}."
            raise InputError(msg)
        if np.linalg.det(m) < 0:
            raise InputError("Expected `matrix` to be a rotation (det +1), got a reflection.")
        return cls.from_scipy(Rotation.from_matrix(m))

    @classmethod
    def from_scipy(cls, rotation) -> Rotor:
        """From a single ``scipy.spatial.transform.Rotation``."""
        quat = np.asarray(rotation.as_quat(), dtype=np.float64)
        if quat.shape != (4,):
            raise InputError("Expected a single scipy Rotation, got a stack.")
        return cls.from_quaternion(quat, scalar_first=False)

    # ---------------------------------------------------------------- export
    @property
    def scalar(self) -> float:
        """``q0 = cos(θ/2)``."""
        return float(self.q[0])

    @property
    def bivector(self) -> np.ndarray:
        """``(qx, qy, qz)``, the e23, e31, e12 coefficients."""
        return self.q[1:].copy()

    def as_quaternion(self, *, scalar_first: bool = True) -> np.ndarray:
        """Hamilton quaternion of the same rotation."""
        h = np.array([self.q[0], -self.q[1], -self.q[2], -self.q[3]])
        return h if scalar_first else h[[1, 2, 3, 0]]

    def as_scipy(self):
        """``scipy.spatial.transform.Rotation`` of the same rotation."""
        from scipy.spatial.transform import Rotation

        return Rotation.from_quat(self.as_quaternion(scalar_first=False))

    def as_matrix(self) -> np.ndarray:
        """Rotation matrix ``M`` with ``R x ~R = M x`` for column vectors."""
        w, x, y, z = self.as_quaternion()
        return np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )

    def as_axis_angle(self) -> tuple[np.ndarray, float]:
        """``(axis, angle)`` with ``angle`` in [0, π]; axis ``e3`` for identity."""
        v = -self.q[1:]
        s = float(np.linalg.norm(v))
        angle = 2.0 * float(np.arctan2(s, self.q[0]))
        if s < 1e-300:
            return np.array([0.0, 0.0, 1.0]), 0.0
        return v / s, angle

    @property
    def angle(self) -> float:
        """Rotation angle in radians, in [0, π]."""
        return self.as_axis_angle()[1]

    @property
    def axis(self) -> np.ndarray:
        """Unit rotation axis (the normal of the eq.-30 plane)."""
        return self.as_axis_angle()[0]

    # ------------------------------------------------------------ operations
    def reverse(self) -> Rotor:
        """The reverse ``~R`` (the inverse rotation)."""
        return Rotor(np.array([self.q[0], -self.q[1], -self.q[2], -self.q[3]]))

    __invert__ = reverse
    inv = reverse

    def __mul__(self, other: Rotor) -> Rotor:
        """Composition ``R1 R2``: rotate by ``R2`` first, then ``R1``."""
        if not isinstance(other, Rotor):
            return NotImplemented
        return Rotor(rotor_product(self.q, other.q))

    def apply(self, points) -> np.ndarray:
        """Rotate points: ``R x ~R`` for each row of an (N, 3) array (or one (3,) vector)."""
        x = np.asarray(points, dtype=np.float64)
        if x.shape == (3,):
            return sandwich(self.q, x[None, :])[0]
        return sandwich(self.q, as_points(x, "points", min_points=0))

    __rshift__ = apply

    def angle_to(self, other: Rotor) -> float:
        """Angle (radians) of the rotation ``other ~self``, the geodesic distance."""
        return (other * self.reverse()).angle

    def __repr__(self) -> str:
        q0, qx, qy, qz = self.q
        return f"Rotor({q0:+.6g} {qx:+.6g} e23 {qy:+.6g} e31 {qz:+.6g} e12)"


# ----------------------------------------------------------------- joint spaces
def pair_differences(source, target) -> tuple[np.ndarray, np.ndarray]:
    """``d = x' - x`` and ``s = x' + x`` for paired rows of ``source``/``target``."""
    x = as_points(source, "source", min_points=0)
    xp = as_points(target, "target", min_points=0)
    if x.shape != xp.shape:
        msg = (
            f"Expected `source` and `target` to hold the same number of paired "
            f"points, got {x.shape[0]} and {xp.shape[0]}."
        )
        raise InputError(msg)
    return xp - x, xp + x


def joint_space_coordinates(source, target) -> np.ndarray:
    """Token coordinates of candidate pairs in the four joint spaces.

    Parameters
    ----------
    source, target : (N, 3) array_like
        Row ``i`` of ``source`` is paired with row ``i`` of ``target``
        (the candidate pair ``x ↔ x'``).

    Returns
    -------
    (4, N, 3) ndarray
        ``out[k]`` are the coordinates in the joint space of eq. ``27 + k``:
        ``(dx, sz, sy)``, ``(dy, sz, sx)``, ``(dz, sy, sx)``,
        ``(dx, dy, dz)`` (see :data:`JOINT_SPACE_NAMES`).
    """
    d, s = pair_differences(source, target)
    out = np.empty((4,) + d.shape)
    out[0] = np.stack([d[:, 0], s[:, 2], s[:, 1]], axis=1)
    out[1] = np.stack([d[:, 1], s[:, 2], s[:, 0]], axis=1)
    out[2] = np.stack([d[:, 2], s[:, 1], s[:, 0]], axis=1)
    out[3] = d
    return out


def joint_space_planes(rotor: Rotor, translation) -> np.ndarray:
    """Planes that a rigid motion predicts in the four joint spaces (eqs. 27–30).

    Parameters
    ----------
    rotor : Rotor
        Rotation of the motion ``x' = R x ~R + t``.
    translation : (3,) array_like
        ``t``.

    Returns
    -------
    (4, 4) ndarray
        Row ``k`` is ``(n1, n2, n3, c)``: every true pair's coordinates ``u``
        in joint space ``k`` (see :func:`joint_space_coordinates`) satisfy
        ``n · u + c = 0``.  Rows are not normalised; the paper's equation
        coefficients are returned as they stand.
    """
    t = np.asarray(translation, dtype=np.float64).reshape(-1)
    if t.shape != (3,) or not np.all(np.isfinite(t)):
        raise InputError(f"Expected `translation` to be 3 finite numbers, got {t!r}.")
    p0, px, py, pz = rotor.reverse().q
    tx, ty, tz = t
    return np.array(
        [
            [p0, -py, pz, py * tz - p0 * tx - pz * ty],  # (27)
            [p0, px, -pz, pz * tx - p0 * ty - px * tz],  # (28)
            [p0, -px, py, px * ty - p0 * tz - py * tx],  # (29)
            [px, py, pz, -(px * tx + py * ty + pz * tz)],  # (30)
        ]
    )


# ----------------------------------------------------------------- eq. 41
def eq41(d_i, s_i, d_j, s_j, axis) -> np.ndarray:
    """The geometric constraint ``V × (A × Vs)`` of eq. 41, vectorised.

    For two candidate pairs with difference/sum vectors ``(d_i, s_i)`` and
    ``(d_j, s_j)``, ``V = d_i - d_j`` and ``Vs = s_i - s_j``.  For two pairs
    of one rigid motion with unit rotation axis ``A`` the result is zero.
    Expanded, ``V × (A × Vs) = A (V·Vs) - Vs (V·A)``: it vanishes iff the
    pair distance is preserved (``V·Vs = |Δx'|² - |Δx|² = 0``) and both
    tokens lie on one plane normal to ``A`` (``V·A = 0``).

    Parameters
    ----------
    d_i, s_i, d_j, s_j : (N, 3) or (3,) array_like
        Broadcastable difference and sum vectors.
    axis : (3,) or (N, 3) array_like
        Rotation axis ``A`` (normal of the eq.-30 plane), normalised here.

    Returns
    -------
    (N, 3) ndarray
    """
    V = np.asarray(d_i, dtype=np.float64) - np.asarray(d_j, dtype=np.float64)
    Vs = np.asarray(s_i, dtype=np.float64) - np.asarray(s_j, dtype=np.float64)
    A = np.asarray(axis, dtype=np.float64)
    A = A / np.linalg.norm(A, axis=-1, keepdims=True)
    return np.cross(V, np.cross(A, Vs))


def eq41_residual(d_i, s_i, d_j, s_j, axis, *, normalize: str = "length") -> np.ndarray:
    """Relaxed, scale-aware residual of eq. 41 for noisy data (section 4.1).

    Parameters
    ----------
    normalize : {"length", "angle", "none"}, default: "length"
        How the residual is scaled:

        * ``"length"``: ``|V × (A × Vs)| / |Vs|``, in the data's length unit,
          comparable with the noise level (the pair-distance change and the
          out-of-plane offset ``V·A``, mixed).
        * ``"angle"``: ``|V × (A × Vs)| / (|V| |Vs|)``, scale free, in [0, 1].
        * ``"none"``: ``|V × (A × Vs)|``.

        Pairs with ``|Vs| = 0`` (or ``|V| = 0`` for ``"angle"``) give 0.

    Returns
    -------
    (N,) ndarray
    """
    V = np.asarray(d_i, dtype=np.float64) - np.asarray(d_j, dtype=np.float64)
    Vs = np.asarray(s_i, dtype=np.float64) - np.asarray(s_j, dtype=np.float64)
    r = np.linalg.norm(eq41(d_i, s_i, d_j, s_j, axis), axis=-1)
    if normalize == "none":
        return r
    den = np.linalg.norm(Vs, axis=-1)
    if normalize == "angle":
        den = den * np.linalg.norm(V, axis=-1)
    elif normalize != "length":
        msg = f"Expected `normalize` to be 'length', 'angle' or 'none', got {normalize!r}."
        raise InputError(msg)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(den > 0, r / np.where(den > 0, den, 1.0), 0.0)


def eq41_length_residual(d_i, s_i, d_j, s_j) -> np.ndarray:
    """The length half of eq. 41, ``|V · Vs| / |Vs|``, which needs no axis.

    ``V · Vs = |Δx'|² - |Δx|²`` vanishes when the pair distance is kept
    (Fig. 2 b/e); divided by ``|Vs|`` it is in the data's length unit.
    Pairs with ``|Vs| = 0`` give ``|V · Vs|`` (that is, 0 for ``V = 0``).

    Returns
    -------
    (N,) ndarray
    """
    V = np.asarray(d_i, dtype=np.float64) - np.asarray(d_j, dtype=np.float64)
    Vs = np.asarray(s_i, dtype=np.float64) - np.asarray(s_j, dtype=np.float64)
    nvs = np.linalg.norm(Vs, axis=-1)
    return np.abs(np.einsum("...i,...i->...", V, Vs)) / np.where(nvs > 0, nvs, 1.0)


def rotation_angle_deg(rotation) -> float:
    """Angle of a rotation matrix in degrees (robust near 0 and 180)."""
    r = np.asarray(rotation, dtype=np.float64)
    c = (np.trace(r) - 1.0) / 2.0
    s = 0.5 * np.linalg.norm([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    return float(np.degrees(np.arctan2(s, c)))


def turn_about(axis, angle: float, through) -> tuple[np.ndarray, np.ndarray]:
    """The turn by ``angle`` (radians) about the line along unit ``axis`` through the point ``through``, as
    ``(R, t)`` with ``x -> R x + t``: ``through`` stays where it is."""
    R = Rotor.from_axis_angle(axis, angle).as_matrix()
    c = np.asarray(through, dtype=np.float64)
    return R, c - R @ c
