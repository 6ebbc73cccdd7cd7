"""``goodFeaturesToTrack`` (VINS's call) on a CUDA device: Triton kernels for the response, its maximum
over the mask, the quality threshold and the 3x3 maximum; the capturable tensor selection for the rest.

Convention:
    ``img`` ``(B, H, W)`` uint8, contiguous; ``mask`` ``(B, H, W)`` bool or None; ``max_corners``
    ``(B,)`` int64; the result as ``torch_frontend::good_features`` (``fused/corners_op.py``):
    ``pts (B, K, 2)`` float32, ``valid (B, K)`` bool, ``overflow (B,)`` bool.

The contract is :mod:`._numba_corners`'s (the tensor path's bits). Two launches, whatever B and the
data:

1. :func:`_resp_kernel`, one lane a pixel: the nine Sobel-3 products of its 3x3 block (each from its
   own reflect-101 3x3 of grey levels: a product at a reflected position is the product *there*, so
   the reflection is applied twice, as the tensor path's padded planes do), their integer sums, the
   float32 response (no FMA: ``enable_fp_fusion=False``; ``tl.sqrt_rn``), and per program the
   maximum over the mask's pixels (``-inf`` where none): a maximum is exact in any order.
2. :func:`_cand_kernel`, one lane a pixel: the stream's maximum from the programs' maxima, ``thr =
   float32(double(max) * quality)``, ``t = r > thr ? r : 0``, the candidate test (interior, mask,
   ``t != 0``, ``t`` equal to the 3x3 maximum of ``t``) and the candidate's key: its response's bits
   as an int32 (> 0: a candidate's response exceeds ``thr >= 0``, or there is none), 0 elsewhere.

The ranking and the greedy minimum-distance pass stay the capturable tensor selection
(``corners.selection_capturable``: one top-k of the keys, fixed windows and rounds, the ``overflow``
flag), fed these keys instead of the image-sized tensor passes it takes on the response. A Triton
greedy pass would be one program per stream walking candidates in order (sequential by nature);
the tensor windows keep the kernel count fixed and were measured already on the simulated device,
so this stays tensor code (unmeasured on a GPU either way).

On the GPU every pixel's response is computed (no skipping by the mask: a warp's lanes run
together, and the two launches are one pass over the image each).
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

from ._numba_corners import RESP_SCALE
from ._triton_pyramid import _COMPILE_OPTIONS

__all__ = ["good_features_cuda", "KERNELS", "SIGNATURES", "CONSTEXPRS"]

#: pixels per program (a power of two)
_BLOCK = 512
#: the programs' maxima reduced per step by :func:`_cand_kernel`
_TBLOCK = 256
_NUM_WARPS = 4


@triton.jit
def _refl(i, n):
    """BORDER_REFLECT_101 of an index at most one out of ``[0, n)``."""
    i = tl.where(i < 0, -i, i)
    return tl.where(i >= n, 2 * n - 2 - i, i)


@triton.jit
def _products(base, ry, rx, H, W, m):
    """The Sobel-3 products (int32) at pixel ``(ry, rx)`` (inside the image) of the image at ``base``."""
    ya = _refl(ry - 1, H) * W
    yb = ry * W
    yc = _refl(ry + 1, H) * W
    xl = _refl(rx - 1, W)
    xr = _refl(rx + 1, W)
    a0 = tl.load(base + ya + xl, mask=m, other=0).to(tl.int32)
    a1 = tl.load(base + ya + rx, mask=m, other=0).to(tl.int32)
    a2 = tl.load(base + ya + xr, mask=m, other=0).to(tl.int32)
    b0 = tl.load(base + yb + xl, mask=m, other=0).to(tl.int32)
    b2 = tl.load(base + yb + xr, mask=m, other=0).to(tl.int32)
    c0 = tl.load(base + yc + xl, mask=m, other=0).to(tl.int32)
    c1 = tl.load(base + yc + rx, mask=m, other=0).to(tl.int32)
    c2 = tl.load(base + yc + xr, mask=m, other=0).to(tl.int32)
    dx = (a2 - a0) + 2 * (b2 - b0) + (c2 - c0)
    dy = (c0 + 2 * c1 + c2) - (a0 + 2 * a1 + a2)
    return dx * dx, dx * dy, dy * dy


@triton.jit
def _resp_kernel(img_ptr, mask_ptr, resp_ptr, pmax_ptr, H, W, n_tiles, scale, HAS_MASK: tl.constexpr,
                 BLOCK: tl.constexpr):
    """Responses of ``BLOCK`` pixels and their maximum over the mask. Grid ``(n_tiles, B)``."""
    pid = tl.program_id(0)
    b = tl.program_id(1).to(tl.int64)
    HW = H * W
    e = pid * BLOCK + tl.arange(0, BLOCK)
    m = e < HW
    y = e // W
    x = e % W
    base = img_ptr + b * HW
    sxx = tl.zeros([BLOCK], dtype=tl.int32)
    sxy = tl.zeros([BLOCK], dtype=tl.int32)
    syy = tl.zeros([BLOCK], dtype=tl.int32)
    for dy in tl.static_range(3):
        ry = _refl(y + (dy - 1), H)
        for dx in tl.static_range(3):
            rx = _refl(x + (dx - 1), W)
            pxx, pxy, pyy = _products(base, ry, rx, H, W, m)
            sxx += pxx
            sxy += pxy
            syy += pyy
    fxx = sxx.to(tl.float32)
    fxy = sxy.to(tl.float32)
    fyy = syy.to(tl.float32)
    d = fxx - fyy
    disc = d * d
    disc = disc + (fxy * 4.0) * fxy
    r = ((fxx + fyy) - tl.sqrt_rn(disc)) * scale
    tl.store(resp_ptr + b * HW + e, r, mask=m)
    inside = m
    if HAS_MASK:
        inside = inside & (tl.load(mask_ptr + b * HW + e, mask=m, other=0) != 0)
    tl.store(pmax_ptr + b * n_tiles + pid, tl.max(tl.where(inside, r, float("-inf")), 0))


@triton.jit
def _cand_kernel(resp_ptr, mask_ptr, pmax_ptr, keys_ptr, H, W, n_tiles, quality: tl.float64,
                 HAS_MASK: tl.constexpr, BLOCK: tl.constexpr, TBLOCK: tl.constexpr):
    """The stream's threshold and the candidates' keys of ``BLOCK`` pixels. Grid ``(n_tiles, B)``."""
    pid = tl.program_id(0)
    b = tl.program_id(1).to(tl.int64)
    HW = H * W
    mx = tl.full([TBLOCK], float("-inf"), dtype=tl.float32)
    for t0 in range(0, n_tiles, TBLOCK):
        t = t0 + tl.arange(0, TBLOCK)
        mx = tl.maximum(mx, tl.load(pmax_ptr + b * n_tiles + t, mask=t < n_tiles, other=float("-inf")))
    smax = tl.max(mx, 0)
    smax = tl.where(smax == float("-inf"), 0.0, smax)  # an empty mask: maxVal 0 (minMaxLoc)
    thr = (smax.to(tl.float64) * quality).to(tl.float32)
    e = pid * BLOCK + tl.arange(0, BLOCK)
    m = e < HW
    y = e // W
    x = e % W
    inner = m & (y >= 1) & (y < H - 1) & (x >= 1) & (x < W - 1)
    if HAS_MASK:
        inner = inner & (tl.load(mask_ptr + b * HW + e, mask=m, other=0) != 0)
    row = resp_ptr + b * HW
    v = tl.load(row + e, mask=inner, other=0.0)
    tv = tl.where(v > thr, v, 0.0)
    ok = inner & (tv != 0.0)
    for dy in tl.static_range(3):
        for dx in tl.static_range(3):
            u = tl.load(row + e + ((dy - 1) * W + (dx - 1)), mask=ok, other=0.0)
            ok = ok & (tl.where(u > thr, u, 0.0) <= tv)
    key = tl.where(ok, tv.to(tl.int32, bitcast=True), 0)
    tl.store(keys_ptr + b * HW + e, key, mask=m)


#: the kernels, their signatures and constexprs for the PTX check (``_triton_lk.ptx_sm90``)
KERNELS = {"corners_response": _resp_kernel, "corners_candidates": _cand_kernel}
SIGNATURES = {
    "corners_response": {"img_ptr": "*u8", "mask_ptr": "*u8", "resp_ptr": "*fp32", "pmax_ptr": "*fp32", "H": "i32",
                         "W": "i32", "n_tiles": "i32", "scale": "fp32", "HAS_MASK": "constexpr",
                         "BLOCK": "constexpr"},
    "corners_candidates": {"resp_ptr": "*fp32", "mask_ptr": "*u8", "pmax_ptr": "*fp32", "keys_ptr": "*i32",
                           "H": "i32", "W": "i32", "n_tiles": "i32", "quality": "fp64", "HAS_MASK": "constexpr",
                           "BLOCK": "constexpr", "TBLOCK": "constexpr"},
}
CONSTEXPRS = {"corners_response": {"HAS_MASK": True, "BLOCK": _BLOCK},
              "corners_candidates": {"HAS_MASK": True, "BLOCK": _BLOCK, "TBLOCK": _TBLOCK}}
NUM_WARPS = _NUM_WARPS


def candidate_keys(img: torch.Tensor, mask, quality_level: float):
    """Launches 1 and 2 (module docstring): ``(keys (B, H * W) int32, resp (B, H, W) float32)``."""
    B, H, W = img.shape
    dev = img.device
    n_tiles = triton.cdiv(H * W, _BLOCK)
    resp = torch.empty((B, H, W), dtype=torch.float32, device=dev)
    pmax = torch.empty((B, n_tiles), dtype=torch.float32, device=dev)
    keys = torch.empty((B, H * W), dtype=torch.int32, device=dev)
    m = img if mask is None else mask.view(torch.uint8)
    grid = (n_tiles, B)
    torch.library.wrap_triton(_resp_kernel)[grid](
        img, m, resp, pmax, H, W, n_tiles, float(RESP_SCALE), HAS_MASK=mask is not None, BLOCK=_BLOCK,
        num_warps=_NUM_WARPS, **_COMPILE_OPTIONS)
    torch.library.wrap_triton(_cand_kernel)[grid](
        resp, m, pmax, keys, H, W, n_tiles, float(quality_level), HAS_MASK=mask is not None, BLOCK=_BLOCK,
        TBLOCK=_TBLOCK, num_warps=_NUM_WARPS, **_COMPILE_OPTIONS)
    return keys, resp


def good_features_cuda(img: torch.Tensor, max_corners: torch.Tensor, mask, capacity: int, quality_level: float,
                       min_distance: float, select):
    """``torch_frontend::good_features`` on CUDA (CPU tensors under ``TRITON_INTERPRET=1``): the two
    launches, then ``select(keys, max_corners, min_distance, H, W, K)``: the capturable selection
    (``corners.selection_capturable._select_from_keys`` with ``GFTT_BUDGET``, which
    ``torch_frontend.corners`` registers: ``corners_op.set_selection``)."""
    if select is None:
        raise RuntimeError("torch_frontend::good_features on CUDA: import torch_frontend.corners first (it "
                           "registers the capturable selection the op runs after its kernels)")
    B, H, W = img.shape
    dev = img.device
    K = int(capacity)
    if K <= 0 or B == 0:
        return (torch.zeros(B, max(K, 0), 2, dtype=torch.float32, device=dev),
                torch.zeros(B, max(K, 0), dtype=torch.bool, device=dev), torch.zeros(B, dtype=torch.bool, device=dev))
    keys, _ = candidate_keys(img, mask, quality_level)
    return select(keys, max_corners.clamp_min(0), float(min_distance), H, W, K)
