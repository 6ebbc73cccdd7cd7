"""The packed 8-bit pyramid on a CUDA device: Triton kernels (``fused/layout.py`` says where each level lies).

Convention:
    ``img``: ``(B, H, W)`` uint8, contiguous, on the kernels' device; the result: ``(B, total)`` uint8
    of a :class:`~.layout.PyramidLayout` ``(H, W, max_level, pad)``. Level 0 is the image; level ``l``
    is ``cv2.pyrDown`` of level ``l - 1`` for 8-bit images, ``(S + 128) >> 8`` with ``S`` the
    ``[1 4 6 4 1]^T [1 4 6 4 1]`` sum around source pixel ``(2x, 2y)``, BORDER_REFLECT_101. Every
    level's ``pad`` border holds the level's BORDER_REFLECT_101 values (repeated reflection where
    ``pad`` exceeds the level).

Every value is an integer sum: any order of the taps gives the same bits as the CPU kernel
(``_numba_pyramid.py``) and ``cv2.pyrDown``. One program writes ``_BLOCK`` consecutive elements of a
level's *padded* block: an element of the border is computed as the interior pixel it reflects
(``reflect101`` of its coordinates), so a level and its border are written by one launch, and the
down-sampling reflects its source indices itself (it reads only the previous level's interior: any
``pad >= 0`` works). Launches: one for level 0, one per further level, in order on the stream.
"""

import torch
import triton
import triton.language as tl

from .layout import PyramidLayout

__all__ = ["pyramid_cuda"]

#: elements of a padded level written by one program (a power of two)
_BLOCK = 1024
#: warps per program: 1024 elements = 4 per thread (ptxas for sm_90: 100 registers, no spill; at 4
#: warps the down-sampling used 255 registers and spilled)
_NUM_WARPS = 8
#: compile options of every fused kernel (launch keywords): no FMA contraction (OpenCV rounds every
#: product before its sum), no flush-to-zero in libdevice (Triton's default reflects ftz into
#: libdevice: tl.floor became cvt.rmi.ftz.f32, floor(-subnormal) = -0 instead of -1)
_COMPILE_OPTIONS = {"enable_fp_fusion": False, "enable_reflect_ftz": False}
#: the pyrDown rounding: (S + 2^7) >> 8 (the kernel [1 4 6 4 1] sums to 16 per axis, 256 in all)
_ROUND = tl.constexpr(128)
_SHIFT = tl.constexpr(8)


@triton.jit
def _reflect101(p, n):
    """``cv2.borderInterpolate(p, n, BORDER_REFLECT_101)`` of int32 ``p`` (any value), ``n >= 1``."""
    # period 2 (n - 1); max(., 1) keeps the modulo defined for n == 1 (whose answer is 0)
    period = tl.maximum(2 * (n - 1), 1)
    q = tl.abs(p) % period
    q = tl.where(q >= n, period - q, q)
    return tl.where(n == 1, 0, q)


@triton.jit
def _level0_kernel(img_ptr, out_ptr, height, width, total, pad, BLOCK: tl.constexpr):
    """Level 0 and its border: ``out[b, (Y) Wp + X] = img[b, r(Y - pad), r(X - pad)]`` (``r`` reflect-101).

    Grid: ``(cdiv(Hp * Wp, BLOCK), B)``.
    """
    pid = tl.program_id(0)
    b = tl.program_id(1).to(tl.int64)
    pitch = width + 2 * pad
    n_el = (height + 2 * pad) * pitch
    e = pid * BLOCK + tl.arange(0, BLOCK)
    m = e < n_el
    y = _reflect101(e // pitch - pad, height)
    x = _reflect101(e % pitch - pad, width)
    v = tl.load(img_ptr + b * height * width + y * width + x, mask=m, other=0)
    tl.store(out_ptr + b * total + e, v, mask=m)


@triton.jit
def _down_row(row, y, x, s_pitch, s_h, s_w, pad):
    """``sum_j k[j] L(2x + j - 2, y)`` (int32) of the source level at ``row`` (its interior's origin
    element is ``row + pad * s_pitch + pad``), ``y`` already reflected."""
    base = row + (y + pad) * s_pitch + pad
    c0 = tl.load(base + _reflect101(2 * x - 2, s_w)).to(tl.int32)
    c1 = tl.load(base + _reflect101(2 * x - 1, s_w)).to(tl.int32)
    c2 = tl.load(base + _reflect101(2 * x, s_w)).to(tl.int32)
    c3 = tl.load(base + _reflect101(2 * x + 1, s_w)).to(tl.int32)
    c4 = tl.load(base + _reflect101(2 * x + 2, s_w)).to(tl.int32)
    return (c0 + c4) + 4 * (c1 + c3) + 6 * c2


@triton.jit
def _down_kernel(out_ptr, total, src_off, s_h, s_w, dst_off, d_h, d_w, pad, BLOCK: tl.constexpr):
    """Level ``(d_h, d_w)`` at ``dst_off`` (with its border) = pyrDown of level ``(s_h, s_w)`` at ``src_off``.

    Grid: ``(cdiv(Hp * Wp, BLOCK), B)`` over the destination's padded block. Masked-off elements
    (past the block) compute in-range indices (their ``e`` only exceeds the block) and store nothing.
    """
    pid = tl.program_id(0)
    b = tl.program_id(1).to(tl.int64)
    d_pitch = d_w + 2 * pad
    s_pitch = s_w + 2 * pad
    n_el = (d_h + 2 * pad) * d_pitch
    e = pid * BLOCK + tl.arange(0, BLOCK)
    m = e < n_el
    e = tl.where(m, e, 0)
    y = _reflect101(e // d_pitch - pad, d_h)
    x = _reflect101(e % d_pitch - pad, d_w)
    src = out_ptr + b * total + src_off
    r0 = _down_row(src, _reflect101(2 * y - 2, s_h), x, s_pitch, s_h, s_w, pad)
    r1 = _down_row(src, _reflect101(2 * y - 1, s_h), x, s_pitch, s_h, s_w, pad)
    r2 = _down_row(src, _reflect101(2 * y, s_h), x, s_pitch, s_h, s_w, pad)
    r3 = _down_row(src, _reflect101(2 * y + 1, s_h), x, s_pitch, s_h, s_w, pad)
    r4 = _down_row(src, _reflect101(2 * y + 2, s_h), x, s_pitch, s_h, s_w, pad)
    s = (r0 + r4) + 4 * (r1 + r3) + 6 * r2
    v = (s + _ROUND) >> _SHIFT
    tl.store(out_ptr + b * total + dst_off + e, v.to(tl.uint8), mask=m)


#: the kernels of this module, for the PTX check (``_triton_lk.ptx_sm90``)
KERNELS = {"pyramid_level0": _level0_kernel, "pyramid_down": _down_kernel}


def pyramid_cuda(img: torch.Tensor, max_level: int, pad: int) -> torch.Tensor:
    """The packed pyramid of ``img``: levels ``0..max_level``, each with a ``pad`` reflect-101 border.

    Args:
        img: ``(B, H, W)`` uint8, contiguous, on the kernels' device (a CUDA device; CPU tensors
            under ``TRITON_INTERPRET=1``).
        max_level: the top level (``>= 0``).
        pad: border pixels per side of every level (``>= 0``; an LK needs :func:`~.layout.lk_pad`).

    Returns:
        ``(B, total)`` uint8 on ``img.device``, laid out as ``PyramidLayout(H, W, max_level, pad)``.
    """
    if img.dim() != 3 or img.dtype != torch.uint8:
        raise ValueError(f"pyramid_cuda: expected a (B, H, W) uint8 tensor, got {tuple(img.shape)} "
                         f"{img.dtype}")
    img = img.contiguous()
    B, H, W = img.shape
    lay = PyramidLayout(int(H), int(W), int(max_level), int(pad))
    out = torch.empty((B, lay.total), dtype=torch.uint8, device=img.device)
    if B == 0:
        return out
    sizes, offs = lay.sizes, lay.offsets
    hp, wp = lay.padded_shape(0)
    grid = (triton.cdiv(hp * wp, _BLOCK), B)
    torch.library.wrap_triton(_level0_kernel)[grid](
        img, out, H, W, lay.total, lay.pad, BLOCK=_BLOCK, num_warps=_NUM_WARPS, **_COMPILE_OPTIONS)
    for lvl in range(1, lay.max_level + 1):
        (sh, sw), (dh, dw) = sizes[lvl - 1], sizes[lvl]
        hp, wp = lay.padded_shape(lvl)
        grid = (triton.cdiv(hp * wp, _BLOCK), B)
        torch.library.wrap_triton(_down_kernel)[grid](
            out, lay.total, offs[lvl - 1], sh, sw, offs[lvl], dh, dw, lay.pad, BLOCK=_BLOCK,
            num_warps=_NUM_WARPS, **_COMPILE_OPTIONS)
    return out
