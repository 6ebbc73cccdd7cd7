"""The LK's fused path: when a call runs the fused op (``torch_frontend::lk``), the packed pyramids it
reads, and the call itself (``docs/kernels.md``, ``docs/lk.md``).

The fused op runs every level and iteration of every point of every stream in one kernel, with
OpenCV's x86 arithmetic (status and float32 positions bit-identical to ``cv2.calcOpticalFlowPyrLK``),
and VINS-Fusion's forward-backward check in the same call. It covers OpenCV's 8-bit setting:
:func:`fused_applies` says when a call qualifies; any other call runs the tensor LK
(:mod:`.eager`, :mod:`.capturable`).

Convention:
    As :mod:`.track`: :class:`~torch_frontend.pyramid.Pyramid` pairs of equal level sizes, ``pts``
    ``(B, N, 2)`` float32 pixels ``(x, y)``, ``valid`` / ``status`` ``(B, N)`` bool. The op reads
    packed pyramids (``fused/layout.py``) with a border of at least ``max(win) + 1``: a pyramid built
    by the fused pyramid op for this window is read as it is, any other is packed once (a few tensor
    ops per level, kept on the pyramid as its next call's previous pyramid).
"""

from __future__ import annotations

from typing import Optional, Tuple

import torch

from ..fused import MIN_FUSED_WIDTH
from ..fused.layout import PyramidLayout, lk_pad
from ..fused.ops import lk_op
from ..pyramid import Pyramid, pad_reflect101
from .implicit import _wants_grad
from .options import LKOptions

__all__ = ["fused_applies", "lk_fused"]

FBArgs = Tuple[int, float, bool]  # (top level of the backward pass, threshold px, start at pts)


def fused_applies(prev: Pyramid, nxt: Pyramid, pts: torch.Tensor, init: Optional[torch.Tensor],
                  opts: LKOptions) -> bool:
    """The call runs the fused LK: ``opts.backend == "fused"``, OpenCV's 8-bit fixed point on
    8-bit pyramids (``rounded``), float32 points, the full iteration count (no ``iter_budget``), a
    window at least 8 pixels wide (the kernels read rows in 8-pixel blocks), a CPU or CUDA device,
    and no derivative to record through the iterations (the implicit gradient attaches after the
    forward; ``grad_mode="unrolled"`` with a derivative runs the tensor LK)."""
    if opts.backend != "fused" or not opts.fixed_point or opts.iter_budget is not None:
        return False
    if pts.dtype != torch.float32 or (init is not None and init.dtype != torch.float32):
        return False
    if opts.win_size[0] < MIN_FUSED_WIDTH or pts.device.type not in ("cpu", "cuda"):
        return False
    if not (prev.rounded and nxt.rounded):
        return False
    # the implicit gradient runs this forward on detached inputs (.track._lk_pass_implicit)
    return not (opts.grad_mode == "unrolled" and _wants_grad(prev, nxt, pts, init))


def packed_levels(pyr: Pyramid, pad: int, levels: int) -> Tuple[torch.Tensor, int]:
    """``(packed, pad)`` of ``pyr`` for an LK that reads levels ``0..levels`` with a border ``pad``: its
    own packed tensor when it has one with a border that wide, else its levels packed once (uint8,
    BORDER_REFLECT_101; 8-bit values, so exact) and kept on the pyramid for its next call."""
    if pyr.packed is not None and pyr.pad >= pad:
        return pyr.packed, pyr.pad
    key = ("packed", pad, levels)
    got = pyr._padded.get(key)
    if got is not None:
        return got, pad
    B = pyr.batch
    parts = [pad_reflect101(t.detach().to(torch.uint8), pad, pad).reshape(B, -1) for t in pyr.levels[:levels + 1]]
    packed = torch.cat(parts, 1)
    H, W = pyr.levels[0].shape[-2:]
    assert packed.shape[1] == PyramidLayout(int(H), int(W), levels, pad).total
    pyr._padded[key] = packed
    return packed, pad


def lk_fused(prev: Pyramid, nxt: Pyramid, pts: torch.Tensor, valid: torch.Tensor, init: Optional[torch.Tensor],
             opts: LKOptions, top: int, capturable: bool, want_capped: bool = False,
             fb: Optional[FBArgs] = None):
    """The fused LK (checked by :func:`fused_applies`) as :func:`.track._lk_pass` returns it:
    ``(pts, status, overflow, capped)``. ``fb = (fb_top, threshold, from_pts)``: the same op also
    tracks back and keeps the lanes that return within ``threshold`` px (VINS-Fusion's FLOW_BACK;
    ``status`` is then the checked one). ``overflow``: all False on the capturable path (the fused
    LK always runs the full iteration count), None otherwise; ``capped`` ``(B N,)`` with
    ``want_capped``."""
    ww, wh = opts.win_size
    pad = lk_pad(opts.win_size)
    levels = top if fb is None else max(top, fb[0])
    P, pp = packed_levels(prev, pad, levels)
    Q, pq = packed_levels(nxt, pad, levels)
    H, W = prev.levels[0].shape[-2:]
    fb_top, fb_thr, fb_from = (-1, 0.0, False) if fb is None else fb
    out, status, capped = lk_op(P, Q, pts.detach(), valid, None if init is None else init.detach(), int(H), int(W),
                                pp, pq, top, ww, wh, opts.max_iters, opts.eps, opts.min_eig_threshold, fb_top,
                                float(fb_thr), bool(fb_from))
    overflow = torch.zeros(pts.shape[0], dtype=torch.bool, device=pts.device) if capturable else None
    return out.to(pts.dtype), status, overflow, (capped.view(-1) if want_capped else None)
