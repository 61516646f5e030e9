"""Sparse tensor voting in 3D (Reyes, Medioni & Bayro 2007, section 3).

Public functions: :func:`vote` (one sparse ball or stick pass),
:func:`extract_surfaces` (section 3.3 in full) and :func:`default_sigma`.
The voting fields are described in :mod:`gatv.voting._fields`; the numba
kernels live in :mod:`gatv.voting._passes` (ball and stick passes),
:mod:`gatv.voting._eigen` (3×3 eigen-solver), :mod:`gatv.voting._simd`
(8-lane helpers) and :mod:`gatv.voting._grid` (neighbour grid).  Timings
behind the choices below are in ``docs/design-notes.md``.

Neighbour search.  A numba uniform grid (cells of side ``r`` for voting
radius ``r = 2σ``, tokens counting-sorted by cell; every token scans the 5
of the 3×3 x-rows of cells around its own that lie after it in cell order,
each x-row a contiguous run trimmed to the voting sphere), not
``scipy.spatial.cKDTree``, whose build and ball queries cost about 100× more
than building the grid (``benchmarks/voting.py``).  Cells of side ``r``, not
``r/2``: a row costs far more than a candidate (a dependent ``start`` lookup
and a mispredicted loop exit), so fewer, longer rows win; the runs are found
first and their first tokens touched before any is scanned.

Each pair of tokens is visited once, from its lower sorted index, and its
votes are added to both tokens (the ball vote is the same both ways; the two
stick votes share the distance); chunks of ``reach`` cell keys, run even then
odd, keep the parallel loop race-free and the sums in a fixed order.  This
halves the neighbour search and the ball votes.  See
:mod:`gatv.voting._passes`.

Neighbour lists.  :func:`extract_surfaces` runs its ball pass and its first
stick pass at the same σ, so the ball pass records each token's upper
neighbours (int32 CSR, ``NL_ROW`` entries reserved per token, ~k/2 used) and
the stick pass sums over them instead of scanning the grid again.  The lists
get the memory budget left after the O(N) storage; tokens whose list does
not fit their chunk's share are scanned as before, with the same results.
Later stick passes grow σ, so they scan the grid.

Eight lanes.  On x86 hosts with AVX2 or AVX-512 (``_simd.SIMD``) the
distance test of the scan, the ball and stick votes and the eigen-analysis
run on 8 tokens at a time through explicit LLVM vectors: the scan
compress-stores the indices and offsets of the tokens inside the sphere, so
the ball votes read contiguous offsets; the stick flush keeps two 4-wide
dependency chains in flight; the eigen-analysis sums Chebyshev series
instead of calling acos and cos.  Same arithmetic as the scalar loops up to
rounding (property tests; the scalar loops stay, for other hosts and for the
tests).  Each is faster than its scalar loop on those hosts.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numba import get_num_threads

from gatv import _icp_kernels  # its KDTree, at call time (it imports gatv.voting._eigen)
from gatv._validation import memory_budget_limit, as_points, as_vectors, check_memory, check_positive
from gatv.voting import _fields
from gatv.voting import _passes as K
from gatv.voting._simd import SIMD
from gatv.voting._grid import Grid, build_grid, grid_layout

from ..errors import InputError

if TYPE_CHECKING:  # pragma: no cover
    from numpy.typing import NDArray

    FloatArray = NDArray[np.float64]

__all__ = [
    "TensorVotes",
    "SurfaceResult",
    "vote",
    "extract_surfaces",
    "default_sigma",
    "voting_radius",
]

#: Grid cells per voting radius (cell side ``r / GRID_SUBDIV``); see the module notes.
GRID_SUBDIV = 1
#: Bytes of O(N) working storage per token at the peak of :func:`extract_surfaces`
#: (first stick pass): grid 80 (sorted copy and coordinates, order, cells), ball
#: pass 104 (tensor, eigen output, counts) kept sorted plus 104 unsorted for the
#: result, list starts and lengths 16, stick inputs 96 (weights, normals, the
#: (N, 8) voter records) and outputs 104.
VOTING_BYTES_PER_TOKEN = 512
#: Bytes per entry of the neighbour lists shared by a ball and a stick pass (int32).
NL_BYTES_PER_PAIR = 4
#: Tokens that make fewer race-free chunks than this (a cluster within a few voting radii: a phase of the
#: ball pass would run one chunk, on one thread) are voted in :data:`PRIVATE_CHUNKS` chunks instead, each
#: into an accumulator of its own (:func:`gatv.voting._passes.ball_pass_private`).
PRIVATE_BELOW = 4
#: A fixed count, so that the sums' order does not depend on the threads.
PRIVATE_CHUNKS = 16
#: Most tokens of such a pass (its accumulators: 29 MB at most).
PRIVATE_MAX_TOKENS = 32768
#: Bytes a token takes in each private accumulator (a tensor and a count).
PRIVATE_BYTES_PER_TOKEN = 8 * (6 + 1)
#: Bytes per entry of a thread's scratch buffers, sized by
#: :func:`gatv.voting._passes.half_shell_capacity`: an int64 index, 7 stick
#: inputs (4 offsets in the ball pass) and 6 outputs (float64).
SCRATCH_BYTES = 8 * (1 + 7 + 6)


def voting_radius(sigma: float) -> float:
    """Voting radius ``r = 2σ``: tokens at ``l ≥ r`` neither vote nor are voted on.

    At ``l = 2σ`` the decay of eq. 44 is at most ``e⁻⁴ ≈ 0.018``.
    """
    return _fields.RADIUS_FACTOR * sigma


# ---------------------------------------------------------------------------
# results
# ---------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class TensorVotes:
    """Accumulated tensors of one sparse voting pass, one row per token.

    Attributes
    ----------
    eigenvalues : (N, 3) ndarray of float
        λ1 ≥ λ2 ≥ λ3 of each token's tensor.
    normals : (N, 3) ndarray of float
        Unit eigenvector e1 (preferred normal; sign arbitrary).
    components : (N, 6) ndarray of float
        Tensor components ``(xx, xy, xz, yy, yz, zz)``; :attr:`tensors`
        expands them to ``(N, 3, 3)``.
    sigma : float
        Scale σ used; the voting radius is :attr:`radius` ``= 2σ``.
    kind : str
        ``"ball"`` or ``"stick"``.
    n_votes : (N,) ndarray of int
        Voters within the voting radius of each token (self included; for the
        stick pass only voters with nonzero saliency).
    """

    eigenvalues: np.ndarray
    normals: np.ndarray
    components: np.ndarray
    sigma: float
    kind: str
    n_votes: np.ndarray = field(repr=False)

    @property
    def radius(self) -> float:
        return voting_radius(self.sigma)

    @property
    def surfaceness(self) -> np.ndarray:
        """λ1 − λ2."""
        return self.eigenvalues[:, 0] - self.eigenvalues[:, 1]

    @property
    def curveness(self) -> np.ndarray:
        """λ2 − λ3."""
        return self.eigenvalues[:, 1] - self.eigenvalues[:, 2]

    @property
    def pointness(self) -> np.ndarray:
        """λ3."""
        return self.eigenvalues[:, 2]

    @property
    def tensors(self) -> np.ndarray:
        """(N, 3, 3) symmetric tensors."""
        c = self.components
        return c[:, [0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(-1, 3, 3)

    def __len__(self) -> int:
        return self.eigenvalues.shape[0]


@dataclass(frozen=True, eq=False)
class SurfaceResult:
    """Tokens kept by the surface detection of section 3.3.

    Attributes
    ----------
    indices : (K,) ndarray of int
        Indices (into the input tokens) of the surviving tokens, ascending.
    normals : (K, 3) ndarray of float
        Their unit normals after the last stick pass.
    surfaceness : (K,) ndarray of float
        Their λ1 − λ2 after the last stick pass.
    eigenvalues : (K, 3) ndarray of float
        Their eigenvalues after the last stick pass.
    sigma : float
        σ of the last stick pass.
    ball : TensorVotes
        The sparse ball pass over all tokens (σ of the first pass); its
        eigenvalues give the absolute saliency used to find the dense
        pure-translation cluster of section 3.4.
    n_surviving : tuple of int
        Survivors after each stick pass.
    """

    indices: np.ndarray
    normals: np.ndarray
    surfaceness: np.ndarray
    eigenvalues: np.ndarray
    sigma: float
    ball: TensorVotes = field(repr=False)
    n_surviving: tuple[int, ...] = ()

    def __len__(self) -> int:
        return self.indices.shape[0]

    def __bool__(self) -> bool:
        return self.indices.shape[0] > 0


# ---------------------------------------------------------------------------
# engine (sorted order)
# ---------------------------------------------------------------------------


def _chunks(grid: Grid) -> np.ndarray:
    """Token bounds of the chunks of the kernels' race-free parallel loop.

    Dense layout: runs of ``reach ≤ m·(nx·ny + nx + 1)`` consecutive cell keys,
    the farthest a token's upper neighbours can lie ahead of its own cell, so
    chunks of the same parity never write the same token.  Hashed layout: one
    chunk (serial).
    """
    if grid.hashed:
        return np.array([0, grid.n], np.int64)
    nx, ny, nz = grid.dims
    ncells = nx * ny * nz
    keys = np.append(np.arange(0, ncells, _reach(grid.dims, grid.subdiv)), ncells)
    return np.ascontiguousarray(grid.start[keys])


def _reach(dims, m: int) -> int:
    """The farthest key offset of an upper neighbour (no offset along a 1-cell axis): a chunk's cell keys."""
    nx, ny, nz = dims
    return max(1, min(m, nz - 1) * nx * ny + min(m, ny - 1) * nx + min(m, nx - 1))


def _private(n: int, dims, hashed: bool, m: int) -> bool:
    """Whether the ball pass over ``n`` tokens on a grid of ``dims`` (in the kernels' axis order) votes into
    private accumulators (:data:`PRIVATE_CHUNKS`): fewer race-free chunks (:func:`_chunks`) than
    :data:`PRIVATE_BELOW`, and few enough tokens."""
    nx, ny, nz = dims
    n_chunks = 1 if hashed else -(-(nx * ny * nz) // _reach(dims, m))
    return n_chunks < PRIVATE_BELOW and n <= PRIVATE_MAX_TOKENS


class Engine:
    """Grid over the tokens at one σ; passes return sorted-order arrays.

    ``ball(record=True)`` also keeps each token's upper-neighbour list (CSR,
    int32; see :func:`gatv.voting._passes.ball_pass`) that the next
    :meth:`stick` at the same σ reuses instead of scanning the grid again;
    ``max_pairs`` (from the memory budget, less the kernels' per-thread
    scratch buffers of :func:`~gatv.voting._passes.half_shell_capacity`
    entries) caps their length; tokens whose list does not fit are scanned
    as usual.
    """

    def __init__(self, points: np.ndarray, sigma: float, max_pairs: int = 0):
        self._K = K
        self.sigma = sigma
        self.radius = voting_radius(sigma)
        # The chunks of the parallel loop are layers of cells along the grid's
        # slowest key axis (the third); flat data (a plane z = const) would make
        # a single chunk, so the axis with the most cells goes last.  The
        # kernels then work in that axis order; outputs are permuted back.
        h, lo, dims, hashed, nkeys = grid_layout(points, self.radius, GRID_SUBDIV)
        big = int(np.argmax(dims))
        self.perm = None if dims[2] == dims[big] else np.array([a for a in range(3) if a != big] + [big])
        if self.perm is None:
            self.grid: Grid = build_grid(points, self.radius, GRID_SUBDIV, (h, lo, dims, hashed, nkeys))
        else:
            layout = (h, lo[self.perm], tuple(dims[a] for a in self.perm), hashed, nkeys)
            self.grid = build_grid(np.ascontiguousarray(points[:, self.perm]), self.radius, GRID_SUBDIV, layout)
            inv = np.argsort(self.perm)
            comp = {(0, 0): 0, (0, 1): 1, (0, 2): 2, (1, 1): 3, (1, 2): 4, (2, 2): 5}
            self._t6_back = np.array([comp[tuple(sorted((inv[i], inv[j])))]
                                      for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))])
            self._inv = inv
        self.cb = _chunks(self.grid)
        g = self.grid
        # A few race-free chunks (tokens packed within a few voting radii, a judge's dense cluster): the ball
        # pass votes PRIVATE_CHUNKS chunks of tokens into accumulators of their own, in parallel.
        few = _private(g.n, g.dims, g.hashed, g.subdiv)
        self.cb_private = np.linspace(0, g.n, PRIVATE_CHUNKS + 1).round().astype(np.int64) if few else None
        self.cap = int(K.half_shell_capacity(g.start, g.dims[0], g.dims[1], g.dims[2], g.hashed, g.subdiv))
        # the kernels' per-thread buffers (indices, stick inputs and outputs:
        # SCRATCH_BYTES per entry) come out of the neighbour lists' share
        scratch = get_num_threads() * self.cap * SCRATCH_BYTES
        self.max_pairs = max(0, int(max_pairs) - scratch // NL_BYTES_PER_PAIR)
        self.simd = SIMD  # tests switch it off to check the scalar loops
        self.lists = None  # (nbr, nstart, nup) after a recording ball pass

    @property
    def points(self) -> np.ndarray:
        """``(N, 3)`` tokens in sorted order and the caller's axis order (a new array)."""
        g = self.grid
        cols = (g.xs, g.ys, g.zs)  # kernel axis k is the caller's axis perm[k]
        return np.column_stack(cols if self.perm is None else [cols[k] for k in self._inv])

    def _back(self, acc, vals, e1, cnt):
        """Outputs of a kernel in the original axis order."""
        if self.perm is None:
            return acc, vals, e1, cnt
        return (np.ascontiguousarray(acc[:, self._t6_back]), vals,
                np.ascontiguousarray(e1[:, self._inv]), cnt)

    def _cells(self):
        g = self.grid
        return (g.cix, g.ciy, g.ciz, g.start, g.dims[0], g.dims[1], g.dims[2], g.hashed, g.mask,
                g.subdiv, g.lo, g.h, self.radius**2)

    def _out(self):
        n = self.grid.n
        return np.zeros((n, 6)), np.empty((n, 3)), np.empty((n, 3)), np.zeros(n, np.int64)

    def ball(self, record: bool = False):
        tab = _fields.ball_table4()
        tscale = _fields.BALL_TABLE_SIZE / self.radius**2
        g = self.grid
        n = g.n
        acc, vals, e1, cnt = self._out()
        row = min(self._K.NL_ROW, self.max_pairs // max(n, 1)) if record else 0
        if row > 0:
            nbr = np.empty(n * row, np.int32)
            nstart, nup = np.empty(n, np.int64), np.empty(n, np.int64)
        else:
            nbr, nstart, nup = np.empty(0, np.int32), np.empty(0, np.int64), np.empty(0, np.int64)
        run = self._K.ball_pass if self.cb_private is None else self._K.ball_pass_private
        cb = self.cb if self.cb_private is None else self.cb_private
        run(g.xs, g.ys, g.zs, *self._cells(), tab, tscale, cb, get_num_threads(), self.cap, self.simd, acc, vals, e1,
            cnt, nbr, cb * row, nstart, nup)
        self.lists = (nbr, nstart, nup) if row > 0 else None
        return self._back(acc, vals, e1, cnt)

    def stick(self, normals_sorted: np.ndarray, weights_sorted: np.ndarray):
        g = self.grid
        acc, vals, e1, cnt = self._out()
        nrm = np.asarray(normals_sorted, dtype=np.float64)
        nrm = np.ascontiguousarray(nrm if self.perm is None else nrm[:, self.perm])
        if self.lists is None:
            nbr, nstart, nup = np.empty(0, np.int32), np.empty(0, np.int64), np.empty(0, np.int64)
        else:
            nbr, nstart, nup = self.lists
        w = np.ascontiguousarray(weights_sorted, dtype=np.float64)
        self._K.stick_pass(g.xs, g.ys, g.zs, nrm, w, *self._cells(), 1.0 / self.sigma**2, 4.0 * _fields.GAMMA,
                           1.0 / _fields.SIGMA_REF**2, self.cb, get_num_threads(), self.cap, self.simd,
                           acc, vals, e1, cnt, nbr, nstart, nup)
        return self._back(acc, vals, e1, cnt)

    def drop_lists(self) -> None:
        self.lists = None

    def to_sorted(self, a: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(a[self.grid.order])

    def unsort(self, *arrays):
        order = self.grid.order
        out = []
        for a in arrays:
            b = np.empty_like(a)
            b[order] = a
            out.append(b)
        return out


def check_budget(points: np.ndarray, sigma: float, memory_budget) -> int:
    """Check the O(N) working storage; return how many neighbour-list entries fit.

    The upper-neighbour lists of a recording ball pass (int32, ``NL_ROW``
    entries reserved per token, ~k/2 used at the default σ) are optional:
    they get what the budget leaves after the O(N) storage.  If nothing is
    left the stick pass scans the grid instead (same results, slower).
    """
    n = points.shape[0]
    radius = voting_radius(sigma)
    _, _, dims, hashed, nkeys = grid_layout(points, radius, GRID_SUBDIV)
    nbytes = n * VOTING_BYTES_PER_TOKEN + 8 * (nkeys + 1)
    big = int(np.argmax(dims))  # the kernels' axis order (Engine): the axis with the most cells last
    if _private(n, tuple(dims[a] for a in range(3) if a != big) + (dims[big],), hashed, GRID_SUBDIV):
        nbytes += n * PRIVATE_CHUNKS * PRIVATE_BYTES_PER_TOKEN
    check_memory(nbytes, f"Voting on {n} tokens", memory_budget)
    spare = memory_budget_limit(memory_budget) - nbytes
    return max(0, int(spare // NL_BYTES_PER_PAIR))


def _votes(engine: Engine, kind: str, res) -> TensorVotes:
    t6, vals, e1, cnt = engine.unsort(*res)
    for a in (t6, vals, e1, cnt):
        a.setflags(write=False)
    return TensorVotes(vals, e1, t6, engine.sigma, kind, cnt)


# ---------------------------------------------------------------------------
# public API
# ---------------------------------------------------------------------------


def default_sigma(tokens, k: int = 40, *, sample: int = 2000, seed: int = 0) -> float:
    """Scale σ such that a typical token has about ``k`` others within ``r = 2σ``.

    σ is half the median, over a random subsample of ``sample`` tokens, of the
    distance to the ``k``-th nearest other token (exact, by a k-d tree).
    If that median is 0 (more than half the tokens have ``k`` coincident
    copies) the median of the positive distances is used.

    Parameters
    ----------
    tokens : (N, 3) array_like of float
        Token positions, N ≥ 2.
    k : int, default: 40
        Target number of neighbours inside the voting radius (clipped to N − 1).
    sample : int, default: 2000
        Number of query tokens.
    seed : int, default: 0
        Seed of the subsample.

    Returns
    -------
    float

    Raises
    ------
    ValueError
        Bad tokens, fewer than 2 tokens, or all tokens coincide.

    Examples
    --------
    >>> import numpy as np
    >>> pts = np.random.default_rng(0).uniform(size=(20000, 3))
    >>> s = default_sigma(pts)
    >>> bool(0.03 < s < 0.05)
    True
    """
    pts = as_points(tokens, "tokens", min_points=2)
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        msg = f"Expected `k` to be a positive integer, got {k!r}."
        raise InputError(msg)
    return _default_sigma(pts, int(k), sample, seed)


def _default_sigma(pts: np.ndarray, k: int, sample: int = 2000, seed: int = 0) -> float:
    n = pts.shape[0]
    k = min(k, n - 1)
    rng = np.random.default_rng(seed)
    q = pts if n <= sample else pts[rng.choice(n, size=sample, replace=False)]
    # Exact k-th distances, as cKDTree's, from the numba tree (faster here: design notes, section 6).
    d = _icp_kernels.KDTree(pts).query(q, k=k + 1)[0][:, k]
    r = float(np.median(d))
    if r <= 0.0:
        pos = d[d > 0]
        if pos.size == 0:
            msg = "Cannot derive `sigma` from the tokens: they coincide; pass `sigma` explicitly."
            raise InputError(msg)
        r = float(np.median(pos))
    return r / _fields.RADIUS_FACTOR


def _prepare(tokens, sigma, memory_budget, k):
    pts = as_points(tokens, "tokens", min_points=1)
    sigma = check_positive(sigma, "sigma", allow_none=True)
    if sigma is None:
        if pts.shape[0] < 2:
            msg = "Cannot derive `sigma` from a single token; pass `sigma` explicitly."
            raise InputError(msg)
        sigma = _default_sigma(pts, k)
    max_pairs = check_budget(pts, sigma, memory_budget)
    return pts, sigma, max_pairs


def _as_normals(normals, n: int) -> np.ndarray:
    nrm = as_vectors(normals, "normals", n)
    length = np.linalg.norm(nrm, axis=1)
    if np.any(length == 0):
        msg = f"`normals` has {int(np.count_nonzero(length == 0))} zero rows; normals must be nonzero."
        raise InputError(msg)
    return np.ascontiguousarray(nrm / length[:, None])


def _as_saliency(saliency, n: int) -> np.ndarray:
    if saliency is None:
        return np.ones(n)
    try:
        w = np.asarray(saliency, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        msg = f"Expected `saliency` to be an array of {n} numbers: {exc}."
        raise InputError(msg) from exc
    if w.ndim == 0:
        w = np.full(n, float(w))
    if w.shape != (n,):
        msg = f"Expected `saliency` to have shape ({n},) to match the tokens, got {w.shape}."
        raise InputError(msg)
    if not np.all(np.isfinite(w)):
        msg = "`saliency` contains NaN or infinite values."
        raise InputError(msg)
    if np.any(w < 0):
        msg = f"`saliency` must be >= 0, got a minimum of {float(w.min())!r}."
        raise InputError(msg)
    return np.ascontiguousarray(w)


def vote(tokens, sigma=None, normals=None, *, saliency=None, k: int = 40,
         memory_budget: float | None = None) -> TensorVotes:
    """One sparse tensor-voting pass over 3D tokens (section 3.3).

    Without ``normals`` every token is a unit ball tensor and casts a ball vote
    (eqs. 46–48); with ``normals`` each token casts a stick vote (eq. 44) along
    its normal, weighted by ``saliency``.  Every token receives the votes of
    all tokens within the voting radius ``r = 2σ``, **its own included**: the
    accumulator of a votee starts from its own encoded tensor (the identity for
    the ball pass, ``saliency·n nᵀ`` for the stick pass), as in section 3.2
    where a stick vote is added to the tensor already at the votee.

    Parameters
    ----------
    tokens : (N, 3) array_like of float
        Token positions (finite).
    sigma : float, optional
        Scale σ in the units of ``tokens``; default :func:`default_sigma`.
    normals : (N, 3) array_like of float, optional
        Voter normals (normalised here); ``None`` runs the ball pass.
    saliency : (N,) array_like of float, optional
        Stick-vote weights ≥ 0, default 1.  A weight of 0 switches a token off
        as a voter (it still receives votes).  Ignored by the ball pass.
    k : int, default: 40
        Neighbour target of :func:`default_sigma` when ``sigma`` is None.
    memory_budget : float, optional
        Byte budget (default ``GATV_MEMORY_BUDGET`` or 4 GiB).

    Returns
    -------
    TensorVotes

    Raises
    ------
    ValueError
        Bad input (naming the argument), or an input over the memory budget.

    References
    ----------
    Reyes, Medioni & Bayro, IJCV 75(3) 2007, eqs. 43–48 and section 3.3.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> plane = np.c_[rng.uniform(-1, 1, (2000, 2)), np.zeros(2000)]
    >>> tv = vote(plane)
    >>> bool(np.median(np.abs(tv.normals[:, 2])) > 0.99)
    True
    """
    pts, sigma, _ = _prepare(tokens, sigma, memory_budget, k)
    n = pts.shape[0]
    if normals is None:
        if saliency is not None:
            _as_saliency(saliency, n)
        eng = Engine(pts, sigma)
        return _votes(eng, "ball", eng.ball())
    nrm = _as_normals(normals, n)
    w = _as_saliency(saliency, n)
    eng = Engine(pts, sigma)
    return _votes(eng, "stick", eng.stick(eng.to_sorted(nrm), eng.to_sorted(w)))


def _parse_threshold(threshold) -> tuple[float, float]:
    if np.ndim(threshold) == 0:
        t = (threshold, threshold)
    else:
        t = tuple(threshold)
    if len(t) != 2:
        msg = f"Expected `threshold` to be a number or a pair, got {threshold!r}."
        raise InputError(msg)
    out = []
    for v in t:
        if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)) \
                or not 0 <= float(v) < 1:
            msg = f"Expected `threshold` values in [0, 1), got {threshold!r}."
            raise InputError(msg)
        out.append(float(v))
    return out[0], out[1]


#: Draws of :func:`chance_surfaceness`'s Monte Carlo null, per voter count.
CHANCE_DRAWS = 4000


@functools.lru_cache(maxsize=None)
def _chance_table(voters: int, chance: float) -> float:
    # n voters uniform in the ball of radius RADIUS_FACTOR·σ (σ = 1, the ratio is scale-free), each a ball
    # vote b I + (a − b) v̂v̂ᵀ (eqs. 46–48), and the votee's own identity (see :func:`vote`).
    rng = np.random.default_rng([voters, 7])
    u = rng.normal(size=(CHANCE_DRAWS, voters, 3))
    u /= np.linalg.norm(u, axis=2, keepdims=True)
    q = _fields.RADIUS_FACTOR ** 2 * rng.uniform(size=(CHANCE_DRAWS, voters)) ** (2.0 / 3.0)
    a, b = _fields.ball_radial(q)
    t = np.matmul(((a - b)[:, :, None] * u).transpose(0, 2, 1), u)
    t += (1.0 + b.sum(axis=1))[:, None, None] * np.eye(3)
    w = np.linalg.eigvalsh(t)
    return float(np.quantile((w[:, 2] - w[:, 1]) / w[:, 2], 1.0 - chance))


#: Voter counts at which :func:`chance_surfaceness` runs its null; counts between them take the larger of
#: the two neighbouring quantiles, counts beyond the last the last's.
CHANCE_VOTERS = (2, 3, 4, 5, 6, 8, 10, 12, 16, 20, 24, 32, 40, 48, 64, 80, 96, 128)


def chance_surfaceness(voters, chance: float = 0.01) -> np.ndarray:
    """What a ball-pass token's surfaceness ``(λ1 − λ2)/λ1`` reaches by chance.

    The ``1 − chance`` quantile of ``(λ1 − λ2)/λ1`` of the ball pass
    (eqs. 46–48, the token's own unit ball included) at a token whose
    ``voters`` other tokens lie uniformly at random in its voting ball:
    unstructured clutter, at any density.  Tokens on a plane reach about
    0.25 (the ball field's ``(b − a)/2b`` summed over the plane), and more
    the more voters they have; isotropic voters reach 0.11–0.18 at
    ``chance`` 0.01.  The ratio does not depend on the scale or the density,
    only on the number of voters, which is why it tells a sparse surface
    from clutter where the saliency ``λ1 − λ2``, which grows with the
    voters, cannot (:func:`extract_surfaces`' ``planar_chance``).

    Parameters
    ----------
    voters : int or array_like of int
        Other tokens within the voting radius (``n_votes − 1``).
    chance : float, default: 0.01
        Share of isotropic tokens above the returned level, in (0, 1).

    Returns
    -------
    ndarray of float
        One level per entry of ``voters`` (a Monte Carlo estimate over
        :data:`CHANCE_DRAWS` draws a count, seeded by the count: the same
        on every call); ``inf`` below two voters (with one, ``λ1 = λ2``
        exactly: no plane).
    """
    chance = float(chance)
    if not 0.0 < chance < 1.0:
        raise InputError(f"Expected `chance` in (0, 1), got {chance!r}.")
    n = np.asarray(voters)
    if n.size and (not np.issubdtype(n.dtype, np.integer) or n.min() < 0):
        raise InputError("Expected `voters` to be non-negative integers.")
    grid = np.asarray(CHANCE_VOTERS)
    levels = np.array([_chance_table(int(v), chance) for v in grid])
    k = np.clip(np.searchsorted(grid, n, side="right") - 1, 0, grid.size - 1)  # grid[k] <= n
    above = np.minimum(k + 1, grid.size - 1)
    exact = grid[k] == n
    out = np.where(exact | (n > grid[-1]), levels[k], np.maximum(levels[k], levels[above]))
    return np.where(n < 2, np.inf, out)


def extract_surfaces(tokens, sigma=None, *, n_stick_passes: int = 3, sigma_growth: float = 1.5,
                     threshold=0.1, k: int = 40, planar_chance: float | None = None,
                     memory_budget: float | None = None) -> SurfaceResult:
    """Detect the most salient surface(s) among 3D tokens (section 3.3).

    1. Every token is a unit ball tensor; a sparse ball pass at σ gives each
       token a normal e1 and a surfaceness λ1 − λ2 (kept in ``result.ball``).
    2. Sparse stick pass: every token votes along its normal with saliency
       ``(λ1 − λ2)/max(λ1 − λ2)``.
    3. Thresholding relative to the most salient token t* (largest λ1 − λ2):
       a token survives if ``λ1 ≥ τ1·λ1(t*)`` and ``λ1 − λ2 ≥ τ2·(λ1 − λ2)(t*)``.
       Discarded tokens are set to zero: they never vote or count again.
       With ``planar_chance``, a token whose ball pass alone looks planar
       beyond chance survives too (below).
    4. Steps 2–3 are repeated, ``n_stick_passes`` stick passes in all, σ being
       multiplied by ``sigma_growth`` before each pass after the first, and
       only the survivors voting (and being voted on).

    Parameters
    ----------
    tokens : (N, 3) array_like of float
        Tokens in the joint space.
    sigma : float, optional
        Initial scale; default :func:`default_sigma` (``k`` neighbours).
    n_stick_passes : int, default: 3
        Number of sparse stick passes (≥ 1).
    sigma_growth : float, default: 1.5
        Factor (≥ 1) applied to σ between stick passes to grow the surfaces.
    threshold : float or (float, float), default: 0.1
        ``(τ1, τ2)`` fractions of the most salient token's λ1 and λ1 − λ2; one
        number sets both.
    planar_chance : float, optional
        Also keep, at every pass, each token whose ball pass's ``(λ1 − λ2)/λ1``
        reaches :func:`chance_surfaceness` of its voters at this chance: one
        whose neighbourhood is planar beyond what isotropic clutter gives.
        Step 3's rule is relative to the *densest* surface (saliency grows with
        the voters), so a surface sampled more sparsely than another drops out
        whole; the ratio depends on the shape of the neighbourhood alone.
        None (default): step 3 alone, the paper's rule.
    k, memory_budget
        As in :func:`vote`.

    Returns
    -------
    SurfaceResult
        Falsy when no token survives.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(1)
    >>> plane = np.c_[rng.uniform(-1, 1, (3000, 2)), np.zeros(3000)]
    >>> noise = rng.uniform(-1, 1, (3000, 3))
    >>> res = extract_surfaces(np.vstack([plane, noise]))
    >>> bool(np.mean(res.indices < 3000) > 0.9)
    True
    """
    pts, sigma, max_pairs = _prepare(tokens, sigma, memory_budget, k)
    if isinstance(n_stick_passes, bool) or not isinstance(n_stick_passes, (int, np.integer)) \
            or n_stick_passes < 1:
        msg = f"Expected `n_stick_passes` to be an integer >= 1, got {n_stick_passes!r}."
        raise InputError(msg)
    growth = check_positive(sigma_growth, "sigma_growth")
    if growth < 1.0:
        msg = f"Expected `sigma_growth` >= 1, got {sigma_growth!r}."
        raise InputError(msg)
    tau1, tau2 = _parse_threshold(threshold)
    if planar_chance is not None:
        planar_chance = float(planar_chance)
        if not 0.0 < planar_chance < 1.0:
            raise InputError(f"Expected `planar_chance` in (0, 1) or None, got {planar_chance!r}.")

    eng = Engine(pts, sigma, max_pairs)
    res = eng.ball(record=True)  # neighbour lists for the first stick pass
    ball = _votes(eng, "ball", res)
    _, vals, e1, cnt = res  # sorted order
    if planar_chance is None:
        planar = np.zeros(vals.shape[0], bool)
    else:  # density-free: the ball tensor's shape against isotropic voters as many
        ratio = (vals[:, 0] - vals[:, 1]) / np.maximum(vals[:, 0], np.finfo(np.float64).tiny)
        planar = ratio >= chance_surfaceness(np.maximum(cnt.astype(np.int64) - 1, 0), planar_chance)
    idx = eng.grid.order.copy()  # original index of each current token
    cur_pts = eng.points
    counts = []
    s = sigma
    for p in range(n_stick_passes):
        if p > 0:
            s *= growth
            check_budget(cur_pts, s, memory_budget)
            sub = Engine(cur_pts, s)  # larger σ: the ball pass's lists are too short
            e1 = sub.to_sorted(e1)
            sal = sub.to_sorted(sal)
            planar = sub.to_sorted(planar)
            idx = idx[sub.grid.order]
            eng = sub
        else:
            sal = vals[:, 0] - vals[:, 1]
        top = float(sal.max()) if sal.size else 0.0
        w = sal / top if top > 0 else np.zeros_like(sal)
        _, vals, e1, _ = eng.stick(e1, np.ascontiguousarray(w))
        eng.drop_lists()
        sal = vals[:, 0] - vals[:, 1]
        if sal.size == 0 or sal.max() <= 0:
            keep = np.zeros(sal.shape[0], bool)
        else:
            star = int(np.argmax(sal))
            keep = (vals[:, 0] >= tau1 * vals[star, 0]) & (sal >= tau2 * sal[star])
        keep |= planar & (sal > 0)
        cur_pts = np.ascontiguousarray(eng.points[keep])
        e1 = np.ascontiguousarray(e1[keep])
        vals = vals[keep]
        sal = sal[keep]
        planar = planar[keep]
        idx = idx[keep]
        counts.append(int(keep.sum()))
        if not keep.any():
            break
    order = np.argsort(idx, kind="stable")
    return SurfaceResult(idx[order], e1[order], sal[order], vals[order], s, ball, tuple(counts))
