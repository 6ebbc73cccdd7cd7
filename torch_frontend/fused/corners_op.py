"""``goodFeaturesToTrack`` (as VINS calls it) as one ``torch.library`` op: ``torch_frontend::good_features``
(``docs/kernels.md``, "Detection").

``good_features(img, max_corners, mask, capacity, quality_level, min_distance) -> (pts, valid, overflow)``:

* ``img`` ``(B, H, W)`` uint8 (``H, W >= 2``); ``max_corners`` ``(B,)`` int64 (corners per stream,
  clipped to ``capacity``; ``<= 0``: none); ``mask`` ``(B, H, W)`` bool (True = allowed) or None;
  block size 3, Sobel aperture 3, the min-eigenvalue response; ``0 <= quality_level <= 1``;
  ``min_distance`` in pixels (``< 1``: no distance test).
* ``pts`` ``(B, capacity, 2)`` float32 integer pixel positions ``(x, y)`` in OpenCV's order (response
  descending, ties later raster position first), zeros in the lanes past a stream's count;
  ``valid`` ``(B, capacity)`` bool (a stream's corners are its first lanes); ``overflow`` ``(B,)``
  bool: always False on the CPU (exact, all candidates); on CUDA True where the capturable
  selection's fixed budget (``corners.GFTT_BUDGET``) was too small for OpenCV's exact answer (as
  the tensor capturable path's flag; where False the corners are the exact ones).

The CPU kernel is :mod:`._numba_corners` (streams in groups over the thread pool of :mod:`.ops`); the
CUDA one is :mod:`._triton_corners` (the response, its maximum over the mask, the threshold and the
3x3 maximum in Triton; the capturable tensor selection on the candidates). Both equal the tensor
reference (``corners.responses`` + ``corners.selection``) bit for bit.
"""

from __future__ import annotations

import math
import threading
from typing import Optional, Tuple

import numpy as np
import torch

from .ops import _np, _np_out, _run_groups

__all__ = ["good_features_op", "fused_corners_applies", "cell_and_r2"]

Tensor = torch.Tensor

torch.library.define(
    "torch_frontend::good_features",
    "(Tensor img, Tensor max_corners, Tensor? mask, int capacity, float quality_level, float min_distance) "
    "-> (Tensor, Tensor, Tensor)")

#: the capturable selection from the candidates' keys, which the CUDA implementation runs after its
#: kernels: ``corners.selection_capturable._select_from_keys``, registered by ``torch_frontend.corners``
#: when it is imported (:func:`set_selection`). The kernel layer's ``fused`` imports nothing of
#: ``corners`` (which calls the op): no import cycle.
_SELECTION: list = [None]


def set_selection(fn) -> None:
    """Register the capturable selection the CUDA implementation runs (``torch_frontend.corners`` does)."""
    _SELECTION[0] = fn


_NO_MASK = np.zeros((1, 1, 1), dtype=np.uint8)  # the kernel's ``mask`` when none is given (not read)
_NO_MASK.flags.writeable = False


_SCRATCH = threading.local()  # per thread: (H, W) -> the CPU kernel's image-sized scratch


def _scratch(H: int, W: int):
    """This thread's scratch of :func:`._numba_corners.scratch` for ``H x W`` (kept for the last size)."""
    from ._numba_corners import scratch

    held = getattr(_SCRATCH, "held", None)
    if held is None or held[0] != (H, W):
        held = _SCRATCH.held = ((H, W), scratch(1, H, W))
    return held[1]


def cell_and_r2(min_distance: float) -> Tuple[int, int]:
    """OpenCV's grid cell ``cvRound(min_distance)`` (half to even; at least 1) and ``ceil(min_distance²)``
    (an integer ``d²`` conflicts iff ``d² < ceil(min_distance²)``)."""
    return max(int(round(min_distance)), 1), int(math.ceil(min_distance * min_distance))


def _check(img: Tensor, max_corners: Tensor, mask: Optional[Tensor], capacity: int, quality_level: float) -> None:
    if img.dim() != 3 or img.dtype != torch.uint8:
        raise ValueError(f"torch_frontend::good_features: img must be (B, H, W) uint8, got {tuple(img.shape)} "
                         f"{img.dtype}")
    B, H, W = img.shape
    if H < 2 or W < 2:
        raise ValueError(f"torch_frontend::good_features: img: expected H, W >= 2, got {(H, W)}")
    if tuple(max_corners.shape) != (B,):
        raise ValueError(f"torch_frontend::good_features: max_corners must be ({B},), got {tuple(max_corners.shape)}")
    if mask is not None and (tuple(mask.shape) != (B, H, W) or mask.dtype != torch.bool):
        raise ValueError(f"torch_frontend::good_features: mask must be ({B}, {H}, {W}) bool, got "
                         f"{tuple(mask.shape)} {mask.dtype}")
    if capacity < 0:
        raise ValueError(f"torch_frontend::good_features: capacity must be >= 0, got {capacity}")
    if not 0.0 <= quality_level <= 1.0:
        raise ValueError(f"torch_frontend::good_features: quality_level must be in [0, 1], got {quality_level}")


@torch.library.impl("torch_frontend::good_features", "cpu")
def _gftt_cpu(img: Tensor, max_corners: Tensor, mask: Optional[Tensor], capacity: int, quality_level: float,
              min_distance: float) -> Tuple[Tensor, Tensor, Tensor]:
    """The CPU kernel (numba, :mod:`._numba_corners`); see the module docstring."""
    from ._numba_corners import gftt_streams

    _check(img, max_corners, mask, capacity, quality_level)
    B, H, W = img.shape
    dev = img.device
    pts = torch.zeros((B, capacity, 2), dtype=torch.float32, device=dev)
    valid = torch.zeros((B, capacity), dtype=torch.bool, device=dev)
    overflow = torch.zeros((B,), dtype=torch.bool, device=dev)
    if B == 0 or capacity == 0:
        return pts, valid, overflow
    src = _np(img.contiguous())
    mc = _np(max_corners.to(torch.int64).contiguous())
    m = _np(mask.contiguous().view(torch.uint8)) if mask is not None else _NO_MASK
    o, v = _np_out(pts), _np_out(valid)
    cell, r2 = cell_and_r2(min_distance)
    q, md = float(quality_level), float(min_distance)

    def run(s0, s1):
        gftt_streams(src, m, mask is not None, mc, q, md, cell, r2, o, v, s0, s1, *_scratch(H, W))

    _run_groups(run, B)
    return pts, valid, overflow


@torch.library.register_fake("torch_frontend::good_features")
def _gftt_fake(img, max_corners, mask, capacity, quality_level, min_distance):
    B = img.shape[0]
    return (img.new_empty((B, capacity, 2), dtype=torch.float32), img.new_empty((B, capacity), dtype=torch.bool),
            img.new_empty((B,), dtype=torch.bool))


@torch.library.impl("torch_frontend::good_features", "cuda")
def _gftt_cuda(img, max_corners, mask, capacity, quality_level, min_distance):
    from ._triton_corners import good_features_cuda

    _check(img, max_corners, mask, capacity, quality_level)
    return good_features_cuda(img.contiguous(), max_corners.to(torch.int64), None if mask is None else mask.contiguous(),
                              capacity, float(quality_level), float(min_distance), _SELECTION[0])


def fused_corners_applies(img: Tensor, use_harris: bool, block_size: int, quality_level: float) -> bool:
    """True when the fused op computes what the tensor path does for these arguments: a uint8 image
    (``(B, 1, H, W)`` or ``(B, H, W)``), the min-eigenvalue response on 3x3 blocks, and
    ``0 <= quality_level <= 1`` (other settings run the tensor path)."""
    return (img.dtype == torch.uint8 and not use_harris and block_size == 3 and 0.0 <= quality_level <= 1.0
            and not img.requires_grad)


#: the op (``torch.ops.torch_frontend.good_features``)
good_features_op = torch.ops.torch_frontend.good_features
