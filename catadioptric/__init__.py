"""Catadioptric (omnidirectional) images for gatv.

The unified sphere camera model, a sub-pixel corner detector and synthetic
two-view scenes: the front end of the catadioptric correspondence example
of Reyes, Medioni & Bayro (IJCV 2007, end of section 5.1 and Fig. 15),
where the corners of two catadioptric images are lifted to the unit sphere
before tensor voting.
"""

from __future__ import annotations

from catadioptric.camera import UnifiedCamera
from catadioptric.corners import detect_corners, read_image, refine_corners
from catadioptric.matching import SphereMatch, match, sphere_noise
from catadioptric.peeling import SphereMotion
from catadioptric.synthetic import SyntheticViews, synthetic_views

__all__ = [
    "SphereMatch",
    "SphereMotion",
    "SyntheticViews",
    "UnifiedCamera",
    "detect_corners",
    "match",
    "read_image",
    "refine_corners",
    "sphere_noise",
    "synthetic_views",
]
