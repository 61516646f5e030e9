"""Multiple overlapping rigid motions (Reyes, Medioni & Bayro 2007, section 5).

:func:`segment` finds every rigid motion between two point sets, K
unknown, and labels each point with its motion, choosing its pipeline from
the data as :func:`gatv.register` does: exact or noisy point sets
(:func:`segment_points`, the graph grouping of section 5, or :func:`peel`
with the noise-aware search) or real scans (:func:`segment_scans`).  Models
other than rigid are peeled one at a time by :func:`peel`;
:func:`ransac_segment` is the sequential-RANSAC baseline;
:func:`multi_motion_scene`, :func:`fig12_scene` and :func:`scan_scene`
build test scenes with known motions.  :func:`instances` finds every copy
of a model in a scene, and :func:`track` every copy in each frame of a
sequence, with identities kept by the closest pose (section 4.1, Fig. 9).
"""

from __future__ import annotations

from .instance_search import Instances, instances
from .peeling import peel
from .pipelines import segment
from .ransac import ransac_segment
from .result import Segmentation
from .scans import segment_scans
from .scenes import MotionScene, ScanScene, fig12_scene, multi_motion_scene, scan_scene
from .segmentation import joint_space_residuals, segment_points
from .tracking import Track, track

__all__ = [
    "Instances",
    "MotionScene",
    "ScanScene",
    "Segmentation",
    "Track",
    "fig12_scene",
    "instances",
    "joint_space_residuals",
    "multi_motion_scene",
    "peel",
    "ransac_segment",
    "scan_scene",
    "segment",
    "segment_points",
    "segment_scans",
    "track",
]
