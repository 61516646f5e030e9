"""Voting fields in 3D: the stick vote of eq. 44 and the ball field of eqs. 46–48.

Conventions (used by every kernel, the reference and the tests)
-----------------------------------------------------------------
Voter ``p`` with unit normal ``n``, votee ``x``, offset ``v = x - p``,
``l = |v|`` and ``θ`` the angle between ``v`` and the voter's tangent plane,
so ``sin θ = |n·v̂|``.  The stick vote is

    S(n, v) = DF · m mᵀ,     m = n − 2 (n·v̂) v̂,

``m`` being the normal at ``x`` of the osculating circle through ``p`` and
``x`` tangent to the voter's plane (the reflection of ``n`` in the plane
orthogonal to ``v̂``; its sign is irrelevant for a 2nd-order tensor), with the
decay of eq. 44 written in dimensionless form

    DF = exp(−(s/σ)² − γ (σκ)²),   s = θ l / sin θ,   κ = 2 sin θ / max(l, σ/σ_ref),

and no vote when ``θ > 45°``.

Why this ``c``.  Eq. 44 reads ``exp(−(s² + cκ²)/σ²)`` with the classic
``c = −16 ln(0.1)(σ − 1)/π²``, which only makes sense for σ measured in
pixels (``c`` has units of length⁴ but grows linearly with σ).  Writing
``c = γσ⁴`` makes the exponent ``(s/σ)² + γ(σκ)²``, invariant to the unit of
the data.  ``γ = c(σ_ref)/σ_ref⁴`` reproduces the classic field exactly at the
reference scale ``σ_ref = 5`` pixels (a small scale, typical of sparse data),
i.e. when one "pixel" is ``σ/σ_ref``: ``γ = 16 ln 10 (σ_ref − 1)/(π² σ_ref⁴)
≈ 0.0239``.  The classic field lived on a pixel grid where two distinct tokens
are never closer than one pixel; we keep that by evaluating the curvature
with ``l`` no smaller than one reference pixel, ``l_min = σ/σ_ref``.  Without
this floor ``γ(σκ)²`` diverges as ``l → 0`` for any ``θ > 0`` and the ball
field would vanish at the voter, so coincident tokens (the pure-translation
cluster of section 3.4) would not support each other.

Voting radius.  Votes are cast only to tokens with ``l < r = 2σ``
(:data:`RADIUS_FACTOR`), where the decay is at most ``e⁻⁴ ≈ 0.018``.

Ball field.  Averaging ``S(n, v)`` over unit normals ``n`` uniform on the
sphere (eqs. 46–48 integrate the stick field over all orientations) gives, by
symmetry, ``a(l) v̂v̂ᵀ + b(l)(I − v̂v̂ᵀ)``.  With ``u = n·v̂`` (uniform on
[−1, 1]), ``(m·v̂)² = u²`` and the rest of ``m m ᵀ`` has trace ``1 − u²``
spread evenly over the two directions orthogonal to ``v̂``::

    a(l) = ∫₀^{1/√2} DF(l, u) u² du,     b(l) = ∫₀^{1/√2} DF(l, u) (1 − u²)/2 du.

These are computed once by Gauss–Legendre quadrature into a table over
``q = (l/σ)² ∈ [0, 4]`` (linear interpolation) and divided by
``Z = (a(0) + 2 b(0))/3`` so that the ball vote between coincident tokens
(``l = 0``, where ``v̂`` is undefined and the vote is the isotropic average)
is exactly the identity — the unit ball tensor of section 3.3.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "RADIUS_FACTOR",
    "SIGMA_REF",
    "GAMMA",
    "BALL_TABLE_SIZE",
    "stick_vote",
    "decay",
    "ball_coefficients",
    "ball_table",
    "ball_radial",
]

#: Voting radius in units of σ: votes reach tokens with ``l < RADIUS_FACTOR·σ``.
RADIUS_FACTOR = 2.0
#: Reference scale (pixels) at which the classic constant ``c`` is reproduced.
SIGMA_REF = 5.0
#: Dimensionless curvature weight: ``c = GAMMA · σ⁴``.
GAMMA = 16.0 * math.log(10.0) * (SIGMA_REF - 1.0) / (math.pi**2 * SIGMA_REF**4)
#: Number of intervals of the ball table over ``q = (l/σ)² ∈ [0, RADIUS_FACTOR²]``.
BALL_TABLE_SIZE = 4096
#: sin²(45°): votes with ``sin² θ`` above this are not cast.
MAX_SIN2 = 0.5


def _arcsin_ratio2(t):
    """``(θ / sin θ)²`` as a function of ``t = sin² θ`` (→ 1 as t → 0)."""
    t = np.asarray(t, dtype=np.float64)
    x = np.sqrt(t)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.where(x > 0, np.arcsin(x) / np.where(x > 0, x, 1.0), 1.0)
    return r * r


def decay(rho2, sin2):
    """Eq. 44 decay from ``ρ² = (l/σ)²`` and ``sin² θ`` (dimensionless form).

    Returns 0 where ``sin² θ > 1/2`` (θ > 45°).
    """
    rho2 = np.asarray(rho2, dtype=np.float64)
    sin2 = np.asarray(sin2, dtype=np.float64)
    s2 = rho2 * _arcsin_ratio2(sin2)  # (s/σ)²
    lmin2 = 1.0 / SIGMA_REF**2
    k2 = 4.0 * sin2 / np.maximum(rho2, lmin2)  # (σκ)² = 4 sin²θ σ²/l_eff²
    out = np.exp(-s2 - GAMMA * k2)
    return np.where(sin2 > MAX_SIN2, 0.0, out)


def stick_vote(normal, offset, sigma: float) -> np.ndarray:
    """Stick vote tensor (eq. 44) cast by a voter with ``normal`` on a votee at ``offset``.

    Parameters
    ----------
    normal : (..., 3) array_like of float
        Voter normals (normalised here).
    offset : (..., 3) array_like of float
        ``x − p``, votee minus voter (broadcast against ``normal``).
    sigma : float
        Scale σ, in the units of ``offset``.

    Returns
    -------
    (..., 3, 3) ndarray of float
        ``DF · m mᵀ`` with ``m = n − 2(n·v̂)v̂``; ``n nᵀ`` at ``l = 0``; zero for
        θ > 45°.  No voting-radius cut-off is applied here.

    Examples
    --------
    >>> import numpy as np
    >>> t = stick_vote([0, 0, 1], [1.0, 0, 0], sigma=1.0)
    >>> bool(np.isclose(t[2, 2], np.exp(-1.0)))
    True
    """
    n = np.asarray(normal, dtype=np.float64)
    v = np.asarray(offset, dtype=np.float64)
    n, v = np.broadcast_arrays(n, v)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    l2 = np.einsum("...i,...i->...", v, v)
    u = np.einsum("...i,...i->...", n, v)
    safe = np.where(l2 > 0, l2, 1.0)
    sin2 = np.where(l2 > 0, u * u / safe, 0.0)
    df = np.where(l2 > 0, decay(l2 / sigma**2, sin2), 1.0)
    m = n - (2.0 * np.where(l2 > 0, u / safe, 0.0))[..., None] * v
    return df[..., None, None] * m[..., :, None] * m[..., None, :]


def ball_coefficients(rho, n_nodes: int = 128) -> tuple[np.ndarray, np.ndarray]:
    """Unnormalised radial functions ``a(ρ), b(ρ)`` of the ball field by quadrature.

    The average over unit normals uniform on the sphere of :func:`stick_vote`
    at offset ``v`` with ``|v| = ρσ`` equals ``a v̂v̂ᵀ + b (I − v̂v̂ᵀ)``.
    """
    rho = np.atleast_1d(np.asarray(rho, dtype=np.float64))
    x, w = np.polynomial.legendre.leggauss(n_nodes)
    half = 0.5 * math.sqrt(0.5)
    u = half * (x + 1.0)  # nodes on [0, 1/√2]
    w = half * w
    df = decay(rho[:, None] ** 2, (u * u)[None, :])
    a = df @ (w * u * u)
    b = df @ (w * 0.5 * (1.0 - u * u))
    return a, b


_TABLE: tuple[np.ndarray, np.ndarray, float] | None = None


def ball_table() -> tuple[np.ndarray, np.ndarray, float]:
    """Normalised ball-field lookup table ``(A, B, Z)`` over ``q = (l/σ)²``.

    ``A[k], B[k]`` sample ``a/Z, b/Z`` at ``q = k · RADIUS_FACTOR² / BALL_TABLE_SIZE``
    for ``k = 0 … BALL_TABLE_SIZE`` (plus one guard entry); linear
    interpolation in ``q`` between samples.  Built once per process.
    """
    global _TABLE
    if _TABLE is None:
        q = np.linspace(0.0, RADIUS_FACTOR**2, BALL_TABLE_SIZE + 1)
        a, b = ball_coefficients(np.sqrt(q))
        z = (a[0] + 2.0 * b[0]) / 3.0
        A = np.append(a / z, a[-1] / z)
        B = np.append(b / z, b[-1] / z)
        A.setflags(write=False)
        B.setflags(write=False)
        _TABLE = (A, B, float(z))
    return _TABLE


_TABLE4: np.ndarray | None = None


def ball_table4() -> np.ndarray:
    """The ball table interleaved for the kernels: ``(BALL_TABLE_SIZE + 1, 4)``.

    Row ``k`` is ``(A[k], A[k+1] − A[k], B[k], B[k+1] − B[k])`` (the last row
    uses the guard entry), so one lookup touches one cache line and the
    interpolant ``A[k] + (A[k+1] − A[k])·f`` is reproduced bit for bit.
    """
    global _TABLE4
    if _TABLE4 is None:
        A, B, _ = ball_table()
        t = np.empty((A.size - 1, 4))
        t[:, 0] = A[:-1]
        t[:, 1] = A[1:] - A[:-1]
        t[:, 2] = B[:-1]
        t[:, 3] = B[1:] - B[:-1]
        t.setflags(write=False)
        _TABLE4 = t
    return _TABLE4


def ball_radial(q) -> tuple[np.ndarray, np.ndarray]:
    """``(a, b)``: the normalised ball field's radial functions at ``q = (l/σ)² ≥ 0`` (numpy).

    Read off :func:`ball_table` linearly in ``q``, as ``A[k] + (A[k+1] − A[k])·f``
    (the kernels' interpolant, :func:`ball_table4`); beyond the voting radius,
    the last sample's.
    """
    A, B, _ = ball_table()
    x = np.minimum(np.asarray(q, dtype=np.float64) * (BALL_TABLE_SIZE / RADIUS_FACTOR**2), BALL_TABLE_SIZE)
    k = np.minimum(x.astype(np.int64), BALL_TABLE_SIZE - 1)
    f = x - k
    return A[k] + (A[k + 1] - A[k]) * f, B[k] + (B[k + 1] - B[k]) * f


def ball_vote(offset, sigma: float) -> np.ndarray:
    """Normalised ball vote tensor at ``offset`` from the lookup table (numpy).

    Identity at ``l = 0``; zero at and beyond the voting radius.
    """
    v = np.asarray(offset, dtype=np.float64)
    l2 = np.einsum("...i,...i->...", v, v)
    q = l2 / sigma**2
    a, b = ball_radial(q)
    inside = q < RADIUS_FACTOR**2
    safe = np.where(l2 > 0, l2, 1.0)
    c = np.where(l2 > 0, (a - b) / safe, 0.0)
    eye = np.eye(3)
    t = b[..., None, None] * eye + c[..., None, None] * v[..., :, None] * v[..., None, :]
    t = np.where((l2 > 0)[..., None, None], t, eye)
    return np.where(inside[..., None, None], t, 0.0)
