"""Motion models behind one seam (:class:`MotionModel`).

>>> from gatv.models import get_model
>>> get_model("rigid").name
'rigid'
"""

from __future__ import annotations

from ..errors import InputError
from .base import Motion, MotionModel, apply_matrix, homogeneous, split_matrix

__all__ = ["Motion", "MotionModel", "get_model", "MODEL_NAMES", "homogeneous", "split_matrix",
           "apply_matrix"]

#: Names accepted by ``model=`` and the modules that define them.
_MODULES = {"rigid": "rigid", "similarity": "similarity", "affine2d": "affine2d"}
MODEL_NAMES = tuple(_MODULES)


def get_model(model="rigid", *, name: str = "model") -> MotionModel:
    """The motion model for a name (or the model object itself).

    Raises
    ------
    InputError
        Unknown name; the message lists the models.
    """
    if isinstance(model, str):
        key = model.lower()
        if key not in _MODULES:
            msg = f"Unknown `{name}` {model!r}; expected one of {', '.join(repr(m) for m in MODEL_NAMES)}."
            raise InputError(msg)
        import importlib

        module = importlib.import_module(f"{__name__}.{_MODULES[key]}")
        return module.MODEL
    if isinstance(model, MotionModel):
        return model
    msg = (f"Expected `{name}` to be one of {', '.join(repr(m) for m in MODEL_NAMES)} or a "
           f"MotionModel, got {model!r}.")
    raise InputError(msg)
