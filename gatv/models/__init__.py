"""Motion models behind one seam (:class:`MotionModel`).

>>> from gatv.models import get_model
>>> get_model("rigid").name
'rigid'

A model defined elsewhere (a test, a user's package) joins the registry with
:func:`register_model`; ``model=`` arguments then accept its name.
"""

from __future__ import annotations

import importlib

from ..errors import InputError
from .base import (
    DEFAULT_POLICY,
    Motion,
    MotionModel,
    SearchPolicy,
    apply_matrix,
    homogeneous,
    split_matrix,
)

__all__ = ["DEFAULT_POLICY", "MODEL_NAMES", "Motion", "MotionModel", "SearchPolicy", "apply_matrix",
           "get_model", "homogeneous", "model_names", "register_model", "split_matrix"]

#: Names of the built-in models and the modules that define them (imported
#: on first use: their kernels compile with numba).
_MODULES = {"rigid": "rigid", "similarity": "similarity", "affine2d": "affine2d"}
#: Names accepted by ``model=`` out of the box.
MODEL_NAMES = tuple(_MODULES)
#: Models registered by :func:`register_model`, by name.
_REGISTERED: dict[str, MotionModel] = {}


def model_names() -> tuple[str, ...]:
    """Every name ``model=`` accepts now: :data:`MODEL_NAMES`, then those :func:`register_model` added."""
    return MODEL_NAMES + tuple(n for n in _REGISTERED if n not in _MODULES)


def register_model(model: MotionModel, name: str | None = None) -> MotionModel:
    """Make ``model`` known by ``name`` (default ``model.name``) to every ``model=`` argument.

    ``model`` follows :class:`MotionModel` (its ``search_policy()`` may
    return ``SearchPolicy()``, the defaults).  A built-in name is refused;
    registering a name again replaces the earlier model.  Returns ``model``.

    Raises
    ------
    InputError
        ``model`` lacks a member of the protocol, or ``name`` is a built-in
        model's.
    """
    if not isinstance(model, MotionModel):
        missing = [m for m in _protocol_members() if not hasattr(model, m)]
        raise InputError(f"Expected `model` to follow gatv.models.MotionModel; it lacks {', '.join(missing)}.")
    key = str(model.name if name is None else name).lower()
    if key in _MODULES:
        raise InputError(f"The name {key!r} is a built-in model's; register {model!r} under another name.")
    _REGISTERED[key] = model
    return model


def _protocol_members() -> list[str]:
    return sorted({m for m in dir(MotionModel) if not m.startswith("_")}
                  | set(getattr(MotionModel, "__annotations__", {})))


def get_model(model="rigid", *, name: str = "model") -> MotionModel:
    """The motion model for a name (or the model object itself).

    Raises
    ------
    InputError
        Unknown name; the message lists the models.
    """
    if isinstance(model, str):
        key = model.lower()
        if key in _REGISTERED:
            return _REGISTERED[key]
        if key not in _MODULES:
            msg = (f"Unknown `{name}` {model!r}; expected one of "
                   f"{', '.join(repr(m) for m in model_names())}.")
            raise InputError(msg)
        return importlib.import_module(f"{__name__}.{_MODULES[key]}").MODEL
    if isinstance(model, MotionModel):
        return model
    msg = (f"Expected `{name}` to be one of {', '.join(repr(m) for m in model_names())} or a "
           f"MotionModel, got {model!r}.")
    raise InputError(msg)
