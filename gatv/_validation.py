"""Input validation shared by every public entry point.

Each validator takes the argument's *name* so that error messages can say
which argument is wrong and how to fix it, before any numba code runs.
"""

from __future__ import annotations

import numbers
import os

import numpy as np

from .errors import InputError

__all__ = [
    "DEFAULT_MEMORY_BUDGET",
    "as_points",
    "as_rng",
    "as_vectors",
    "check_finite_array",
    "check_fraction",
    "check_int",
    "check_memory",
    "check_positive",
    "check_progress",
    "coordinates",
    "frozen_array",
    "memory_budget_limit",
    "seed_int",
]

#: Default budget (bytes) for the largest array one call may allocate.
#: Override per call with ``memory_budget=`` or globally with the environment
#: variable ``GATV_MEMORY_BUDGET`` (bytes, e.g. ``8e9``).
DEFAULT_MEMORY_BUDGET = 4 * 1024**3


def frozen_array(a, dtype=np.float64) -> np.ndarray:
    """A read-only copy of ``a`` as ``dtype``: the arrays of frozen result dataclasses."""
    a = np.array(a, dtype=dtype)
    a.setflags(write=False)
    return a


def memory_budget_limit(budget: float | None) -> float:
    """The memory budget in bytes: ``budget``, else ``GATV_MEMORY_BUDGET``, else the default."""
    import os

    if budget is not None:
        return float(budget)
    env = os.environ.get("GATV_MEMORY_BUDGET")
    if env:
        try:
            return float(env)
        except ValueError as exc:  # pragma: no cover - defensive
            msg = f"GATV_MEMORY_BUDGET must be a number of bytes, got {env!r}."
            raise InputError(msg) from exc
    return float(DEFAULT_MEMORY_BUDGET)


def check_memory(nbytes: float, what: str, budget: float | None = None) -> None:
    """Raise ``MemoryError``-like ``ValueError`` when ``nbytes`` exceeds the budget.

    Parameters
    ----------
    nbytes : float
        Bytes the operation would allocate.
    what : str
        Human description of the allocation (e.g. "1.2e8 candidate pairs").
    budget : float, optional
        Budget in bytes; default :data:`DEFAULT_MEMORY_BUDGET` or the
        ``GATV_MEMORY_BUDGET`` environment variable.
    """
    limit = memory_budget_limit(budget)
    if nbytes > limit:
        msg = (
            f"{what} would need about {nbytes / 1024**3:.2f} GiB, over the memory "
            f"budget of {limit / 1024**3:.2f} GiB. Reduce the input (downsample, "
            "prune candidate pairs) or raise the budget with `memory_budget=` "
            "or the GATV_MEMORY_BUDGET environment variable (bytes)."
        )
        raise InputError(msg)


def coordinates(obj):
    """The coordinates held by a point container, or ``obj`` itself.

    Duck-typed, so that neither Open3D nor trimesh is imported:

    * ``.points`` — PyVista meshes and point clouds, Open3D
      ``geometry.PointCloud`` (a ``Vector3dVector``);
    * ``.vertices`` — trimesh ``Trimesh`` and ``PointCloud``, Open3D
      ``geometry.TriangleMesh``;
    * ``.point.positions`` — Open3D's tensor ``t.geometry.PointCloud``
      (its ``.numpy()``).

    Arrays and other objects are returned unchanged.
    """
    if isinstance(obj, np.ndarray):
        return obj
    for attr in ("points", "vertices"):
        if hasattr(obj, attr):
            return getattr(obj, attr)
    point = getattr(obj, "point", None)
    if point is not None:
        try:
            positions = point.positions
        except (AttributeError, KeyError, RuntimeError):
            return obj
        return positions.numpy() if hasattr(positions, "numpy") else positions
    return obj


def file_hint(obj, dim: int) -> str | None:
    """The advice for a file path given where ``dim``-dimensional points were expected, else None."""
    if not isinstance(obj, (str, bytes, os.PathLike)):
        return None
    if dim == 2:
        return ("read an image's corners first with `catadioptric.corners.detect_corners("
                "catadioptric.read_image(path))`")
    return "read the file first with `gatv.io.read_points(path)`"


def shape_hint(shape: tuple, dim: int) -> str:
    """Advice for an array of the wrong shape: transpose it when it looks transposed."""
    if len(shape) == 2 and shape[0] == dim and shape[1] != dim:
        return f"; it looks transposed: pass its transpose `.T`, of shape ({shape[1]}, {dim})"
    return ""


def as_points(obj, name: str, *, min_points: int = 1, dim: int = 3) -> np.ndarray:
    """Return ``obj`` as a C-contiguous, writable float64 ``(N, dim)`` array.

    Accepts array-likes and point containers (see :func:`coordinates`):
    PyVista meshes and point clouds, Open3D ``PointCloud`` (legacy and
    tensor) and ``TriangleMesh``, trimesh ``Trimesh`` and ``PointCloud``.
    The array is always writable (a read-only input is copied), so that the
    numba kernels are compiled for one kind of array only.

    Raises
    ------
    InputError
        A file path (the message says how to read it), complex numbers,
        wrong shape (a transposed array is named as such), too few rows,
        or non-finite values; the message names the argument.
    """
    if obj is None:
        msg = f"Expected `{name}` to be an (N, {dim}) array of points, got None."
        raise InputError(msg)
    hint = file_hint(obj, dim)
    if hint is not None:
        msg = f"Expected `{name}` to be an (N, {dim}) array of points, got the path {str(obj)!r}; {hint}."
        raise InputError(msg)
    obj = coordinates(obj)
    try:
        raw = np.asarray(obj)
        if np.iscomplexobj(raw):
            msg = (f"Expected `{name}` to hold real numbers, got complex values ({raw.dtype}); "
                   f"pass the real part (`.real`) if that is what you mean.")
            raise InputError(msg)
        arr = np.asarray(raw, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        if isinstance(exc, InputError):
            raise
        msg = f"Expected `{name}` to be an (N, {dim}) array of numbers: {exc}."
        raise InputError(msg) from exc
    if arr.ndim != 2 or arr.shape[1] != dim:
        msg = f"Expected `{name}` to have shape (N, {dim}), got {arr.shape}{shape_hint(arr.shape, dim)}."
        raise InputError(msg)
    if arr.shape[0] < min_points:
        msg = (
            f"Expected `{name}` to have at least {min_points} point"
            f"{'s' if min_points != 1 else ''}, got {arr.shape[0]}."
        )
        raise InputError(msg)
    check_finite_array(arr, name)
    arr = np.ascontiguousarray(arr)
    return arr if arr.flags.writeable else arr.copy()


def as_vectors(obj, name: str, n: int) -> np.ndarray:
    """Return ``obj`` as a float64 ``(n, 3)`` array matching ``n`` rows."""
    arr = as_points(obj, name, min_points=0)
    if arr.shape[0] != n:
        msg = f"Expected `{name}` to have {n} rows to match the tokens, got {arr.shape[0]}."
        raise InputError(msg)
    return arr


def check_finite_array(arr: np.ndarray, name: str) -> None:
    """Raise ``ValueError`` if ``arr`` holds NaN or inf."""
    if not np.all(np.isfinite(arr)):
        bad = int(np.count_nonzero(~np.isfinite(arr)))
        msg = (
            f"`{name}` contains {bad} NaN or infinite value{'s' if bad != 1 else ''}; "
            "remove or replace them before calling."
        )
        raise InputError(msg)


def check_positive(value, name: str, *, allow_none: bool = False) -> float | None:
    """Return ``value`` as a finite positive float, or raise ``ValueError``."""
    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        msg = f"Expected `{name}` to be a positive number, got {value!r}."
        raise InputError(msg)
    value = float(value)
    if not np.isfinite(value) or value <= 0:
        msg = f"Expected `{name}` to be a finite number > 0, got {value!r}."
        raise InputError(msg)
    return value


def check_nonnegative(value, name: str, *, hint: str = "") -> float:
    """Return ``value`` as a finite float ``>= 0``, or raise naming ``name`` (``hint``: what it is)."""
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and np.isfinite(float(value))
    if not ok or float(value) < 0:
        msg = f"Expected `{name}` to be a finite number >= 0{f' ({hint})' if hint else ''}, got {value!r}."
        raise InputError(msg)
    return float(value)


def check_int(value, name: str, minimum: int, *, allow_none: bool = False) -> int | None:
    """Return ``value`` as an ``int >= minimum`` (or ``None`` when allowed), else raise."""
    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or int(value) < minimum:
        tail = " or None" if allow_none else ""
        msg = f"Expected `{name}` to be an integer >= {minimum}{tail}, got {value!r}."
        raise InputError(msg)
    return int(value)


def check_fraction(value, name: str, *, low: float = 0.0, high: float = 1.0,
                   open_low: bool = True, open_high: bool = False) -> float:
    """Return ``value`` as a float in the interval ``(low, high]`` (ends as asked), else raise."""
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and np.isfinite(float(value))
    if ok:
        v = float(value)
        ok = (v > low if open_low else v >= low) and (v < high if open_high else v <= high)
    if not ok:
        interval = f"{'(' if open_low else '['}{low:g}, {high:g}{')' if open_high else ']'}"
        msg = f"Expected `{name}` in {interval}, got {value!r}."
        raise InputError(msg)
    return float(value)


def as_rng(seed, name: str = "seed") -> np.random.Generator:
    """A :class:`numpy.random.Generator` from ``seed``.

    ``seed`` is a non-negative integer (same seed, same result) or a
    ``Generator``, used as it is (its state advances).
    """
    if isinstance(seed, np.random.Generator):
        return seed
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or int(seed) < 0:
        msg = (f"Expected `{name}` to be a non-negative integer or a numpy.random.Generator, "
               f"got {seed!r}.")
        raise InputError(msg)
    return np.random.default_rng(int(seed))


def seed_int(seed, name: str = "seed") -> int:
    """An integer seed from ``seed`` (an int, or a ``Generator`` that draws one).

    For stages that hand an integer to several independent sub-steps.
    """
    if isinstance(seed, np.random.Generator):
        return int(seed.integers(0, 2**63 - 1))
    return int(check_int(seed, name, 0))


def check_progress(progress, name: str = "progress"):
    """``progress`` as a callable ``(fraction, message)``; ``None`` gives a no-op."""
    if progress is None:
        return lambda fraction, message="": None
    if not callable(progress):
        msg = f"Expected `{name}` to be a callable progress(fraction, message) or None, got {progress!r}."
        raise InputError(msg)
    return progress
