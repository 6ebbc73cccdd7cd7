"""VINS's ``setMask`` on a CUDA device: two Triton kernels (the contract is ``docs/kernels.md``, "setMask").

Convention:
    As the CPU kernel (``_numba_mask.py``): ``pts (B, N, 2)`` float32 / float64, ``pri (B, N)``
    integer, ``valid (B, N)`` bool, ``base (Bm, H, W)`` uint8 (``Bm`` 1 or ``B``: batch stride 0 or
    ``H W``), the integer squared radius ``r2``; out: ``keep (B, N)`` bool and ``mask (B, H, W)``
    uint8, bit for bit the CPU kernel's.

* ``_decide_kernel``: one program per stream. The features' ranks in the stable order (track count
  descending, ties by slot) are counted pairwise, then the features are visited rank by rank, one
  at a time, as VINS does. The mask at a feature's centre is "still 255" iff the base mask is 255
  there and no feature kept before covers it (``dx² + dy² <= r2``: the kept discs are exactly the
  zeros drawn so far). The kept centres are written compacted, in visiting order, with their count.
* ``_draw_kernel``: the mask, one program per ``BLOCK`` pixels of a stream: the base value, or 0
  where a kept disc covers the pixel (the same test). A program skips the discs whose rows miss
  its pixels' rows.

Every value is an integer or an integer comparison; ``cvRound`` of a coordinate is
``floor(|v|)`` plus the half-to-even step, with the sign restored (``|v| - floor(|v|)`` is exact).
"""

import torch
import triton
import triton.language as tl

from ._triton_pyramid import _COMPILE_OPTIONS

__all__ = ["set_mask_cuda", "KERNELS"]

#: pixels per program of the draw kernel, and its warps
_BLOCK = 1024
_NUM_WARPS = 4
#: the decide kernel: columns of the pairwise rank tile per step, warps
_RANK_CHUNK = 16
_DECIDE_WARPS = 4


@triton.jit
def _round_inside(v, size):
    """``cvRound(v)`` (half to even) as int32 where it lies in ``[0, size)``, else -1 (NaN, inf)."""
    ok = (v > -1.0) & (v < size + 1.0)  # False for NaN
    a = tl.where(ok, tl.abs(v), 0.0)
    f = tl.floor(a)
    frac = a - f  # exact: a >= 0
    fi = f.to(tl.int32)
    up = (frac > 0.5) | ((frac == 0.5) & ((fi & 1) == 1))
    c = fi + up.to(tl.int32)
    c = tl.where(v < 0, -c, c)
    return tl.where(ok & (c >= 0) & (c < size), c, -1)


@triton.jit
def _decide_kernel(pts_ptr, pri_ptr, valid_ptr, base_ptr, keep_ptr, centre_ptr, count_ptr, N, H, W,
                   base_stride, r2, BLOCK_N: tl.constexpr, CHUNK: tl.constexpr):
    """Stream ``program_id(0)``: ``keep`` (input order), the kept centres ``(N, 2)`` int32 in visiting
    order and their count."""
    b = tl.program_id(0).to(tl.int64)
    i = tl.arange(0, BLOCK_N)
    m = i < N
    v = tl.load(valid_ptr + b * N + i, mask=m, other=0) != 0
    p = tl.load(pri_ptr + b * N + i, mask=m, other=0)
    x = _round_inside(tl.load(pts_ptr + (b * N + i) * 2, mask=m, other=-2.0), W)
    y = _round_inside(tl.load(pts_ptr + (b * N + i) * 2 + 1, mask=m, other=-2.0), H)
    inside = v & (x >= 0) & (y >= 0)
    bv = tl.load(base_ptr + b * base_stride + tl.where(inside, y * W + x, 0), mask=inside, other=0)
    eligible = inside & (bv == 255)
    # rank among the valid features: j before i iff p_j > p_i, or p_j == p_i and j < i
    rank = tl.zeros((BLOCK_N,), dtype=tl.int32)
    for j0 in range(0, N, CHUNK):
        j = j0 + tl.arange(0, CHUNK)
        mj = j < N
        vj = tl.load(valid_ptr + b * N + j, mask=mj, other=0) != 0
        pj = tl.load(pri_ptr + b * N + j, mask=mj, other=0)
        before = (pj[None, :] > p[:, None]) | ((pj[None, :] == p[:, None]) & (j[None, :] < i[:, None]))
        before = before & (vj & mj)[None, :]
        rank += tl.sum(before.to(tl.int32), axis=1)
    rank = tl.where(v & m, rank, -1)
    n_valid = tl.sum((v & m).to(tl.int32), axis=0)
    kept = tl.zeros((BLOCK_N,), dtype=tl.int1)
    count = n_valid * 0
    for k in range(0, n_valid):
        sel = rank == k
        cx = tl.sum(tl.where(sel, x, 0), axis=0)
        cy = tl.sum(tl.where(sel, y, 0), axis=0)
        ok = tl.sum(tl.where(sel & eligible, 1, 0), axis=0) > 0
        dx = x - cx
        dy = y - cy
        hit = kept & (dx * dx + dy * dy <= r2)
        ok = ok & (tl.max(hit.to(tl.int32), axis=0) == 0)
        kept = kept | (sel & ok)
        tl.store(centre_ptr + (b * N + count) * 2, cx, mask=ok)
        tl.store(centre_ptr + (b * N + count) * 2 + 1, cy, mask=ok)
        count += ok.to(tl.int32)
    tl.store(keep_ptr + b * N + i, kept, mask=m)
    tl.store(count_ptr + b, count)


@triton.jit
def _draw_kernel(base_ptr, out_ptr, centre_ptr, count_ptr, N, H, W, base_stride, r2, R, BLOCK: tl.constexpr):
    """Pixels ``[pid * BLOCK, (pid + 1) * BLOCK)`` of stream ``program_id(1)``: the base value, 0 under a
    kept disc. Grid: ``(cdiv(H W, BLOCK), B)``."""
    pid = tl.program_id(0)
    b = tl.program_id(1).to(tl.int64)
    e = pid * BLOCK + tl.arange(0, BLOCK)
    m = e < H * W
    py = e // W
    px = e % W
    y_lo = (pid * BLOCK) // W
    y_hi = tl.minimum(pid * BLOCK + BLOCK - 1, H * W - 1) // W
    val = tl.load(base_ptr + b * base_stride + e, mask=m, other=0)
    cover = tl.zeros((BLOCK,), dtype=tl.int1)
    n = tl.load(count_ptr + b)
    for k in range(0, n):
        cx = tl.load(centre_ptr + (b * N + k) * 2)
        cy = tl.load(centre_ptr + (b * N + k) * 2 + 1)
        if (cy + R >= y_lo) & (cy - R <= y_hi):
            dx = px - cx
            dy = py - cy
            cover = cover | (dx * dx + dy * dy <= r2)
    tl.store(out_ptr + b * H * W + e, tl.where(cover, 0, val).to(tl.uint8), mask=m)


#: the kernels of this module for the PTX check (``_triton_lk._compile_all``): name -> (kernel,
#: signature, constexprs, warps); the tracker's setting: float32 points, int64 track counts, N <= 256
KERNELS = {
    "mask_decide": (_decide_kernel, {
        "pts_ptr": "*fp32", "pri_ptr": "*i64", "valid_ptr": "*i1", "base_ptr": "*u8", "keep_ptr": "*i1",
        "centre_ptr": "*i32", "count_ptr": "*i32", "N": "i32", "H": "i32", "W": "i32", "base_stride": "i32",
        "r2": "i32", "BLOCK_N": "constexpr", "CHUNK": "constexpr"},
        {"BLOCK_N": 256, "CHUNK": _RANK_CHUNK}, _DECIDE_WARPS),
    "mask_draw": (_draw_kernel, {
        "base_ptr": "*u8", "out_ptr": "*u8", "centre_ptr": "*i32", "count_ptr": "*i32", "N": "i32", "H": "i32",
        "W": "i32", "base_stride": "i32", "r2": "i32", "R": "i32", "BLOCK": "constexpr"},
        {"BLOCK": _BLOCK}, _NUM_WARPS),
}


def set_mask_cuda(pts: torch.Tensor, pri: torch.Tensor, valid: torch.Tensor, base: torch.Tensor, r2: int,
                  R: int):
    """``(keep (B, N) bool, mask (B, H, W) uint8)``: setMask of every stream (two launches).

    Args:
        pts: ``(B, N, 2)`` float32 / float64, contiguous; pri: ``(B, N)`` int32 / int64; valid: ``(B, N)``
            bool; base: ``(Bm, H, W)`` uint8, ``Bm`` 1 or ``B``; all on the kernels' device (CPU tensors
            under ``TRITON_INTERPRET=1``).
        r2: the disc's integer squared radius; R: its row reach ``isqrt(r2)``.
    """
    B, N = valid.shape
    H, W = base.shape[-2:]
    dev = pts.device
    keep = torch.empty((B, N), dtype=torch.bool, device=dev)
    out = torch.empty((B, H, W), dtype=torch.uint8, device=dev)
    if B == 0 or H * W == 0:
        keep.zero_()
        return keep, out
    centres = torch.empty((B, max(N, 1), 2), dtype=torch.int32, device=dev)
    count = torch.empty((B,), dtype=torch.int32, device=dev)
    base_stride = 0 if base.shape[0] == 1 else H * W
    block_n = max(16, triton.next_power_of_2(max(N, 1)))
    torch.library.wrap_triton(_decide_kernel)[(B,)](
        pts, pri, valid, base, keep, centres, count, N, H, W, base_stride, int(r2), BLOCK_N=block_n,
        CHUNK=_RANK_CHUNK, num_warps=_DECIDE_WARPS, **_COMPILE_OPTIONS)
    torch.library.wrap_triton(_draw_kernel)[(triton.cdiv(H * W, _BLOCK), B)](
        base, out, centres, count, N, H, W, base_stride, int(r2), int(R), BLOCK=_BLOCK, num_warps=_NUM_WARPS,
        **_COMPILE_OPTIONS)
    return keep, out
