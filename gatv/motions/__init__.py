"""Multiple overlapping rigid motions (Reyes, Medioni & Bayro 2007, section 5).

:func:`segment` finds every rigid motion between two point sets and
labels each point with its motion (any model: ``model=``; models other
than rigid are peeled one at a time by :func:`peel`); :func:`ransac_segment` is the
sequential-RANSAC baseline; :func:`multi_motion_scene` and
:func:`fig12_scene` build test scenes with known motions.
"""

from __future__ import annotations

from .peeling import peel
from .ransac import ransac_segment
from .scenes import MotionScene, fig12_scene, multi_motion_scene
from .segmentation import Segmentation, joint_space_residuals, segment

__all__ = [
    "Segmentation",
    "segment",
    "peel",
    "joint_space_residuals",
    "ransac_segment",
    "MotionScene",
    "multi_motion_scene",
    "fig12_scene",
]
