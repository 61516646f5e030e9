"""Reading and writing point sets and results, with atomic writes.

Formats, chosen by the file's extension (case-insensitive):

==================  =======  =======  ==========================================
extension           read     write    notes
==================  =======  =======  ==========================================
``.ply``            yes      yes      through PyVista; the PLY writer stores
                                      float32 coordinates
``.vtk``, ``.vtp``  yes      yes      through PyVista; float64 kept
``.stl``, ``.obj``  yes      no       through PyVista; the mesh's vertices
``.xyz``, ``.txt``  yes      yes      text, one point a line, whitespace or
``.csv``, ``.pts``                    comma separated; the first three columns
                                      are x, y, z, extra columns are ignored;
                                      ``#`` comments and one header line are
                                      skipped
``.npy``            yes      yes      an ``(N, 3)`` (or ``(N, >3)``) array
==================  =======  =======  ==========================================

Every writer is atomic: it writes a temporary file in the destination's
folder and moves it into place with :func:`os.replace`, so an interrupted or
failed write never leaves a half-written output file behind.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import re
import tempfile
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from .errors import InputError

__all__ = [
    "PointFileError",
    "read_points",
    "write_points",
    "write_json",
    "atomic_path",
    "to_jsonable",
    "one_line",
    "result_record",
    "READ_EXTENSIONS",
    "WRITE_EXTENSIONS",
]

_PYVISTA_READ = (".ply", ".vtk", ".vtp", ".stl", ".obj")
_TEXT = (".xyz", ".txt", ".csv", ".pts")
_PYVISTA_WRITE = (".ply", ".vtk", ".vtp")

#: Extensions :func:`read_points` understands.
READ_EXTENSIONS = (*_PYVISTA_READ, *_TEXT, ".npy")
#: Extensions :func:`write_points` understands.
WRITE_EXTENSIONS = (*_PYVISTA_WRITE, *_TEXT, ".npy")


class PointFileError(InputError):
    """A point file is missing, of an unknown kind, unreadable or invalid.

    A subclass of :class:`ValueError`; the message names the path.
    """


def _fail(path, problem: str) -> PointFileError:
    return PointFileError(f"{os.fspath(path)!s}: {problem}")


# --------------------------------------------------------------------- reading
def read_points(path: str | os.PathLike) -> np.ndarray:
    """Read the points of a point-cloud or mesh file.

    Parameters
    ----------
    path : str or path-like
        File to read; the format is chosen by its extension (see the module
        docstring): ``.ply .vtk .vtp .stl .obj .xyz .txt .csv .pts .npy``.

    Returns
    -------
    points : (N, 3) ndarray of float64
        C-contiguous, finite, ``N >= 1``.

    Raises
    ------
    PointFileError
        (a :class:`ValueError`) when the file is missing, is a folder, has an
        unknown extension, cannot be parsed, holds fewer than three columns,
        holds no point, or holds NaN or infinite coordinates. The message
        starts with the path.

    Examples
    --------
    >>> import numpy as np, tempfile, os
    >>> from gatv.io import read_points, write_points
    >>> folder = tempfile.mkdtemp()
    >>> write_points(os.path.join(folder, "p.xyz"), np.eye(3))
    >>> read_points(os.path.join(folder, "p.xyz"))
    array([[1., 0., 0.],
           [0., 1., 0.],
           [0., 0., 1.]])
    """
    p = Path(path)
    ext = p.suffix.lower()
    if not p.exists():
        raise _fail(path, "no such file.")
    if p.is_dir():
        raise _fail(path, "is a folder, expected a point file.")
    if ext not in READ_EXTENSIONS:
        got = f"extension {p.suffix!r}" if p.suffix else "no extension"
        raise _fail(
            path, f"unknown point-file format ({got}); expected one of {', '.join(READ_EXTENSIONS)}."
        )
    if ext in _PYVISTA_READ:
        arr = _read_pyvista(p)
    elif ext == ".npy":
        arr = _read_npy(p)
    else:
        arr = _read_text(p)
    return _check_points(arr, path)


def _check_points(arr: np.ndarray, path) -> np.ndarray:
    arr = np.asarray(arr)
    if arr.ndim == 1 and arr.size == 3:
        arr = arr.reshape(1, 3)
    if arr.ndim != 2:
        raise _fail(path, f"expected a table of points (N, 3), got an array of shape {arr.shape}.")
    if arr.shape[0] == 0:
        raise _fail(path, "contains no points.")
    if arr.shape[1] < 3:
        raise _fail(
            path, f"expected at least 3 columns (x, y, z), got {arr.shape[1]} (shape {arr.shape})."
        )
    try:
        arr = np.ascontiguousarray(arr[:, :3], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise _fail(path, f"coordinates are not numbers ({exc}).") from exc
    bad = ~np.isfinite(arr)
    if bad.any():
        rows = np.flatnonzero(bad.any(axis=1))
        raise _fail(
            path,
            f"{int(bad.sum())} NaN or infinite coordinate{'s' if bad.sum() != 1 else ''} "
            f"(first at point {int(rows[0])}); remove or fix them.",
        )
    return arr


@contextlib.contextmanager
def _quiet_vtk() -> Iterator[list]:
    """Silence VTK's and PyVista's console chatter; collect warnings."""
    import pyvista as pv

    previous = logging.root.manager.disable
    logging.disable(logging.CRITICAL)
    try:
        with (
            pv.vtk_verbosity("off"),
            warnings.catch_warnings(record=True) as caught,
            pv.VtkErrorCatcher(raise_errors=False, send_to_logging=False),
        ):
            warnings.simplefilter("always")
            yield caught
    finally:
        logging.disable(previous)


def _read_pyvista(p: Path) -> np.ndarray:
    import pyvista as pv

    with _quiet_vtk() as caught:
        try:
            mesh = pv.read(p)
        except Exception as exc:  # VTK readers raise assorted types
            raise _fail(p, f"cannot be read as {p.suffix.lower()} ({one_line(exc)}).") from exc
    if isinstance(mesh, pv.MultiBlock):
        mesh = mesh.combine()
    points = getattr(mesh, "points", None)
    if points is None or len(points) == 0:
        reason = "unreadable or empty file"
        errors = [w for w in caught if "error" in str(w.message).lower()]
        if errors:
            reason = f"the {p.suffix.lower()} reader reported an error"
        raise _fail(p, f"contains no points ({reason}).")
    return np.asarray(points)


def _read_npy(p: Path) -> np.ndarray:
    try:
        arr = np.load(p, allow_pickle=False)
    except Exception as exc:  # ValueError, OSError, EOFError, UnpicklingError
        raise _fail(p, f"cannot be read as .npy ({one_line(exc)}).") from exc
    if arr.dtype.kind not in "biuf":
        raise _fail(p, f"expected a numeric array, got dtype {arr.dtype}.")
    return arr


_SPLIT = re.compile(r"[,;\s]+")


def _read_text(p: Path) -> np.ndarray:
    try:
        text = p.read_text(encoding="utf-8", errors="strict")
    except UnicodeDecodeError as exc:
        raise _fail(p, "is not a text file (cannot decode it as UTF-8).") from exc
    except OSError as exc:
        raise _fail(p, f"cannot be read ({exc.strerror or exc}).") from exc
    rows: list[list[float]] = []
    width = None
    first_data = True
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        fields = [f for f in _SPLIT.split(line) if f]
        try:
            values = [float(f) for f in fields]
        except ValueError:
            if first_data:  # a header such as "x,y,z"
                first_data = False
                continue
            raise _fail(p, f"line {lineno} is not a row of numbers: {raw.strip()[:60]!r}.") from None
        first_data = False
        if width is None:
            width = len(values)
        elif len(values) != width:
            raise _fail(p, f"line {lineno} has {len(values)} columns, the first row had {width}.")
        rows.append(values)
    if not rows:
        raise _fail(p, "contains no points.")
    return np.asarray(rows, dtype=np.float64)


def one_line(exc: BaseException, limit: int | None = 200) -> str:
    """``exc``'s message on one line (whitespace collapsed, cut at ``limit`` characters
    unless ``limit`` is None), or its type name when it has no message."""
    text = " ".join(str(exc).split())
    return text[:limit] if text else type(exc).__name__


# --------------------------------------------------------------------- writing
@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; move it onto ``path`` on success.

    The temporary file lives in the destination's folder (so that
    :func:`os.replace` is atomic) and keeps the destination's extension (so
    that extension-driven writers pick the right format). On any exception
    the temporary file is removed and the destination is left untouched.

    Parameters
    ----------
    path : str or path-like
        Final destination. Its folder must exist.

    Raises
    ------
    PointFileError
        When the destination's folder does not exist.
    """
    dest = Path(path)
    folder = dest.parent if str(dest.parent) else Path(".")
    if not folder.is_dir():
        raise _fail(path, f"cannot write: folder {str(folder)!r} does not exist.")
    if dest.is_dir():
        raise _fail(path, "cannot write: is a folder.")
    fd, tmp = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=f".tmp{dest.suffix}", dir=folder)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp_path, 0o666 & ~umask)
        os.replace(tmp_path, dest)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp_path.unlink()
        raise


def write_points(path: str | os.PathLike, points) -> None:
    """Write points atomically; the format is chosen by the extension.

    Parameters
    ----------
    path : str or path-like
        Destination: ``.ply .vtk .vtp`` (PyVista; PLY stores float32),
        ``.xyz .txt .pts`` (space separated), ``.csv`` (comma separated with
        an ``x,y,z`` header) or ``.npy``. Text formats keep full float64
        precision (17 significant digits).
    points : (N, 3) array_like
        Finite coordinates.

    Raises
    ------
    ValueError
        For bad ``points`` (shape, NaN); :class:`PointFileError` for an
        unsupported extension or a missing destination folder. Nothing is
        written in either case.
    """
    from ._validation import as_points

    pts = as_points(points, "points", min_points=0)
    p = Path(path)
    ext = p.suffix.lower()
    if ext not in WRITE_EXTENSIONS:
        raise _fail(
            path,
            f"cannot write points as {p.suffix or 'a file without extension'!r}; "
            f"expected one of {', '.join(WRITE_EXTENSIONS)}.",
        )
    with atomic_path(p) as tmp:
        if ext in _PYVISTA_WRITE:
            import pyvista as pv

            cloud = pv.PolyData(pts)
            with _quiet_vtk():
                cloud.save(tmp, binary=True)
        elif ext == ".npy":
            with open(tmp, "wb") as fh:
                np.save(fh, pts, allow_pickle=False)
        else:
            sep = "," if ext == ".csv" else " "
            header = "x,y,z" if ext == ".csv" else ""
            np.savetxt(tmp, pts, fmt="%.17g", delimiter=sep, header=header, comments="")


def to_jsonable(obj, _default: Callable | None = None):
    """Convert ``obj`` to plain JSON types.

    NumPy arrays become lists, NumPy scalars Python numbers, paths strings,
    non-finite floats ``None`` (strict JSON has no NaN), tuples and sets
    lists; dictionary keys become strings. Anything else becomes its
    ``str``.
    """
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return to_jsonable(obj.item())
    if isinstance(obj, bool) or obj is None or isinstance(obj, (int, str)):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    return str(obj)


def write_json(path: str | os.PathLike, obj) -> None:
    """Write ``obj`` as indented, strict JSON, atomically.

    Values are first passed through :func:`to_jsonable` (NumPy types
    converted, NaN and inf written as ``null``).

    Parameters
    ----------
    path : str or path-like
        Destination file; its folder must exist.
    obj : object
        A dictionary, list or value.
    """
    text = json.dumps(to_jsonable(obj), indent=2, allow_nan=False) + "\n"
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def result_record(inputs: dict, source, target, *, seed, options: dict, seconds: float, result) -> dict:
    """The JSON record of a point-set command (``gatv register --out``, one row of a batch).

    Parameters
    ----------
    inputs : dict
        ``{"source": path, "target": path}`` (or what the inputs were).
    source, target : (N, 3) ndarray
        The points read.
    seed : int
    options : dict
        The command's options besides the seed.
    seconds : float
        Wall time of the command.
    result : Motion, Segmentation or NonRigidMotion
        Anything with ``to_dict()`` and a truth value; its ``info`` is kept.

    Returns
    -------
    dict
        ``inputs``, ``n_source``, ``n_target``, ``seed``, ``options``,
        ``success``, ``time_s``, the result's ``to_dict()`` (a motion's 4×4
        ``matrix``, row-major, ``correspondences``, ``support``...) and
        ``info``.
    """
    return {
        **inputs,
        "n_source": int(len(source)),
        "n_target": int(len(target)),
        "seed": seed,
        "options": options,
        "success": bool(result),
        "time_s": seconds,
        **result.to_dict(),
        "info": to_jsonable(getattr(result, "info", {})),
    }
