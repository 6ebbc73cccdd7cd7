"""VINS's ``setMask`` as one custom op: ``torch_frontend::set_mask`` (``docs/kernels.md``, "setMask").

``set_mask(pts, priority, valid, base, radius) -> (keep, mask)``:

* ``pts``: ``(B, N, 2)`` float32 or float64 pixels ``(x, y)``; ``priority``: ``(B, N)`` int32 / int64
  (track counts, larger first); ``valid``: ``(B, N)`` bool;
* ``base``: ``(Bm, H, W)`` uint8, ``Bm`` 1 (one mask for every stream: no per-stream copy) or ``B``;
* ``radius``: the disc radius in pixels (``MIN_DIST``), ``>= 0``;
* ``keep``: ``(B, N)`` bool in the input order; ``mask``: ``(B, H, W)`` uint8, a new tensor: ``base``
  with the kept features' filled discs set to 0.

The rules are :func:`torch_frontend.masks.distance_mask`'s, and the results its tensor kernel's bit for
bit: the features visited by track count, descending, ties by slot (stable); a feature is kept iff its
``cvRound``-ed centre lies in the image and the mask there is exactly 255; a kept feature sets
``dx² + dy² <= radius²`` around its centre to 0 (``cv2.circle(mask, c, radius, 0, FILLED)`` for an
integer radius: :func:`disc_spans` are its rows). The op is exact on every input: no budget, no
overflow. Registered like the other fused ops (:mod:`.ops`): a hand-written fake, a numba CPU kernel
(:mod:`._numba_mask`, stream groups on the thread pool) and Triton CUDA kernels (:mod:`._triton_mask`,
two launches).
"""

from __future__ import annotations

import math
from typing import Tuple

import numpy as np
import torch

from .._cache import cached
from .ops import _np, _np_out, _run_groups

__all__ = ["set_mask_op", "disc_spans", "disc_r2"]

Tensor = torch.Tensor

torch.library.define("torch_frontend::set_mask",
                     "(Tensor pts, Tensor priority, Tensor valid, Tensor base, float radius) -> (Tensor, Tensor)")


def disc_r2(radius: float, height: int, width: int) -> int:
    """The disc's integer squared radius: ``d² <= radius²  <=>  d² <= floor(radius²)`` for integer
    ``d²``, capped at ``H² + W²`` (beyond every distance between two pixels: the same discs, and int32
    arithmetic in the kernels)."""
    return int(min(math.floor(float(radius) ** 2), int(height) ** 2 + int(width) ** 2))


@cached(32)
def disc_spans(r2: int) -> np.ndarray:
    """``(R + 1,)`` int64 (read-only): the half width of the filled disc ``dx² + dy² <= r2`` on row
    ``|dy|``, ``dy = 0..R``, ``R = isqrt(r2)``: row ``dy`` covers ``dx = -hw..hw``. For ``r2 = r²`` of
    an integer ``r`` these are ``cv2.circle``'s filled rows (``tests/test_fused_mask.py``)."""
    R = math.isqrt(int(r2))
    out = np.array([math.isqrt(int(r2) - dy * dy) for dy in range(R + 1)], dtype=np.int64)
    out.flags.writeable = False
    return out


def _check(pts: Tensor, priority: Tensor, valid: Tensor, base: Tensor, radius: float) -> None:
    if pts.dim() != 3 or pts.shape[-1] != 2 or pts.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"torch_frontend::set_mask: pts must be (B, N, 2) float32 / float64, got "
                         f"{tuple(pts.shape)} {pts.dtype}")
    B, N = pts.shape[:2]
    if tuple(priority.shape) != (B, N) or priority.dtype not in (torch.int32, torch.int64):
        raise ValueError(f"torch_frontend::set_mask: priority must be ({B}, {N}) int32 / int64, got "
                         f"{tuple(priority.shape)} {priority.dtype}")
    if tuple(valid.shape) != (B, N) or valid.dtype != torch.bool:
        raise ValueError(f"torch_frontend::set_mask: valid must be ({B}, {N}) bool, got {tuple(valid.shape)} "
                         f"{valid.dtype}")
    if base.dim() != 3 or base.dtype != torch.uint8 or base.shape[0] not in (1, B):
        raise ValueError(f"torch_frontend::set_mask: base must be (1 or {B}, H, W) uint8, got {tuple(base.shape)} "
                         f"{base.dtype}")
    if not radius >= 0:
        raise ValueError(f"torch_frontend::set_mask: radius must be >= 0, got {radius}")


@torch.library.impl("torch_frontend::set_mask", "cpu")
def _set_mask_cpu(pts: Tensor, priority: Tensor, valid: Tensor, base: Tensor, radius: float) -> Tuple[Tensor, Tensor]:
    """``(keep (B, N) bool, mask (B, H, W) uint8)`` (CPU kernel: numba)."""
    from ._numba_mask import set_mask_streams

    _check(pts, priority, valid, base, radius)
    B, N = valid.shape
    H, W = base.shape[-2:]
    keep = torch.empty((B, N), dtype=torch.bool, device=pts.device)
    out = torch.empty((B, H, W), dtype=torch.uint8, device=pts.device)
    spans = disc_spans(disc_r2(radius, H, W))
    p, q, v, m = _np(pts.contiguous()), _np(priority.contiguous()), _np(valid.contiguous()), _np(base.contiguous())
    k, o = _np_out(keep), _np_out(out)
    _run_groups(lambda s0, s1: set_mask_streams(p, q, v, m, spans, k, o, s0, s1), B)
    return keep, out


@torch.library.register_fake("torch_frontend::set_mask")
def _set_mask_fake(pts, priority, valid, base, radius):
    B, N = valid.shape
    H, W = base.shape[-2:]
    return valid.new_empty((B, N)), base.new_empty((B, H, W))


@torch.library.impl("torch_frontend::set_mask", "cuda")
def _set_mask_cuda(pts, priority, valid, base, radius):
    from ._triton_mask import set_mask_cuda

    _check(pts, priority, valid, base, radius)
    H, W = base.shape[-2:]
    r2 = disc_r2(radius, H, W)
    return set_mask_cuda(pts.contiguous(), priority.contiguous(), valid.contiguous(), base.contiguous(), r2,
                         math.isqrt(r2))


#: the op (``torch.ops.torch_frontend.set_mask``): ``set_mask_op(pts, priority, valid, base, radius)``
set_mask_op = torch.ops.torch_frontend.set_mask
