"""Batched pyramidal Lucas–Kanade tracking, as ``cv2.calcOpticalFlowPyrLK`` (spec §5.1, §6.2–6.3).

All points of all streams move together: per pyramid level the template windows of the previous
image and the 2x2 gradient matrices are computed once for every point; each iteration samples only
the next image's windows, solves the 2x2 systems in closed form and moves the points still active.
OpenCV's 14-bit fixed-point interpolation is emulated on 8-bit input: on EuRoC temporal pairs
>= 99 % of the points are bit-identical to cv2 4.x, the rest within ~1e-4 px (``tests/test_lk.py``).
The algorithm, the OpenCV behaviour it reproduces, the two paths, the gradients and ``torch.func``
are described in ``docs/lk.md``.

The kernel's rooms:

* :mod:`.options`: :class:`LKOptions`, the settings of one pass, checked and normalised;
* :mod:`.windows`: the per-level machinery both paths share (weights, templates, window
  differences, gradient systems, per-size tables);
* :mod:`.eager`: the default path (early exit and compaction, host syncs; tuned for the CPU);
* :mod:`.capturable`: the capturable path (fixed budgets, no host sync, a kernel count independent
  of B), the same results bit for bit;
* :mod:`.implicit`: implicit-function gradients of the level-0 solution;
* :mod:`.track`: :func:`_track_lk_impl` and :func:`_forward_backward_impl`, which the tracker's
  stages call with ``capturable=...`` and which return :class:`LKResult` / :class:`FlowBackResult`;
* :mod:`.transforms`: ``torch.func.vmap`` through public ``torch.autograd.Function`` gateways;
* here, the door: :func:`track_lk` (checked, normalised arguments; ``(next_pts, status)``).
"""

from __future__ import annotations

import warnings
from typing import Optional, Tuple, Union

import torch

from .._checks import as_image_batch, check_points, check_shape, default_valid
from ..errors import ConfigError
from ..fused import MIN_FUSED_WIDTH, lk_pad, resolve_backend
from ..pyramid import Pyramid, _build_pyramid_impl
from .capturable import _capturable_consts, _capturable_tables, _lk_capturable, exact_float32  # noqa: F401
from .eager import _compiled_step, _lk_eager, _lk_step, _write_back  # noqa: F401
from .implicit import _implicit_attach, _newton_terms, _patch_offsets, _solve2, _wants_grad  # noqa: F401
from .options import GRAD_MODES, LKOptions
from .track import (  # noqa: F401
    FlowBackResult,
    LKResult,
    _forward_backward_impl,
    _level_cap,
    _lk_pass,
    _prime_next_pyramid,
    _track_lk_impl,
)
from .transforms import has_wrapped_tensor, track_transformed
from .windows import (  # noqa: F401  (the private names are imported from here too)
    _fixed_weights,
    _gather,
    _gradient_system,
    _interp_flat,
    _lane_index,
    _Level,
    _level_offsets,
    _level_start,
    _level_tables,
    _pitch,
    _scharr_flat,
    _soft_weights,
    _ste,
    _template,
    _win_consts,
    _window_diff,
)

__all__ = ["track_lk", "LKOptions", "LKResult", "FlowBackResult", "GRAD_MODES"]

ImageOrPyramid = Union[torch.Tensor, Pyramid]


def track_lk(
    prev: ImageOrPyramid,
    next: ImageOrPyramid,
    pts: torch.Tensor,
    valid: Optional[torch.Tensor] = None,
    win_size: Union[int, Tuple[int, int]] = 21,
    max_level: int = 3,
    max_iters: int = 30,
    eps: float = 0.01,
    min_eig_threshold: float = 1e-4,
    init_pts: Optional[torch.Tensor] = None,
    forward_backward: bool = False,
    fb_threshold: float = 0.5,
    fb_max_level: Optional[int] = None,
    *,
    fb_use_initial_flow: bool = True,
    fixed_point: Optional[bool] = None,
    capturable: bool = False,
    grad_mode: str = "implicit",
    compile_step=False,
    early_exit: Optional[bool] = None,
    lk_backend: Optional[str] = None,
) -> Tuple[torch.Tensor, torch.Tensor]:
    """Sparse pyramidal Lucas–Kanade, as ``cv2.calcOpticalFlowPyrLK`` with the same arguments.

    Args:
        prev: previous image ``(B, 1, H, W)`` / ``(B, H, W)`` (uint8 or float 0..255) or its
            :class:`~torch_frontend.pyramid.Pyramid` (reused across frames; the LK takes the
            derivatives it needs from its own windows, so the pyramid needs no ``grads``).
        next: next image or pyramid, same sizes.
        pts: ``(B, N, 2)`` float, pixels ``(x, y)`` in ``prev``.
        valid: ``(B, N)`` bool, padded lanes False (not tracked, status False). Default all True.
        win_size: window ``int`` or ``(w, h)`` (OpenCV ``winSize``), each > 2.
        max_level: top pyramid level (0 = no pyramid); capped as OpenCV does (level size must stay
            > ``win_size``, and by the levels of given pyramids).
        max_iters, eps: ``TermCriteria(COUNT|EPS, max_iters, eps)``; a point stops when
            ``|delta|^2 <= eps^2`` (OpenCV squares ``epsilon``). Clamped to ``[0, 100]``/``[0, 10]``.
        min_eig_threshold: ``minEigThreshold`` (OpenCV default 1e-4).
        init_pts: ``(B, N, 2)`` initial guess in ``next`` (``OPTFLOW_USE_INITIAL_FLOW``).
        forward_backward: also track back from the result (``next -> prev``) and require both
            statuses and ``|back - pts| <= fb_threshold`` (VINS-Fusion FLOW_BACK).
        fb_threshold: pixels (0.5 in VINS-Fusion).
        fb_max_level: levels of the backward pass (default ``max_level``; VINS-Fusion uses 1 for the
            temporal check, 3 for the stereo one).
        fb_use_initial_flow: backward pass starts at ``pts`` (VINS-Fusion temporal check); set False
            for the stereo check (backward starts at the forward result, no guess).
        fixed_point: emulate OpenCV's 14-bit fixed-point interpolation and rounding. Default: True
            when both inputs are uint8 images (or pyramids built from uint8). Bit-level agreement
            needs float32 ``pts``; gradients use a straight-through estimator for the rounding.
        capturable: False (default) compacts the iteration to the still-moving points and stops
            when none is left (one host sync per iteration). True runs exactly ``max_iters`` masked
            iterations per level with no host sync (CUDA graphs / ``torch.compile`` friendly); the
            same results.
        grad_mode: ``"implicit"`` (default) runs the forward without a graph and attaches the
            implicit-function gradient of the level-0 solution (bounded on real images; memory
            independent of the iteration count; no gradient to ``init_pts`` or the coarse levels;
            zero gradient for lanes with status False, lanes that hit ``max_iters`` at level 0,
            and ill-posed lanes). ``"unrolled"`` (opt in) differentiates every iteration of every
            level: the exact derivative of the unconverged forward, with a gradient to
            ``init_pts``, but on real images a coarse level can blow it up (Middlebury
            RubberWhale: 40 of 1,049 points above 10, worst 1.3e8; ``docs/differentiability.md``).
            Same values either way.
        compile_step: the default path's per-iteration kernel through ``torch.compile`` for this
            call (True, or a mapping of ``torch.compile`` keywords; see :class:`LKOptions`).
        early_exit: deprecated (``DeprecationWarning``): ``capturable = not early_exit``.
        lk_backend: ``None`` / ``"auto"`` (default: the device's ``_tuning`` strategy: the fused LK on
            the CPU and CUDA), ``"fused"`` or ``"tensor"``. The fused LK is one custom op for the
            whole call (both passes with ``forward_backward``), OpenCV's x86 arithmetic: status and
            float32 positions bit-identical to ``cv2.calcOpticalFlowPyrLK`` (``docs/kernels.md``). It
            covers 8-bit fixed point, float32 points, windows >= 8 wide; other calls (float images,
            float64 points, ``grad_mode="unrolled"`` with a gradient) run the tensor LK, whose
            float sums take another order (the same status on >= 99 % of EuRoC points).

    Returns:
        ``next_pts``: ``(B, N, 2)`` pts dtype, pixels in ``next``; ``status``: ``(B, N)`` bool.

    Convention:
        Pixel centres at integer coordinates. ``status`` is False for invalid lanes, for points whose
        level-0 window leaves ``[-win, W) x [-win, H)``, whose level-0 ``minEig`` is below the
        threshold, (with ``forward_backward``) that fail the check. Lanes with status False hold
        whatever OpenCV would leave there (finite); a lane whose ``init_pts`` is not finite gets
        status False (OpenCV: 0) and holds its ``pts`` (OpenCV: the NaN guess). Gradients flow to
        ``pts`` and float images (level 0) by the implicit-function theorem, or with
        ``grad_mode="unrolled"`` to ``pts``, ``init_pts`` and float images (through the pyramid)
        via the iterations; the backward check is discrete (no gradient). The values do not depend on whether gradients are recorded.

    ``torch.func``: ``vmap`` over an outer batch (``(V, B, ...)`` inputs, any of them shared with
    ``in_dims=None``) gives the per-``v`` calls' results bit for bit; ``grad``, ``vjp``, ``jacrev``,
    ``jvp``, ``jacfwd``, ``hessian`` and forward-AD dual tensors work in both grad modes (and
    compose with that ``vmap`` inside them). ``vmap`` over the primals of a derivative transform
    (``vmap(grad(f))``) raises ``NotImplementedError``: take the derivative of the loss summed over
    the batch (the streams are independent).
    """
    if early_exit is not None:
        warnings.warn("track_lk: early_exit is deprecated; use capturable (capturable = not early_exit)",
                      DeprecationWarning, stacklevel=2)
        capturable = not early_exit

    def call(prev, next, pts, valid, init_pts):
        return _track_lk_door(prev, next, pts, valid, init_pts, win_size, max_level, max_iters, eps,
                              min_eig_threshold, forward_backward, fb_threshold, fb_max_level, fb_use_initial_flow,
                              fixed_point, capturable, grad_mode, compile_step, lk_backend)

    if not torch.compiler.is_compiling() and has_wrapped_tensor(prev, next, pts, valid, init_pts):
        # torch.func wrappers: a vmap is folded into the call (.transforms)
        return track_transformed((prev, next, pts, valid, init_pts), call)
    if torch.compiler.is_compiling() or not isinstance(pts, torch.Tensor):
        return call(prev, next, pts, valid, init_pts)
    with exact_float32(pts.device):  # CUDA: TF32 off while it runs (the capturable path's exact window sums)
        return call(prev, next, pts, valid, init_pts)


def _track_lk_door(prev, next, pts, valid, init_pts, win_size, max_level, max_iters, eps, min_eig_threshold,
                   forward_backward, fb_threshold, fb_max_level, fb_use_initial_flow, fixed_point, capturable,
                   grad_mode, compile_step, lk_backend=None) -> Tuple[torch.Tensor, torch.Tensor]:
    """:func:`track_lk`'s checks and calls (its arguments, in its order)."""
    check_points(pts, "pts")
    valid = default_valid(pts, valid, "valid")
    if init_pts is not None:
        check_shape(init_pts, tuple(pts.shape), "init_pts")
    if fixed_point is None:

        def _is8(x):
            return x.rounded if isinstance(x, Pyramid) else as_image_batch(x).dtype == torch.uint8

        fixed_point = _is8(prev) and _is8(next)
    opts = LKOptions(win_size, max_level, max_iters, eps, min_eig_threshold, fixed_point, capturable,
                     grad_mode=grad_mode, compile_step=compile_step,
                     backend=resolve_backend(lk_backend, pts.device))
    fb_level = opts.max_level if fb_max_level is None else fb_max_level
    if not isinstance(fb_level, int) or fb_level < 0:
        raise ConfigError(f"fb_max_level must be an int >= 0, got {fb_max_level!r}")
    levels = max(opts.max_level, fb_level if forward_backward else 0)
    B = pts.shape[0]
    for name, x in (("prev", prev), ("next", next)):
        nb = x.batch if isinstance(x, Pyramid) else as_image_batch(x, name).shape[0]
        if nb != B:
            raise ValueError(f"{name}: batch {nb} does not match pts batch {B}")
    P, Q = _as_pyramid(prev, "prev", levels, opts), _as_pyramid(next, "next", levels, opts)
    _check_level_sizes(P, Q, levels)
    fb = (fb_level, float(fb_threshold), bool(fb_use_initial_flow)) if forward_backward else None
    out, status, _ = _track_lk_impl(P, Q, pts, valid, init_pts, opts, fb=fb)
    return out, status


def _as_pyramid(x: ImageOrPyramid, name: str, levels: int, opts: LKOptions) -> Pyramid:
    if isinstance(x, Pyramid):
        return x
    img = as_image_batch(x, name)
    return _build_pyramid_impl(img, levels, False, img.dtype == torch.uint8, pad=lk_pad(opts.win_size),
                               backend=opts.backend if opts.win_size[0] >= MIN_FUSED_WIDTH else "tensor")


def _check_level_sizes(prev: Pyramid, nxt: Pyramid, levels: int) -> None:
    for l in range(min(levels, prev.max_level, nxt.max_level) + 1):
        if prev.levels[l].shape[-2:] != nxt.levels[l].shape[-2:]:
            raise ValueError(
                f"prev/next: level {l} sizes differ: {tuple(prev.levels[l].shape)} vs {tuple(nxt.levels[l].shape)}"
            )
