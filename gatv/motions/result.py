"""The result of every multi-motion search: :class:`Segmentation`.

Its own module, below the searches that build it (the graph grouping of
:mod:`gatv.motions.segmentation`, :func:`gatv.motions.peel`,
:func:`gatv.motions.segment_scans`, the RANSAC baseline), so that none of
them imports another for it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .._validation import frozen_array as _frozen
from ..motion import RigidMotion

__all__ = ["Segmentation"]


@dataclass(frozen=True, eq=False)
class Segmentation:
    """Rigid motions found between two point sets, and who belongs to which.

    Attributes
    ----------
    motions : tuple of RigidMotion
        Largest support first; each with its own one-to-one
        ``correspondences``.  No source or target point is in two motions.
    source_labels, target_labels : (N,) ndarray of int
        Index into ``motions`` of each point's motion, ``-1`` when no
        motion explains it.
    tokens : (T, 2) ndarray of int
        Candidate pairs ``(source, target)`` that voted: every pair within
        the residual gate of a hypothesis, multiple matches included.
    token_labels : (T,) ndarray of int
        Motion (plane) each token was given to, ``-1`` for none.  A
        motion's ``correspondences`` are a one-to-one subset of its tokens.
    info : dict
        Diagnostics: tolerance, support threshold, trials, hypotheses,
        surfaces and which of them were split, timings.  Not compared.
    """

    motions: tuple
    source_labels: np.ndarray
    target_labels: np.ndarray
    tokens: np.ndarray
    token_labels: np.ndarray
    info: dict = field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "motions", tuple(self.motions))
        for name in ("source_labels", "target_labels", "token_labels"):
            object.__setattr__(self, name, _frozen(getattr(self, name), np.int64))
        object.__setattr__(self, "tokens", _frozen(np.asarray(self.tokens).reshape(-1, 2), np.int64))

    def __len__(self) -> int:
        return len(self.motions)

    def __bool__(self) -> bool:
        return len(self.motions) > 0

    def __iter__(self):
        return iter(self.motions)

    def __getitem__(self, k) -> RigidMotion:
        return self.motions[k]

    def to_dict(self) -> dict:
        """JSON-friendly dictionary."""
        return {
            "n_motions": len(self.motions),
            "motions": [m.to_dict() for m in self.motions],
            "source_labels": self.source_labels.tolist(),
            "target_labels": self.target_labels.tolist(),
            "tokens": self.tokens.tolist(),
            "token_labels": self.token_labels.tolist(),
        }

    def __repr__(self) -> str:
        inner = ", ".join((f"{m.angle_deg:.2f} deg/{m.support}" if hasattr(m, "angle_deg")
                           else f"{m.model}/{m.support}") for m in self.motions)
        return f"Segmentation({len(self.motions)} motions: [{inner}])"
