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

from .errors import InputError
from .ga import Rotor
from .models import Motion, get_model
from .motion import RigidMotion, fit_rigid

__version__ = "0.1.0"

__all__ = ["Rotor", "Motion", "RigidMotion", "InputError", "get_model", "fit_rigid", "register",
           "register_scans", "__version__"]


def __getattr__(name):
    # Heavy modules (numba kernels) load on first use.
    if name == "register":
        from .registration import register

        return register
    if name == "register_scans":
        from .scans import register_scans

        return register_scans
    raise AttributeError(f"module 'gatv' has no attribute {name!r}")
