"""What every ``gatv`` command shares: options, output checks, progress,
the atomic writer of all outputs of a command, and the one error handler.

Exit statuses (:data:`EXIT_OK`, :data:`EXIT_FAILED`, :data:`EXIT_USAGE`):

* 0 — success;
* 1 — nothing found (no motion, no match), or an internal error: any
  exception that is neither bad input nor a failed read or write, reported
  as ``gatv: error: <Type>: <message> (set GATV_DEBUG=1 for a traceback)``;
* 2 — bad input or options: :class:`gatv.errors.InputError` (every
  validator of gatv and catadioptric, :class:`gatv.io.PointFileError`), an
  :class:`OSError` from reading or writing, or an argparse usage error,
  reported as ``gatv: error: <message>``.

Errors are one line on stderr, never a traceback, unless ``GATV_DEBUG`` is
set, in which case the exception propagates.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import os
import sys
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io import READ_EXTENSIONS, WRITE_EXTENSIONS, atomic_path, one_line, result_record
from ..models import MODEL_NAMES

__all__ = [
    "EXIT_FAILED",
    "EXIT_OK",
    "EXIT_USAGE",
    "IMAGE_EXTENSIONS",
    "MODELS",
    "POINT_FILES",
    "PROG",
    "ArgumentParser",
    "ProgressBar",
    "ProgressLines",
    "UsageError",
    "WRITTEN_POINT_FILES",
    "add_model",
    "add_noise",
    "add_outputs",
    "add_point_files",
    "add_seed",
    "add_verbosity",
    "check_outputs",
    "check_point_counts",
    "error",
    "fmt",
    "guarded",
    "handle_error",
    "model_options",
    "motion_lines",
    "progress_printer",
    "result_record",
    "write_outputs",
]

PROG = "gatv"
EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
#: The point files the commands read and write, for their help (from :mod:`gatv.io`).
POINT_FILES = " ".join(READ_EXTENSIONS)
WRITTEN_POINT_FILES = " ".join(WRITE_EXTENSIONS)
#: Motion models of ``--model`` (``register`` and ``segment``): the registry's
#: (:data:`gatv.models.MODEL_NAMES`); one for other than 3D points is refused
#: when the command runs (:func:`model_options`), not when the parser is built,
#: which would import every model.
MODELS = MODEL_NAMES


class UsageError(InputError):
    """Bad command-line input detected by the command line itself (exit status 2)."""


class ArgumentParser(argparse.ArgumentParser):
    """An argument parser whose errors are one line and exit status 2."""

    def error(self, message):  # no usage dump, no SystemExit: the error handler reports it
        raise UsageError(f"{message} (see `{self.prog} --help`)")


# ------------------------------------------------------------------ options
def add_point_files(p: argparse.ArgumentParser) -> None:
    """Positional ``source`` and ``target`` point files."""
    p.add_argument("source", type=Path, help=f"source point file ({POINT_FILES})")
    p.add_argument("target", type=Path, help="target point file (the same formats)")


def add_outputs(p: argparse.ArgumentParser, *, out: str = "write the result as JSON",
                render: str = "write an off-screen picture", aligned: bool = False) -> None:
    """``--out JSON``, ``--render PNG`` and, with ``aligned=True``, ``--aligned FILE``."""
    p.add_argument("--out", type=Path, metavar="JSON", help=out)
    if aligned:
        p.add_argument(
            "--aligned", type=Path, metavar="FILE",
            help=f"write the moved source points ({WRITTEN_POINT_FILES})",
        )
    p.add_argument("--render", type=Path, metavar="PNG", help=render)


def add_seed(p: argparse.ArgumentParser, what: str = "the registration") -> None:
    p.add_argument("--seed", type=int, default=0, help=f"seed of {what} (default: 0)")


def add_noise(p: argparse.ArgumentParser) -> None:
    p.add_argument("--noise", type=float, metavar="SIGMA", help="point noise, data units")


def add_model(p: argparse.ArgumentParser) -> None:
    """``--model {rigid,similarity}`` (default rigid)."""
    p.add_argument("--model", choices=MODELS, default="rigid",
                   help="motion model of 3D points: rigid, or similarity (rotation, uniform scale, "
                        "translation) (default: rigid)")


def add_verbosity(p: argparse.ArgumentParser, *, progress: bool = True) -> None:
    """``--quiet`` and, with ``progress=True``, ``--progress``."""
    if progress:
        p.add_argument("--progress", action="store_true", help="print progress lines to stderr")
    p.add_argument("--quiet", "-q", action="store_true", help="print nothing on success")


def model_options(args, dim: int = 3) -> dict:
    """``{"model": ...}`` for a non-rigid ``--model``, else ``{}`` (rigid is the default).

    UsageError for a registered model of other than ``dim``-dimensional
    points (the commands read 3D point files).
    """
    model = getattr(args, "model", "rigid")
    if model == "rigid":
        return {}
    from ..models import get_model

    model_dim = getattr(get_model(model), "dim", dim)
    if model_dim != dim:
        raise UsageError(f"--model {model} is a model of {model_dim}D points; the point files here are "
                         f"{dim}D (use the Python API for {model_dim}D points).")
    return {"model": model}


# ------------------------------------------------------------ input checks
_OUTPUT_KINDS = (("out", "the result", None), ("aligned", "aligned points", WRITE_EXTENSIONS),
                 ("render", "a picture", IMAGE_EXTENSIONS), ("matrix", "the 4x4 matrix", None))


def _check_output(path: Path | None, what: str, extensions: tuple[str, ...] | None) -> None:
    if path is None:
        return
    if extensions is not None and path.suffix.lower() not in extensions:
        raise UsageError(
            f"{path}: cannot write {what} as {path.suffix or 'a file without extension'!r}; "
            f"expected one of {', '.join(extensions)}."
        )
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise UsageError(f"{path}: cannot write {what}: folder {str(folder)!r} does not exist.")
    if path.is_dir():
        raise UsageError(f"{path}: cannot write {what}: is a folder.")
    if not os.access(folder, os.W_OK):
        raise UsageError(f"{path}: cannot write {what}: folder {str(folder)!r} is not writable.")


def check_outputs(args, inputs: Sequence[Path] = ()) -> list[Path]:
    """Fail before any work if an output (``--out``, ``--aligned``, ``--render``) cannot be written.

    Only the output options ``args`` has are checked: each must have a
    writable extension and folder, they must name different files, and none
    may be one of ``inputs``.  Returns the resolved paths of the outputs
    asked for.
    """
    present = [(dest, what, ext) for dest, what, ext in _OUTPUT_KINDS if hasattr(args, dest)]
    for dest, what, ext in present:
        _check_output(getattr(args, dest), what, ext)
    outs = [getattr(args, dest).resolve() for dest, _, _ in present if getattr(args, dest) is not None]
    if len(set(outs)) != len(outs):
        flags = [f"--{dest}" for dest, _, _ in present]
        raise UsageError(f"{', '.join(flags[:-1])} and {flags[-1]} must name different files.")
    resolved = {Path(p).resolve() for p in inputs}
    for dest, _, _ in present:
        out = getattr(args, dest)
        if out is not None and out.resolve() in resolved:
            raise UsageError(f"{out}: refusing to overwrite an input file.")
    return outs


def check_point_counts(named: Iterable[tuple[str, np.ndarray, object]], minimum: int = 3) -> None:
    """``(name, points, where)`` triples: each needs ``minimum`` points."""
    for name, pts, where in named:
        if len(pts) < minimum:
            raise UsageError(f"{where}: expected at least {minimum} points in `{name}`, got {len(pts)}.")


class ProgressLines:
    """``progress(fraction, message)`` printing ``gatv: [ 42.0%] message`` lines to stderr.

    Lines closer than 1% apart are dropped unless they carry a message or
    reach 100%.
    """

    def __init__(self, stream=None):
        self.stream = stream
        self.last = -1.0

    def __call__(self, fraction, message=""):
        fraction = float(min(max(fraction, 0.0), 1.0))
        if fraction - self.last < 0.01 and fraction < 1.0 and not message:
            return
        self.last = fraction
        print(f"{PROG}: [{100 * fraction:5.1f}%] {message}", file=self.stream or sys.stderr, flush=True)

    def close(self) -> None:
        """Nothing to close (the counterpart of :meth:`ProgressBar.close`)."""


class ProgressBar:
    """``progress(fraction, message)`` drawing a tqdm bar on stderr; closed at 100%.

    ``total`` counts items (rows of a batch) when given, else percent.
    """

    #: Bar without the time left: while numba compiles, the rate (and so the estimate) means nothing.
    COMPILING_FORMAT = "{desc}: {percentage:3.0f}%|{bar}| [{elapsed}]{postfix}"

    def __init__(self, total: int | None = None, unit: str = "%", desc: str = PROG):
        from tqdm import tqdm

        self.total = int(total) if total else 100
        self.format = None if total else "{desc}: {percentage:3.0f}%|{bar}| [{elapsed}<{remaining}]{postfix}"
        self.bar = tqdm(total=self.total, unit=unit if total else "%", desc=desc, file=sys.stderr,
                        dynamic_ncols=True, leave=False, bar_format=self.format)

    def __call__(self, fraction, message=""):
        if self.bar is None:
            return
        fraction = float(min(max(fraction, 0.0), 1.0))
        n = round(fraction * self.total)
        if n > self.bar.n:
            self.bar.update(n - self.bar.n)
        if message:
            compiling = str(message).startswith("compiling kernels")
            self.bar.bar_format = self.COMPILING_FORMAT if compiling else self.format
            self.bar.set_postfix_str(str(message)[:60], refresh=True)
        if fraction >= 1.0:
            self.close()

    def close(self) -> None:
        """Remove the bar from the terminal."""
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def progress_printer(args, *, total: int | None = None, unit: str = "%") -> Callable[..., None] | None:
    """A ``progress(fraction, message)`` callback for a long command, or None.

    * stderr is a terminal and no ``--quiet``: a progress bar (tqdm) that
      closes itself at 100%;
    * ``--progress`` (stderr not a terminal, or ``--quiet``): plain lines
      ``gatv: [ 42.0%] message`` on stderr;
    * otherwise (``--quiet``, or output piped): None, silent.

    ``total`` and ``unit`` make the bar count items (``37/100 rows``)
    instead of percent.
    """
    quiet = bool(getattr(args, "quiet", False))
    if not quiet and sys.stderr.isatty():
        try:
            return ProgressBar(total, unit)
        except ImportError:  # tqdm is a dependency; plain lines if it was removed
            return ProgressLines()
    if getattr(args, "progress", False):
        return ProgressLines()
    return None


# ------------------------------------------------------------------ outputs
def write_outputs(outputs: Iterable[tuple[Path | None, Callable[[Path], object]]], *,
                  quiet: bool = False) -> list[Path]:
    """Write every output of a command atomically: all of them land, or none.

    Parameters
    ----------
    outputs : iterable of (path or None, writer)
        ``writer(tmp)`` writes the output to the temporary path ``tmp``
        beside ``path`` (same extension); entries whose path is None are
        skipped.  The temporary files are moved onto their destinations
        only when every writer succeeded; on any exception all of them are
        removed and no destination is touched.
    quiet : bool
        Do not print ``wrote PATH`` lines.

    Returns
    -------
    list of Path
        The destinations written, in order.
    """
    written = []
    with contextlib.ExitStack() as stack:
        for path, write in outputs:
            if path is None:
                continue
            write(stack.enter_context(atomic_path(path)))
            written.append(path)
    if not quiet:
        for path in written:
            print(f"wrote {path}")
    return written


def fmt(v) -> str:
    """``[a, b, c]`` with 6 significant digits."""
    return "[" + ", ".join(f"{x:.6g}" for x in np.asarray(v, dtype=float).ravel()) + "]"


def _axis(rotation: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    v = Rotation.from_matrix(rotation).as_rotvec()
    n = np.linalg.norm(v)
    return v / n if n > 0 else np.array([0.0, 0.0, 1.0])


def motion_lines(motion) -> list[tuple[str, str]]:
    """``(label, text)`` of the quantities a motion result has, from its matrix.

    ``rotation`` (angle and axis) when it has a 3×3 rotation, ``scale`` when
    it has one, ``translation``; the whole ``matrix`` when it has neither a
    rotation nor a scale (e.g. an affine map).  Nothing for a falsy result.
    """
    if not motion:
        return []
    from ..motion import rotation_angle_deg

    lines = []
    rotation = getattr(motion, "rotation", None)
    if rotation is not None and np.shape(rotation) == (3, 3):
        angle = getattr(motion, "angle_deg", None)
        angle = rotation_angle_deg(rotation) if angle is None else angle
        lines.append(("rotation", f"{angle:.4f} deg about axis {fmt(_axis(np.asarray(rotation)))}"))
    scale = getattr(motion, "scale", None)
    if scale is not None:
        lines.append(("scale", f"{float(scale):.6g}"))
    matrix = np.asarray(motion.matrix)
    d = matrix.shape[0] - 1
    if rotation is None and scale is None:
        lines.append(("matrix", "[" + ", ".join(fmt(row) for row in matrix[:d]) + "]"))
    translation = getattr(motion, "translation", None)
    lines.append(("translation", fmt(matrix[:d, d] if translation is None else translation)))
    return lines


# ------------------------------------------------------------------- errors
def error(message: str) -> None:
    """Print ``gatv: error: <message>`` on stderr."""
    print(f"{PROG}: error: {message}", file=sys.stderr, flush=True)


def handle_error(exc: BaseException) -> int:
    """The one error handler: report ``exc`` in one line and return the exit status.

    ``SystemExit`` (``--help``) keeps its code; ``KeyboardInterrupt`` is
    130; :class:`~gatv.errors.InputError` (argparse usage errors included)
    and :class:`OSError` are bad input, 2; anything else is an internal
    error, 1, reported with its type.
    """
    if isinstance(exc, SystemExit):
        return exc.code if isinstance(exc.code, int) else EXIT_OK
    if isinstance(exc, KeyboardInterrupt):
        error("interrupted")
        return 130
    if isinstance(exc, (InputError, OSError)):
        error(one_line(exc, limit=None))
        return EXIT_USAGE
    error(f"{type(exc).__name__}: {one_line(exc, limit=None)} (set GATV_DEBUG=1 for a traceback)")
    return EXIT_FAILED


def guarded(run: Callable[..., int]) -> Callable[..., int]:
    """Wrap a command so that every exception goes through :func:`handle_error`.

    With ``GATV_DEBUG`` set, exceptions (but not ``SystemExit`` or
    ``KeyboardInterrupt``) propagate with their traceback.
    """

    @functools.wraps(run)
    def wrapper(*args, **kwargs) -> int:
        try:
            return int(run(*args, **kwargs))
        except BaseException as exc:
            if os.environ.get("GATV_DEBUG") and isinstance(exc, Exception):
                raise
            return handle_error(exc)

    return wrapper
