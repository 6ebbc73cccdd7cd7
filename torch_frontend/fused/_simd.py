"""Explicit SIMD values for the numba kernels: ``<4 x float>``, ``<4 x i32>``, ``<8 x i32>`` as numba types.

numba's auto-vectoriser handles plain loops over a window row, but not OpenCV's lane accumulators
(four float32 sums that a row adds to in a fixed order): written as four scalars they stay scalar
(~4x the work). Here they are LLVM vector values, through numba's public extension API
(``numba.extending``: a type, its data model, intrinsics), so a kernel states OpenCV's SSE2 steps
one for one: load 8 pixels, multiply by the splatted weights, shift, add the pixel pairs ``x`` and
``x + 4`` in int32, convert, add to the lanes. Every operation is a single LLVM instruction with
IEEE semantics (no fast-math flags: no contraction, no reassociation), so the values are those of
the scalar code, lane by lane.

Convention:
    ``F32x4`` lanes are float32, ``I32x4`` / ``I32x8`` int32 (wrap-around arithmetic; the kernels'
    values stay far inside int32). Loads and stores take a 1-D C-contiguous array and an element
    index; they do not check bounds (the kernels read inside their padded buffers).
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.extending import intrinsic, models, register_model

__all__ = [
    "f4_zero", "f4_add", "f4_mul", "f4_hsum", "i4_load", "i4_to_f4",
    "i8_load", "u8_load8", "i8_splat", "i8_add", "i8_sub", "i8_mul", "i8_sra", "i8_store", "i8_pairsum",
    "u8_load_even8", "u8_store8",
]

_F4 = ir.VectorType(ir.FloatType(), 4)
_I4 = ir.VectorType(ir.IntType(32), 4)
_I8 = ir.VectorType(ir.IntType(32), 8)
_U8x8 = ir.VectorType(ir.IntType(8), 8)
_i32 = ir.IntType(32)


class _Vec(types.Type):
    def __init__(self, name):
        super().__init__(name=name)


F32x4 = _Vec("F32x4")
I32x4 = _Vec("I32x4")
I32x8 = _Vec("I32x8")

@register_model(_Vec)
class _VecModel(models.PrimitiveModel):
    def __init__(self, dmm, fe_type):
        llty = {"F32x4": _F4, "I32x4": _I4, "I32x8": _I8}[fe_type.name]
        super().__init__(dmm, fe_type, llty)


def _ptr(context, builder, arrty, arr, idx, vecty):
    a = context.make_array(arrty)(context, builder, arr)
    p = builder.gep(a.data, [idx])
    return builder.bitcast(p, ir.PointerType(vecty))


def _as_i32(context, builder, val, ty):
    return context.cast(builder, val, ty, types.int32)


@intrinsic
def f4_zero(typingctx):
    """``<4 x float>`` zeros."""
    def cg(context, builder, sig, args):
        return ir.Constant(_F4, None)
    return F32x4(), cg


@intrinsic
def f4_add(typingctx, a, b):
    """Lane-wise float32 ``a + b`` (IEEE, round to nearest)."""
    def cg(context, builder, sig, args):
        return builder.fadd(args[0], args[1])
    return F32x4(a, b), cg


@intrinsic
def f4_mul(typingctx, a, b):
    """Lane-wise float32 ``a * b``."""
    def cg(context, builder, sig, args):
        return builder.fmul(args[0], args[1])
    return F32x4(a, b), cg


@intrinsic
def f4_hsum(typingctx, a):
    """x86's horizontal sum of four float32 lanes: ``(q0 + q2) + (q1 + q3)``."""
    def cg(context, builder, sig, args):
        v = args[0]
        e = [builder.extract_element(v, ir.Constant(_i32, i)) for i in range(4)]
        return builder.fadd(builder.fadd(e[0], e[2]), builder.fadd(e[1], e[3]))
    return types.float32(a), cg


@intrinsic
def i4_load(typingctx, arr, idx):
    """Four int32 from ``arr[idx:idx + 4]``."""
    def cg(context, builder, sig, args):
        return builder.load(_ptr(context, builder, sig.args[0], args[0], args[1], _I4), align=4)
    return I32x4(arr, idx), cg


@intrinsic
def i4_to_f4(typingctx, a):
    """Lane-wise int32 -> float32 (round to nearest even, as ``cvtdq2ps``)."""
    def cg(context, builder, sig, args):
        return builder.sitofp(args[0], _F4)
    return F32x4(a), cg


@intrinsic
def i8_load(typingctx, arr, idx):
    """Eight int32 from ``arr[idx:idx + 8]``."""
    def cg(context, builder, sig, args):
        return builder.load(_ptr(context, builder, sig.args[0], args[0], args[1], _I8), align=4)
    return I32x8(arr, idx), cg


@intrinsic
def u8_load8(typingctx, arr, idx):
    """Eight uint8 from ``arr[idx:idx + 8]``, zero-extended to int32."""
    def cg(context, builder, sig, args):
        v = builder.load(_ptr(context, builder, sig.args[0], args[0], args[1], _U8x8), align=1)
        return builder.zext(v, _I8)
    return I32x8(arr, idx), cg


@intrinsic
def i8_store(typingctx, arr, idx, v):
    """``arr[idx:idx + 8] = v`` (int32)."""
    def cg(context, builder, sig, args):
        builder.store(args[2], _ptr(context, builder, sig.args[0], args[0], args[1], _I8), align=4)
        return context.get_dummy_value()
    return types.none(arr, idx, v), cg


@intrinsic
def i8_splat(typingctx, x):
    """Eight copies of the integer ``x`` (as int32)."""
    def cg(context, builder, sig, args):
        s = _as_i32(context, builder, args[0], sig.args[0])
        v = builder.insert_element(ir.Constant(_I8, None), s, ir.Constant(_i32, 0))
        return builder.shuffle_vector(v, ir.Constant(_I8, None), ir.Constant(_I8, [0] * 8))
    return I32x8(x), cg


@intrinsic
def i8_add(typingctx, a, b):
    """Lane-wise int32 ``a + b``."""
    def cg(context, builder, sig, args):
        return builder.add(args[0], args[1])
    return I32x8(a, b), cg


@intrinsic
def i8_sub(typingctx, a, b):
    """Lane-wise int32 ``a - b``."""
    def cg(context, builder, sig, args):
        return builder.sub(args[0], args[1])
    return I32x8(a, b), cg


@intrinsic
def i8_mul(typingctx, a, b):
    """Lane-wise int32 ``a * b`` (low 32 bits, ``pmulld``)."""
    def cg(context, builder, sig, args):
        return builder.mul(args[0], args[1])
    return I32x8(a, b), cg


@intrinsic
def i8_sra(typingctx, a, n):
    """Lane-wise arithmetic shift right by the integer ``n`` (``CV_DESCALE``'s ``>>``: a floor)."""
    def cg(context, builder, sig, args):
        s = _as_i32(context, builder, args[1], sig.args[1])
        v = builder.insert_element(ir.Constant(_I8, None), s, ir.Constant(_i32, 0))
        v = builder.shuffle_vector(v, ir.Constant(_I8, None), ir.Constant(_I8, [0] * 8))
        return builder.ashr(args[0], v)
    return I32x8(a, n), cg


@intrinsic
def i8_pairsum(typingctx, a):
    """``<4 x i32>``: lane ``l`` = ``a[l] + a[l + 4]`` (``_mm_madd_epi16``'s pairs: pixels ``x`` and ``x + 4``)."""
    def cg(context, builder, sig, args):
        lo = builder.shuffle_vector(args[0], ir.Constant(_I8, None), ir.Constant(_I4, [0, 1, 2, 3]))
        hi = builder.shuffle_vector(args[0], ir.Constant(_I8, None), ir.Constant(_I4, [4, 5, 6, 7]))
        return builder.add(lo, hi)
    return I32x4(a), cg


_U8x16 = ir.VectorType(ir.IntType(8), 16)


@intrinsic
def u8_load_even8(typingctx, arr, idx):
    """``arr[idx], arr[idx + 2], ..., arr[idx + 14]`` (uint8, zero-extended to int32): one 16-byte load
    (reads ``arr[idx:idx + 16]``) and a shuffle."""
    def cg(context, builder, sig, args):
        v = builder.load(_ptr(context, builder, sig.args[0], args[0], args[1], _U8x16), align=1)
        evens = ir.Constant(_I8, [0, 2, 4, 6, 8, 10, 12, 14])
        e = builder.shuffle_vector(v, ir.Constant(_U8x16, None), evens)
        return builder.zext(e, _I8)
    return I32x8(arr, idx), cg


@intrinsic
def u8_store8(typingctx, arr, idx, v):
    """``arr[idx:idx + 8] = v`` truncated to uint8 (the values are 0..255)."""
    def cg(context, builder, sig, args):
        t = builder.trunc(args[2], _U8x8)
        builder.store(t, _ptr(context, builder, sig.args[0], args[0], args[1], _U8x8), align=1)
        return context.get_dummy_value()
    return types.none(arr, idx, v), cg
