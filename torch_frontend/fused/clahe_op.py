"""CLAHE as one ``torch.library`` custom op, the way ``ops.py`` defines the pyramid and the LK (``docs/kernels.md``).

``torch_frontend::clahe(img, clip_limit, tiles_x, tiles_y) -> out``: ``cv2.createCLAHE(clip_limit,
(tiles_x, tiles_y)).apply`` of every stream of ``img (B, H, W)`` uint8, bit for bit; ``out`` ``(B, H, W)``
uint8. Each stream depends on its own image only.

* fake (``register_fake``): the output's shape only;
* ``"cpu"``: the numba kernel (:mod:`._numba_clahe`: histograms, clip, LUTs and blend of one stream
  while its image is in cache), over stream groups in the fused kernels' thread pool
  (``ops._run_groups``: ``torch.get_num_threads()`` groups, the GIL released);
* ``"cuda"``: two Triton launches (:mod:`._triton_clahe`), no host sync, a launch count independent
  of B and of the data (capturable). A cuda-labelled tensor without a CUDA runtime (the simulated
  device of ``count_step.py``) runs the CPU kernel, as the other ops.

No autograd formula: the differentiable tracker takes its gradient from the tensor CLAHE's slope
(``equalize._clahe_straight_through``); this op gives the values.
"""

from __future__ import annotations

import torch

from .ops import _np, _np_out, _run_groups

__all__ = ["clahe_op", "check_clahe_args"]

Tensor = torch.Tensor

torch.library.define("torch_frontend::clahe", "(Tensor img, float clip_limit, int tiles_x, int tiles_y) -> Tensor")


def check_clahe_args(img: Tensor, tiles_x: int, tiles_y: int) -> None:
    """``ValueError`` unless ``img`` is ``(B, H, W)`` uint8 and the grid positive and small enough for
    the reflect-101 padding (``equalize.check_grid``)."""
    if img.dim() != 3 or img.dtype != torch.uint8:
        raise ValueError(f"torch_frontend::clahe: img must be a (B, H, W) uint8 tensor, got {tuple(img.shape)} "
                         f"{img.dtype}")
    if tiles_x < 1 or tiles_y < 1:
        raise ValueError(f"torch_frontend::clahe: tiles must be positive, got ({tiles_x}, {tiles_y})")
    H, W = int(img.shape[1]), int(img.shape[2])
    if (W % tiles_x or H % tiles_y) and (tiles_x - W % tiles_x >= W or tiles_y - H % tiles_y >= H):
        raise ValueError(f"torch_frontend::clahe: image {W}x{H} too small for the padding of grid "
                         f"{tiles_x}x{tiles_y}")


@torch.library.impl("torch_frontend::clahe", "cpu")
def _clahe_cpu(img: Tensor, clip_limit: float, tiles_x: int, tiles_y: int) -> Tensor:
    """CLAHE of ``img (B, H, W)`` uint8 (CPU kernel: numba)."""
    from ._numba_clahe import clahe_streams

    check_clahe_args(img, tiles_x, tiles_y)
    out = torch.empty(img.shape, dtype=torch.uint8, device=img.device)
    B = int(img.shape[0])
    if out.numel() == 0:
        return out
    src, dst = _np(img.contiguous()), _np_out(out)
    _run_groups(lambda s0, s1: clahe_streams(src, dst, float(clip_limit), tiles_x, tiles_y, s0, s1), B)
    return out


@torch.library.register_fake("torch_frontend::clahe")
def _clahe_fake(img, clip_limit, tiles_x, tiles_y):
    return img.new_empty(img.shape, dtype=torch.uint8)


@torch.library.impl("torch_frontend::clahe", "cuda")
def _clahe_cuda(img, clip_limit, tiles_x, tiles_y):
    from ._triton_clahe import clahe_cuda

    check_clahe_args(img, tiles_x, tiles_y)
    return clahe_cuda(img.contiguous(), clip_limit, tiles_x, tiles_y)


#: the op (``torch.ops.torch_frontend.clahe``): ``clahe_op(img, clip_limit, tiles_x, tiles_y)``
clahe_op = torch.ops.torch_frontend.clahe
