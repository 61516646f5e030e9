"""gatv: correspondences and motions between 3D point sets with Geometric
Algebra + Tensor Voting (Reyes, Medioni & Bayro, IJCV 75(3), 2007).

Main entry points
-----------------
register
    Rigid registration with no initial guess (Algorithm 1, sections 2–3).
register_scans
    The same for real, differently sampled range scans (section 4.1).
gatv.motions.segment
    Several motions (section 5), of any model.
gatv.models
    The motion models behind one seam (rigid, similarity, affine2d).
gatv.stages
    The named stages of the pipeline.
Rotor
    Rotors of G(3,0,0) (section 2).
gatv.voting
    Sparse 3D tensor voting (section 3).
"""

from __future__ import annotations

import os

# Numba's parallel kernels run on OpenMP (libgomp), whose idle threads spin
# for a while before sleeping.  On a busy machine the spinning threads take
# the cores from the working ones: a batch of Table-2 calls took 3-5x longer
# beside one other 2-thread job, and no less time on an idle machine with
# passive waiting.  Set before numba starts its threads; a user's own setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from .errors import InputError
from .ga import Rotor
from .models import Motion, get_model
from .motion import RigidMotion, fit_rigid

__version__ = "0.1.0"

__all__ = [
    "InputError",
    "Motion",
    "RigidMotion",
    "Rotor",
    "__version__",
    "fit_rigid",
    "get_model",
    "register",
    "register_scans",
]


def __getattr__(name):
    # Heavy modules (numba kernels) load on first use.
    if name == "register":
        from .registration import register

        return register
    if name == "register_scans":
        from .scans import register_scans

        return register_scans
    raise AttributeError(f"module 'gatv' has no attribute {name!r}")
