"""Numba kernels for sparse tensor voting: the ball and stick passes (private).

Arrays and scalars in, arrays out; float64 throughout; no Python objects.
Tensors are stored as 6 components ``(xx, xy, xz, yy, yz, zz)``.  The
eigen-analysis of the passes comes from :mod:`gatv.voting._eigen`; the
8-lane paths build on :mod:`gatv.voting._simd`.

Every kernel is ``@njit(cache=True)``; only the outer loops over chunks of
tokens or over tokens are ``prange``.  Voting visits each pair of tokens once
and adds its votes to both (see the comment above :func:`ball_pass`); the
chunking that keeps the parallel loop race-free also fixes the order of every
sum, so the result does not depend on the number of threads.
"""

from __future__ import annotations

import math

import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.core import cgutils
from numba.extending import intrinsic

from gatv.voting._eigen import eig_rows, eig_rows_simd
from gatv.voting._simd import LANES, Ops, lane_sums, row_vector_ptr
from gatv.voting._simd import splat as splat_ir


@njit(cache=True, inline="always")
def arcsin_ratio2(t):
    """``(asin(√t)/√t)² = (θ/sin θ)²`` for ``t = sin²θ ∈ [0, 1/2]``.

    Degree-16 polynomial in ``x = 4t − 1`` (Chebyshev fit, max error 3e-15 on
    [0, 1/2]); replaces a ``sqrt``, an ``asin`` and a division per vote.
    Estrin's scheme (depth 5 instead of 16 dependent FMAs: the vectorised
    stick flush is latency-bound).
    """
    x = 4.0 * t - 1.0
    x2 = x * x
    x4 = x2 * x2
    x8 = x4 * x4
    a0 = 1.096622711232152 + 0.1125768649239618 * x
    a1 = 0.019223205716590357 + 0.004021191635587047 * x
    a2 = 0.0009380950980537155 + 0.00023423067685740802 * x
    a3 = 6.125736394522079e-05 + 1.6567610831680862e-05 * x
    a4 = 4.59633842594097e-06 + 1.3003728142575214e-06 * x
    a5 = 3.739019978974341e-07 + 1.0982521186436823e-07 * x
    a6 = 3.244813103299451e-08 + 8.71749458263692e-09 * x
    a7 = 2.55834384061086e-09 + 1.3053246796434555e-09 * x
    b0 = a0 + a1 * x2
    b1 = a2 + a3 * x2
    b2 = a4 + a5 * x2
    b3 = a6 + a7 * x2
    d0 = b0 + b1 * x4
    d1 = b2 + b3 * x4
    return (d0 + d1 * x8) + 4.1044578648793166e-10 * (x8 * x8)


#: exp(C) for the centre C of the reduced argument of :func:`exp_neg_small`.
_EXP_C = -0.385
_EXP_EC = math.exp(_EXP_C)
#: Largest argument for which :func:`exp_neg_small` keeps full accuracy.
EXP_NEG_MAX = 6.16


@njit(cache=True, inline="always")
def exp_neg_small(x):
    """``exp(−x)`` for ``0 ≤ x ≤ EXP_NEG_MAX`` without a libm call (vectorisable).

    ``exp(−x) = (e^{y})⁸`` with ``y = −x/8 ∈ [−0.77, 0]``; ``e^{y} = e^{C} ·
    Σ_{k≤13} t^k/k!`` with ``t = y − C``, ``|t| ≤ 0.385`` (truncation 2e-17),
    then three squarings: relative error below 2e-15 (tested against
    ``math.exp``).  Larger ``x`` give finite, less accurate values.
    """
    t = -0.125 * x - _EXP_C
    t2 = t * t
    t4 = t2 * t2
    # Estrin: Σ_{k≤13} t^k/k! in pairs (depth 5 instead of 13 dependent FMAs)
    a0 = 1.0 + t
    a1 = 0.5 + (1.0 / 6.0) * t
    a2 = (1.0 / 24.0) + (1.0 / 120.0) * t
    a3 = (1.0 / 720.0) + (1.0 / 5040.0) * t
    a4 = (1.0 / 40320.0) + (1.0 / 362880.0) * t
    a5 = (1.0 / 3628800.0) + (1.0 / 39916800.0) * t
    a6 = (1.0 / 479001600.0) + (1.0 / 6227020800.0) * t
    b0 = a0 + a1 * t2
    b1 = a2 + a3 * t2
    b2 = a4 + a5 * t2
    d0 = b0 + b1 * t4
    d1 = b2 + a6 * t4
    p = (d0 + d1 * (t4 * t4)) * _EXP_EC
    p *= p
    p *= p
    return p * p


# ---------------------------------------------------------------------------
# Sparse voting, each pair once.  ``xs, ys, zs`` are the tokens sorted by
# grid cell (structure of arrays), ``cix, ciy, ciz`` their integer cells and
# ``start`` the run of each cell (dense) or hash bucket (hashed); see
# ``_grid.py``.  Outputs are in sorted order.
#
# Both votes between tokens i and j depend on the offset ``v = x_i − x_j``
# only through ``|v|`` and ``v vᵀ`` (both are even in v), so a pair is visited
# once, from its lower sorted index i: the *upper neighbours* of i are the
# tokens j > i within the voting radius, found in the half-shell of rows
# (dz > 0, or dz = 0 and dy ≥ 0; with dy = dz = 0 only j > i).  The ball vote
# of the pair is computed once and added to both tokens; the stick pass
# computes j → i and i → j with the shared distance.  i's own sum stays in
# registers and is added to its row at the end; the votes for the j's are
# scattered to their rows.
#
# Races.  In the dense layout a token only writes rows of cells at most
# ``reach ≤ m·(nx·ny + nx + 1)`` cell keys ahead of its own.  The tokens are
# cut into *chunks* of ``reach`` consecutive keys; two chunks of the same
# parity never write the same row, so the even chunks run in parallel, then
# the odd ones; threads take the next chunk of a phase from an atomic
# counter (dynamic scheduling: a thread the OS preempts on a shared machine
# does not hold back a fixed half of the work).  The order of every sum is
# fixed by the chunking alone (not by the thread that runs a chunk, nor by
# the number of threads), so results are reproducible.
# The hashed layout (rare: huge boxes) runs as one chunk.
#
# Per votee the upper neighbours are first *collected* into a buffer of
# indices (branch-free compaction: always store at ``cnt``, then
# ``cnt += inside``), then the votes are evaluated over the buffer.  The
# buffers are allocated once per chunk with room for every token of the
# half-shell runs (``cap``, see :func:`half_shell_capacity`): an array
# variable reassigned inside the token loop would cost numba's atomic
# reference counting on every token.
# ---------------------------------------------------------------------------

_H1 = 73856093
_H2 = 19349663
_H3 = 83492791
#: Upper-neighbour list entries reserved per token when a ball pass records
#: the lists for the stick pass (int32; the mean is ~k/2 at the default σ).
NL_ROW = 48

# The flush loops may reassociate their sums (vectorised reduction) and
# contract a*b+c into FMAs: both change results by a few ulps only (relative
# 1e-15, far below the 1e-12 budget), and the result stays identical from run
# to run (the code path does not depend on the number of threads).
_FLUSH_FLAGS = {"reassoc", "contract"}


def prange_only():
    """numba's ``parallel`` option with only ``prange`` loops made parallel.

    ``parallel=True`` also turns array expressions, allocations and
    reductions (``np.zeros``, ``a.max()``) into parallel loops, each compiled
    as one more outlined function with its wrappers; on small arrays
    they cost more compile time than they save.  A fresh dict for each
    use: numba empties the one it is given.
    """
    return {"comprehension": False, "reduction": False, "inplace_binop": False, "setitem": False,
            "numpy": False, "stencil": False, "fusion": False, "prange": True}


@intrinsic
def _collect_simd(typingctx, xs, ys, zs, j0, j1, xi, yi, zi, r2, bj, db, cnt):
    """:func:`_collect` for the dense layout, 8 candidates at a time.

    Per block of 8 sorted tokens: masked loads (lanes at or past ``j1`` are
    off and never read), ``d² = ((dx² + dy²) + dz²)`` in the same order and
    precision as the scalar test, and LLVM compress-stores of the lanes
    inside the sphere: indices to ``bj[cnt:]``, dx, dy, dz, d² to
    ``db[:4, cnt:]`` (a C-contiguous float64 array).  Same output as
    :func:`_collect`, in less time (most with AVX-512; AVX2 code emulates
    the compress-store).
    """
    if not all(isinstance(a, types.Array) and a.dtype == types.float64 for a in (xs, ys, zs)):
        return None
    if not (isinstance(bj, types.Array) and bj.dtype == types.int64 and bj.ndim == 1):
        return None
    if not (isinstance(db, types.Array) and db.dtype == types.float64 and db.ndim == 2 and db.layout == "C"):
        return None
    sig = types.int64(xs, ys, zs, types.int64, types.int64, types.float64, types.float64, types.float64,
                      types.float64, bj, db, types.int64)

    def codegen(context, builder, signature, args):
        axs, ays, azs, aj0, aj1, vxi, vyi, vzi, vr2, abj, adb, acnt = args
        ptrs = [context.make_array(signature.args[k])(context, builder, args[k]).data for k in (0, 1, 2)]
        pbj = context.make_array(signature.args[9])(context, builder, abj).data
        dba = context.make_array(signature.args[10])(context, builder, adb)
        pdb = dba.data
        row = cgutils.unpack_tuple(builder, dba.shape, 2)[1]  # C order: row r starts at r * shape[1]
        mod = builder.module
        o = Ops(builder, mod)
        f64, i64, i32, vd, vi, vm = o.lane_types
        mask_t = ir.IntType(LANES)
        mload = o.intrinsic("load")
        cstore = cgutils.get_or_insert_function(
            mod, ir.FunctionType(ir.VoidType(), [vi, i64.as_pointer(), vm]), f"llvm.masked.compressstore.v{LANES}i64")
        cstore_d = cgutils.get_or_insert_function(
            mod, ir.FunctionType(ir.VoidType(), [vd, f64.as_pointer(), vm]), f"llvm.masked.compressstore.v{LANES}f64")
        ctpop = cgutils.get_or_insert_function(mod, ir.FunctionType(mask_t, [mask_t]), f"llvm.ctpop.i{LANES}")

        def splat(v, ty):
            return splat_ir(builder, v, ty)

        centre = [splat(v, vd) for v in (vxi, vyi, vzi)]
        vr2s = splat(vr2, vd)
        end = splat(aj1, vi)
        iota = ir.Constant(vi, list(range(LANES)))
        zero = ir.Constant(vd, [0.0] * LANES)
        cntp = cgutils.alloca_once_value(builder, acnt)
        with cgutils.for_range_slice(builder, aj0, aj1, ir.Constant(i64, LANES), inc=True) as (base, _):
            idx = builder.add(splat(base, vi), iota)
            lane = builder.icmp_signed("<", idx, end)
            offs = []
            for p, c in zip(ptrs, centre):
                v = builder.call(mload, [builder.bitcast(builder.gep(p, [base]), vd.as_pointer()),
                                         ir.Constant(i32, 8), lane, zero])
                offs.append(builder.fsub(c, v))
            sq = [builder.fmul(d, d) for d in offs]
            offs.append(builder.fadd(builder.fadd(sq[0], sq[1]), sq[2]))
            inside = builder.and_(builder.fcmp_ordered("<", offs[3], vr2s), lane)
            c = builder.load(cntp)
            builder.call(cstore, [idx, builder.gep(pbj, [c]), inside])
            for r, d in enumerate(offs):
                at = builder.add(builder.mul(ir.Constant(i64, r), row), c)
                builder.call(cstore_d, [d, builder.gep(pdb, [at]), inside])
            k = builder.zext(builder.call(ctpop, [builder.bitcast(inside, mask_t)]), i64)
            builder.store(builder.add(c, k), cntp)
        return builder.load(cntp)

    return sig, codegen


@intrinsic
def _fetch_add(typingctx, arr, idx, val):
    """Atomic ``arr[idx] += val`` returning the old value (int64 array)."""
    if not (isinstance(arr, types.Array) and arr.dtype == types.int64):
        return None
    sig = types.int64(arr, types.intp, types.int64)

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        ptr = builder.gep(ary.data, [args[1]])
        return builder.atomic_rmw("add", ptr, args[2], "seq_cst")

    return sig, codegen


@njit(cache=True, inline="always")
def _run(start, hashed, mask, nx, ny, m, ix, cy, cz, kx, xl, yl, zl, h, inv_h, r2):
    """Run ``[j0, j1)`` of sorted tokens for the kx-th x-run of row (cy, cz).

    ``xl, yl, zl``: votee in box-local coordinates (as the binning computed
    them).  Dense layout: the row is skipped when its y–z extent is already
    farther than the voting radius from the votee, and its x-range is trimmed
    to the cells the radius can reach (slack of 1e-6 cell so rounding never
    drops a token; the exact ``d² < r²`` test follows anyway).
    """
    if hashed:
        cx = ix - m + kx
        b = ((cx * _H1) ^ (cy * _H2) ^ (cz * _H3)) & mask
        return start[b], start[b + 1], cx
    y0 = cy * h
    z0 = cz * h
    slack = 1e-6 * h
    ddy = max(max(y0 - yl, yl - (y0 + h)) - slack, 0.0)
    ddz = max(max(z0 - zl, zl - (z0 + h)) - slack, 0.0)
    rem = r2 - ddy * ddy - ddz * ddz
    if rem <= 0.0:
        return 0, 0, -1
    ext = math.sqrt(rem) + slack
    xa = (xl - ext) * inv_h
    xb = (xl + ext) * inv_h
    x0 = max(ix - m, 0)
    x1 = min(ix + m, nx - 1)
    if xa > x0:
        x0 = int(xa)
    if xb < x1:
        x1 = int(xb)
    if x1 < x0:
        return 0, 0, -1
    base = nx * (cy + ny * cz)
    return start[base + x0], start[base + x1 + 1], -1


@njit(cache=True, parallel=prange_only())
def half_shell_capacity(start, nx, ny, nz, hashed, m):
    """Most tokens that the half-shell runs of one votee can hold (before the distance test).

    Dense layout: the maximum over occupied cells of the tokens in the runs
    :func:`_upper` visits (x-windows ``[ix − m, ix + m]`` of the rows with
    dz > 0, or dz = 0 and dy ≥ 0).  Hashed layout: ``(m + 1)(2m + 1)²``
    times the fullest bucket.  The per-chunk neighbour buffers get this size.
    """
    if hashed:
        best = 0
        for b in range(start.shape[0] - 1):
            best = max(best, start[b + 1] - start[b])
        return best * (m + 1) * (2 * m + 1) ** 2
    zbest = np.zeros(nz, np.int64)
    for iz in prange(nz):
        best = 0
        for iy in range(ny):
            for ix in range(nx):
                c = ix + nx * (iy + ny * iz)
                if start[c + 1] == start[c]:
                    continue
                x0 = max(ix - m, 0)
                x1 = min(ix + m, nx - 1)
                tot = 0
                for dz in range(0, min(m, nz - 1 - iz) + 1):
                    for dy in range(-m if dz > 0 else 0, m + 1):
                        cy = iy + dy
                        if cy < 0 or cy >= ny:
                            continue
                        base = nx * (cy + ny * (iz + dz))
                        tot += start[base + x1 + 1] - start[base + x0]
                best = max(best, tot)
        zbest[iz] = best
    return max(1, zbest.max())


@njit(cache=True, inline="always", boundscheck=False)
def _collect(xs, ys, zs, cix, ciy, ciz, hashed, cx, cy, cz, j0, j1, xi, yi, zi, r2, bj, db, cnt):
    """Append the tokens of ``[j0, j1)`` inside the voting sphere to ``bj`` and ``db``.

    ``bj[c]`` gets the index, ``db[:4, c]`` the offset ``x_i − x_j`` and its
    squared length.  Branch-free compaction (always store at ``c``, then
    ``c += inside``); the caller guarantees room for ``j1 − j0`` more.
    Unsigned indices spare numba's negative-index wraparound code.
    """
    c = np.uint64(cnt)
    for j in range(np.uint64(j0), np.uint64(j1)):
        dx = xi - xs[j]
        dy = yi - ys[j]
        dz = zi - zs[j]
        d2 = dx * dx + dy * dy + dz * dz
        bj[c] = j
        db[0, c] = dx
        db[1, c] = dy
        db[2, c] = dz
        db[3, c] = d2
        ok = d2 < r2
        if hashed:
            ok = ok & (cix[j] == cx) & (ciy[j] == cy) & (ciz[j] == cz)
        c += np.uint64(ok)
    return np.int64(c)


@njit(cache=True, error_model="numpy", boundscheck=False)
def _upper(i, xs, ys, zs, cix, ciy, ciz, start, nx, ny, nz, hashed, mask, m, lo, h, inv_h, r2, bj, db, rows,
           simd):
    """Upper neighbours of token ``i`` (sorted index j > i, ``d² < r²``): their number ``cnt``.

    ``bj[:cnt]`` lists them and ``db[:4, :cnt]`` holds their offsets
    ``x_i − x_j`` and squared lengths (see :func:`_collect`); both must hold
    :func:`half_shell_capacity` entries.  ``simd``: use :func:`_collect_simd`
    (dense layout).
    Dense layout: sorted order is cell-key order, so j > i means a row with
    dz > 0, or dz = 0 and dy > 0, or the own row beyond i.  Hashed layout:
    cells lexicographically after i's by (dz, dy, dx), and j > i within i's
    own cell (all its tokens share one bucket).

    The nonempty runs are found first (into ``rows``, a ``(5, (m+1)(2m+1)²)``
    scratch: j0, j1, cx, cy, cz) and the first token of each is touched, so
    their cache misses overlap; then the runs are scanned.

    A function of its own (not numba-inlined), compiled once for both passes.
    """
    xi = xs[i]
    yi = ys[i]
    zi = zs[i]
    xl = xi - lo[0]
    yl = yi - lo[1]
    zl = zi - lo[2]
    ix = cix[i]
    iy = ciy[i]
    iz = ciz[i]
    nruns = 2 * m + 1 if hashed else 1
    nr = 0
    touch = 0.0
    for dz in range(0, m + 1):
        cz = iz + dz
        if not hashed and cz >= nz:
            break
        for dy in range(-m if dz > 0 else 0, m + 1):
            cy = iy + dy
            if not hashed and (cy < 0 or cy >= ny):
                continue
            own_row = dz == 0 and dy == 0
            for kx in range(m if hashed and own_row else 0, nruns):
                j0, j1, cx = _run(start, hashed, mask, nx, ny, m, ix, cy, cz, kx, xl, yl, zl, h, inv_h, r2)
                if own_row and (kx == m or not hashed):
                    j0 = max(j0, i + 1)
                rows[0, nr] = j0
                rows[1, nr] = j1
                rows[2, nr] = cx
                rows[3, nr] = cy
                rows[4, nr] = cz
                if j1 > j0:
                    touch += xs[j0] + ys[j0] + zs[j0]
                    nr += 1
    cnt = 0
    for r in range(nr):
        if simd and not hashed:
            cnt = _collect_simd(xs, ys, zs, rows[0, r], rows[1, r], xi, yi, zi, r2, bj, db, cnt)
        else:
            cnt = _collect(xs, ys, zs, cix, ciy, ciz, hashed, rows[2, r], rows[3, r], rows[4, r], rows[0, r],
                           rows[1, r], xi, yi, zi, r2, bj, db, cnt)
    return cnt + (touch != touch)  # never true (no NaN tokens): keeps the touches


@njit(cache=True, inline="always", boundscheck=False)
def _put6(out, k, t00, t01, t02, t11, t12, t22):
    """Tensor components to column ``k`` of ``out`` (6 rows)."""
    out[0, k] = t00
    out[1, k] = t01
    out[2, k] = t02
    out[3, k] = t11
    out[4, k] = t12
    out[5, k] = t22


@njit(cache=True, fastmath=_FLUSH_FLAGS, error_model="numpy", boundscheck=False)
def _ball_pairs(db, cnt, tab, tscale, out):
    """Ball votes of i's upper neighbours from their offsets ``db[:4, :cnt]`` (see :func:`_upper`).

    The vote of each pair goes to ``out[:, k]`` (for :func:`_scatter`) and
    their sum, i's share, is returned.  ``tab[k] = (A[k], A[k+1] − A[k],
    B[k], B[k+1] − B[k])`` (see :func:`ball_table4`): one cache line per
    lookup, same interpolant as ``A[k] + (A[k+1] − A[k])·f``.  No scatter in
    this loop, so it vectorises.
    """
    s00 = 0.0
    s01 = 0.0
    s02 = 0.0
    s11 = 0.0
    s12 = 0.0
    s22 = 0.0
    for k in range(cnt):
        dx = db[0, k]
        dy = db[1, k]
        dz = db[2, k]
        d2 = db[3, k]
        q = d2 * tscale
        t = np.uint64(q)
        f = q - t
        a = tab[t, 0] + tab[t, 1] * f
        b = tab[t, 2] + tab[t, 3] * f
        pos = d2 > 0.0
        # l = 0: the isotropic average, exactly the identity
        g = (a - b) / (d2 if pos else 1.0)
        g = g if pos else 0.0
        b = b if pos else 1.0
        cx = g * dx
        cy = g * dy
        t00 = b + cx * dx
        t01 = cx * dy
        t02 = cx * dz
        t11 = b + cy * dy
        t12 = cy * dz
        t22 = b + g * dz * dz
        s00 += t00
        s01 += t01
        s02 += t02
        s11 += t11
        s12 += t12
        s22 += t22
        _put6(out, k, t00, t01, t02, t11, t12, t22)
    return s00, s01, s02, s11, s12, s22


@njit(cache=True, error_model="numpy", boundscheck=False)
def _eig_chunks(acc, vals, e1, cb, ch, nch, simd):
    """Eigen-analysis of the tokens of chunks ``ch, ch + 1`` (and 0 when ``ch == 1``).

    Called after odd chunk ``ch`` is done: its tokens and those of even chunk
    ``ch + 1`` (written only by ``ch`` and itself) have their final tensors,
    and no other iteration of the parallel loop writes them.  ``simd``: use
    :func:`eig_rows_simd`.  A function of its own (not numba-inlined),
    compiled once for both passes.
    """
    c0 = 0 if ch == 1 else ch
    c1 = min(ch + 2, nch)
    if c0 < c1:
        _eig_rows(acc, vals, e1, cb[c0], cb[c1], simd)


@njit(cache=True, error_model="numpy", boundscheck=False)
def _eig_rows(acc, vals, e1, i0, i1, simd):
    """Eigen-analysis (:func:`gatv.voting._eigen.eig_rows`) of the tokens ``i0 .. i1 - 1``; ``simd``:
    :func:`eig_rows_simd`."""
    if simd:
        eig_rows_simd(acc, vals, e1, i0, i1)
    else:
        eig_rows(acc, vals, e1, i0, i1)


@njit(cache=True, error_model="numpy", boundscheck=False)
def _ball_task(ch, phase, nch, record, xs, ys, zs, cix, ciy, ciz, start, nx, ny, nz, hashed, mask, m, lo, h, r2,
               tab, tscale, cb, cap, simd, acc, vals, e1, counts, nbr, rb, nstart, nup):
    """Chunk ``ch`` of :func:`ball_pass` (phase ``phase``): its tokens' votes, then the eigen-analysis.

    The body of the pass's parallel loop, as a function of its own: numba's
    parallel passes (copy propagation, outlining, typing the body a second
    time) then see one call instead of the inlined scan, votes and
    eigen-solver, which halves the pass's compile time.  The arithmetic and
    the order of every sum are the same.  ``error_model="numpy"`` and
    ``boundscheck=False`` as the pass had for its inlined body.
    """
    inv_h = 1.0 / h
    if ch < nch:
        bj = np.empty(cap, np.int64)
        db = np.empty((4, cap))
        out = np.empty((6, cap))
        rows = np.empty((5, (m + 1) * (2 * m + 1) ** 2), np.int64)
        pos = rb[ch] if record else 0
        lim = rb[ch + 1] if record else 0
        for i in range(cb[ch], cb[ch + 1]):
            cnt = _upper(i, xs, ys, zs, cix, ciy, ciz, start, nx, ny, nz, hashed, mask, m,
                         lo, h, inv_h, r2, bj, db, rows, simd)
            if simd:
                s00, s01, s02, s11, s12, s22 = _ball_pairs_simd(db, cnt, tab, tscale, out)
            else:
                s00, s01, s02, s11, s12, s22 = _ball_pairs(db, cnt, tab, tscale, out)
            _scatter(bj, 0, cnt, out, acc, counts)
            acc[i, 0] += 1.0 + s00
            acc[i, 1] += s01
            acc[i, 2] += s02
            acc[i, 3] += 1.0 + s11
            acc[i, 4] += s12
            acc[i, 5] += 1.0 + s22
            counts[i] += 1 + cnt
            if record:
                nup[i] = cnt
                if pos + cnt <= lim:
                    nstart[i] = pos
                    for k in range(cnt):
                        nbr[pos + k] = np.int32(bj[k])
                    pos += cnt
                else:
                    nstart[i] = -1
    if phase == 1:
        _eig_chunks(acc, vals, e1, cb, ch, nch, simd)


@njit(cache=True, parallel=True, error_model="numpy", boundscheck=False)
def ball_pass(xs, ys, zs, cix, ciy, ciz, start, nx, ny, nz, hashed, mask, m, lo, h, r2,
              tab, tscale, cb, nth, cap, simd, acc, vals, e1, counts, nbr, rb, nstart, nup):
    """Sparse ball voting, each pair once (see the section comment).

    Every token is a unit ball voter; the votee's own ball (self vote, l = 0)
    is included, so a lone token ends with the identity.  ``acc (N, 6)`` and
    ``counts (N,)`` must be zero on entry; they receive the tensors and the
    number of voters (self included); ``vals (N, 3)``, ``e1 (N, 3)`` receive
    the eigen-analysis (:func:`gatv.voting._eigen.eig3_top`).  ``cb``: token
    bounds of the chunks; ``nth``: number of numba threads (passed in: calling
    ``numba.get_num_threads`` here would make the function uncachable);
    ``cap``: :func:`half_shell_capacity`; ``simd``: the 8-lane scan, votes
    and eigen-analysis (pass :data:`gatv.voting._simd.SIMD`).

    Recording (``nstart.shape[0] == N``): the upper neighbours of token i go
    to ``nbr[nstart[i] : nstart[i] + nup[i]]`` (int32), each chunk ``c``
    filling its slice ``nbr[rb[c] : rb[c + 1]]`` in order; ``nstart[i] = −1``
    when they did not fit (the stick pass then scans for them).
    """
    n = xs.shape[0]
    record = nstart.shape[0] == n
    nch = cb.shape[0] - 1
    ctr = np.zeros(2, np.int64)  # next chunk of each phase (dynamic scheduling)
    for phase in range(2):
        for _t in prange(nth):
            while True:
                c = _fetch_add(ctr, phase, 1)
                if c >= (nch + 1) // 2:
                    break
                _ball_task(2 * c + phase, phase, nch, record, xs, ys, zs, cix, ciy, ciz, start, nx, ny, nz,
                           hashed, mask, m, lo, h, r2, tab, tscale, cb, cap, simd, acc, vals, e1, counts, nbr,
                           rb, nstart, nup)


@njit(cache=True, parallel=True, error_model="numpy", boundscheck=False)
def ball_pass_private(xs, ys, zs, cix, ciy, ciz, start, nx, ny, nz, hashed, mask, m, lo, h, r2,
                      tab, tscale, cb, nth, cap, simd, acc, vals, e1, counts, nbr, rb, nstart, nup):
    """:func:`ball_pass` for a few tokens packed within a few voting radii (a judge's dense cluster): the
    race-free chunks of cell layers would be one or two, and one thread would vote them all.

    ``cb``: token bounds of chunks of any extent (a fixed count of them, whatever the threads ``nth``),
    each voting into an accumulator of its own, in parallel; the accumulators are then added in chunk order,
    so the result does not depend on the number of threads either.  Arguments and outputs otherwise as
    :func:`ball_pass` (its ``rb``: the recording's slices of these chunks).
    """
    n = xs.shape[0]
    nch = cb.shape[0] - 1
    record = nstart.shape[0] == n
    part_acc = np.zeros((nch, n, 6))
    part_counts = np.zeros((nch, n), np.int64)
    ctr = np.zeros(1, np.int64)  # the next chunk (dynamic scheduling: early tokens have more upper neighbours)
    for _t in prange(nth):
        while True:
            ch = _fetch_add(ctr, 0, 1)
            if ch >= nch:
                break
            _ball_task(ch, 0, nch, record, xs, ys, zs, cix, ciy, ciz, start, nx, ny, nz, hashed, mask, m, lo, h,
                       r2, tab, tscale, cb, cap, simd, part_acc[ch], vals, e1, part_counts[ch], nbr, rb, nstart,
                       nup)
    for ch in prange(nch):
        for i in range(cb[ch], cb[ch + 1]):
            for c in range(nch):
                for a in range(6):
                    acc[i, a] += part_acc[c, i, a]
                counts[i] += part_counts[c, i]
        _eig_rows(acc, vals, e1, cb[ch], cb[ch + 1], simd)


@njit(cache=True, parallel=True, boundscheck=False)
def stick_records(xs, ys, zs, normals, ws):
    """``(N, 8)`` rows ``x, y, z, nx, ny, nz, w, 0``: one cache line per voter for the gathers."""
    n = xs.shape[0]
    rec = np.empty((n, 8))
    for i in prange(n):
        rec[i, 0] = xs[i]
        rec[i, 1] = ys[i]
        rec[i, 2] = zs[i]
        rec[i, 3] = normals[i, 0]
        rec[i, 4] = normals[i, 1]
        rec[i, 5] = normals[i, 2]
        rec[i, 6] = ws[i]
        rec[i, 7] = 0.0
    return rec


@njit(cache=True, inline="always", boundscheck=False)
def _gather(bj, k0, cnt, xi, yi, zi, rec, buf):
    """Offsets ``x_i − x_j``, normals and weights of the j's of ``bj[k0 : k0 + cnt]`` to ``buf``.

    ``rec``: see :func:`stick_records`.  ``buf`` rows: dx, dy, dz, nx, ny,
    nz, w (contiguous, so the vectorised flush needs no gathers).  Returns how
    many j's have a nonzero weight.
    """
    nv = 0
    for k in range(cnt):
        j = np.uint64(bj[k0 + k])
        w = rec[j, 6]
        buf[0, k] = xi - rec[j, 0]
        buf[1, k] = yi - rec[j, 1]
        buf[2, k] = zi - rec[j, 2]
        buf[3, k] = rec[j, 3]
        buf[4, k] = rec[j, 4]
        buf[5, k] = rec[j, 5]
        buf[6, k] = w
        nv += w != 0.0
    return nv


@njit(cache=True, inline="always")
def _stick_one(dx, dy, dz, d2, inv, rho2, gl, nx_, ny_, nz_, w):
    """Stick vote ``w·DF·m mᵀ`` of a voter with normal n at offset d (see :func:`_stick_pairs`)."""
    u = nx_ * dx + ny_ * dy + nz_ * dz
    u2 = u * u
    cone = not (u2 + u2 > d2)  # θ ≤ 45°
    s2 = min(u2 * inv, 0.5)
    ex = rho2 * arcsin_ratio2(s2) + gl * s2
    df = w * exp_neg_small(ex)
    df = df if cone else 0.0
    kk = 2.0 * u * inv
    mx = nx_ - kk * dx
    my = ny_ - kk * dy
    mz = nz_ - kk * dz
    dmx = df * mx
    dmy = df * my
    return dmx * mx, dmx * my, dmx * mz, dmy * my, dmy * mz, df * mz * mz


@njit(cache=True, fastmath=_FLUSH_FLAGS, error_model="numpy", boundscheck=False)
def _stick_pairs(buf, cnt, nix, niy, niz, wi, both, inv_s2, gamma4, lmin2, out):
    """Stick votes of the buffered pairs (branch-free, masked cone).

    Votes of the j's on i are summed and returned; with ``both`` the votes of
    i (normal ``ni``, weight ``wi``) on each j go to ``out[:, k]``.  A stick
    vote is even in the offset, so both use ``d = x_i − x_j``.  l = 0 gives
    ``s2 = 0``, ``m = n``, ``DF = 1``.
    """
    # γ(σκ)² = 4γ sin²θ / max(ρ², l_min²/σ²) = s2 · min(4γσ²/l², 4γσ²/l_min²):
    # one division per pair (1/l², needed anyway) instead of two
    gs2 = gamma4 / inv_s2
    gmax = gamma4 / lmin2
    s00 = 0.0
    s01 = 0.0
    s02 = 0.0
    s11 = 0.0
    s12 = 0.0
    s22 = 0.0
    for k in range(cnt):
        dx = buf[0, k]
        dy = buf[1, k]
        dz = buf[2, k]
        d2 = dx * dx + dy * dy + dz * dz
        pos = d2 > 0.0
        inv = 1.0 / (d2 if pos else 1.0)
        inv = inv if pos else 0.0  # l = 0: s2 = 0, the curvature term vanishes
        rho2 = d2 * inv_s2
        gl = min(gs2 * inv, gmax)
        t00, t01, t02, t11, t12, t22 = _stick_one(dx, dy, dz, d2, inv, rho2, gl,
                                                  buf[3, k], buf[4, k], buf[5, k], buf[6, k])
        s00 += t00
        s01 += t01
        s02 += t02
        s11 += t11
        s12 += t12
        s22 += t22
        if both:
            t00, t01, t02, t11, t12, t22 = _stick_one(dx, dy, dz, d2, inv, rho2, gl, nix, niy, niz, wi)
            _put6(out, k, t00, t01, t02, t11, t12, t22)
    return s00, s01, s02, s11, s12, s22


@intrinsic
def _stick_pairs_simd(typingctx, buf, cnt, nix, niy, niz, wi, both, inv_s2, gamma4, lmin2, out):
    """:func:`_stick_pairs` on 8 pairs at a time (explicit LLVM vectors).

    The scalar loop is latency-bound (each pair is a long chain: division,
    two polynomials, three squarings) and LLVM vectorises it 4 wide; 8 lanes
    keep two 4-wide chains in flight, which is faster.  Lanes at
    or past ``cnt`` load a zero-weight voter (so they add nothing) and store
    nothing.  Same arithmetic as :func:`_stick_pairs`, up to FMA contraction;
    the sums are reduced lane 0 to 7, so results stay independent of threads.
    """
    f64 = types.float64
    if not (isinstance(buf, types.Array) and buf.ndim == 2 and buf.layout == "C" and buf.dtype == f64):
        return None
    if not (isinstance(out, types.Array) and out.ndim == 2 and out.layout == "C" and out.dtype == f64):
        return None
    ret = types.UniTuple(f64, 6)
    sig = ret(buf, types.int64, f64, f64, f64, f64, types.boolean, f64, f64, f64, out)

    def codegen(context, builder, signature, args):
        abuf, acnt, vnx, vny, vnz, vwi, vboth, vis2, vg4, vlm2, aout = args
        bufa = context.make_array(signature.args[0])(context, builder, abuf)
        outa = context.make_array(signature.args[10])(context, builder, aout)
        brow = cgutils.unpack_tuple(builder, bufa.shape, 2)[1]
        orow = cgutils.unpack_tuple(builder, outa.shape, 2)[1]
        mod = builder.module
        o = Ops(builder, mod)
        _, i64, i32, vd, vi, _ = o.lane_types
        mload, mstore = o.intrinsic("load"), o.intrinsic("store")

        def splat(v, ty=vd):
            return splat_ir(builder, v, ty)

        L = o.L
        const = o.v
        sel = o.sel
        vmin = o.min

        # γ(σκ)² = s2 · min(4γσ²/l², 4γσ²/l_min²), as in _stick_pairs
        gs2 = L(splat(builder.fdiv(vg4, vis2)))
        gmax = L(splat(builder.fdiv(vg4, vlm2)))
        is2 = L(splat(vis2))
        ni = [L(splat(v)) for v in (vnx, vny, vnz)]
        wiv = L(splat(vwi))
        end = splat(acnt, vi)
        iota = ir.Constant(vi, list(range(LANES)))
        # an inactive lane is a voter at unit distance along x with weight 0
        idle = [const(1.0), const(0.0), const(0.0), const(1.0), const(0.0), const(0.0), const(0.0)]
        sums = [cgutils.alloca_once_value(builder, const(0.0)) for _ in range(6)]
        half = const(0.5)

        def stick_one(d, d2, inv, rho2, gl, n, w):
            u = n[0] * d[0] + n[1] * d[1] + n[2] * d[2]
            u2 = u * u
            cone = builder.not_(builder.fcmp_ordered(">", (u2 + u2).v, d2.v))
            s2 = vmin(u2 * inv, L(half))
            ex = rho2 * arcsin_ratio2.py_func(s2) + gl * s2
            df = sel(cone, w * exp_neg_small.py_func(ex), const(0.0))
            kk = 2.0 * u * inv
            mx = n[0] - kk * d[0]
            my = n[1] - kk * d[1]
            mz = n[2] - kk * d[2]
            dmx = df * mx
            dmy = df * my
            return dmx * mx, dmx * my, dmx * mz, dmy * my, dmy * mz, df * mz * mz

        with cgutils.for_range_slice(builder, ir.Constant(i64, 0), acnt, ir.Constant(i64, LANES), inc=True) as (k, _):
            lane = builder.icmp_signed("<", builder.add(splat(k, vi), iota), end)

            def row_ptr(arr, rowlen, r):
                return row_vector_ptr(builder, arr, rowlen, r, k, vd)

            col = [L(builder.call(mload, [row_ptr(bufa, brow, r), ir.Constant(i32, 8), lane, idle[r]]))
                   for r in range(7)]
            d = col[:3]
            d2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
            pos = builder.fcmp_ordered(">", d2.v, const(0.0))
            inv = sel(pos, 1.0 / sel(pos, d2, const(1.0)), const(0.0))
            rho2 = d2 * is2
            gl = vmin(gs2 * inv, gmax)
            t = stick_one(d, d2, inv, rho2, gl, col[3:6], col[6])
            for r in range(6):
                builder.store((L(builder.load(sums[r])) + t[r]).v, sums[r])
            with builder.if_then(vboth, likely=True):
                t = stick_one(d, d2, inv, rho2, gl, ni, wiv)
                for r in range(6):
                    builder.call(mstore, [t[r].v, row_ptr(outa, orow, r), ir.Constant(i32, 8), lane])
        return context.make_tuple(builder, signature.return_type, lane_sums(builder, sums))

    return sig, codegen

@intrinsic
def _ball_pairs_simd(typingctx, db, cnt, tab, tscale, out):
    """:func:`_ball_pairs` on 8 pairs at a time (explicit LLVM vectors, table rows gathered).

    LLVM leaves the scalar loop unvectorised (the table lookup); here the
    four entries of each lane's table row are gathered.  Lanes at or past
    ``cnt`` add nothing and store nothing.  Same arithmetic as
    :func:`_ball_pairs`, up to FMA contraction; sums reduced lane 0 to 7.
    """
    f64 = types.float64
    for a in (db, tab, out):
        if not (isinstance(a, types.Array) and a.ndim == 2 and a.layout == "C" and a.dtype == f64):
            return None
    sig = types.UniTuple(f64, 6)(db, types.int64, tab, f64, out)

    def codegen(context, builder, signature, args):
        adb, acnt, atab, vts, aout = args
        dba = context.make_array(signature.args[0])(context, builder, adb)
        taba = context.make_array(signature.args[2])(context, builder, atab)
        outa = context.make_array(signature.args[4])(context, builder, aout)
        drow = cgutils.unpack_tuple(builder, dba.shape, 2)[1]
        orow = cgutils.unpack_tuple(builder, outa.shape, 2)[1]
        mod = builder.module
        o = Ops(builder, mod)
        _, i64, i32, vd, vi, _ = o.lane_types
        vpd = o.vpd
        mload, mstore, gather = o.intrinsic("load"), o.intrinsic("store"), o.intrinsic("gather")

        def splat(v, ty=vd):
            return splat_ir(builder, v, ty)

        end = splat(acnt, vi)
        iota = ir.Constant(vi, list(range(LANES)))
        zero = ir.Constant(vd, [0.0] * LANES)
        tsc = splat(vts)
        tbase = splat(builder.ptrtoint(taba.data, i64), vi)
        sums = [cgutils.alloca_once_value(builder, zero) for _ in range(6)]
        with cgutils.for_range_slice(builder, ir.Constant(i64, 0), acnt, ir.Constant(i64, LANES), inc=True) as (k, _):
            lane = builder.icmp_signed("<", builder.add(splat(k, vi), iota), end)

            def row_ptr(arr, rowlen, r):
                return row_vector_ptr(builder, arr, rowlen, r, k, vd)

            dx, dy, dz, d2 = (o.L(builder.call(mload, [row_ptr(dba, drow, r), ir.Constant(i32, 8), lane, zero]))
                              for r in range(4))
            q = d2 * o.L(tsc)
            t = builder.fptoui(q.v, vi)
            f = q - o.L(builder.uitofp(t, vd))
            row = builder.add(tbase, builder.mul(t, ir.Constant(vi, [32] * LANES)))
            tv = [o.L(builder.call(gather, [builder.inttoptr(builder.add(row, ir.Constant(vi, [8 * c] * LANES)), vpd),
                                            ir.Constant(i32, 8), lane, zero])) for c in range(4)]
            a = tv[0] + tv[1] * f
            b = tv[2] + tv[3] * f
            pos = o.cmp(">", d2, 0.0)
            # l = 0: the isotropic average, exactly the identity
            g = o.sel(pos, o.div(a - b, o.sel(pos, d2, 1.0)), 0.0)
            b = o.sel(pos, b, 1.0)
            cx = g * dx
            cy = g * dy
            tt = (b + cx * dx, cx * dy, cx * dz, b + cy * dy, cy * dz, b + g * dz * dz)
            for r in range(6):
                builder.call(mstore, [tt[r].v, row_ptr(outa, orow, r), ir.Constant(i32, 8), lane])
                part = o.sel(lane, tt[r], 0.0)
                builder.store((o.L(builder.load(sums[r])) + part).v, sums[r])
        return context.make_tuple(builder, signature.return_type, lane_sums(builder, sums))

    return sig, codegen


@njit(cache=True, inline="always", boundscheck=False)
def _scatter(bj, k0, cnt, out, acc, counts):
    """Add ``out[:, k]`` to the row of token ``bj[k0 + k]`` and count one voter."""
    for k in range(cnt):
        j = np.uint64(bj[k0 + k])
        acc[j, 0] += out[0, k]
        acc[j, 1] += out[1, k]
        acc[j, 2] += out[2, k]
        acc[j, 3] += out[3, k]
        acc[j, 4] += out[4, k]
        acc[j, 5] += out[5, k]
        counts[j] += 1


@njit(cache=True, error_model="numpy", boundscheck=False)
def _stick_task(ch, phase, nch, use_nl, rec, xs, ys, zs, ws, cix, ciy, ciz, start, nx, ny, nz, hashed, mask, m,
                lo, h, r2, inv_s2, gamma4, lmin2, cb, cap, simd, acc, vals, e1, counts, nbr, nstart, nup):
    """Chunk ``ch`` of :func:`stick_pass` (phase ``phase``): its tokens' votes, then the eigen-analysis.

    The body of the pass's parallel loop, as a function of its own (see :func:`_ball_task`).
    """
    inv_h = 1.0 / h
    if ch < nch:
        bj = np.empty(cap, np.int64)
        rows = np.empty((5, (m + 1) * (2 * m + 1) ** 2), np.int64)
        buf = np.empty((7, cap))
        out = np.empty((6, cap))
        for i in range(cb[ch], cb[ch + 1]):
            wi = ws[i]
            nix = rec[i, 3]
            niy = rec[i, 4]
            niz = rec[i, 5]
            listed = use_nl and nstart[i] >= 0
            if listed:
                k0 = nstart[i]
                cnt = nup[i]
            else:
                # buf's first rows take the offsets; _gather overwrites them
                cnt = _upper(i, xs, ys, zs, cix, ciy, ciz, start, nx, ny, nz, hashed, mask, m,
                             lo, h, inv_h, r2, bj, buf, rows, simd)
                k0 = 0
            if listed:
                nv = _gather(nbr, k0, cnt, xs[i], ys[i], zs[i], rec, buf)
            else:
                nv = _gather(bj, k0, cnt, xs[i], ys[i], zs[i], rec, buf)
            both = wi != 0.0
            if simd:
                s00, s01, s02, s11, s12, s22 = _stick_pairs_simd(buf, cnt, nix, niy, niz, wi, both,
                                                                 inv_s2, gamma4, lmin2, out)
            else:
                s00, s01, s02, s11, s12, s22 = _stick_pairs(buf, cnt, nix, niy, niz, wi, both,
                                                            inv_s2, gamma4, lmin2, out)
            if both:
                if listed:
                    _scatter(nbr, k0, cnt, out, acc, counts)
                else:
                    _scatter(bj, k0, cnt, out, acc, counts)
                # own stick (l = 0): w n nᵀ
                wx = wi * nix
                wy = wi * niy
                s00 += wx * nix
                s01 += wx * niy
                s02 += wx * niz
                s11 += wy * niy
                s12 += wy * niz
                s22 += wi * niz * niz
            acc[i, 0] += s00
            acc[i, 1] += s01
            acc[i, 2] += s02
            acc[i, 3] += s11
            acc[i, 4] += s12
            acc[i, 5] += s22
            counts[i] += nv + (1 if both else 0)
    if phase == 1:
        _eig_chunks(acc, vals, e1, cb, ch, nch, simd)


@njit(cache=True, parallel=True, error_model="numpy", boundscheck=False)
def stick_pass(xs, ys, zs, normals, ws, cix, ciy, ciz, start, nx, ny, nz, hashed, mask, m,
               lo, h, r2, inv_s2, gamma4, lmin2, cb, nth, cap, simd, acc, vals, e1, counts, nbr, nstart, nup):
    """Sparse stick voting (eq. 44), each pair once (see the section comment).

    Voter ``j`` votes with unit normal ``normals[j]`` and weight
    ``ws[j]`` (``ws[j] == 0``: no vote, not counted).  The votee's own stick
    ``ws[i]·nᵢnᵢᵀ`` (self vote, l = 0) is included.  ``gamma4 = 4γ`` and
    ``lmin2 = (l_min/σ)²``.  ``acc`` and ``counts`` must be zero on entry;
    outputs as in :func:`ball_pass`.

    ``simd``: scan with :func:`_collect_simd` and vote with
    :func:`_stick_pairs_simd` (pass :data:`gatv.voting._simd.SIMD`).

    ``nbr, nstart, nup``: upper-neighbour lists recorded by :func:`ball_pass`
    at the same σ; a token with ``nstart[i] ≥ 0`` takes its upper neighbours
    from there, the others scan the grid.  Pass an empty ``nstart`` to scan
    for every token.
    """
    n = xs.shape[0]
    use_nl = nstart.shape[0] == n
    nch = cb.shape[0] - 1
    rec = stick_records(xs, ys, zs, normals, ws)
    ctr = np.zeros(2, np.int64)  # next chunk of each phase (dynamic scheduling)
    for phase in range(2):
        for _t in prange(nth):
            while True:
                c = _fetch_add(ctr, phase, 1)
                if c >= (nch + 1) // 2:
                    break
                _stick_task(2 * c + phase, phase, nch, use_nl, rec, xs, ys, zs, ws, cix, ciy, ciz, start, nx, ny,
                            nz, hashed, mask, m, lo, h, r2, inv_s2, gamma4, lmin2, cb, cap, simd, acc, vals, e1,
                            counts, nbr, nstart, nup)
