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
``.pcd``            yes      yes      the Point Cloud Library's format: ``DATA``
                                      ``ascii``, ``binary`` and
                                      ``binary_compressed`` (LZF) read, any
                                      field types; written ``binary`` (or
                                      ``ascii``) with float32 ``x y z`` as PCL
                                      and Open3D do (``double=True``: float64,
                                      as ``ascii``: Open3D's legacy reader
                                      reads binary float64 as zeros)
==================  =======  =======  ==========================================

Per-point scalars (a segmentation's ``motion`` label, an intensity) travel
with the points in ``.ply`` (one vertex property each, its integer or float
type kept), ``.vtk``/``.vtp`` (point arrays) and ``.csv`` (named columns after
``x,y,z``): ``write_points(path, points, scalars={"motion": labels})`` and
``read_points(path, scalars=True)``.

Motions travel as 4×4 homogeneous matrices: ``matrix`` in every JSON
record (row-major), and as text with :func:`write_matrix` /
:func:`read_matrix` (four lines of four numbers, what ``numpy.loadtxt``
reads and Open3D's examples keep) and :func:`write_log` / :func:`read_log`
(the trajectory ``.log`` of Open3D and the 3DMatch/Redwood benchmarks: a
line ``i j n`` before each matrix).

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
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path

import numpy as np

from .errors import InputError

__all__ = [
    "READ_EXTENSIONS",
    "SCALAR_EXTENSIONS",
    "WRITE_EXTENSIONS",
    "PointFileError",
    "atomic_path",
    "one_line",
    "read_log",
    "read_matrix",
    "read_points",
    "result_record",
    "to_jsonable",
    "write_json",
    "write_log",
    "write_matrix",
    "write_points",
]

_PYVISTA_READ = (".ply", ".vtk", ".vtp", ".stl", ".obj")
_TEXT = (".xyz", ".txt", ".csv", ".pts")
_PYVISTA_WRITE = (".ply", ".vtk", ".vtp")

#: Extensions :func:`read_points` understands.
READ_EXTENSIONS = (*_PYVISTA_READ, *_TEXT, ".npy", ".pcd")
#: Extensions :func:`write_points` understands.
WRITE_EXTENSIONS = (*_PYVISTA_WRITE, *_TEXT, ".npy", ".pcd")
#: Extensions whose files carry named per-point scalars (``scalars=``).
SCALAR_EXTENSIONS = (".ply", ".vtk", ".vtp", ".csv")


class PointFileError(InputError):
    """A point file is missing, of an unknown kind, unreadable or invalid.

    A subclass of :class:`ValueError`; the message names the path.
    """


def _fail(path, problem: str) -> PointFileError:
    return PointFileError(f"{os.fspath(path)!s}: {problem}")


# --------------------------------------------------------------------- reading
def read_points(path: str | os.PathLike, *, scalars: bool = False):
    """Read the points of a point-cloud or mesh file.

    Parameters
    ----------
    path : str or path-like
        File to read; the format is chosen by its extension (see the module
        docstring): ``.ply .vtk .vtp .stl .obj .xyz .txt .csv .pts .npy .pcd``.
    scalars : bool, default: False
        Also return the file's per-point scalars (see :func:`write_points`):
        a PLY file's vertex properties other than ``x y z``, a VTK file's
        one-component point arrays, a CSV file's named columns after the
        first three; ``{}`` for a format that holds none.

    Returns
    -------
    points : (N, 3) ndarray of float64
        C-contiguous, finite, ``N >= 1``.
    scalars : dict of str to (N,) ndarray
        Only with ``scalars=True``: name to values, in the file's order and
        type (a PLY ``int`` property is int32; text columns are float64).

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
    extra: dict[str, np.ndarray] = {}
    if ext in _PYVISTA_READ:
        arr, point_data = _read_pyvista(p)
        if scalars:
            extra = _read_ply_scalars(p, arr.shape[0]) if ext == ".ply" else point_data
    elif ext == ".npy":
        arr = _read_npy(p)
    elif ext == ".pcd":
        arr = _read_pcd(p)
    else:
        arr, names = _read_text(p)
        if scalars and names is not None and arr.ndim == 2:
            extra = {name: np.ascontiguousarray(arr[:, k]) for k, name in enumerate(names) if k >= 3}
    points = _check_points(arr, path)
    return (points, extra) if scalars else points


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
    n = len(points)
    point_data = {}
    for name, array in mesh.point_data.items():
        values = np.asarray(array)
        if values.shape == (n,) and values.dtype.kind in "biuf":
            point_data[str(name)] = values
    return np.asarray(points), point_data


def _read_npy(p: Path) -> np.ndarray:
    try:
        arr = np.load(p, allow_pickle=False)
    except Exception as exc:  # ValueError, OSError, EOFError, UnpicklingError
        raise _fail(p, f"cannot be read as .npy ({one_line(exc)}).") from exc
    if arr.dtype.kind not in "biuf":
        raise _fail(p, f"expected a numeric array, got dtype {arr.dtype}.")
    return arr


_SPLIT = re.compile(r"[,;\s]+")


def _read_text(p: Path) -> tuple[np.ndarray, list[str] | None]:
    """The rows of numbers, and the header line's column names (None without one)."""
    try:
        text = p.read_text(encoding="utf-8", errors="strict")
    except UnicodeDecodeError as exc:
        raise _fail(p, "is not a text file (cannot decode it as UTF-8).") from exc
    except OSError as exc:
        raise _fail(p, f"cannot be read ({exc.strerror or exc}).") from exc
    rows: list[list[float]] = []
    width = None
    first_data = True
    names = None
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
                names = fields
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
    if names is not None and len(names) != width:
        names = None  # not a header of these columns
    return np.asarray(rows, dtype=np.float64), names


# ------------------------------------------------------------------------ PLY
#: PLY property types (both spellings) and the NumPy type of each.
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_PLY_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
              "f4": "float", "f8": "double"}


def _read_ply_scalars(p: Path, n_points: int) -> dict[str, np.ndarray]:
    """The vertex properties of a PLY file other than ``x y z``, name to values.

    Reads the header (``format ascii`` or ``binary_little/big_endian``),
    skips the elements before ``vertex`` (fixed-size ones only) and reads the
    vertex table.  PyVista's reader keeps only the coordinates, normals,
    colours and texture coordinates of a PLY file.
    """
    raw = p.read_bytes()
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise _fail(p, "cannot read its vertex properties: not a PLY header.")
    start = raw.index(b"\n", end) + 1
    fmt, elements = None, []
    for line in raw[:end].decode("ascii", errors="replace").splitlines():
        words = line.split()
        if not words or words[0] in ("ply", "comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements:
            kind = "list" if len(words) >= 2 and words[1] == "list" else words[1] if len(words) == 3 else None
            if kind != "list" and kind not in _PLY_TYPES:
                raise _fail(p, f"cannot read its vertex properties: property line {line.strip()!r}.")
            elements[-1][2].append((words[-1], kind))
    order = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": None}
    if fmt not in order:
        raise _fail(p, f"cannot read its vertex properties: PLY format {fmt!r}.")
    body, offset = raw[start:], 0
    lines = body.split(b"\n") if fmt == "ascii" else None
    for name, count, props in elements:
        if any(kind == "list" for _, kind in props):
            raise _fail(p, f"cannot read its vertex properties: element {name!r} has list properties.")
        dtype = np.dtype([(prop, (order[fmt] or "<") + _PLY_TYPES[kind]) for prop, kind in props])
        if name != "vertex":
            offset += count * (1 if fmt == "ascii" else dtype.itemsize)
            continue
        if count != n_points:
            raise _fail(p, f"has {count} vertices in its header, {n_points} points read.")
        if fmt == "ascii":
            try:
                table = np.array([row.split() for row in lines[offset:offset + count]], dtype=np.float64)
            except ValueError:
                raise _fail(p, "cannot read its vertex properties: ascii rows are not numbers.") from None
            if table.shape != (count, len(props)):
                raise _fail(p, f"cannot read its vertex properties: expected {count} rows of {len(props)} values.")
            return {prop: table[:, k].astype(dtype[prop].newbyteorder("=")) for k, (prop, _) in enumerate(props)
                    if prop not in ("x", "y", "z")}
        if len(body) < offset + count * dtype.itemsize:
            raise _fail(p, "is truncated: its vertex table is shorter than the header says.")
        rec = np.frombuffer(body, dtype=dtype, count=count, offset=offset)
        return {prop: rec[prop].astype(dtype[prop].newbyteorder("=")) for prop, _ in props
                if prop not in ("x", "y", "z")}
    raise _fail(p, "has no vertex element.")


def _write_ply(tmp: Path, pts: np.ndarray, scalars: dict[str, np.ndarray]) -> None:
    """Binary little-endian PLY: float32 ``x y z`` and one property per scalar, its type kept."""
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    fields += [(name, "<" + values.dtype.kind + str(values.dtype.itemsize)) for name, values in scalars.items()]
    rows = np.empty(pts.shape[0], dtype=fields)
    rows["x"], rows["y"], rows["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    for name, values in scalars.items():
        rows[name] = values
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {pts.shape[0]}"]
    header += [f"property {_PLY_NAMES[code[1:]]} {name}" for name, code in fields]
    header.append("end_header\n")
    with open(tmp, "wb") as fh:
        fh.write("\n".join(header).encode("ascii"))
        fh.write(rows.tobytes())


def _check_scalars(scalars, n: int) -> dict[str, np.ndarray]:
    """``scalars`` as name to (n,) arrays of a type PLY, VTK and CSV all hold."""
    if scalars is None:
        return {}
    if not isinstance(scalars, Mapping):
        raise InputError(f"Expected `scalars` to be a mapping of names to per-point values (e.g. "
                         f"{{'motion': labels}}), got {type(scalars).__name__}.")
    out = {}
    for name, values in scalars.items():
        if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
            raise InputError(f"Expected every name in `scalars` to be a word of letters, digits and _, "
                             f"got {name!r}.")
        if name.lower() in ("x", "y", "z") or name.lower() in {k.lower() for k in out}:
            raise InputError(f"`scalars` cannot hold {name!r}: x, y, z are the coordinates and names must differ "
                             "(ignoring case).")
        arr = np.asarray(values)
        if arr.dtype.kind == "b":
            arr = arr.astype(np.uint8)
        if arr.dtype.kind not in "iuf":
            raise InputError(f"Expected `scalars[{name!r}]` to hold numbers, got dtype {arr.dtype}.")
        if arr.shape != (n,):
            raise InputError(f"Expected `scalars[{name!r}]` to hold one value per point, shape ({n},), "
                             f"got {arr.shape}.")
        if arr.dtype.kind in "iu" and arr.dtype.itemsize > 4:  # PLY has no 64-bit integers
            small = np.int32 if arr.dtype.kind == "i" else np.uint32
            if arr.size and (arr.min() < np.iinfo(small).min or arr.max() > np.iinfo(small).max):
                raise InputError(f"Expected `scalars[{name!r}]` to fit in 32-bit integers (PLY has no wider "
                                 f"ones), got values in [{arr.min()}, {arr.max()}]; pass them as floats.")
            arr = arr.astype(small)
        elif arr.dtype.kind == "f" and arr.dtype.itemsize not in (4, 8):
            arr = arr.astype(np.float64)
        out[name] = np.ascontiguousarray(arr)
    return out


# ------------------------------------------------------------------------ PCD
_PCD_KINDS = {"F": "f", "I": "i", "U": "u"}


def _pcd_header(p: Path, raw: bytes) -> tuple[dict, int]:
    """The header of a PCD file (keys upper-case, values as lists of words) and where its data start."""
    header: dict[str, list[str]] = {}
    pos = 0
    while True:
        end = raw.find(b"\n", pos)
        if end < 0:
            raise _fail(p, "is not a PCD file: no DATA line in its header.")
        line = raw[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        header[key.upper()] = values
        if key.upper() == "DATA":
            return header, pos


def _pcd_layout(p: Path, header: dict) -> tuple[list[str], np.dtype, int, str]:
    """Field names, the record dtype of one point, the point count and the DATA kind."""
    try:
        fields = header["FIELDS"]
        sizes = [int(v) for v in header["SIZE"]]
        types = [v.upper() for v in header["TYPE"]]
        counts = [int(v) for v in header.get("COUNT", ["1"] * len(fields))]
        width = int(header.get("WIDTH", ["0"])[0])
        height = int(header.get("HEIGHT", ["1"])[0])
        n = int(header["POINTS"][0]) if "POINTS" in header else width * height
        data = header["DATA"][0].lower()
    except (KeyError, IndexError, ValueError) as exc:
        raise _fail(p, f"has a broken PCD header ({one_line(exc)}).") from None
    if not (len(fields) == len(sizes) == len(types) == len(counts)):
        raise _fail(p, "has a broken PCD header: FIELDS, SIZE, TYPE and COUNT differ in length.")
    names, formats = [], []
    for k, (name, size, kind, count) in enumerate(zip(fields, sizes, types, counts)):
        if kind not in _PCD_KINDS or size not in (1, 2, 4, 8) or (kind == "F" and size < 4) or count < 1:
            raise _fail(p, f"has an unsupported PCD field {name!r} (TYPE {kind}, SIZE {size}).")
        names.append(name if name not in names else f"{name}_{k}")
        base = np.dtype(f"<{_PCD_KINDS[kind]}{size}")
        formats.append(base if count == 1 else np.dtype((base, (count,))))
    if not {"x", "y", "z"} <= set(names):
        raise _fail(p, f"has no x, y, z fields (FIELDS {' '.join(fields)}).")
    if data not in ("ascii", "binary", "binary_compressed"):
        raise _fail(p, f"has an unknown PCD DATA kind {data!r}; expected ascii, binary or binary_compressed.")
    return names, np.dtype({"names": names, "formats": formats}), n, data


def _lzf_decompress(data: bytes, size: int) -> bytes:
    """LZF decompression (liblzf's format, used by PCD's ``binary_compressed``)."""
    out = bytearray(size)
    i = o = 0
    n = len(data)
    while i < n:
        ctrl = data[i]
        i += 1
        if ctrl < 32:  # a run of ctrl + 1 literal bytes
            length = ctrl + 1
            if i + length > n or o + length > size:
                raise ValueError("literal run past the end")
            out[o:o + length] = data[i:i + length]
            i += length
            o += length
            continue
        length = ctrl >> 5  # a back reference
        if length == 7:
            length += data[i]
            i += 1
        ref = o - ((ctrl & 0x1F) << 8) - data[i] - 1
        i += 1
        length += 2
        if ref < 0 or o + length > size:
            raise ValueError("back reference out of range")
        while length > 0:  # overlapping copies repeat the period o - ref
            step = min(length, o - ref)
            out[o:o + step] = out[ref:ref + step]
            o += step
            ref += step
            length -= step
    if o != size:
        raise ValueError(f"decompressed {o} bytes, expected {size}")
    return bytes(out)


def _read_pcd(p: Path) -> np.ndarray:
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise _fail(p, f"cannot be read ({exc.strerror or exc}).") from exc
    header, start = _pcd_header(p, raw)
    names, dtype, n, data = _pcd_layout(p, header)
    body = raw[start:]
    if data == "ascii":
        text = body.decode("ascii", errors="replace").split()
        width = sum(int(np.prod(dtype[name].shape or (1,))) for name in names)
        try:
            values = np.asarray(text, dtype=np.float64)
        except ValueError:
            raise _fail(p, "has PCD ascii data that are not numbers.") from None
        if values.size != n * width:
            raise _fail(p, f"expected {n} points of {width} values in its ascii data, got {values.size} values.")
        table = values.reshape(n, width)
        columns, col = {}, 0
        for name in names:  # the text's full precision, as Open3D reads it (PCL would round to SIZE)
            w = int(np.prod(dtype[name].shape or (1,)))
            columns[name] = table[:, col]
            col += w
        return np.column_stack([columns["x"], columns["y"], columns["z"]])
    if data == "binary":
        if len(body) < n * dtype.itemsize:
            raise _fail(p, f"is truncated: {n} points need {n * dtype.itemsize} bytes of data, got {len(body)}.")
        rec = np.frombuffer(body, dtype=dtype, count=n)
        return np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(np.float64)
    if len(body) < 8:
        raise _fail(p, "is truncated: no compressed PCD data.")
    packed, unpacked = (int(v) for v in np.frombuffer(body[:8], dtype="<u4"))
    if unpacked != n * dtype.itemsize or len(body) < 8 + packed:
        raise _fail(p, f"has inconsistent compressed sizes ({packed} -> {unpacked} bytes for {n} points).")
    try:
        plain = _lzf_decompress(body[8:8 + packed], unpacked)
    except (ValueError, IndexError) as exc:
        raise _fail(p, f"has corrupt compressed PCD data ({one_line(exc)}).") from None
    columns, offset = {}, 0  # binary_compressed stores each field's values together
    for name in names:
        field_dtype = dtype[name]
        size = n * field_dtype.itemsize
        columns[name] = np.frombuffer(plain, dtype=field_dtype.base, count=n * int(np.prod(field_dtype.shape or (1,))),
                                      offset=offset)
        offset += size
    return np.column_stack([columns["x"], columns["y"], columns["z"]]).astype(np.float64)


def _write_pcd(tmp: Path, pts: np.ndarray, *, ascii: bool, double: bool) -> None:
    size, dtype, fmt = (8, "<f8", "%.17g") if double else (4, "<f4", "%.9g")
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\n"
        f"SIZE {size} {size} {size}\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {len(pts)}\nHEIGHT 1\n"
        f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(pts)}\nDATA {'ascii' if ascii else 'binary'}\n"
    )
    values = np.ascontiguousarray(pts, dtype=dtype)
    with open(tmp, "wb") as fh:
        fh.write(header.encode("ascii"))
        if ascii:
            np.savetxt(fh, values, fmt=fmt, delimiter=" ")
        else:
            fh.write(values.tobytes())


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


def write_points(path: str | os.PathLike, points, *, ascii: bool | None = None, double: bool = False,
                 scalars: Mapping | None = None) -> None:
    """Write points atomically; the format is chosen by the extension.

    Parameters
    ----------
    path : str or path-like
        Destination: ``.ply .vtk .vtp`` (PyVista; PLY stores float32),
        ``.xyz .txt .pts`` (space separated), ``.csv`` (comma separated with
        an ``x,y,z`` header), ``.npy`` or ``.pcd``. Text formats keep full
        float64 precision (17 significant digits).
    points : (N, 3) array_like or point container
        Finite coordinates (an array, a PyVista, Open3D or trimesh object).
    ascii : bool, optional
        ``.pcd`` only: ``DATA ascii`` instead of ``DATA binary``.  Default:
        binary for float32, ascii for ``double=True``.
    double : bool, default: False
        ``.pcd`` only: float64 coordinates (``SIZE 8``; exact) instead of
        float32 (what PCL's ``PointXYZ`` and Open3D read and write), written
        as ascii with 17 significant digits.  ``double=True, ascii=False``
        is refused: Open3D's legacy reader (``o3d.io.read_point_cloud``)
        reads binary float64 fields as zeros, without a word.
    scalars : mapping of str to (N,) array_like, optional
        Per-point values written with the points, e.g. ``{"motion": labels}``
        (``.ply .vtk .vtp .csv``, :data:`SCALAR_EXTENSIONS`): a PLY vertex
        property each (``int`` for int32 labels, what PyVista, Open3D's tensor
        API, CloudCompare and MeshLab read as a scalar field), a VTK point
        array, a named CSV column.  Names are words (letters, digits, ``_``)
        other than ``x y z``; integers must fit in 32 bits (PLY has no wider).

    Raises
    ------
    ValueError
        For bad ``points`` (shape, NaN) or ``scalars`` (names, lengths,
        types); :class:`PointFileError` for an unsupported extension, scalars
        for a format that cannot hold them, or a missing destination folder.
        Nothing is written in any case.
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
    if ext == ".pcd" and double and ascii is not None and not ascii:
        raise _fail(path, "cannot write a binary PCD of float64 coordinates: Open3D's legacy reader "
                          "(o3d.io.read_point_cloud) reads them as zeros; write double=True as ascii "
                          "(the default, exact) or float32 binary (double=False).")
    extra = _check_scalars(scalars, pts.shape[0])
    if extra and ext not in SCALAR_EXTENSIONS:
        raise _fail(path, f"cannot write `scalars` in {ext} (it has no named per-point values); "
                          f"use one of {', '.join(SCALAR_EXTENSIONS)}.")
    with atomic_path(p) as tmp:
        if ext == ".ply":
            _write_ply(tmp, pts, extra)
        elif ext in _PYVISTA_WRITE:
            import pyvista as pv

            cloud = pv.PolyData(pts)
            for name, values in extra.items():
                cloud.point_data[name] = values
            with _quiet_vtk():
                cloud.save(tmp, binary=True)
        elif ext == ".npy":
            with open(tmp, "wb") as fh:
                np.save(fh, pts, allow_pickle=False)
        elif ext == ".pcd":
            _write_pcd(tmp, pts, ascii=bool(double) if ascii is None else bool(ascii), double=bool(double))
        else:
            sep = "," if ext == ".csv" else " "
            header = ",".join(["x", "y", "z", *extra]) if ext == ".csv" else ""
            if extra:
                table = np.column_stack([pts, *(v.astype(np.float64) for v in extra.values())])
                fmt = ["%.17g"] * 3 + ["%d" if v.dtype.kind in "iu" else "%.17g" for v in extra.values()]
            else:
                table, fmt = pts, "%.17g"
            np.savetxt(tmp, table, fmt=fmt, delimiter=sep, header=header, comments="")


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
        "n_source": len(source),
        "n_target": len(target),
        "seed": seed,
        "options": options,
        "success": bool(result),
        "time_s": seconds,
        **result.to_dict(),
        "info": to_jsonable(getattr(result, "info", {})),
    }


# ------------------------------------------------------------------ matrices
def _as_matrix(matrix, name: str = "matrix") -> np.ndarray:
    m = getattr(matrix, "matrix", matrix)  # a motion result, or its matrix
    try:
        m = np.asarray(m, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"Expected `{name}` to be a 4x4 matrix or a motion, got {type(matrix).__name__}.") from exc
    if m.shape != (4, 4):
        raise InputError(f"Expected `{name}` to have shape (4, 4), got {m.shape}.")
    if not np.all(np.isfinite(m)):
        raise InputError(f"`{name}` contains NaN or infinite values.")
    return m


def write_matrix(path: str | os.PathLike, matrix) -> None:
    """Write a 4×4 homogeneous matrix as text, atomically: four lines of four numbers.

    The layout ``numpy.loadtxt`` reads and Open3D's registration examples
    keep (``source.transform(numpy.loadtxt(path))``), 17 significant digits.

    Parameters
    ----------
    path : str or path-like
    matrix : (4, 4) array_like or a motion result
        A motion's ``.matrix`` is taken (rigid, similarity).

    Examples
    --------
    >>> import numpy as np, tempfile, os
    >>> from gatv.io import read_matrix, write_matrix
    >>> path = os.path.join(tempfile.mkdtemp(), "motion.txt")
    >>> write_matrix(path, np.eye(4))
    >>> read_matrix(path)[3]
    array([0., 0., 0., 1.])
    """
    m = _as_matrix(matrix)
    with atomic_path(path) as tmp:
        np.savetxt(tmp, m, fmt="%.17g", delimiter=" ")


def read_matrix(path: str | os.PathLike) -> np.ndarray:
    """Read a 4×4 matrix written by :func:`write_matrix` (or ``numpy.savetxt``).

    Raises
    ------
    PointFileError
        Missing file, not four rows of four numbers, or not finite.
    """
    p = Path(path)
    if not p.is_file():
        raise _fail(path, "no such file.")
    try:
        m = np.loadtxt(p, dtype=np.float64, ndmin=2)
    except ValueError as exc:
        raise _fail(path, f"is not a table of numbers ({one_line(exc)}).") from None
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise _fail(path, f"expected a finite 4x4 matrix, got shape {m.shape}.")
    return m


def write_log(path: str | os.PathLike, entries) -> None:
    """Write a trajectory ``.log`` (Open3D, 3DMatch, Redwood), atomically.

    Each entry is written as a line ``i j n`` (source index, target index,
    number of fragments) followed by its 4×4 matrix, four lines.

    Parameters
    ----------
    path : str or path-like
    entries : iterable of (int, int, int, matrix)
        ``(i, j, n, matrix)``; a matrix may be a motion result.
    """
    lines = []
    for k, entry in enumerate(entries):
        try:
            i, j, n, matrix = entry
        except (TypeError, ValueError):
            raise InputError(f"Expected `entries[{k}]` to be (i, j, n, matrix), got {entry!r}.") from None
        m = _as_matrix(matrix, f"entries[{k}]")
        lines.append(f"{int(i)} {int(j)} {int(n)}")
        lines += [" ".join(f"{v:.17g}" for v in row) for row in m]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + ("\n" if lines else ""), encoding="ascii")


def read_log(path: str | os.PathLike) -> list[tuple[int, int, int, np.ndarray]]:
    """Read a trajectory ``.log``: a list of ``(i, j, n, (4, 4) matrix)``.

    Raises
    ------
    PointFileError
        Missing file, or lines that are not blocks of one ``i j n`` line and
        four lines of four numbers.
    """
    p = Path(path)
    if not p.is_file():
        raise _fail(path, "no such file.")
    rows = [line.split() for line in p.read_text(encoding="utf-8").splitlines() if line.strip()]
    if len(rows) % 5:
        raise _fail(path, f"expected blocks of 5 lines (i j n, then a 4x4 matrix), got {len(rows)} lines.")
    out = []
    for b in range(0, len(rows), 5):
        try:
            i, j, n = (int(v) for v in rows[b])
            m = np.array([[float(v) for v in r] for r in rows[b + 1:b + 5]])
        except ValueError:
            raise _fail(path, f"block at line {b + 1} is not `i j n` and a 4x4 matrix.") from None
        if m.shape != (4, 4):
            raise _fail(path, f"block at line {b + 1}: expected a 4x4 matrix, got shape {m.shape}.")
        out.append((i, j, n, m))
    return out
