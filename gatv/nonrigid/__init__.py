"""Non-rigid registration: the local-constraint mode of section 5.1.

>>> from gatv.nonrigid import register, segment, NonRigidMotion
>>> from gatv.nonrigid import deformations

See :mod:`gatv.nonrigid.registration` for the algorithm,
:mod:`gatv.nonrigid.multiscale` for the multi-resolution path (10⁴–10⁵
points), :mod:`gatv.nonrigid.segment` for several non-rigid motions,
:mod:`gatv.nonrigid.parts` for articulated motions (seeds in every part,
near-rigid parts and their joints in ``info["parts"]``), and
:mod:`gatv.nonrigid.deformations` for the generators used by the tests,
benchmarks and gallery.
"""

from __future__ import annotations

from . import deformations
from .motion import Diagnostics, NonRigidMotion
from .registration import register
from .segment import NonRigidSegmentation, segment

__all__ = [
           "Diagnostics",
           "NonRigidMotion",
           "NonRigidSegmentation",
           "deformations",
           "register",
           "segment",
]
