"""Non-rigid registration: the local-constraint mode of section 5.1.

>>> from gatv.nonrigid import register, NonRigidMotion
>>> from gatv.nonrigid import deformations

See :mod:`gatv.nonrigid.registration` for the algorithm and
:mod:`gatv.nonrigid.deformations` for the generators used by the tests,
benchmarks and gallery.
"""

from __future__ import annotations

from . import deformations
from .motion import Diagnostics, NonRigidMotion
from .registration import register

__all__ = ["register", "NonRigidMotion", "Diagnostics", "deformations"]
