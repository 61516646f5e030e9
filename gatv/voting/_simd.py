"""Helpers of the 8-lane voting kernels: explicit LLVM vectors (private).

The 8-lane paths of :mod:`gatv.voting._passes` (scan, ball and stick votes)
and :mod:`gatv.voting._eigen` (eigen-analysis) are numba intrinsics that emit
LLVM vector code directly.  This module holds what they share: whether to
take them at all (:data:`SIMD`), the lane count (:data:`LANES`), the LLVM
lane types and masked memory intrinsics (:class:`Ops`), lane-wise Python
arithmetic (:class:`Lanes`, so a scalar formula can be emitted lane by lane
from its own source) and small IR builders (:func:`splat`,
:func:`lane_sums`, :func:`row_vector_ptr`).
"""

from __future__ import annotations

import llvmlite.binding as llvm
from llvmlite import ir
from numba.core import cgutils

__all__ = ["SIMD", "LANES", "Lanes", "Ops", "splat", "lane_sums", "row_vector_ptr"]

#: Whether the kernels take their explicit 8-lane paths (the scan, ball and
#: stick votes of :mod:`gatv.voting._passes`, :func:`gatv.voting._eigen.eig_rows_simd`).
#: They are correct on any target (LLVM expands what the CPU lacks), but were
#: shown faster than the scalar loops only for x86 code with AVX2 or AVX-512,
#: so other hosts keep the scalar loops.  Fixed per host, as numba's cache is.
SIMD = bool(llvm.get_host_cpu_features().get("avx2", False))
#: Lanes of the explicit vectors (float64, int64 and bool).
LANES = 8


def splat(builder, value, vty):
    """``value`` in every lane of a vector of type ``vty``."""
    i32 = ir.IntType(32)
    u = builder.insert_element(ir.Constant(vty, ir.Undefined), value, ir.Constant(i32, 0))
    return builder.shuffle_vector(u, u, ir.Constant(ir.VectorType(i32, vty.count), [0] * vty.count))


def lane_sums(builder, slots):
    """The lanes of each vector in ``slots`` (allocas) summed from lane 0 to the last: a fixed order."""
    i32 = ir.IntType(32)
    out = []
    for slot in slots:
        v = builder.load(slot)
        acc = builder.extract_element(v, ir.Constant(i32, 0))
        for q in range(1, v.type.count):
            acc = builder.fadd(acc, builder.extract_element(v, ir.Constant(i32, q)))
        out.append(acc)
    return out


def row_vector_ptr(builder, arr, rowlen, r, k, vty):
    """Pointer to the vector at ``arr[r, k : k + lanes]`` of a C-contiguous 2-D array with rows of ``rowlen``."""
    i64 = ir.IntType(64)
    at = builder.add(builder.mul(ir.Constant(i64, r), rowlen), k)
    return builder.bitcast(builder.gep(arr.data, [at]), vty.as_pointer())


class Lanes:
    """An LLVM vector of float64 lanes with Python arithmetic.

    Lets the scalar polynomials (:func:`gatv.voting._passes.arcsin_ratio2`,
    :func:`~gatv.voting._passes.exp_neg_small`) and eigen-solver steps be
    emitted lane-wise from their own Python source, so the two stay one
    formula.  Products and sums carry the ``contract`` flag, as the scalar
    stick flush's fastmath flags allow.
    """

    __slots__ = ("b", "v")

    def __init__(self, builder, value):
        self.b = builder
        self.v = value

    def _lift(self, other):
        if isinstance(other, Lanes):
            return other.v
        return ir.Constant(self.v.type, [float(other)] * self.v.type.count)

    def _op(self, name, a, c):
        inst = getattr(self.b, name)(a, c)
        inst.flags.append("contract")
        return Lanes(self.b, inst)

    def __add__(self, o):
        return self._op("fadd", self.v, self._lift(o))

    def __radd__(self, o):
        return self._op("fadd", self._lift(o), self.v)

    def __sub__(self, o):
        return self._op("fsub", self.v, self._lift(o))

    def __rsub__(self, o):
        return self._op("fsub", self._lift(o), self.v)

    def __mul__(self, o):
        return self._op("fmul", self.v, self._lift(o))

    def __rmul__(self, o):
        return self._op("fmul", self._lift(o), self.v)

    def __rtruediv__(self, o):
        return Lanes(self.b, self.b.fdiv(self._lift(o), self.v))


class Ops:
    """Lane-wise comparisons, selects and math of the 8-lane intrinsics, and their LLVM types.

    ``lane_types``: ``(f64, i64, i32, vd, vi, vm)``, the scalar types and the
    vectors of :data:`LANES` doubles, int64 and bools; ``vpd`` a vector of
    double pointers. :meth:`intrinsic` declares the masked memory intrinsics
    the kernels use (once per module).
    """

    def __init__(self, builder, mod):
        self.b = builder
        self.mod = mod
        f64, i64, i32 = ir.DoubleType(), ir.IntType(64), ir.IntType(32)
        vd = ir.VectorType(f64, LANES)
        self.vd = vd
        self.lane_types = (f64, i64, i32, vd, ir.VectorType(i64, LANES), ir.VectorType(ir.IntType(1), LANES))
        self.vpd = ir.VectorType(f64.as_pointer(), LANES)
        self._sqrt = cgutils.get_or_insert_function(mod, ir.FunctionType(vd, [vd]), f"llvm.sqrt.v{LANES}f64")
        self._fabs = cgutils.get_or_insert_function(mod, ir.FunctionType(vd, [vd]), f"llvm.fabs.v{LANES}f64")

    def intrinsic(self, name):
        """Declaration of ``llvm.masked.<name>`` on vectors of doubles: load, store, gather or scatter."""
        _, _, i32, vd, _, vm = self.lane_types
        vpd, void = self.vpd, ir.VoidType()
        ty, suffix = {
            "load": (ir.FunctionType(vd, [vd.as_pointer(), i32, vm, vd]), f"v{LANES}f64.p0v{LANES}f64"),
            "store": (ir.FunctionType(void, [vd, vd.as_pointer(), i32, vm]), f"v{LANES}f64.p0v{LANES}f64"),
            "gather": (ir.FunctionType(vd, [vpd, i32, vm, vd]), f"v{LANES}f64.v{LANES}p0f64"),
            "scatter": (ir.FunctionType(void, [vd, vpd, i32, vm]), f"v{LANES}f64.v{LANES}p0f64"),
        }[name]
        return cgutils.get_or_insert_function(self.mod, ty, f"llvm.masked.{name}.{suffix}")

    def v(self, a):
        """The LLVM vector of lanes, an LLVM value as it is, or a float in every lane."""
        if isinstance(a, Lanes):
            return a.v
        if isinstance(a, ir.Value):
            return a
        return ir.Constant(self.vd, [float(a)] * LANES)

    def L(self, x):
        return Lanes(self.b, x)

    def cmp(self, op, a, c):
        return self.b.fcmp_ordered(op, self.v(a), self.v(c))

    def sel(self, m, a, c):
        return self.L(self.b.select(m, self.v(a), self.v(c)))

    def max(self, a, c):  # numba's max(a, c): c if c > a else a
        return self.sel(self.cmp(">", c, a), c, a)

    def min(self, a, c):  # numba's min(a, c): c if c < a else a
        return self.sel(self.cmp("<", c, a), c, a)

    def sqrt(self, a):
        return self.L(self.b.call(self._sqrt, [self.v(a)]))

    def abs(self, a):
        return self.L(self.b.call(self._fabs, [self.v(a)]))

    def div(self, a, c):
        return self.L(self.b.fdiv(self.v(a), self.v(c)))

    def and_(self, *ms):
        out = ms[0]
        for m in ms[1:]:
            out = self.b.and_(out, m)
        return out

    def not_(self, m):
        return self.b.not_(m)
