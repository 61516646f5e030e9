"""Numba kernels for sparse tensor voting (private).

Arrays and scalars in, arrays out; float64 throughout; no Python objects.
Tensors are stored as 6 components ``(xx, xy, xz, yy, yz, zz)``.

Every kernel is ``@njit(cache=True)``; only the outer loops over votees or
tokens are ``prange``.  Voting uses the *gather* formulation: each votee sums
the votes of the tokens in the grid cells around it, so the parallel loop
writes only to its own row and the result does not depend on the number of
threads (the order of the sums is fixed).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

_TWO_PI_3 = 2.0 * math.pi / 3.0

# ---------------------------------------------------------------------------
# 3x3 symmetric eigen-solver (closed form, robust for repeated eigenvalues).
# Eberly, "A Robust Eigensolver for 3 × 3 Symmetric Matrices" (Geometric Tools,
# 2014): trigonometric eigenvalues, eigenvectors by cross products of the rows
# of A − λI for the well-separated eigenvalue and a 2×2 problem in its
# orthogonal complement for the next one.
# ---------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _evec_single(a00, a01, a02, a11, a12, a22, lam):
    """Unit eigenvector for an eigenvalue of multiplicity one (max cross product)."""
    r00 = a00 - lam
    r11 = a11 - lam
    r22 = a22 - lam
    # rows: (r00, a01, a02), (a01, r11, a12), (a02, a12, r22)
    c0x = a01 * a12 - a02 * r11
    c0y = a02 * a01 - r00 * a12
    c0z = r00 * r11 - a01 * a01
    c1x = a01 * r22 - a02 * a12
    c1y = a02 * a02 - r00 * r22
    c1z = r00 * a12 - a01 * a02
    c2x = r11 * r22 - a12 * a12
    c2y = a12 * a02 - a01 * r22
    c2z = a01 * a12 - r11 * a02
    d0 = c0x * c0x + c0y * c0y + c0z * c0z
    d1 = c1x * c1x + c1y * c1y + c1z * c1z
    d2 = c2x * c2x + c2y * c2y + c2z * c2z
    if d0 == 0.0 and d1 == 0.0 and d2 == 0.0:
        # A − λI vanished in rounding (λ is, to the last bit, a triple
        # eigenvalue that the exact test of _eigvals missed): every unit
        # vector is an eigenvector; without this the division gives NaN.
        return 1.0, 0.0, 0.0
    if d0 >= d1 and d0 >= d2:
        s = 1.0 / math.sqrt(d0)
        return c0x * s, c0y * s, c0z * s
    if d1 >= d2:
        s = 1.0 / math.sqrt(d1)
        return c1x * s, c1y * s, c1z * s
    s = 1.0 / math.sqrt(d2)
    return c2x * s, c2y * s, c2z * s


@njit(cache=True, inline="always")
def _evec_complement(a00, a01, a02, a11, a12, a22, wx, wy, wz, lam):
    """Unit eigenvector for ``lam`` orthogonal to the unit eigenvector ``w``."""
    if abs(wx) > abs(wy):
        s = 1.0 / math.sqrt(wx * wx + wz * wz)
        ux, uy, uz = -wz * s, 0.0, wx * s
    else:
        s = 1.0 / math.sqrt(wy * wy + wz * wz)
        ux, uy, uz = 0.0, wz * s, -wy * s
    vx = wy * uz - wz * uy
    vy = wz * ux - wx * uz
    vz = wx * uy - wy * ux
    aux = a00 * ux + a01 * uy + a02 * uz
    auy = a01 * ux + a11 * uy + a12 * uz
    auz = a02 * ux + a12 * uy + a22 * uz
    avx = a00 * vx + a01 * vy + a02 * vz
    avy = a01 * vx + a11 * vy + a12 * vz
    avz = a02 * vx + a12 * vy + a22 * vz
    m00 = ux * aux + uy * auy + uz * auz - lam
    m01 = vx * aux + vy * auy + vz * auz
    m11 = vx * avx + vy * avy + vz * avz - lam
    b00 = abs(m00)
    b01 = abs(m01)
    b11 = abs(m11)
    if b00 >= b11:
        if max(b00, b01) > 0.0:
            if b00 >= b01:
                m01 /= m00
                m00 = 1.0 / math.sqrt(1.0 + m01 * m01)
                m01 *= m00
            else:
                m00 /= m01
                m01 = 1.0 / math.sqrt(1.0 + m00 * m00)
                m00 *= m01
            return m01 * ux - m00 * vx, m01 * uy - m00 * vy, m01 * uz - m00 * vz
        return ux, uy, uz
    if max(b11, b01) > 0.0:
        if b11 >= b01:
            m01 /= m11
            m11 = 1.0 / math.sqrt(1.0 + m01 * m01)
            m01 *= m11
        else:
            m11 /= m01
            m01 = 1.0 / math.sqrt(1.0 + m11 * m11)
            m11 *= m01
        return m11 * ux - m01 * vx, m11 * uy - m01 * vy, m11 * uz - m01 * vz
    return ux, uy, uz


@njit(cache=True, inline="always")
def _eigvals(a00, a01, a02, a11, a12, a22):
    """Scaled eigen-setup: returns (scale, l1, l2, l3, half_det, degenerate) on scaled A."""
    mx = max(abs(a00), abs(a01), abs(a02), abs(a11), abs(a12), abs(a22))
    if mx == 0.0:
        return 0.0, 0.0, 0.0, 0.0, 0.0, True
    inv = 1.0 / mx
    a00 *= inv
    a01 *= inv
    a02 *= inv
    a11 *= inv
    a12 *= inv
    a22 *= inv
    q = (a00 + a11 + a22) / 3.0
    b00 = a00 - q
    b11 = a11 - q
    b22 = a22 - q
    off = a01 * a01 + a02 * a02 + a12 * a12
    p2 = (b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * off) / 6.0
    if off == 0.0 and b00 == 0.0 and b11 == 0.0 and b22 == 0.0:
        return mx, q, q, q, 0.0, True
    p = math.sqrt(p2)
    c00 = b11 * b22 - a12 * a12
    c01 = a01 * b22 - a12 * a02
    c02 = a01 * a12 - b11 * a02
    hd = 0.5 * (b00 * c00 - a01 * c01 + a02 * c02) / (p * p2)
    hd = min(max(hd, -1.0), 1.0)
    ang = math.acos(hd) / 3.0
    beta2 = 2.0 * math.cos(ang)
    beta0 = 2.0 * math.cos(ang + _TWO_PI_3)
    beta1 = min(max(-(beta0 + beta2), beta0), beta2)  # keep the order under rounding
    return mx, q + p * beta2, q + p * beta1, q + p * beta0, hd, False


@njit(cache=True, inline="always")
def eig3_top(a00, a01, a02, a11, a12, a22):
    """Eigenvalues (descending) and unit e1 of a symmetric 3×3 tensor.

    Returns ``(l1, l2, l3, e1x, e1y, e1z)``.
    """
    mx, l1, l2, l3, hd, degen = _eigvals(a00, a01, a02, a11, a12, a22)
    if degen:
        return l1 * mx, l2 * mx, l3 * mx, 1.0, 0.0, 0.0
    inv = 1.0 / mx
    a00 *= inv
    a01 *= inv
    a02 *= inv
    a11 *= inv
    a12 *= inv
    a22 *= inv
    if hd >= 0.0:
        ex, ey, ez = _evec_single(a00, a01, a02, a11, a12, a22, l1)
    else:
        wx, wy, wz = _evec_single(a00, a01, a02, a11, a12, a22, l3)
        ex, ey, ez = _evec_complement(a00, a01, a02, a11, a12, a22, wx, wy, wz, l1)
    return l1 * mx, l2 * mx, l3 * mx, ex, ey, ez


@njit(cache=True, inline="always")
def _eig3_full_one(a00, a01, a02, a11, a12, a22, vals, vecs, i):
    mx, l1, l2, l3, hd, degen = _eigvals(a00, a01, a02, a11, a12, a22)
    vals[i, 0] = l1 * mx
    vals[i, 1] = l2 * mx
    vals[i, 2] = l3 * mx
    if degen:
        for r in range(3):
            for c in range(3):
                vecs[i, r, c] = 1.0 if r == c else 0.0
        return
    inv = 1.0 / mx
    a00 *= inv
    a01 *= inv
    a02 *= inv
    a11 *= inv
    a12 *= inv
    a22 *= inv
    if hd >= 0.0:
        ax, ay, az = _evec_single(a00, a01, a02, a11, a12, a22, l1)
        bx, by, bz = _evec_complement(a00, a01, a02, a11, a12, a22, ax, ay, az, l2)
        cx = ay * bz - az * by
        cy = az * bx - ax * bz
        cz = ax * by - ay * bx
    else:
        cx, cy, cz = _evec_single(a00, a01, a02, a11, a12, a22, l3)
        bx, by, bz = _evec_complement(a00, a01, a02, a11, a12, a22, cx, cy, cz, l2)
        ax = by * cz - bz * cy
        ay = bz * cx - bx * cz
        az = bx * cy - by * cx
    # columns are eigenvectors (numpy.linalg.eigh convention), descending order
    vecs[i, 0, 0] = ax
    vecs[i, 1, 0] = ay
    vecs[i, 2, 0] = az
    vecs[i, 0, 1] = bx
    vecs[i, 1, 1] = by
    vecs[i, 2, 1] = bz
    vecs[i, 0, 2] = cx
    vecs[i, 1, 2] = cy
    vecs[i, 2, 2] = cz


@njit(cache=True, parallel=True)
def eig3_batch(t6, vals, vecs):
    """Eigen-decomposition of ``(N, 6)`` tensors into ``vals (N,3)``, ``vecs (N,3,3)``.

    Eigenvalues descending; ``vecs[i, :, k]`` is the unit eigenvector of
    ``vals[i, k]``; right-handed.
    """
    for i in prange(t6.shape[0]):
        _eig3_full_one(t6[i, 0], t6[i, 1], t6[i, 2], t6[i, 3], t6[i, 4], t6[i, 5], vals, vecs, i)


@njit(cache=True, parallel=True)
def eig3_top_batch(t6, vals, e1):
    """Eigenvalues (descending) and e1 of ``(N, 6)`` tensors (unfused variant)."""
    for i in prange(t6.shape[0]):
        l1, l2, l3, ex, ey, ez = eig3_top(t6[i, 0], t6[i, 1], t6[i, 2], t6[i, 3], t6[i, 4], t6[i, 5])
        vals[i, 0] = l1
        vals[i, 1] = l2
        vals[i, 2] = l3
        e1[i, 0] = ex
        e1[i, 1] = ey
        e1[i, 2] = ez


# ---------------------------------------------------------------------------
# Sparse voting (gather).  ``xs, ys, zs`` are the tokens sorted by grid cell
# (structure of arrays), ``cix, ciy, ciz`` their integer cells and ``start``
# the run of each cell (dense) or hash bucket (hashed); see ``_grid.py``.
# Outputs are in sorted order.
#
# Each votee works in two steps so that the expensive field evaluation runs
# as a branch-free, vectorisable loop over a dense buffer:
#
# 1. *collect*: scan the candidate runs (the 5×5 x-rows of cells around the
#    votee, each trimmed to the voting sphere) and append every token with
#    ``d² < r²`` to a small per-thread buffer by branch-free compaction
#    (always store at ``cnt``, then ``cnt += inside``);
# 2. *flush*: evaluate the votes of the buffered tokens and add them to the
#    votee's accumulator (a fixed-order, deterministic reduction).
#
# The buffer holds ``CAP`` tokens; it is flushed early when a run would not
# fit, so any number of neighbours is handled.
# ---------------------------------------------------------------------------

_H1 = 73856093
_H2 = 19349663
_H3 = 83492791
BLOCK = 256
#: Capacity of the per-thread neighbour buffer.
CAP = 256
#: Largest neighbour list (self included) a votee may record in the ball pass.
NL_CAP = 192
#: Mean list length reserved per votee of a block (a block's scratch row holds
#: BLOCK·NL_ROW entries; votees that no longer fit are scanned by the stick pass).
NL_ROW = 96
#: Blocks per wave of the recording ball pass (scratch: WAVE·BLOCK·NL_ROW int32).
#: Few waves: each ends with a barrier, costly when the cores are shared.
WAVE = 64

# The flush loops may reassociate their sums (vectorised reduction) and
# contract a*b+c into FMAs: both change results by a few ulps only (relative
# 1e-15, far below the 1e-12 budget), and the result stays identical from run
# to run (the code path does not depend on the number of threads).
_FLUSH_FLAGS = {"reassoc", "contract"}


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


@njit(cache=True, inline="always")
def _store(i, a00, a01, a02, a11, a12, a22, t6, vals, e1):
    t6[i, 0] = a00
    t6[i, 1] = a01
    t6[i, 2] = a02
    t6[i, 3] = a11
    t6[i, 4] = a12
    t6[i, 5] = a22
    l1, l2, l3, ex, ey, ez = eig3_top(a00, a01, a02, a11, a12, a22)
    vals[i, 0] = l1
    vals[i, 1] = l2
    vals[i, 2] = l3
    e1[i, 0] = ex
    e1[i, 1] = ey
    e1[i, 2] = ez


@njit(cache=True, inline="always", boundscheck=False)
def _collect(xs, ys, zs, ws, use_w, cix, ciy, ciz, hashed, cx, cy, cz, j0, j1,
             xi, yi, zi, r2, bj, bdx, bdy, bdz, cnt, nxs, nys, nzs, bnx, bny, bnz, bw):
    """Append the tokens of ``[j0, j1)`` inside the voting sphere to the buffer.

    Offsets are stored as votee − voter; with ``use_w`` the voter's normal
    ``(nxs, nys, nzs)[j]`` and weight ``ws[j]`` go to ``bnx, bny, bnz, bw``
    (unused otherwise).  Branch-free compaction; the caller
    guarantees ``cnt + (j1 − j0) ≤ CAP``.  Unsigned indices spare numba's
    negative-index wraparound code.
    """
    c = np.uint64(cnt)
    for j in range(np.uint64(j0), np.uint64(j1)):
        dx = xi - xs[j]
        dy = yi - ys[j]
        dz = zi - zs[j]
        d2 = dx * dx + dy * dy + dz * dz
        bj[c] = j
        bdx[c] = dx
        bdy[c] = dy
        bdz[c] = dz
        ok = d2 < r2
        if use_w:
            # the voter's normal and weight too: the flush then reads only
            # contiguous buffers (vector gathers are slow on this hardware)
            w = ws[j]
            bnx[c] = nxs[j]
            bny[c] = nys[j]
            bnz[c] = nzs[j]
            bw[c] = w
            ok = ok & (w != 0.0)
        if hashed:
            ok = ok & (cix[j] == cx) & (ciy[j] == cy) & (ciz[j] == cz)
        c += np.uint64(ok)
    return np.int64(c)


@njit(cache=True, fastmath=_FLUSH_FLAGS, error_model="numpy", boundscheck=False)
def _ball_flush(bdx, bdy, bdz, cnt, tab, tscale, ba, bb):
    """Sum of the ball votes at the buffered offsets (branch-free).

    ``tab[k] = (A[k], A[k+1] − A[k], B[k], B[k+1] − B[k])`` (see
    :func:`ball_table4`): one cache line per lookup, same interpolant as
    ``A[k] + (A[k+1] − A[k])·f``.  The lookups run in a scalar loop first
    (into ``ba, bb``; vector gathers are slow on this hardware), then the
    votes in a vectorised loop over contiguous buffers.
    """
    c = np.uint64(0)
    for k in range(np.uint64(0), np.uint64(cnt)):
        dx = bdx[k]
        dy = bdy[k]
        dz = bdz[k]
        q = (dx * dx + dy * dy + dz * dz) * tscale
        i = np.uint64(q)
        f = q - i
        ba[c] = tab[i, 0] + tab[i, 1] * f
        bb[c] = tab[i, 2] + tab[i, 3] * f
        c += np.uint64(q >= 0.0)  # always 1, but keeps the loop scalar (no gathers)
    s00 = 0.0
    s01 = 0.0
    s02 = 0.0
    s11 = 0.0
    s12 = 0.0
    s22 = 0.0
    for k in range(cnt):
        dx = bdx[k]
        dy = bdy[k]
        dz = bdz[k]
        d2 = dx * dx + dy * dy + dz * dz
        a = ba[k]
        b = bb[k]
        pos = d2 > 0.0
        # l = 0: the isotropic average, exactly the identity
        g = (a - b) / (d2 if pos else 1.0)
        g = g if pos else 0.0
        b = b if pos else 1.0
        cx = g * dx
        cy = g * dy
        s00 += b + cx * dx
        s01 += cx * dy
        s02 += cx * dz
        s11 += b + cy * dy
        s12 += cy * dz
        s22 += b + g * dz * dz
    return s00, s01, s02, s11, s12, s22


@njit(cache=True, inline="always", boundscheck=False)
def _record(bj, cnt, scr, row, pos, lim):
    """Append ``bj[:cnt]`` to ``scr[row, pos:]``; returns the new end, or −1 if over ``lim``."""
    if pos < 0 or pos + cnt > lim:
        return -1
    for k in range(cnt):
        scr[row, pos + k] = np.int32(bj[k])
    return pos + cnt


@njit(cache=True, boundscheck=False)
def _copy_prefix(src, dst, n):
    for k in range(n):
        dst[k] = src[k]


@njit(cache=True, parallel=True, boundscheck=False)
def _publish(scr, used, nbr, base, w0, wn, stride, nb, n, nstart):
    """Copy the wave's scratch rows into ``nbr`` at ``base`` and make ``nstart`` global."""
    for tt in prange(wn):
        b = base[tt]
        if b < 0:
            continue
        u = used[tt]
        for k in range(u):
            nbr[b + k] = scr[tt, k]
        blk = ((w0 + tt) * stride) % nb
        for i in range(blk * BLOCK, min((blk + 1) * BLOCK, n)):
            if nstart[i] >= 0:
                nstart[i] += b


@njit(cache=True, parallel=True, error_model="numpy", boundscheck=False)
def ball_pass(xs, ys, zs, cix, ciy, ciz, start, nx, ny, nz, hashed, mask, m, lo, h, r2,
              tab, tscale, stride, t6, vals, e1, counts, nstart, record, max_pairs):
    """Sparse ball voting with eigen-analysis fused at the end of each votee.

    Every token is a unit ball voter; the votee's own ball (self vote, l = 0)
    is included, so a lone token ends with the identity.

    With ``record`` the neighbours of each votee (self included, in scan
    order) are also written to the returned int32 array ``nbr``: votee ``i``'s
    list is ``nbr[nstart[i] : nstart[i] + counts[i]]``, or ``nstart[i] = −1``
    when it was not kept (more than ``NL_CAP`` neighbours, or the list would
    exceed ``max_pairs`` entries, or its block's scratch row is full); a stick
    pass then scans the grid for it.
    Blocks are processed in waves of ``WAVE`` blocks; each wave fills a
    scratch row per block, then is copied (in parallel) into ``nbr``.
    """
    n = xs.shape[0]
    nb = (n + BLOCK - 1) // BLOCK
    nruns = 2 * m + 1 if hashed else 1
    inv_h = 1.0 / h
    lx = lo[0]
    ly = lo[1]
    lz = lo[2]
    wave = WAVE if record else nb
    lim = BLOCK * NL_ROW if record else 0
    scr = np.empty((wave if record else 0, lim), np.int32)
    used = np.zeros(wave, np.int64)
    nbr = np.empty(0, np.int32)
    filled = 0
    done = 0
    for w0 in range(0, nb, wave):
        wn = min(wave, nb - w0)
        for tt in prange(wn):
            blk = ((w0 + tt) * stride) % nb  # interleave blocks across threads (load balance)
            bj = np.empty(CAP, np.int64)
            bdx = np.empty(CAP)
            bdy = np.empty(CAP)
            bdz = np.empty(CAP)
            ba = np.empty(CAP)
            bb = np.empty(CAP)
            pos = 0
            for i in range(blk * BLOCK, min((blk + 1) * BLOCK, n)):
                xi = xs[i]
                yi = ys[i]
                zi = zs[i]
                xl = xi - lx
                yl = yi - ly
                zl = zi - lz
                ix = cix[i]
                iy = ciy[i]
                iz = ciz[i]
                a00 = 0.0
                a01 = 0.0
                a02 = 0.0
                a11 = 0.0
                a12 = 0.0
                a22 = 0.0
                total = 0
                cnt = 0
                p0 = pos
                p = pos if record else -1
                plim = min(lim, p0 + NL_CAP)
                for dz in range(-m, m + 1):
                    cz = iz + dz
                    if not hashed and (cz < 0 or cz >= nz):
                        continue
                    for dy in range(-m, m + 1):
                        cy = iy + dy
                        if not hashed and (cy < 0 or cy >= ny):
                            continue
                        for kx in range(nruns):
                            j0, j1, cx = _run(start, hashed, mask, nx, ny, m, ix, cy, cz, kx,
                                              xl, yl, zl, h, inv_h, r2)
                            j = j0
                            while j < j1:
                                room = CAP - cnt
                                if j1 - j > room and cnt > 0:
                                    s00, s01, s02, s11, s12, s22 = _ball_flush(bdx, bdy, bdz, cnt, tab, tscale, ba, bb)
                                    a00 += s00
                                    a01 += s01
                                    a02 += s02
                                    a11 += s11
                                    a12 += s12
                                    a22 += s22
                                    p = _record(bj, cnt, scr, tt, p, plim)
                                    total += cnt
                                    cnt = 0
                                    room = CAP
                                je = min(j1, j + room)
                                cnt = _collect(xs, ys, zs, xs, False, cix, ciy, ciz, hashed, cx, cy, cz,
                                               j, je, xi, yi, zi, r2, bj, bdx, bdy, bdz, cnt,
                                               xs, xs, xs, bdx, bdx, bdx, bdx)
                                j = je
                s00, s01, s02, s11, s12, s22 = _ball_flush(bdx, bdy, bdz, cnt, tab, tscale, ba, bb)
                a00 += s00
                a01 += s01
                a02 += s02
                a11 += s11
                a12 += s12
                a22 += s22
                p = _record(bj, cnt, scr, tt, p, plim)
                counts[i] = total + cnt
                if p >= 0:
                    nstart[i] = p0
                    pos = p
                else:
                    nstart[i] = -1
                _store(i, a00, a01, a02, a11, a12, a22, t6, vals, e1)
            used[tt] = pos
        if record:
            # place the wave's rows (fixed order) in the growing list
            base = np.empty(wn, np.int64)
            need = filled
            for tt in range(wn):
                if need + used[tt] <= max_pairs:
                    base[tt] = need
                    need += used[tt]
                else:
                    base[tt] = -1
            done += wn
            if need > nbr.shape[0]:
                est = need * nb // done + need // 8  # projected total from the blocks so far
                cap = min(max(est, 2 * nbr.shape[0], need), max_pairs)
                grown = np.empty(cap, np.int32)
                _copy_prefix(nbr, grown, filled)
                nbr = grown
            _publish(scr, used, nbr, base, w0, wn, stride, nb, n, nstart)
            for tt in range(wn):
                if base[tt] < 0:  # over max_pairs: these votees stream
                    blk = ((w0 + tt) * stride) % nb
                    for i in range(blk * BLOCK, min((blk + 1) * BLOCK, n)):
                        nstart[i] = -1
            filled = need
    return nbr[:filled]


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


@njit(cache=True, fastmath=_FLUSH_FLAGS, error_model="numpy", boundscheck=False)
def _stick_flush(bdx, bdy, bdz, bnx, bny, bnz, bw, cnt, inv_s2, gamma4, lmin2):
    """Sum of the stick votes of the buffered voters (branch-free, masked cone).

    Offsets, normals and weights come from contiguous buffers only, so the
    vectorised loop needs no gathers.
    """
    s00 = 0.0
    s01 = 0.0
    s02 = 0.0
    s11 = 0.0
    s12 = 0.0
    s22 = 0.0
    for k in range(cnt):
        dx = bdx[k]
        dy = bdy[k]
        dz = bdz[k]
        w = bw[k]
        nx_ = bnx[k]
        ny_ = bny[k]
        nz_ = bnz[k]
        d2 = dx * dx + dy * dy + dz * dz
        pos = d2 > 0.0
        inv = 1.0 / (d2 if pos else 1.0)
        inv = inv if pos else 0.0  # l = 0: s2 = 0, m = n, DF = 1
        u = nx_ * dx + ny_ * dy + nz_ * dz
        u2 = u * u
        cone = not (u2 + u2 > d2)  # θ ≤ 45°
        s2 = min(u2 * inv, 0.5)
        rho2 = d2 * inv_s2
        ex = rho2 * arcsin_ratio2(s2) + gamma4 * s2 / max(rho2, lmin2)
        df = w * exp_neg_small(ex)
        df = df if cone else 0.0
        kk = 2.0 * u * inv
        mx = nx_ - kk * dx
        my = ny_ - kk * dy
        mz = nz_ - kk * dz
        dmx = df * mx
        dmy = df * my
        s00 += dmx * mx
        s01 += dmx * my
        s02 += dmx * mz
        s11 += dmy * my
        s12 += dmy * mz
        s22 += df * mz * mz
    return s00, s01, s02, s11, s12, s22


@njit(cache=True, inline="always", boundscheck=False)
def _gather_nl(nbr, k0, k1, xi, yi, zi, xs, ys, zs, nxs, nys, nzs, ws,
               bdx, bdy, bdz, bnx, bny, bnz, bw):
    """Copy the voters of the recorded list ``nbr[k0:k1]`` with nonzero weight to the buffers.

    Scalar compaction (``c += w ≠ 0``): not vectorised, so no gathers.
    Returns the number of voters copied.
    """
    c = np.uint64(0)
    for k in range(np.uint64(k0), np.uint64(k1)):
        j = np.uint64(nbr[k])
        w = ws[j]
        bdx[c] = xi - xs[j]
        bdy[c] = yi - ys[j]
        bdz[c] = zi - zs[j]
        bnx[c] = nxs[j]
        bny[c] = nys[j]
        bnz[c] = nzs[j]
        bw[c] = w
        c += np.uint64(w != 0.0)
    return np.int64(c)


@njit(cache=True, parallel=True, error_model="numpy", boundscheck=False)
def stick_pass(xs, ys, zs, nxs, nys, nzs, ws, cix, ciy, ciz, start, nx, ny, nz, hashed, mask, m,
               lo, h, r2, inv_s2, gamma4, lmin2, stride, t6, vals, e1, counts, nbr, nstart, ncount):
    """Sparse stick voting (eq. 44) with eigen-analysis fused per votee.

    Voter ``j`` votes with unit normal ``(nxs[j], nys[j], nzs[j])`` and weight
    ``ws[j]`` (``ws[j] == 0``: no vote).  The votee's own stick ``ws[i]·nᵢnᵢᵀ``
    (self vote, l = 0) is included.  ``gamma4 = 4γ`` and ``lmin2 = (l_min/σ)²``.

    ``nbr, nstart, ncount``: neighbour lists recorded by :func:`ball_pass` at
    the same σ (see there); a votee with ``nstart[i] ≥ 0`` sums the votes of
    its list, the others scan the grid.  Pass an empty ``nstart`` to scan for
    every votee.
    """
    use_nl = nstart.shape[0] == xs.shape[0]
    n = xs.shape[0]
    nb = (n + BLOCK - 1) // BLOCK
    nruns = 2 * m + 1 if hashed else 1
    inv_h = 1.0 / h
    lx = lo[0]
    ly = lo[1]
    lz = lo[2]
    for t in prange(nb):
        blk = (t * stride) % nb
        bj = np.empty(CAP, np.int64)
        bdx = np.empty(CAP)
        bdy = np.empty(CAP)
        bdz = np.empty(CAP)
        bnx = np.empty(CAP)
        bny = np.empty(CAP)
        bnz = np.empty(CAP)
        bw = np.empty(CAP)
        for i in range(blk * BLOCK, min((blk + 1) * BLOCK, n)):
            xi = xs[i]
            yi = ys[i]
            zi = zs[i]
            xl = xi - lx
            yl = yi - ly
            zl = zi - lz
            ix = cix[i]
            iy = ciy[i]
            iz = ciz[i]
            a00 = 0.0
            a01 = 0.0
            a02 = 0.0
            a11 = 0.0
            a12 = 0.0
            a22 = 0.0
            if use_nl and nstart[i] >= 0:
                k0 = nstart[i]
                nv = _gather_nl(nbr, k0, k0 + ncount[i], xi, yi, zi, xs, ys, zs, nxs, nys, nzs, ws,
                                bdx, bdy, bdz, bnx, bny, bnz, bw)
                a00, a01, a02, a11, a12, a22 = _stick_flush(bdx, bdy, bdz, bnx, bny, bnz, bw, nv,
                                                            inv_s2, gamma4, lmin2)
                counts[i] = nv
                _store(i, a00, a01, a02, a11, a12, a22, t6, vals, e1)
                continue
            total = 0
            cnt = 0
            for dz in range(-m, m + 1):
                cz = iz + dz
                if not hashed and (cz < 0 or cz >= nz):
                    continue
                for dy in range(-m, m + 1):
                    cy = iy + dy
                    if not hashed and (cy < 0 or cy >= ny):
                        continue
                    for kx in range(nruns):
                        j0, j1, cx = _run(start, hashed, mask, nx, ny, m, ix, cy, cz, kx,
                                          xl, yl, zl, h, inv_h, r2)
                        j = j0
                        while j < j1:
                            room = CAP - cnt
                            if j1 - j > room and cnt > 0:
                                s00, s01, s02, s11, s12, s22 = _stick_flush(
                                    bdx, bdy, bdz, bnx, bny, bnz, bw, cnt, inv_s2, gamma4, lmin2)
                                a00 += s00
                                a01 += s01
                                a02 += s02
                                a11 += s11
                                a12 += s12
                                a22 += s22
                                total += cnt
                                cnt = 0
                                room = CAP
                            je = min(j1, j + room)
                            cnt = _collect(xs, ys, zs, ws, True, cix, ciy, ciz, hashed, cx, cy, cz,
                                           j, je, xi, yi, zi, r2, bj, bdx, bdy, bdz, cnt,
                                           nxs, nys, nzs, bnx, bny, bnz, bw)
                            j = je
            s00, s01, s02, s11, s12, s22 = _stick_flush(
                bdx, bdy, bdz, bnx, bny, bnz, bw, cnt, inv_s2, gamma4, lmin2)
            a00 += s00
            a01 += s01
            a02 += s02
            a11 += s11
            a12 += s12
            a22 += s22
            counts[i] = total + cnt
            _store(i, a00, a01, a02, a11, a12, a22, t6, vals, e1)
