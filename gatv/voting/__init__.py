"""Sparse tensor voting in 3D (Reyes, Medioni & Bayro, IJCV 2007, section 3).

>>> from gatv.voting import vote, extract_surfaces, default_sigma
"""

from __future__ import annotations

from gatv.voting._fields import RADIUS_FACTOR, ball_vote, stick_vote
from gatv.voting.api import (
    SurfaceResult,
    TensorVotes,
    chance_surfaceness,
    default_sigma,
    extract_surfaces,
    vote,
    voting_radius,
)

__all__ = [
    "vote",
    "extract_surfaces",
    "default_sigma",
    "chance_surfaceness",
    "voting_radius",
    "TensorVotes",
    "SurfaceResult",
    "stick_vote",
    "ball_vote",
    "RADIUS_FACTOR",
]
