"""The result of a non-rigid registration: :class:`NonRigidMotion`.

A non-rigid motion maps source points onto target points,
``target[j] ≈ warp(source[i])`` for every correspondence ``(i, j)``.  The
warp is a thin-plate-spline interpolation of the matched displacements
(``scipy.interpolate.RBFInterpolator``); each correspondence also carries
the rigid motion fitted on its neighbourhood of matches (the local rigidity
of section 5.1).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import RBFInterpolator

from .._validation import as_points
from .._validation import frozen_array as _frozen
from ..ga import Rotor, rotation_angle_deg
from .multiscale import LocalAffineWarp

__all__ = ["Diagnostics", "NonRigidMotion", "ThinPlateWarp"]

#: Beyond this many correspondences the warp is the moving-least-squares local affine fit
#: of the matches (:class:`gatv.nonrigid.multiscale.LocalAffineWarp`, O(K) memory) instead of
#: the thin-plate interpolation (a dense K × K system).
TPS_MAX_CONTROL = 3000
#: Kernel entries per evaluation block of :class:`ThinPlateWarp` (bounds its temporaries).
_EVAL_ENTRIES = 4_000_000


class ThinPlateWarp:
    """Thin-plate-spline interpolation of displacements at control points.

    ``warp(x) = x + f(x)`` where ``f`` interpolates (``smoothing = 0``) or
    smooths the displacements.  Control points that span fewer than three
    dimensions (a flat source) are handled in their principal subspace; the
    offset of a query point out of that subspace is carried unchanged.
    """

    def __init__(self, points: np.ndarray, displacements: np.ndarray, smoothing=0.0):
        self.points = points
        self.displacements = displacements
        # a scalar, or one value per control point (a weighted fit: smoothing / weight)
        self.smoothing = float(smoothing) if np.ndim(smoothing) == 0 else np.asarray(smoothing, float)
        n = points.shape[0]
        self.center = points.mean(axis=0) if n else np.zeros(3)
        if n == 0:
            self.basis, self.rbf, self.shift = np.eye(3), None, np.zeros(3)
            return
        c = points - self.center
        _, s, vt = np.linalg.svd(c, full_matrices=False)
        scale = s[0] if s.size and s[0] > 0 else 1.0
        rank = int(np.sum(s > 1e-9 * scale)) if s.size else 0
        self.basis = vt[:rank]
        self.shift = displacements.mean(axis=0)
        # a degree-1 polynomial needs rank + 1 affinely independent points
        if rank == 0 or n < rank + 1:
            self.rbf = None
            return
        self.rbf = RBFInterpolator(c @ self.basis.T, displacements, kernel="thin_plate_spline",
                                   smoothing=self.smoothing, degree=1)

    def __call__(self, points) -> np.ndarray:
        p = as_points(points, "points", min_points=0)
        if self.rbf is None:
            return p + self.shift
        if p.shape[0] == 0:
            return p.copy()
        # in blocks: the kernel matrix of a block is (rows, control points)
        rows = max(1, _EVAL_ENTRIES // max(1, self.points.shape[0]))
        out = np.empty_like(p)
        for s in range(0, p.shape[0], rows):
            q = p[s:s + rows]
            out[s:s + rows] = q + self.rbf((q - self.center) @ self.basis.T)
        return out


@dataclass(frozen=True, eq=False)
class Diagnostics:
    """What tensor voting and the local eq.-41 test saw (for Figs. 13–14).

    Attributes
    ----------
    structure : str
        ``"surface"`` (λ1 − λ2 decided) or ``"curve"`` (λ2 − λ3 decided): the
        kind of structure the true tokens formed in the joint space.
    sigma : float
        Tensor-voting scale of the first pass.
    n_candidates : int
        Candidate pairs (tokens) voted on.
    pairs : (M, 2) ndarray of int
        Candidate pairs of the tokens that survived voting.
    tokens : (M, 3) ndarray of float
        Their ``{dx, dy, dz}`` coordinates, ``target[j] − source[i]``.
    normals : (M, 3) ndarray of float
        Their normals after the last pass (surface normal, the local
        rotation axis; for curves the ball pass's ``e1``).
    saliency : (M,) ndarray of float
        Their λ1 − λ2 (surfaces) or λ2 − λ3 (curves).
    verification : (M, 2) ndarray of int
        Row ``m`` is ``(m, n)``: surviving token ``m`` was checked by eq. 41
        against its closest active neighbour ``n`` (−1: none available).
    residual : (M,) ndarray of float
        Relaxed eq.-41 residual of that check, over its tolerance (≤ 1 passes).
    verified : (M,) ndarray of bool
        Tokens that passed.
    seeds : (S, 2) ndarray of int
        One-to-one verified pairs the warp started from.
    """

    structure: str
    sigma: float
    n_candidates: int
    pairs: np.ndarray
    tokens: np.ndarray
    normals: np.ndarray
    saliency: np.ndarray
    verification: np.ndarray
    residual: np.ndarray
    verified: np.ndarray
    seeds: np.ndarray

    def __post_init__(self):
        for name in ("tokens", "normals", "saliency", "residual"):
            object.__setattr__(self, name, _frozen(getattr(self, name)))
        for name in ("pairs", "verification", "seeds"):
            object.__setattr__(self, name, _frozen(getattr(self, name), np.int64))
        object.__setattr__(self, "verified", _frozen(self.verified, bool))


@dataclass(frozen=True, eq=False)
class NonRigidMotion:
    """A locally rigid, globally non-rigid motion with its correspondences.

    Attributes
    ----------
    correspondences : (K, 2) ndarray of int
        One-to-one ``(source index, target index)`` pairs, sorted by source
        index.
    source_points : (K, 3) ndarray of float
        ``source[i]`` of each correspondence (the warp's control points).
    target_points : (K, 3) ndarray of float
        ``target[j]`` of each correspondence.
    rotations : (K, 3, 3) ndarray of float
        Local rigid motion of each correspondence, fitted (Kabsch/Horn) on
        its nearest matched neighbours: ``target ≈ source @ R.T + t`` there.
    translations : (K, 3) ndarray of float
    smoothing : float
        Thin-plate smoothing of :meth:`warp` (0: exact at the matches).
        Beyond ``TPS_MAX_CONTROL`` correspondences the warp is instead the
        moving-least-squares affine fit of the nearest matches (smooth, not
        exact at them).
    diagnostics : Diagnostics or None
    info : dict
        Timings, options, and ``reason`` for a failure. Not compared.

    A failed registration is falsy (no correspondences); ``info["reason"]``
    says why and :meth:`warp` is the identity.
    """

    correspondences: np.ndarray
    source_points: np.ndarray
    target_points: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    smoothing: float = 0.0
    diagnostics: Diagnostics | None = field(default=None, repr=False)
    info: dict = field(default_factory=dict, repr=False)

    def __post_init__(self):
        c = np.asarray(self.correspondences, dtype=np.int64).reshape(-1, 2)
        k = c.shape[0]
        object.__setattr__(self, "correspondences", _frozen(c, np.int64))
        for name, shape in (("source_points", (k, 3)), ("target_points", (k, 3)),
                            ("rotations", (k, 3, 3)), ("translations", (k, 3))):
            a = np.asarray(getattr(self, name), dtype=np.float64).reshape(shape)
            object.__setattr__(self, name, _frozen(a))
        d = self.target_points - self.source_points
        if k > TPS_MAX_CONTROL:
            warp = LocalAffineWarp(self.source_points, d)
        else:
            warp = ThinPlateWarp(self.source_points, d, self.smoothing)
        object.__setattr__(self, "_warp", warp)

    # ------------------------------------------------------------- derived
    @property
    def support(self) -> int:
        return int(self.correspondences.shape[0])

    def __bool__(self) -> bool:
        return self.support > 0

    @property
    def displacements(self) -> np.ndarray:
        """(K, 3) matched displacements ``target_points − source_points``."""
        return self.target_points - self.source_points

    @property
    def rotors(self) -> np.ndarray:
        """(K, 4) local rotors ``(q0, qx, qy, qz)`` (see :mod:`gatv.ga`)."""
        if self.support == 0:
            return np.empty((0, 4))
        return np.stack([Rotor.from_matrix(r).q for r in self.rotations])

    @property
    def local_angles_deg(self) -> np.ndarray:
        """(K,) rotation angle of each local rigid motion, degrees."""
        return np.array([rotation_angle_deg(r) for r in self.rotations])

    # ---------------------------------------------------------- operations
    def warp(self, points) -> np.ndarray:
        """Move source points with the thin-plate interpolation of the matches.

        Parameters
        ----------
        points : (N, 3) array_like

        Returns
        -------
        (N, 3) ndarray
            Exact at the matched source points when ``smoothing == 0``.
        """
        return self._warp(points)

    transform = warp

    def to_dict(self) -> dict:
        """JSON-friendly dictionary."""
        return {
            "model": "nonrigid",
            "correspondences": self.correspondences.tolist(),
            "support": self.support,
            "rotors": self.rotors.tolist(),
            "translations": self.translations.tolist(),
            "smoothing": self.smoothing,
            "structure": self.diagnostics.structure if self.diagnostics is not None else None,
        }

    def __repr__(self) -> str:
        return f"NonRigidMotion(support={self.support}, smoothing={self.smoothing:.3g})"
