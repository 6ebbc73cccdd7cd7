"""The fused kernels as ``torch.library`` custom ops: one op per call, on every device and under every
tool (``docs/kernels.md``).

* ``torch_frontend::pyramid(img, max_level, pad) -> packed``: the packed 8-bit pyramid
  (:mod:`.layout`) of ``(B, H, W)`` uint8 images.
* ``torch_frontend::lk(prev, next, pts, valid, init, ...) -> (next_pts, status, capped)``: every level
  and iteration of OpenCV's pyramidal LK for every stream and point, optionally with VINS-Fusion's
  forward-backward check, on two packed pyramids.

Each op is a plain ``torch.library`` operator (``torch.library.define`` with its schema) with a
hand-written fake (``register_fake``: shapes only, so ``torch.compile`` and the meta device trace it
as one node), a CPU kernel (``torch.library.impl(..., "cpu")``: numba, :mod:`._numba_lk`,
:mod:`._numba_pyramid`) and a CUDA kernel (``impl(..., "cuda")``: Triton through
``torch.library.wrap_triton``, :mod:`._triton_lk`, :mod:`._triton_pyramid`). Not ``triton_op``: that
makes the Triton body the op's fake and decomposition on every device, so CPU ``compile()`` would
trace Triton and a CPU-only install would need it. Not the ``torch.library.custom_op`` decorator
either, although it registers the same kind of operator: its Python wrapper imports ``torch._dynamo``
on a process's first call (3.1 s, measured: every CLI run and test worker would pay it) and costs
~40 µs a call against ~8 here. CUDA graphs, ``OpCounter`` and the simulated CUDA device of
``count_step.py`` see one op per call (the simulated device runs the CPU kernel). No autograd
formula: the callers run the ops on detached inputs (the LK's gradient is implicit, attached after
the forward, ``lk/implicit.py``).

The CPU kernels take numpy views of the tensors (``np.from_dlpack``: no copy, no host sync on the
counters) and run with the GIL released (``nogil``): with more than one torch thread
(``torch.get_num_threads()``, the product's thread policy) the streams are split into groups run
by a small thread pool; each stream's result does not depend on the grouping.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Optional, Tuple

import numpy as np
import torch

from .._cache import cached
from .layout import PyramidLayout

__all__ = ["pyramid_op", "lk_op", "layout_arrays"]

Tensor = torch.Tensor

# the CPU kernels' thread pool: created on first use with the torch thread count, recreated when
# that count changes, dropped in a forked child (its threads do not exist there)
_POOL: list = [None, 0]
_POOL_LOCK = threading.Lock()


def _reset_pool() -> None:
    _POOL[0], _POOL[1] = None, 0


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_reset_pool)


def _run_groups(fn, B: int) -> None:
    """``fn(s0, s1)`` over stream groups: one call on one thread, else ``torch.get_num_threads()``
    contiguous groups run by the pool (the kernels release the GIL)."""
    threads = min(torch.get_num_threads(), B)
    if threads <= 1:
        fn(0, B)
        return
    with _POOL_LOCK:
        if _POOL[0] is None or _POOL[1] != threads:
            if _POOL[0] is not None:
                _POOL[0].shutdown(wait=False)
            _POOL[0], _POOL[1] = ThreadPoolExecutor(threads, thread_name_prefix="torch_frontend_fused"), threads
        pool = _POOL[0]
    bounds = [B * k // threads for k in range(threads + 1)]
    for f in [pool.submit(fn, bounds[k], bounds[k + 1]) for k in range(threads) if bounds[k + 1] > bounds[k]]:
        f.result()


@cached(64)
def layout_arrays(height: int, width: int, max_level: int, pad: int):
    """``(sizes (L + 1, 2), offsets (L + 1,), origins (L + 1,), pitches (L + 1,), total)`` of a
    :class:`~.layout.PyramidLayout`, int64 numpy arrays (read-only): level sizes, block offsets, the
    element of pixel (0, 0), row pitches; and the elements per stream."""
    lay = PyramidLayout(height, width, max_level, pad)
    sizes = np.array(lay.sizes, dtype=np.int64)
    offs = np.array(lay.offsets, dtype=np.int64)
    pitch = sizes[:, 1] + 2 * pad
    out = (sizes, offs, offs + pad * pitch + pad, pitch)
    for a in out:
        a.flags.writeable = False
    return out + (lay.total,)


class _Input:
    """A CPU tensor as a DLPack producer for ``np.from_dlpack`` (a read-only view, no copy, no aten op):
    ~1.3 µs instead of ``Tensor.__dlpack__``'s ~4 (its checks for streams and versions)."""

    __slots__ = ("t",)

    def __init__(self, t: Tensor):
        self.t = t

    def __dlpack__(self, *, stream=None, max_version=None, dl_device=None, copy=None):
        return torch.utils.dlpack.to_dlpack(self.t)

    def __dlpack_device__(self):
        return (1, 0)  # kDLCPU


def _np(t: Tensor) -> np.ndarray:
    """A read-only numpy view of a contiguous CPU tensor (bool as bool)."""
    return np.from_dlpack(_Input(t.detach()))


def _np_out(t: Tensor) -> np.ndarray:
    """A writable numpy view of a freshly made contiguous CPU tensor."""
    return np.from_dlpack(t)


# ---------------------------------------------------------------------------------------------
# pyramid


torch.library.define("torch_frontend::pyramid", "(Tensor img, int max_level, int pad) -> Tensor")

#: the packed pyramid's smallest border on every device: pyrDown reads 2 pixels out, the CPU kernel's
#: 16-byte loads one more
MIN_PAD = 3


def _check_pad(pad: int) -> None:
    if pad < MIN_PAD:
        raise ValueError(f"torch_frontend::pyramid: pad must be >= {MIN_PAD}, got {pad}")


@torch.library.impl("torch_frontend::pyramid", "cpu")
def _pyramid_cpu(img: Tensor, max_level: int, pad: int) -> Tensor:
    """The packed pyramid ``(B, total)`` uint8 of ``img (B, H, W)`` uint8 (CPU kernel: numba)."""
    from ._numba_pyramid import pyramid_streams

    _check_pad(pad)
    B, H, W = img.shape
    sizes, offs, _, _, total = layout_arrays(H, W, max_level, pad)
    out = torch.empty((B, total), dtype=torch.uint8, device=img.device)
    src, dst = _np(img.contiguous()), _np_out(out)
    _run_groups(lambda s0, s1: pyramid_streams(src, dst, sizes, offs, pad, s0, s1), B)
    return out


@torch.library.register_fake("torch_frontend::pyramid")
def _pyramid_fake(img, max_level, pad):
    B, H, W = img.shape
    return img.new_empty((B, PyramidLayout(int(H), int(W), max_level, pad).total), dtype=torch.uint8)


@torch.library.impl("torch_frontend::pyramid", "cuda")
def _pyramid_cuda(img, max_level, pad):
    from ._triton_pyramid import pyramid_cuda

    _check_pad(pad)
    return pyramid_cuda(img.contiguous(), max_level, pad)


# ---------------------------------------------------------------------------------------------
# LK

_NO_INIT = np.zeros((1, 1, 2), dtype=np.float32)  # the kernel's ``init`` when none is given (not read)
_NO_INIT.flags.writeable = False


torch.library.define(
    "torch_frontend::lk",
    "(Tensor prev, Tensor next, Tensor pts, Tensor valid, Tensor? init, int height, int width, int pad_prev, "
    "int pad_next, int top, int win_w, int win_h, int max_iters, float eps, float min_eig, int fb_top, "
    "float fb_threshold, bool fb_from_pts) -> (Tensor, Tensor, Tensor)")


@torch.library.impl("torch_frontend::lk", "cpu")
def _lk_cpu(prev: Tensor, next: Tensor, pts: Tensor, valid: Tensor, init: Optional[Tensor], height: int, width: int,
            pad_prev: int, pad_next: int, top: int, win_w: int, win_h: int, max_iters: int, eps: float,
            min_eig: float, fb_top: int, fb_threshold: float, fb_from_pts: bool) -> Tuple[Tensor, Tensor, Tensor]:
    """OpenCV's pyramidal LK of ``pts (B, N, 2)`` float32 from the packed pyramid ``prev`` into ``next``
    (``(B, total)`` uint8, pads ``pad_prev`` / ``pad_next``, level 0 ``height x width``), levels
    ``top..0``; ``fb_top >= 0``: also VINS-Fusion's FLOW_BACK check. Returns ``(next_pts (B, N, 2)
    float32, status (B, N) bool, capped (B, N) bool)``. CPU kernel: numba."""
    from ._numba_lk import lk_streams

    B, N, _ = pts.shape
    levels = max(top, fb_top)
    sizes, _, org_p, wp_p, _ = layout_arrays(height, width, levels, pad_prev)
    _, _, org_n, wp_n, _ = layout_arrays(height, width, levels, pad_next)
    out = torch.empty((B, N, 2), dtype=torch.float32, device=pts.device)
    status = torch.empty((B, N), dtype=torch.bool, device=pts.device)
    capped = torch.empty((B, N), dtype=torch.bool, device=pts.device)
    P, Q, p, v = _np(prev.contiguous()), _np(next.contiguous()), _np(pts.contiguous()), _np(valid.contiguous())
    g = _np(init.contiguous()) if init is not None else _NO_INIT
    o, s, c = _np_out(out), _np_out(status), _np_out(capped)

    def run(s0, s1):
        lk_streams(P, Q, org_p, wp_p, org_n, wp_n, sizes, p, v, g, init is not None, top, win_w, win_h, max_iters,
                   eps, min_eig, fb_top, fb_threshold, fb_from_pts, o, s, c, s0, s1)

    _run_groups(run, B)
    return out, status, capped


@torch.library.register_fake("torch_frontend::lk")
def _lk_fake(prev, next, pts, valid, init, height, width, pad_prev, pad_next, top, win_w, win_h, max_iters, eps,
             min_eig, fb_top, fb_threshold, fb_from_pts):
    B, N = pts.shape[:2]
    return (pts.new_empty((B, N, 2)), valid.new_empty((B, N), dtype=torch.bool),
            valid.new_empty((B, N), dtype=torch.bool))


@torch.library.impl("torch_frontend::lk", "cuda")
def _lk_cuda(prev, next, pts, valid, init, height, width, pad_prev, pad_next, top, win_w, win_h, max_iters, eps,
             min_eig, fb_top, fb_threshold, fb_from_pts):
    from ._triton_lk import lk_cuda

    return lk_cuda(prev.contiguous(), next.contiguous(), pts.contiguous(), valid.contiguous(),
                   None if init is None else init.contiguous(), height, width, pad_prev, pad_next, top, win_w, win_h,
                   max_iters, eps, min_eig, fb_top, fb_threshold, fb_from_pts)


#: the ops (``torch.ops.torch_frontend.*``): ``pyramid_op(img, max_level, pad)``, ``lk_op(prev, next, ...)``
pyramid_op = torch.ops.torch_frontend.pyramid
lk_op = torch.ops.torch_frontend.lk
