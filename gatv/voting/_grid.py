"""Uniform-grid neighbour structure for radius searches (private).

Tokens are binned into cubic cells of side ``h = radius / subdiv`` and
counting-sorted by cell, so that every cell is a contiguous run of the sorted
token array.  Nothing per pair is stored: a votee visits the
``(2·subdiv + 1)³`` cells around its own and scans their runs.

Two layouts share the kernels:

* **dense** — cell id ``ix + nx·(iy + ny·iz)`` (x fastest) over the bounding
  box; ``start`` has one entry per cell, and the ``2·subdiv + 1`` cells of one
  x-row are one contiguous run.  Used while the box holds at most
  ``max(8·N, 2²⁰)`` cells.
* **hashed** — when the bounding box is too large for a dense cell array
  (tokens spread over a huge box with a tiny σ), cells are hashed into a table
  of ``2^⌈log₂ 2N⌉`` buckets.  Colliding cells share a bucket; every token
  keeps its integer cell coordinates so a scan only accepts tokens of the
  requested cell, hence no vote is counted twice.  Memory stays O(N).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from ..errors import InputError

__all__ = ["Grid", "build_grid"]

#: Largest number of cells of a dense layout, as ``max(DENSE_PER_TOKEN·N, DENSE_MIN)``.
DENSE_PER_TOKEN = 8
DENSE_MIN = 1 << 20
#: Largest bounding-box extent, in cells, that integer cell coordinates can hold.
MAX_CELLS_PER_AXIS = float(2**40)

_H1 = 73856093
_H2 = 19349663
_H3 = 83492791


@njit(cache=True, inline="always")
def cell_hash(cx, cy, cz, mask):
    """Bucket of integer cell ``(cx, cy, cz)`` in a table of ``mask + 1`` buckets."""
    return ((cx * _H1) ^ (cy * _H2) ^ (cz * _H3)) & mask


@njit(cache=True, parallel=True)
def _bounds(points):
    """Per-axis minimum and maximum of ``(N, 3)`` points (N ≥ 1), one parallel pass."""
    n = points.shape[0]
    nb = min(n, 64)
    blo = np.empty((nb, 3))
    bhi = np.empty((nb, 3))
    for b in prange(nb):
        i0 = b * n // nb
        i1 = (b + 1) * n // nb
        for k in range(3):
            lo = points[i0, k]
            hi = lo
            for i in range(i0 + 1, i1):
                v = points[i, k]
                lo = min(lo, v)
                hi = max(hi, v)
            blo[b, k] = lo
            bhi[b, k] = hi
    lo = blo[0].copy()
    hi = bhi[0].copy()
    for b in range(1, nb):
        for k in range(3):
            lo[k] = min(lo[k], blo[b, k])
            hi[k] = max(hi[k], bhi[b, k])
    return lo, hi


@njit(cache=True, inline="always")
def _cell(v, lo, inv_h, ncells):
    """Cell of coordinate ``v`` along an axis of ``ncells`` cells from ``lo`` (upper edge guarded)."""
    c = int((v - lo) * inv_h)
    return ncells - 1 if c >= ncells else c


@njit(cache=True, parallel=True)
def _bin(points, lo, inv_h, nx, ny, nz, hashed, mask):
    """Cell key of every token: dense id or hash bucket."""
    n = points.shape[0]
    key = np.empty(n, np.int64)
    for i in prange(n):
        x = _cell(points[i, 0], lo[0], inv_h, nx)
        y = _cell(points[i, 1], lo[1], inv_h, ny)
        z = _cell(points[i, 2], lo[2], inv_h, nz)
        if hashed:
            key[i] = cell_hash(x, y, z, mask)
        else:
            key[i] = x + nx * (y + ny * z)
    return key


@njit(cache=True, parallel=True)
def _counting_sort(key, nkeys, points, lo, inv_h, nx, ny, nz):
    """Stable counting sort by key: returns start (nkeys+1), order, sorted coordinates and cells.

    Only the coordinates are gathered through ``order`` (one random read per
    token); the cells are recomputed from the sorted coordinates with
    :func:`_bin`'s formula, which gives the same integers and reads
    sequentially (faster than gathering them).
    """
    n = key.shape[0]
    start = np.zeros(nkeys + 1, np.int64)
    for i in range(n):
        start[key[i] + 1] += 1
    for k in range(nkeys):
        start[k + 1] += start[k]
    fill = start[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        k = key[i]
        order[fill[k]] = i
        fill[k] += 1
    xs = np.empty(n, np.float64)
    ys = np.empty(n, np.float64)
    zs = np.empty(n, np.float64)
    for j in prange(n):
        i = order[j]
        xs[j] = points[i, 0]
        ys[j] = points[i, 1]
        zs[j] = points[i, 2]
    sx = np.empty(n, np.int64)
    sy = np.empty(n, np.int64)
    sz = np.empty(n, np.int64)
    for j in prange(n):
        sx[j] = _cell(xs[j], lo[0], inv_h, nx)
        sy[j] = _cell(ys[j], lo[1], inv_h, ny)
        sz[j] = _cell(zs[j], lo[2], inv_h, nz)
    return start, order, xs, ys, zs, sx, sy, sz


@dataclass(frozen=True, eq=False)
class Grid:
    """Tokens sorted by cell plus the cell index (all arrays in sorted order)."""

    xs: np.ndarray  # (N,) sorted x (structure of arrays, for the kernels)
    ys: np.ndarray
    zs: np.ndarray
    order: np.ndarray  # (N,) sorted position -> original index
    cix: np.ndarray
    ciy: np.ndarray
    ciz: np.ndarray
    start: np.ndarray  # (ncells + 1,) dense, or (buckets + 1,) hashed
    dims: tuple[int, int, int]
    hashed: bool
    mask: int
    subdiv: int
    radius: float
    lo: np.ndarray  # (3,) corner of the bounding box
    h: float  # cell side

    @property
    def n(self) -> int:
        return self.xs.shape[0]

    @property
    def points(self) -> np.ndarray:
        """``(N, 3)`` sorted tokens (a new array)."""
        return np.column_stack((self.xs, self.ys, self.zs))


def grid_layout(points: np.ndarray, radius: float, subdiv: int):
    """Cell side, box corner, dims and whether the layout must be hashed."""
    h = radius / subdiv
    lo, hi = _bounds(points)
    ext = hi - lo
    cells = ext / h
    if np.any(cells >= MAX_CELLS_PER_AXIS):
        msg = (
            f"The tokens span {float(ext.max()):.3g} units, more than {MAX_CELLS_PER_AXIS:.3g} "
            f"voting cells of side {h:.3g}; `sigma` is too small for this extent."
        )
        raise InputError(msg)
    dims = tuple(int(c) + 1 for c in cells)
    n = points.shape[0]
    ncells = dims[0] * dims[1] * dims[2]  # Python int: no overflow
    hashed = ncells > max(DENSE_PER_TOKEN * n, DENSE_MIN)
    nkeys = (1 << max(1, math.ceil(math.log2(2 * n)))) if hashed else ncells
    return h, lo, dims, hashed, nkeys


def build_grid(points: np.ndarray, radius: float, subdiv: int = 1, layout=None) -> Grid:
    """Bin and counting-sort ``points`` (C-contiguous float64) by cell.

    ``layout``: :func:`grid_layout` of these points, when the caller has it.
    """
    h, lo, dims, hashed, nkeys = grid_layout(points, radius, subdiv) if layout is None else layout
    mask = nkeys - 1 if hashed else 0
    lo = np.ascontiguousarray(lo, dtype=np.float64)
    key = _bin(points, lo, 1.0 / h, dims[0], dims[1], dims[2], hashed, mask)
    start, order, xs, ys, zs, sx, sy, sz = _counting_sort(key, nkeys, points, lo, 1.0 / h, *dims)
    return Grid(xs, ys, zs, order, sx, sy, sz, start, dims, hashed, mask, subdiv, radius, lo, float(h))
