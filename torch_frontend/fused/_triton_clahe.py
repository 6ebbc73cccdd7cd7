"""CLAHE on a CUDA device: two Triton kernels, the contract of ``_numba_clahe.py`` (``docs/kernels.md``, "CLAHE").

Convention:
    ``img``: ``(B, H, W)`` uint8, contiguous, on the kernels' device; the result: ``(B, H, W)`` uint8,
    ``cv2.createCLAHE(clip_limit, (gx, gy)).apply`` of every stream bit for bit.

* ``_lut_kernel``, grid ``(gx * gy, B)``: one program per tile of a stream. It counts the tile's
  histogram (``tl.histogram`` of ``_BLOCK`` pixels at a time: integer counts, any order), reading the
  bottom / right padding as BORDER_REFLECT_101; clips and redistributes it (integer sums: exact); and
  writes the tile's LUT ``cvRound(float(cumsum) * scale)`` as float32 values (integers 0..255) into a
  ``(B, gx * gy, 256)`` scratch tensor.
* ``_blend_kernel``, grid ``(cdiv(H * W, _BLOCK), B)``: each lane a pixel, OpenCV's float32 blend of
  its four tile LUTs, every product and sum rounded separately (compiled without FMA contraction).

``cvRound`` of a float32 ``f`` in ``[0, 2^22)`` is ``(f + 2^23) - 2^23`` (the spacing of float32 in
``[2^23, 2^24)`` is 1, so the addition rounds half to even). Two launches per call whatever B and the
data (capturable: no host sync).
"""

from __future__ import annotations

from typing import Tuple

import numpy as np
import torch
import triton
import triton.language as tl

__all__ = ["clahe_cuda", "clahe_geometry", "KERNELS"]

#: pixels per program (a power of two)
_BLOCK = 1024
_NUM_WARPS = 4
#: no FMA contraction, no flush-to-zero in libdevice (as the LK's and the pyramid's kernels)
_COMPILE_OPTIONS = {"enable_fp_fusion": False, "enable_reflect_ftz": False}
_MAGIC = tl.constexpr(8388608.0)  # 2^23


def clahe_geometry(height: int, width: int, gx: int, gy: int, clip_limit: float) -> Tuple[int, int, int, float, float,
                                                                                           float]:
    """``(tw, th, clip, lut_scale, inv_tw, inv_th)``: the tile size (of the padded image where the
    size is not a multiple of the grid), the clip count (0: no clipping), ``255.f / area``,
    ``1.f / tw`` and ``1.f / th`` (float32 values, as Python floats: exact)."""
    if width % gx == 0 and height % gy == 0:
        tw, th = width // gx, height // gy
    else:
        tw, th = (width + gx - width % gx) // gx, (height + gy - height % gy) // gy
    area = tw * th
    clip = max(int(clip_limit * area / 256), 1) if clip_limit > 0.0 else 0
    f32 = np.float32
    return (tw, th, clip, float(f32(255.0) / f32(area)), float(f32(1.0) / f32(tw)), float(f32(1.0) / f32(th)))


@triton.jit
def _lut_kernel(img_ptr, lut_ptr, height, width, gx, tw, th, clip, lut_scale, BLOCK: tl.constexpr):
    """The LUT of tile ``program_id(0)`` of stream ``program_id(1)``: ``lut[b, t, :]`` float32."""
    t = tl.program_id(0)
    b = tl.program_id(1).to(tl.int64)
    ntiles = tl.num_programs(0)
    ty = t // gx
    tx = t - ty * gx
    area = tw * th
    base = img_ptr + b * height * width
    hist = tl.zeros((256,), dtype=tl.int32)
    for e0 in range(0, area, BLOCK):
        e = e0 + tl.arange(0, BLOCK)
        m = e < area
        e = tl.where(m, e, 0)
        yy = ty * th + e // tw
        xx = tx * tw + e % tw
        sy = tl.where(yy < height, yy, 2 * height - 2 - yy)  # reflect-101 of the bottom / right padding
        sx = tl.where(xx < width, xx, 2 * width - 2 - xx)
        v = tl.load(base + sy * width + sx, mask=m, other=0).to(tl.int32)
        hist += tl.histogram(v, 256, mask=m)
    i = tl.arange(0, 256)
    if clip > 0:
        excess = tl.sum(tl.maximum(hist - clip, 0), axis=0)
        hist = tl.minimum(hist, clip)
        batch = excess // 256
        residual = excess - batch * 256
        step = tl.maximum(256 // tl.maximum(residual, 1), 1)
        extra = ((i % step) == 0) & ((i // step) < residual)
        hist = hist + batch + extra.to(tl.int32)
    cs = tl.cumsum(hist, axis=0)
    f = cs.to(tl.float32) * lut_scale
    r = (f + _MAGIC) - _MAGIC
    r = tl.minimum(tl.maximum(r, 0.0), 255.0)
    tl.store(lut_ptr + (b * ntiles + t) * 256 + i, r)


@triton.jit
def _blend_kernel(img_ptr, lut_ptr, out_ptr, height, width, gx, gy, inv_tw, inv_th, BLOCK: tl.constexpr):
    """``out[b]``: the bilinear blend of the tile LUTs (``lut (B, gx * gy, 256)`` float32) per pixel."""
    pid = tl.program_id(0)
    b = tl.program_id(1).to(tl.int64)
    n = height * width
    e = pid * BLOCK + tl.arange(0, BLOCK)
    m = e < n
    e = tl.where(m, e, 0)
    y = e // width
    x = e - y * width
    v = tl.load(img_ptr + b * n + e, mask=m, other=0).to(tl.int32)
    txf = x.to(tl.float32) * inv_tw - 0.5
    tx1f = tl.floor(txf)
    xa = txf - tx1f
    xa1 = 1.0 - xa
    tx1 = tx1f.to(tl.int32)
    tyf = y.to(tl.float32) * inv_th - 0.5
    ty1f = tl.floor(tyf)
    ya = tyf - ty1f
    ya1 = 1.0 - ya
    ty1 = ty1f.to(tl.int32)
    c1 = tl.maximum(tx1, 0) * 256 + v
    c2 = tl.minimum(tx1 + 1, gx - 1) * 256 + v
    r1 = tl.maximum(ty1, 0) * gx * 256
    r2 = tl.minimum(ty1 + 1, gy - 1) * gx * 256
    lb = lut_ptr + b * gx * gy * 256
    l11 = tl.load(lb + r1 + c1)
    l12 = tl.load(lb + r1 + c2)
    l21 = tl.load(lb + r2 + c1)
    l22 = tl.load(lb + r2 + c2)
    res = (l11 * xa1 + l12 * xa) * ya1 + (l21 * xa1 + l22 * xa) * ya
    r = (res + _MAGIC) - _MAGIC
    r = tl.minimum(tl.maximum(r, 0.0), 255.0)
    tl.store(out_ptr + b * n + e, r.to(tl.uint8), mask=m)


#: the kernels of this module and their PTX signatures (``_triton_lk.ptx_sm90``)
KERNELS = {"clahe_lut": _lut_kernel, "clahe_blend": _blend_kernel}
SIGNATURES = {
    "clahe_lut": {"img_ptr": "*u8", "lut_ptr": "*fp32", "height": "i32", "width": "i32", "gx": "i32", "tw": "i32",
                  "th": "i32", "clip": "i32", "lut_scale": "fp32", "BLOCK": "constexpr"},
    "clahe_blend": {"img_ptr": "*u8", "lut_ptr": "*fp32", "out_ptr": "*u8", "height": "i32", "width": "i32",
                    "gx": "i32", "gy": "i32", "inv_tw": "fp32", "inv_th": "fp32", "BLOCK": "constexpr"},
}


def clahe_cuda(img: torch.Tensor, clip_limit: float, gx: int, gy: int) -> torch.Tensor:
    """CLAHE of every stream of ``img`` ``(B, H, W)`` uint8 (contiguous, on a CUDA device; CPU tensors
    under ``TRITON_INTERPRET=1``): ``(B, H, W)`` uint8. Two launches, no host sync."""
    if img.dim() != 3 or img.dtype != torch.uint8:
        raise ValueError(f"clahe_cuda: expected a (B, H, W) uint8 tensor, got {tuple(img.shape)} {img.dtype}")
    img = img.contiguous()
    B, H, W = img.shape
    out = torch.empty_like(img)
    if B == 0 or H == 0 or W == 0:
        return out
    tw, th, clip, scale, inv_tw, inv_th = clahe_geometry(int(H), int(W), int(gx), int(gy), float(clip_limit))
    lut = torch.empty((B, gx * gy, 256), dtype=torch.float32, device=img.device)
    torch.library.wrap_triton(_lut_kernel)[(gx * gy, B)](
        img, lut, H, W, gx, tw, th, clip, scale, BLOCK=_BLOCK, num_warps=_NUM_WARPS, **_COMPILE_OPTIONS)
    torch.library.wrap_triton(_blend_kernel)[(triton.cdiv(H * W, _BLOCK), B)](
        img, lut, out, H, W, gx, gy, inv_tw, inv_th, BLOCK=_BLOCK, num_warps=_NUM_WARPS, **_COMPILE_OPTIONS)
    return out
