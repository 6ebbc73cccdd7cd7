"""The front of a mono frame as one ``torch.library`` custom op on the CPU: CLAHE -> pyramid -> LK,
group of streams by group (``docs/kernels.md``, "Stream grouping on the CPU").

``torch_frontend::front(img, prev, pts, valid, clip_limit, tiles_x, tiles_y, max_level, pad, top, win_w,
win_h, max_iters, eps, min_eig, group) -> (eq, packed, next_pts, status, capped)``:

* ``eq (B, H, W)`` uint8: ``torch_frontend::clahe(img, clip_limit, tiles_x, tiles_y)``;
* ``packed (B, total)`` uint8: ``torch_frontend::pyramid(eq, max_level, pad)``;
* ``next_pts (B, N, 2)`` float32, ``status``, ``capped`` ``(B, N)`` bool: ``torch_frontend::lk`` of
  ``pts (B, N, 2)`` float32 / ``valid (B, N)`` bool from ``prev (B, total)`` (the previous frame's packed
  pyramid, the same layout: the tracker's state) into ``packed``, levels ``top..0``, window
  ``win_w x win_h``, no initial guess, no forward-backward check.

The outputs are those three ops' bit for bit; only the order of the work differs. The CPU kernel
(:mod:`._numba_front`) runs the three kernels back to back on ``group`` streams at a time
(``_tuning.Strategy.front_group``), so each stream's equalised image and pyramid are reused while in
cache, over stream groups in the fused kernels' thread pool (``ops._run_groups``). On CUDA the
tracker keeps the three stage ops (one launch each, the whole batch); this op's ``"cuda"`` kernel is
those three ops in sequence.
"""

from __future__ import annotations

import torch

from .clahe_op import check_clahe_args, clahe_op
from .layout import PyramidLayout
from .ops import _check_pad, _np, _np_out, _run_groups, layout_arrays, lk_op, pyramid_op

__all__ = ["front_op"]

Tensor = torch.Tensor

torch.library.define(
    "torch_frontend::front",
    "(Tensor img, Tensor prev, Tensor pts, Tensor valid, float clip_limit, int tiles_x, int tiles_y, int max_level, "
    "int pad, int top, int win_w, int win_h, int max_iters, float eps, float min_eig, int group) "
    "-> (Tensor, Tensor, Tensor, Tensor, Tensor)")


def _check(img: Tensor, prev: Tensor, pts: Tensor, valid: Tensor, tiles_x: int, tiles_y: int, max_level: int,
           pad: int, top: int, group: int) -> int:
    """The packed size per stream; ``ValueError`` naming the argument on a bad shape or value."""
    check_clahe_args(img, tiles_x, tiles_y)
    _check_pad(pad)
    B, H, W = (int(s) for s in img.shape)
    total = PyramidLayout(H, W, max_level, pad).total
    if tuple(prev.shape) != (B, total) or prev.dtype != torch.uint8:
        raise ValueError(f"torch_frontend::front: prev must be the ({B}, {total}) uint8 packed pyramid of "
                         f"{W}x{H}, max_level {max_level}, pad {pad}; got {tuple(prev.shape)} {prev.dtype}")
    if pts.dim() != 3 or pts.shape[0] != B or pts.shape[2] != 2 or pts.dtype != torch.float32:
        raise ValueError(f"torch_frontend::front: pts must be ({B}, N, 2) float32, got {tuple(pts.shape)} {pts.dtype}")
    if tuple(valid.shape) != tuple(pts.shape[:2]) or valid.dtype != torch.bool:
        raise ValueError(f"torch_frontend::front: valid must be {tuple(pts.shape[:2])} bool, got "
                         f"{tuple(valid.shape)} {valid.dtype}")
    if not 0 <= top <= max_level:
        raise ValueError(f"torch_frontend::front: top must be in 0..{max_level}, got {top}")
    if group < 1:
        raise ValueError(f"torch_frontend::front: group must be >= 1, got {group}")
    return total


@torch.library.impl("torch_frontend::front", "cpu")
def _front_cpu(img: Tensor, prev: Tensor, pts: Tensor, valid: Tensor, clip_limit: float, tiles_x: int, tiles_y: int,
               max_level: int, pad: int, top: int, win_w: int, win_h: int, max_iters: int, eps: float,
               min_eig: float, group: int):
    """CPU kernel: numba, ``group`` streams at a time (module docstring)."""
    from ._numba_front import _NO_INIT, front_streams

    _check(img, prev, pts, valid, tiles_x, tiles_y, max_level, pad, top, group)
    B, H, W = (int(s) for s in img.shape)
    N = int(pts.shape[1])
    sizes, offs, org, pitch, total = layout_arrays(H, W, max_level, pad)
    dev = img.device
    eq = torch.empty((B, H, W), dtype=torch.uint8, device=dev)
    packed = torch.empty((B, total), dtype=torch.uint8, device=dev)
    out = torch.empty((B, N, 2), dtype=torch.float32, device=dev)
    status = torch.empty((B, N), dtype=torch.bool, device=dev)
    capped = torch.empty((B, N), dtype=torch.bool, device=dev)
    if B == 0:
        return eq, packed, out, status, capped
    src, P, p, v = _np(img.contiguous()), _np(prev.contiguous()), _np(pts.contiguous()), _np(valid.contiguous())
    e, Q, o, s, c = _np_out(eq), _np_out(packed), _np_out(out), _np_out(status), _np_out(capped)
    clip = float(clip_limit)

    def run(s0, s1):
        front_streams(src, e, clip, tiles_x, tiles_y, sizes, offs, org, pitch, pad, P, Q, p, v, _NO_INIT, top,
                      win_w, win_h, max_iters, eps, min_eig, o, s, c, group, s0, s1)

    _run_groups(run, B)
    return eq, packed, out, status, capped


@torch.library.register_fake("torch_frontend::front")
def _front_fake(img, prev, pts, valid, clip_limit, tiles_x, tiles_y, max_level, pad, top, win_w, win_h, max_iters,
                eps, min_eig, group):
    B, H, W = img.shape
    N = pts.shape[1]
    total = PyramidLayout(int(H), int(W), max_level, pad).total
    return (img.new_empty((B, H, W)), img.new_empty((B, total)), pts.new_empty((B, N, 2)),
            valid.new_empty((B, N)), valid.new_empty((B, N)))


@torch.library.impl("torch_frontend::front", "cuda")
def _front_cuda(img, prev, pts, valid, clip_limit, tiles_x, tiles_y, max_level, pad, top, win_w, win_h, max_iters,
                eps, min_eig, group):
    """The three stage ops in sequence (each over the whole batch)."""
    _check(img, prev, pts, valid, tiles_x, tiles_y, max_level, pad, top, group)
    H, W = int(img.shape[1]), int(img.shape[2])
    eq = clahe_op(img.contiguous(), float(clip_limit), tiles_x, tiles_y)
    packed = pyramid_op(eq, max_level, pad)
    out, status, capped = lk_op(prev, packed, pts, valid, None, H, W, pad, pad, top, win_w, win_h, max_iters, eps,
                                min_eig, -1, 0.0, False)
    return eq, packed, out, status, capped


#: the op (``torch.ops.torch_frontend.front``)
front_op = torch.ops.torch_frontend.front
