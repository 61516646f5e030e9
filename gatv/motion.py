"""Rigid motions as results: :class:`RigidMotion` and the least-squares fit.

A rigid motion maps source points onto target points,
``target ≈ source @ rotation.T + translation`` (rows are points), i.e.
``x' = R x ~R + t`` with the rotor ``R`` of :mod:`gatv.ga`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import InputError
from .fitting import fit_rigid
from .ga import rotation_angle_deg
from .models.base import Motion, Rotational, freeze_fields, homogeneous

__all__ = ["RigidMotion", "fit_rigid", "rotation_angle_deg"]


@dataclass(frozen=True, eq=False)
class RigidMotion(Rotational, Motion):
    """A rigid motion with the correspondences that support it.

    Attributes
    ----------
    rotation : (3, 3) ndarray
        Rotation matrix ``M``; ``target ≈ source @ M.T + translation``.
    translation : (3,) ndarray
    correspondences : (K, 2) ndarray of int
        One-to-one ``(source index, target index)`` pairs.
    support : int
        Number of correspondences.
    score : float
        Quality of the motion: the surface saliency of the extracted plane
        (mean λ1−λ2 of its tokens) when tensor voting judged it, else the
        inlier count.
    rms : float
        Root-mean-square residual of the correspondences under the motion.
    info : dict
        Diagnostics (hypotheses tried, timings, ...). Not compared.

    A failed registration is a falsy ``RigidMotion`` (``support == 0``)
    whose ``info["reason"]`` says why.
    """

    model = "rigid"

    rotation: np.ndarray
    translation: np.ndarray
    correspondences: np.ndarray = field(default_factory=lambda: np.empty((0, 2), np.int64))
    score: float = 0.0
    rms: float = float("nan")
    info: dict = field(default_factory=dict)

    def __post_init__(self):
        freeze_fields(self, rotation=(3, 3), translation=(3,))

    @classmethod
    def from_matrix(cls, matrix, correspondences=None, *, score: float = 0.0,
                    rms: float = float("nan"), info: dict | None = None) -> RigidMotion:
        """From a 4×4 homogeneous matrix whose upper-left block is a rotation."""
        T = np.asarray(matrix, dtype=np.float64)
        if T.shape != (4, 4):
            raise InputError(f"Expected `matrix` to have shape (4, 4), got {T.shape}.")
        pairs = np.empty((0, 2), np.int64) if correspondences is None else correspondences
        return cls(T[:3, :3], T[:3, 3], pairs, score, rms, {} if info is None else info)

    # ------------------------------------------------------------- derived
    @property
    def matrix(self) -> np.ndarray:
        """4×4 homogeneous matrix, ``p_target = T @ [p_source, 1]``."""
        return homogeneous(self.rotation, self.translation)

    # ---------------------------------------------------------- operations
    def inverse(self) -> RigidMotion:
        """The motion from target to source, with swapped correspondences."""
        rot = self.rotation.T
        return RigidMotion(
            rotation=rot,
            translation=-rot @ self.translation,
            correspondences=self.correspondences[:, ::-1],
            score=self.score,
            rms=self.rms,
            info=dict(self.info),
        )

    def to_dict(self) -> dict:
        """JSON-friendly dictionary."""
        return {**super().to_dict(), **self.rotation_dict()}

    def __repr__(self) -> str:
        t = np.array2string(self.translation, precision=4, separator=", ")
        return (
            f"RigidMotion(angle={self.angle_deg:.4f} deg, translation={t}, "
            f"support={self.support}, rms={self.rms:.3g})"
        )
