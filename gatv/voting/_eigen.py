"""3×3 symmetric eigen-solver of the voting kernels (private).

Eberly's closed form (trigonometric eigenvalues, eigenvectors from cross
products), robust for repeated eigenvalues: the scalar :func:`eig3_top`
(eigenvalues and e1, inlined into the passes), :func:`eig3_batch` (all
eigenvectors) and :func:`eig3_top_batch`, and its 8-lane twin
:func:`eig_rows_simd`, emitted through :mod:`gatv.voting._simd` from the same
Python source where the two share a formula.
"""

from __future__ import annotations

import math

from llvmlite import ir
from numba import njit, prange, types
from numba.core import cgutils
from numba.extending import intrinsic

from gatv.voting._simd import LANES, Ops
from gatv.voting._simd import splat as splat_ir

__all__ = ["eig3_top", "eig3_batch", "eig3_top_batch", "eig_rows", "eig_rows_simd"]

_TWO_PI_3 = 2.0 * math.pi / 3.0


# ---------------------------------------------------------------------------
# 3x3 symmetric eigen-solver (closed form, robust for repeated eigenvalues).
# Eberly, "A Robust Eigensolver for 3 × 3 Symmetric Matrices" (Geometric Tools,
# 2014): trigonometric eigenvalues, eigenvectors by cross products of the rows
# of A − λI for the well-separated eigenvalue and a 2×2 problem in its
# orthogonal complement for the next one.
# ---------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _row_crosses(a00, a01, a02, a11, a12, a22, lam):
    """Cross products of the rows of A − λI and their squared lengths.

    Plain arithmetic: :func:`_evec_single` and the 8-lane
    :func:`eig_rows_simd` (through ``py_func``) share it.
    """
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
    return c0x, c0y, c0z, c1x, c1y, c1z, c2x, c2y, c2z, d0, d1, d2


@njit(cache=True, inline="always")
def _evec_single(a00, a01, a02, a11, a12, a22, lam):
    """Unit eigenvector for an eigenvalue of multiplicity one (max cross product)."""
    c0x, c0y, c0z, c1x, c1y, c1z, c2x, c2y, c2z, d0, d1, d2 = _row_crosses(a00, a01, a02, a11, a12, a22, lam)
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
def _complement_2x2(a00, a01, a02, a11, a12, a22, wx, wy, wz, ux, uy, uz, lam):
    """``v = w × u`` and the 2×2 matrix of A − λI on the plane (u, v): ``(v, m00, m01, m11)``.

    Plain arithmetic, shared with the 8-lane :func:`eig_rows_simd`.
    """
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
    return vx, vy, vz, m00, m01, m11


@njit(cache=True, inline="always")
def _evec_complement(a00, a01, a02, a11, a12, a22, wx, wy, wz, lam):
    """Unit eigenvector for ``lam`` orthogonal to the unit eigenvector ``w``."""
    if abs(wx) > abs(wy):
        s = 1.0 / math.sqrt(wx * wx + wz * wz)
        ux, uy, uz = -wz * s, 0.0, wx * s
    else:
        s = 1.0 / math.sqrt(wy * wy + wz * wz)
        ux, uy, uz = 0.0, wz * s, -wy * s
    vx, vy, vz, m00, m01, m11 = _complement_2x2(a00, a01, a02, a11, a12, a22, wx, wy, wz, ux, uy, uz, lam)
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
def eig3_top_batch(t6, vals, e1, simd=False):
    """Eigenvalues (descending) and e1 of ``(N, 6)`` C-contiguous tensors (unfused variant).

    ``simd``: blocks of 256 tokens through :func:`eig_rows_simd`, as the
    fused passes do when :data:`gatv.voting._simd.SIMD` is on.
    """
    nb = (t6.shape[0] + 255) // 256
    for b in prange(nb):
        if simd:
            eig_rows_simd(t6, vals, e1, 256 * b, min(256 * (b + 1), t6.shape[0]))
        else:
            eig_rows(t6, vals, e1, 256 * b, min(256 * (b + 1), t6.shape[0]))


@njit(cache=True)
def eig_rows(t6, vals, e1, i0, i1):
    """:func:`eig3_top` of the rows ``i0 .. i1 - 1`` of ``(N, 6)`` tensors into ``vals``, ``e1`` (the scalar
    twin of :func:`eig_rows_simd`)."""
    for i in range(i0, i1):
        l1, l2, l3, ex, ey, ez = eig3_top(t6[i, 0], t6[i, 1], t6[i, 2], t6[i, 3], t6[i, 4], t6[i, 5])
        vals[i, 0] = l1
        vals[i, 1] = l2
        vals[i, 2] = l3
        e1[i, 0] = ex
        e1[i, 1] = ey
        e1[i, 2] = ez


#: Chebyshev coefficients (in x = 2u − 1, u ∈ [0, 1]) of cos(⅔ acos u) and of
#: sin(⅔ acos u) / sin(acos u); both are analytic on [0, 1] (even in acos u at
#: u = 1), so truncated series reach 1e-17 (computed with mpmath at 40 digits).
_COS_THIRD = (0.7580911654351291, 0.24933602102708852, -0.008021174548795317, 0.000655646818891165,
              -6.89243563279823e-05, 8.188877173129078e-06, -1.0466055460825932e-06, 1.4043322846141953e-07,
              -1.9510326190769272e-08, 2.782320375264605e-09, -4.049391221915355e-10, 5.990386523100158e-11,
              -8.980957670148084e-12, 1.3615450721784287e-12, -2.0837359679227866e-13, 3.2149357013701097e-14,
              -4.995217667621266e-15, 7.80925676827245e-16, -1.2275110870926396e-16)
_SIN_THIRD_RATIO = (0.7540347438607463, -0.09794691839370434, 0.012053361558961478, -0.001692823808160549,
                    0.0002517188189205075, -3.8639256288973876e-05, 6.052503726635105e-06, -9.61456630000523e-07,
                    1.5430813125548396e-07, -2.4960972843598082e-08, 4.0628309911953e-09, -6.646255121059554e-10,
                    1.091758859491952e-10, -1.7996559855293435e-11, 2.9753703192777506e-12,
                    -4.931777247420255e-13, 8.192818804465196e-14, -1.3636828650383968e-14, 2.273769008272972e-15,
                    -3.7970890978346075e-16, 6.349767363173025e-17, -1.0631844237236111e-17)


def _clenshaw(co, x):
    """Σ co[k] T_k(x) by Clenshaw's recurrence (x: a float or :class:`~gatv.voting._simd.Lanes`)."""
    x2 = 2.0 * x
    b1 = co[-1] + 0.0 * x
    b2 = 0.0 * x
    for k in range(len(co) - 2, 0, -1):
        b1, b2 = co[k] + x2 * b1 - b2, b1
    return co[0] + x * b1 - b2


def _evec_single_lanes(o, a00, a01, a02, a11, a12, a22, lam):
    r = _row_crosses.py_func(a00, a01, a02, a11, a12, a22, lam)
    c0, c1, c2 = r[0:3], r[3:6], r[6:9]
    d0, d1, d2 = r[9:12]
    zero = o.and_(o.cmp("==", d0, 0.0), o.cmp("==", d1, 0.0), o.cmp("==", d2, 0.0))
    pick0 = o.and_(o.cmp(">=", d0, d1), o.cmp(">=", d0, d2))
    pick1 = o.cmp(">=", d1, d2)
    c = [o.sel(pick0, c0[k], o.sel(pick1, c1[k], c2[k])) for k in range(3)]
    d = o.sel(pick0, d0, o.sel(pick1, d1, d2))
    s = o.div(1.0, o.sqrt(o.sel(zero, 1.0, d)))
    return [o.sel(zero, 1.0 if k == 0 else 0.0, c[k] * s) for k in range(3)]


def _evec_complement_lanes(o, a00, a01, a02, a11, a12, a22, wx, wy, wz, lam):
    big = o.cmp(">", o.abs(wx), o.abs(wy))
    sa = o.div(1.0, o.sqrt(wx * wx + wz * wz))
    sb = o.div(1.0, o.sqrt(wy * wy + wz * wz))
    ux = o.sel(big, (0.0 - wz) * sa, 0.0)
    uy = o.sel(big, 0.0, wz * sb)
    uz = o.sel(big, wx * sa, (0.0 - wy) * sb)
    vx, vy, vz, m00, m01, m11 = _complement_2x2.py_func(a00, a01, a02, a11, a12, a22, wx, wy, wz, ux, uy, uz, lam)
    b00 = o.abs(m00)
    b01 = o.abs(m01)
    b11 = o.abs(m11)
    case_a = o.cmp(">=", b00, b11)
    p = o.sel(case_a, m00, m11)
    bp = o.sel(case_a, b00, b11)
    nonzero = o.cmp(">", o.max(bp, b01), 0.0)
    lead = o.sel(o.cmp(">=", bp, b01), p, m01)
    sgn = o.sel(o.cmp(">", lead, 0.0), 1.0, -1.0)
    k = o.div(1.0, sgn * o.sqrt(p * p + m01 * m01))
    ga = o.sel(case_a, m01, p)  # coefficient of u
    gb = o.sel(case_a, p, m01)  # coefficient of v
    return [o.sel(nonzero, (ga * uu - gb * vv) * k, uu) for uu, vv in ((ux, vx), (uy, vy), (uz, vz))]


def _eig3_top_lanes(o, a):
    """Lane-wise :func:`eig3_top`: returns (l1, l2, l3, e1x, e1y, e1z) as lanes."""
    mx = o.abs(a[0])
    for k in range(1, 6):
        mx = o.max(mx, o.abs(a[k]))
    inv = o.div(1.0, o.sel(o.cmp(">", mx, 0.0), mx, 1.0))
    a00, a01, a02, a11, a12, a22 = (x * inv for x in a)
    q = o.div(a00 + a11 + a22, 3.0)
    b00 = a00 - q
    b11 = a11 - q
    b22 = a22 - q
    off = a01 * a01 + a02 * a02 + a12 * a12
    p2 = o.div(b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * off, 6.0)
    degen = o.cmp("==", p2, 0.0)
    p = o.sqrt(p2)
    c00 = b11 * b22 - a12 * a12
    c01 = a01 * b22 - a12 * a02
    c02 = a01 * a12 - b11 * a02
    hd = o.div(0.5 * (b00 * c00 - a01 * c01 + a02 * c02), o.sel(degen, 1.0, p * p2))
    hd = o.min(o.max(hd, -1.0), 1.0)
    u = o.sqrt(0.5 + 0.5 * hd)
    x = 2.0 * u - 1.0
    c = _clenshaw(_COS_THIRD, x)  # cos(acos(hd) / 3)
    s = o.sqrt(0.5 - 0.5 * hd) * _clenshaw(_SIN_THIRD_RATIO, x)  # sin(acos(hd) / 3)
    beta2 = 2.0 * c
    beta0 = (0.0 - c) - math.sqrt(3.0) * s  # 2 cos(acos(hd)/3 + 2π/3)
    beta1 = o.min(o.max(0.0 - (beta0 + beta2), beta0), beta2)
    l1 = q + p * beta2
    l2 = q + p * beta1
    l3 = q + p * beta0
    first = o.cmp(">=", hd, 0.0)
    w = _evec_single_lanes(o, a00, a01, a02, a11, a12, a22, o.sel(first, l1, l3))
    e = _evec_complement_lanes(o, a00, a01, a02, a11, a12, a22, w[0], w[1], w[2], l1)
    e1 = [o.sel(degen, 1.0 if k == 0 else 0.0, o.sel(first, w[k], e[k])) for k in range(3)]
    return (l1 * mx, l2 * mx, l3 * mx, *e1)


@intrinsic
def eig_rows_simd(typingctx, acc, vals, e1, i0, i1):
    """:func:`eig3_top` of the tensors ``acc[i0:i1]`` into ``vals`` and ``e1``, 8 tokens at a time.

    Branch-free: both of Eberly's eigenvector branches are computed and
    selected per lane, and the trigonometric eigenvalues take no libm call:
    with ``u = √((1 + hd)/2)``, ``cos(acos(hd)/3)`` and
    ``sin(acos(hd)/3) / √((1 − hd)/2)`` are smooth in u on [0, 1] and are
    summed from their Chebyshev series.  Eigenvalues agree with
    :func:`eig3_top` to 1e-15 of the largest where they are separated (both
    lose ~1e-8 at near-double eigenvalues, as any trigonometric solver), e1
    to 1e-15 where λ1 − λ2 > 1e-6 λ1.  Used instead of the scalar loop
    where :data:`gatv.voting._simd.SIMD` is on: it is several times faster.
    """
    for a in (acc, vals, e1):
        if not (isinstance(a, types.Array) and a.ndim == 2 and a.layout == "C" and a.dtype == types.float64):
            return None
    sig = types.void(acc, vals, e1, types.int64, types.int64)

    def codegen(context, builder, signature, args):
        aacc, avals, ae1, ai0, ai1 = args
        arrs = [context.make_array(signature.args[k])(context, builder, args[k]) for k in range(3)]
        mod = builder.module
        o = Ops(builder, mod)
        _, i64, i32, vd, vi, _ = o.lane_types
        vpd = o.vpd
        gather, scatter = o.intrinsic("gather"), o.intrinsic("scatter")

        def splat(v, ty):
            return splat_ir(builder, v, ty)

        iota = ir.Constant(vi, list(range(LANES)))
        end = splat(ai1, vi)
        one = ir.Constant(vd, [1.0] * LANES)
        bases = [splat(builder.ptrtoint(a.data, i64), vi) for a in arrs]
        with cgutils.for_range_slice(builder, ai0, ai1, ir.Constant(i64, LANES), inc=True) as (i, _):
            idx = builder.add(splat(i, vi), iota)
            lane = builder.icmp_signed("<", idx, end)

            def ptrs(k, width, col):
                off = builder.mul(builder.add(builder.mul(idx, ir.Constant(vi, [width] * LANES)),
                                              ir.Constant(vi, [col] * LANES)), ir.Constant(vi, [8] * LANES))
                return builder.inttoptr(builder.add(bases[k], off), vpd)

            a = [o.L(builder.call(gather, [ptrs(0, 6, c), ir.Constant(i32, 8), lane, one])) for c in range(6)]
            res = _eig3_top_lanes(o, a)
            for c in range(3):
                builder.call(scatter, [o.v(res[c]), ptrs(1, 3, c), ir.Constant(i32, 8), lane])
                builder.call(scatter, [o.v(res[3 + c]), ptrs(2, 3, c), ir.Constant(i32, 8), lane])
        return context.get_dummy_value()

    return sig, codegen

