"""The PINHOLE lift on a CUDA device: one Triton kernel, the contract of ``_numba_lift.py``
(``docs/kernels.md``, "The PINHOLE lift"), bit-identical to the CPU kernel and to the tensor path.

Grid ``(cdiv(N, BLOCK), B)``: each lane one point of one stream, the fixed-point iteration in
float64 with the contract's order; one launch per call whatever B and the data (capturable: no host
sync). Compiled with ``enable_fp_fusion=False`` (no FMA); an fp64 ``/`` lowers to ``div.rn.f64``; the
result is rounded to the output's dtype with ``cvt.rn``. :func:`~._triton_lk.ptx_sm90` lists its PTX
for the tests' check (no FMA, every float op ``.rn``).
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

from ._triton_pyramid import _COMPILE_OPTIONS

__all__ = ["pinhole_lift_cuda", "KERNELS"]

_BLOCK = 128
_NUM_WARPS = 4


@triton.jit
def _lift_kernel(uv_ptr, valid_ptr, par_ptr, out_ptr, N, par_stride, iters, BLOCK: tl.constexpr):
    b = tl.program_id(1).to(tl.int64)
    j = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    m = j < N
    pb = par_ptr + b * par_stride
    k1 = tl.load(pb + 0)
    k2 = tl.load(pb + 1)
    p1 = tl.load(pb + 2)
    p2 = tl.load(pb + 3)
    fx = tl.load(pb + 4)
    fy = tl.load(pb + 5)
    cx = tl.load(pb + 6)
    cy = tl.load(pb + 7)
    tp1 = 2.0 * p1
    tp2 = 2.0 * p2
    idx = b * N + j
    ok = tl.load(valid_ptr + idx, mask=m, other=0) != 0
    u = tl.load(uv_ptr + idx * 2, mask=m, other=0.0).to(tl.float64)
    v = tl.load(uv_ptr + idx * 2 + 1, mask=m, other=0.0).to(tl.float64)
    mxd = (u - cx) / fx
    myd = (v - cy) / fy
    x = mxd
    y = myd
    for _ in range(iters):
        mx2 = x * x
        my2 = y * y
        mxy = x * y
        rho2 = mx2 + my2
        rad = k1 * rho2 + k2 * rho2 * rho2
        dx = x * rad + tp1 * mxy + p2 * (rho2 + 2.0 * mx2)
        dy = y * rad + tp2 * mxy + p1 * (rho2 + 2.0 * my2)
        x = mxd - dx
        y = myd - dy
    # camodocal's noDistortion (k1 = k2 = p1 = p2 = 0: the sum of their magnitudes is 0) for a
    # non-finite component (x - x: 0 for finite x, NaN for inf / NaN)
    no_dist = (tl.abs(k1) + tl.abs(k2) + tl.abs(p1) + tl.abs(p2)) == 0.0
    x = tl.where((x - x) != 0.0, tl.where(no_dist, mxd, x), x)
    y = tl.where((y - y) != 0.0, tl.where(no_dist, myd, y), y)
    x = tl.where(ok, x, 0.0)
    y = tl.where(ok, y, 0.0)
    dt = out_ptr.dtype.element_ty
    tl.store(out_ptr + idx * 2, x.to(dt), mask=m)
    tl.store(out_ptr + idx * 2 + 1, y.to(dt), mask=m)


_SIG = {"uv_ptr": "*fp32", "valid_ptr": "*u8", "par_ptr": "*fp64", "out_ptr": "*fp32", "N": "i32",
        "par_stride": "i32", "iters": "i32", "BLOCK": "constexpr"}
#: PTX name -> (kernel, signature, constexprs, num_warps) for ``_triton_lk.ptx_sm90``
KERNELS = {
    "pinhole_lift": (_lift_kernel, _SIG, {"BLOCK": _BLOCK}, _NUM_WARPS),
    "pinhole_lift_f64": (_lift_kernel, {**_SIG, "uv_ptr": "*fp64", "out_ptr": "*fp64"}, {"BLOCK": _BLOCK}, _NUM_WARPS),
}


def pinhole_lift_cuda(uv: torch.Tensor, valid: torch.Tensor, params: torch.Tensor, iters: int) -> torch.Tensor:
    """The lift of ``uv (B, N, 2)`` float32/float64 (``valid (B, N)`` bool, ``params (1 or B, 8)``
    float64; contiguous, one CUDA device; CPU tensors under ``TRITON_INTERPRET=1``): ``(B, N, 2)`` in
    ``uv``'s dtype. One launch, no host sync."""
    B, N = int(uv.shape[0]), int(uv.shape[1])
    out = torch.empty_like(uv)
    if B == 0 or N == 0:
        return out
    stride = 0 if params.shape[0] == 1 else 8
    torch.library.wrap_triton(_lift_kernel)[(triton.cdiv(N, _BLOCK), B)](
        uv, valid.view(torch.uint8), params, out, N, stride, int(iters), BLOCK=_BLOCK, num_warps=_NUM_WARPS,
        **_COMPILE_OPTIONS)
    return out
