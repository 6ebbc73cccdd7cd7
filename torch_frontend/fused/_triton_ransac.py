"""The fused F-RANSAC scoring on a CUDA device: a Triton kernel with the contract of
``_numba_ransac.py`` (OpenCV's ``computeError`` in double, ``findInliers``, the sequential best-model
and iteration-bound bookkeeping), bit-identical to the CPU kernel.

How: one program per problem. The program walks the block's samples in order (a ``while`` loop over
scalars: it stops at OpenCV's last sample, so a problem that converges after 6 samples scores 18
models, not the block's 3000); each model's error is computed for ``BLOCK`` slots at a time, one slot
per lane, in double, with the contract's order (no float value is reduced across lanes); the count is
an integer ``tl.sum`` (exact in any order). The bookkeeping is scalar. After the loop the accepted
model's mask is written. One launch per call, whatever B and the data (grid ``(B,)``).

Floating point: compiled with ``enable_fp_fusion=False`` (no FMA) and float64 division (Triton lowers an fp64 ``/`` to ``div.rn.f64``; ``tl.div_rn`` is fp32 only),
the error rounded to float32 with ``cvt.rn`` and compared with ``t = float32(thr2)`` (rounded on the
host: a float argument, exact in fp32); :func:`ptx_sm90` gives the PTX for the tests' check.
"""

from typing import Dict, Optional

import numpy as np
import torch
import triton
import triton.language as tl

from ._triton_pyramid import _COMPILE_OPTIONS

__all__ = ["ransac_score_cuda", "KERNELS", "SIGNATURES", "constexprs"]

_MIN_RANSAC_POINTS = tl.constexpr(15)
_MIN_GOOD = tl.constexpr(6)
_NUM_WARPS = 4
_MAX_BLOCK = 1024


@triton.jit
def _inliers(F_ptr, m, x12_ptr, eff_ptr, N, j0, t, BLOCK: tl.constexpr):
    """Slots ``j0 .. j0 + BLOCK - 1`` of a problem (its rows of F, x12, eff): inlier of model ``m``
    (bool, False past N)."""
    base = F_ptr + m * 9
    F0 = tl.load(base + 0)
    F1 = tl.load(base + 1)
    F2 = tl.load(base + 2)
    F3 = tl.load(base + 3)
    F4 = tl.load(base + 4)
    F5 = tl.load(base + 5)
    F6 = tl.load(base + 6)
    F7 = tl.load(base + 7)
    F8 = tl.load(base + 8)
    j = j0 + tl.arange(0, BLOCK)
    pm = j < N
    p = x12_ptr + j * 4
    x1 = tl.load(p + 0, mask=pm, other=0.0)
    y1 = tl.load(p + 1, mask=pm, other=0.0)
    x2 = tl.load(p + 2, mask=pm, other=0.0)
    y2 = tl.load(p + 3, mask=pm, other=0.0)
    e = tl.load(eff_ptr + j, mask=pm, other=0) != 0
    a = F0 * x1 + F1 * y1 + F2
    bb = F3 * x1 + F4 * y1 + F5
    c = F6 * x1 + F7 * y1 + F8
    s2 = 1.0 / (a * a + bb * bb)
    d2 = x2 * a + y2 * bb + c
    a = F0 * x2 + F3 * y2 + F6
    bb = F1 * x2 + F4 * y2 + F7
    c = F2 * x2 + F5 * y2 + F8
    s1 = 1.0 / (a * a + bb * bb)
    d1 = x1 * a + y1 * bb + c
    e1 = d1 * d1 * s1
    e2 = d2 * d2 * s2
    err = tl.where(e1 < e2, e2, e1).to(tl.float32)
    return pm & e & (err <= t)


@triton.jit
def _ransac_score_kernel(F_ptr, fok_ptr, x12_ptr, eff_ptr, n_ptr, table_ptr, live_ptr, best_ptr, nit_ptr, done_ptr,
                         out_best_ptr, out_nit_ptr, out_done_ptr, out_kb_ptr, out_mask_ptr,
                         M, N, table_stride, t, HAS_STATE: tl.constexpr, BLOCK: tl.constexpr):
    b = tl.program_id(0).to(tl.int64)
    nb = tl.load(n_ptr + b)
    Fb = F_ptr + b * M * 9
    fb = fok_ptr + b * M
    xb = x12_ptr + b * N * 4
    eb = eff_ptr + b * N
    if HAS_STATE:
        live = tl.load(live_ptr + b)
        best = tl.load(best_ptr + b)
        nit = tl.load(nit_ptr + b)
        done = tl.load(done_ptr + b)
    else:
        live = tl.full([], 0, tl.int64) + M // 3
        best = tl.full([], -1, tl.int64)
        nit = tl.load(table_ptr + nb * table_stride)
        done = tl.full([], 0, tl.int64)
    kb = tl.full([], -1, tl.int64)
    live = tl.where(nb >= _MIN_RANSAC_POINTS, live, 0)
    i = tl.full([], 0, tl.int64)
    while i < live:
        for r in tl.static_range(3):
            m = 3 * i + r
            ok = tl.load(fb + m) != 0
            if ok:
                cnt = tl.full([], 0, tl.int64)
                for j0 in range(0, N, BLOCK):
                    inl = _inliers(Fb, m, xb, eb, N, j0, t, BLOCK)
                    cnt += tl.sum(inl.to(tl.int32), 0).to(tl.int64)
                better = cnt > tl.maximum(best, _MIN_GOOD)
                kb = tl.where(better, m, kb)
                best = tl.where(better, cnt, best)
                nit = tl.where(better, tl.load(table_ptr + nb * table_stride + best + 1), nit)
        done += 1
        i += 1
        i = tl.where(done >= nit, live, i)
    tl.store(out_best_ptr + b, best)
    tl.store(out_nit_ptr + b, nit)
    tl.store(out_done_ptr + b, done)
    tl.store(out_kb_ptr + b, kb)
    mb = out_mask_ptr + b * N
    for j0 in range(0, N, BLOCK):
        j = j0 + tl.arange(0, BLOCK)
        inl = _inliers(Fb, tl.maximum(kb, 0), xb, eb, N, j0, t, BLOCK)
        tl.store(mb + j, inl & (kb >= 0), mask=j < N)


def _block(N: int) -> int:
    return max(16, min(_MAX_BLOCK, triton.next_power_of_2(max(int(N), 1))))


def ransac_score_cuda(F: torch.Tensor, fok: torch.Tensor, x12: torch.Tensor, eff: torch.Tensor, n: torch.Tensor,
                      table: torch.Tensor, live: Optional[torch.Tensor], best: Optional[torch.Tensor],
                      niters: Optional[torch.Tensor], done: Optional[torch.Tensor], thr2: float):
    """``torch_frontend::ransac_score`` on the tensors' device (arguments and results as the op's,
    ``fused/ransac_op.py``): one launch, grid ``(B,)``."""
    B, M = int(F.shape[0]), int(F.shape[1])
    N = int(x12.shape[1])
    dev = F.device
    out_best = torch.empty((B,), dtype=torch.int64, device=dev)
    out_nit = torch.empty((B,), dtype=torch.int64, device=dev)
    out_done = torch.empty((B,), dtype=torch.int64, device=dev)
    out_kb = torch.empty((B,), dtype=torch.int64, device=dev)
    out_mask = torch.empty((B, N), dtype=torch.bool, device=dev)
    if B == 0:
        return out_best, out_nit, out_done, out_kb, out_mask
    has_state = live is not None
    st = (live, best, niters, done) if has_state else (n, n, n, n)  # unused pointers: never read
    torch.library.wrap_triton(_ransac_score_kernel)[(B,)](
        F, fok, x12, eff, n, table, *st, out_best, out_nit, out_done, out_kb, out_mask,
        M, N, int(table.shape[1]), float(np.float32(thr2)), HAS_STATE=has_state, BLOCK=_block(N), num_warps=_NUM_WARPS,
        **_COMPILE_OPTIONS)
    return out_best, out_nit, out_done, out_kb, out_mask


# ----------------------------------------------------------------------------------- PTX (no GPU)
#: the kernels :func:`ptx_sm90` (``_triton_lk._compile_all``) compiles: name -> (kernel, HAS_STATE)
KERNELS = {"ransac_score": (_ransac_score_kernel, False), "ransac_score_state": (_ransac_score_kernel, True)}

SIGNATURES = {
    "F_ptr": "*fp64", "fok_ptr": "*i1", "x12_ptr": "*fp64", "eff_ptr": "*i1", "n_ptr": "*i64", "table_ptr": "*i64",
    "live_ptr": "*i64", "best_ptr": "*i64", "nit_ptr": "*i64", "done_ptr": "*i64",
    "out_best_ptr": "*i64", "out_nit_ptr": "*i64", "out_done_ptr": "*i64", "out_kb_ptr": "*i64", "out_mask_ptr": "*i1",
    "M": "i32", "N": "i32", "table_stride": "i32", "t": "fp32", "HAS_STATE": "constexpr", "BLOCK": "constexpr",
}


def constexprs(has_state: bool) -> Dict[str, object]:
    """The constexprs of a compiled variant (VINS: 150 points -> 256 lanes)."""
    return {"HAS_STATE": has_state, "BLOCK": _block(150)}


NUM_WARPS = _NUM_WARPS
