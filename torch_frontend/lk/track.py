"""The LK's private layer, what the tracker's stages call (``docs/lk.md``): :func:`_track_lk_impl`
(the forward pass) and :func:`_forward_backward_impl` (VINS-Fusion's FLOW_BACK check), on checked
pyramids and options, each returning a small NamedTuple whose last field is ``overflow``.

Convention:
    ``prev``, ``next``: :class:`~torch_frontend.pyramid.Pyramid` of B streams with equal level
    sizes; ``pts``: ``(B, N, 2)`` float pixels ``(x, y)`` (pixel centres at integer coordinates);
    ``valid``, ``status``: ``(B, N)`` bool; ``overflow``: ``(B,)`` bool or None.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple, Optional, Tuple

import torch

from .. import _tuning
from ..pyramid import Pyramid
from .capturable import _lk_capturable
from .eager import _lk_eager
from .fused_path import FBArgs, fused_applies, lk_fused
from .implicit import _detached, _implicit_attach, _levels_have_tangent, _wants_grad
from .options import LKOptions

__all__ = ["LKResult", "FlowBackResult"]


class LKResult(NamedTuple):
    """The forward LK of :func:`_track_lk_impl`.

    Attributes:
        pts: ``(B, N, 2)`` the points' dtype, pixels in ``next`` (OpenCV's ``nextPts``).
        status: ``(B, N)`` bool (OpenCV's ``status``).
        overflow: ``(B,)`` bool, True where a lane of the stream was still iterating when a
            level's iteration budget (``LKOptions.iter_budget``) ended, so that its result may
            differ from OpenCV's: always a tensor on the capturable path (all False with the full
            budget); on the default path a tensor when some budget is below ``max_iters``, else
            None (no budget, OpenCV's exact answer).
    """

    pts: torch.Tensor
    status: torch.Tensor
    overflow: Optional[torch.Tensor]


class FlowBackResult(NamedTuple):
    """The FLOW_BACK check of :func:`_forward_backward_impl`.

    Attributes:
        status: ``(B, N)`` bool, the forward status and the check.
        overflow: the backward pass's ``(B,)`` overflow flag, as :attr:`LKResult.overflow`.
    """

    status: torch.Tensor
    overflow: Optional[torch.Tensor]


def _level_cap(prev: Pyramid, nxt: Pyramid, max_level: int, win: Tuple[int, int]) -> int:
    """The top level an LK uses: ``max_level`` capped by both pyramids and where OpenCV's
    ``buildOpticalFlowPyramid`` stops (before a level whose size is <= ``win``)."""
    top = min(max_level, prev.max_level, nxt.max_level)
    for l in range(1, top + 1):
        h, w = prev.levels[l].shape[-2:]
        if w <= win[0] or h <= win[1]:
            return l - 1
    return top


def _prime_next_pyramid(pyr: Pyramid, opts: LKOptions, dtype: torch.dtype) -> Pyramid:
    """``pyr`` with the padded levels an LK call with ``opts`` caches on its ``next`` pyramid (the
    following call's ``prev``: the template is read from them) made now, as the call would make
    them: a pyramid that no LK has seen then holds what one that has seen one holds (a compiled
    step guards on that cache: one graph for both)."""
    ww, wh = opts.win_size
    for level in range(_level_cap(pyr, pyr, opts.max_level, opts.win_size) + 1):
        pyr.padded(level, wh + 1, ww + 1, dtype)
    return pyr


def _track_lk_impl(
    prev: Pyramid,
    next: Pyramid,
    pts: torch.Tensor,
    valid: torch.Tensor,
    init_pts: Optional[torch.Tensor],
    opts: LKOptions,
    *,
    capturable: Optional[bool] = None,
    fb: Optional[FBArgs] = None,
) -> LKResult:
    """Forward LK (:func:`~torch_frontend.track_lk`), no input checks; with ``fb`` its backward check too.

    Args:
        prev, next: pyramids of the B streams, with equal level sizes (as many levels as
            ``opts.max_level`` asks for, or fewer: the LK then uses fewer).
        pts: ``(B, N, 2)`` float, pixels ``(x, y)`` in ``prev``.
        valid: ``(B, N)`` bool.
        init_pts: ``(B, N, 2)`` initial guess in ``next``, or None (start at ``pts``).
        opts: :class:`LKOptions`.
        capturable: the path; None (default) takes ``opts.capturable``. The same results on both.
        fb: ``(fb_max_level, fb_threshold, fb_use_initial_flow)``: also VINS-Fusion's FLOW_BACK check
            (:func:`_forward_backward_impl`'s), in the same op on the fused path; ``status`` is then
            the checked one and ``overflow`` both passes' flag.

    Returns:
        :class:`LKResult` ``(pts, status, overflow)``.

    The default path: on the CPU the streams are tracked in groups
    (``_tuning.Strategy.lk_streams``), so that the per-level temporaries (``(win+1)^2 x lanes``
    windows and their indices) stay cache friendly; the padded levels are built once for the whole
    batch and shared by the groups as views (a pyramid that is ``next`` now keeps them for the call
    in which it is ``prev``); elsewhere one pass. The capturable path: one pass on every device (no
    host sync once the per-size constants are cached, a kernel count independent of B).
    ``opts.grad_mode == "implicit"`` with a derivative to compute: the forward above without a
    graph, then the implicit-function gradient (the same values).
    """
    cap = opts.capturable if capturable is None else bool(capturable)
    if fb is not None and not fused_applies(prev, next, pts, init_pts, opts):
        out, status, overflow, _ = _lk_pass(prev, next, pts, valid, init_pts, opts, cap)
        status, of_b = _forward_backward_impl(prev, next, pts, out, status, opts, fb[0], float(fb[1]), bool(fb[2]),
                                              capturable=cap)
        return LKResult(out, status, of_b if overflow is None else (overflow if of_b is None else overflow | of_b))
    out, status, overflow, _ = _lk_pass(prev, next, pts, valid, init_pts, opts, cap, fb=fb)
    return LKResult(out, status, overflow)


def _forward_backward_impl(
    prev: Pyramid,
    next: Pyramid,
    pts: torch.Tensor,
    out: torch.Tensor,
    status: torch.Tensor,
    opts: LKOptions,
    fb_max_level: int,
    fb_threshold: float,
    fb_use_initial_flow: bool,
    *,
    capturable: Optional[bool] = None,
) -> FlowBackResult:
    """VINS-Fusion's FLOW_BACK check of a forward LK result, no input checks.

    Tracks ``out`` back from ``next`` to ``prev`` (lanes with ``status``; ``opts`` with
    ``max_level = fb_max_level``; starting at ``pts`` when ``fb_use_initial_flow``, else at ``out``)
    and keeps ``status & back_status & (|back - pts| <= fb_threshold)``, the distance in float64
    pixels. ``pts``, ``out``: ``(B, N, 2)``; ``status``: ``(B, N)`` bool; ``capturable`` as
    :func:`_track_lk_impl`'s. A discrete test: no gradient, no tangent.

    Returns:
        :class:`FlowBackResult` ``(status, overflow)`` (the backward pass's overflow flag).
    """
    cap = opts.capturable if capturable is None else bool(capturable)
    if _levels_have_tangent(prev, next):  # no_grad does not stop forward-mode AD
        prev, next = _detached(prev), _detached(next)
    with torch.no_grad():
        init = pts.detach() if fb_use_initial_flow else None
        back, st, overflow, _ = _lk_pass(next, prev, out.detach(), status, init,
                                         dataclasses.replace(opts, max_level=fb_max_level), cap)
        err = torch.linalg.vector_norm((back - pts.detach()).double(), dim=-1)
        return FlowBackResult(status & st & (err <= fb_threshold), overflow)


def _lk_pass(prev: Pyramid, next: Pyramid, pts: torch.Tensor, valid: torch.Tensor, init_pts: Optional[torch.Tensor],
             opts: LKOptions, capturable: bool, want_capped: bool = False, fb: Optional[FBArgs] = None):
    """:func:`_track_lk_impl` as ``(pts, status, overflow, capped)``: with ``want_capped`` the
    ``(B N,)`` bool mask of the lanes still iterating when level 0's budget ended (for the implicit
    gradient; else None). ``fb``: the fused path's forward-backward check (callers pass it only when
    :func:`.fused_path.fused_applies`)."""
    if opts.grad_mode == "implicit" and _wants_grad(prev, next, pts, init_pts):
        return _lk_pass_implicit(prev, next, pts, valid, init_pts, opts, capturable, fb)
    top = _level_cap(prev, next, opts.max_level, opts.win_size)
    if fused_applies(prev, next, pts, init_pts, opts):
        fbt = None if fb is None else (_level_cap(next, prev, fb[0], opts.win_size), float(fb[1]), bool(fb[2]))
        return lk_fused(prev, next, pts, valid, init_pts, opts, top, capturable, want_capped, fbt)
    B, N = pts.shape[:2]
    if init_pts is not None:
        # a non-finite guess (a NaN prediction) would index outside the image: its lane is not
        # tracked and starts at its pts (status False, as OpenCV's 0). Elementwise, no host sync;
        # a finite guess is kept exactly.
        guessed = torch.isfinite(init_pts).all(-1)
        init_pts = torch.where(guessed.unsqueeze(-1), init_pts, pts)
        valid = valid & guessed
    if capturable:
        out, status, overflow, capped = _lk_capturable(prev, next, pts, valid, init_pts, opts, top, want_capped)
        if overflow is None:  # the full budget: exact, and still a flag (no branch on the path for arity)
            overflow = torch.zeros(B, dtype=torch.bool, device=pts.device)
        return out, status, overflow, capped
    per = _tuning.for_device(pts.device).lk_streams(B, N)
    if per is None:
        return _lk_eager(prev, next, pts, valid, init_pts, opts, top, opts.inexact, want_capped)
    ww, wh = opts.win_size
    for l in range(top + 1):
        for x in (prev, next):
            x.padded(l, wh + 1, ww + 1, pts.dtype)
    groups = []
    for s0 in range(0, B, per):
        sl = slice(s0, min(B, s0 + per))
        groups.append(_lk_eager(prev.select(sl), next.select(sl), pts[sl], valid[sl],
                                None if init_pts is None else init_pts[sl], opts, top, opts.inexact, want_capped))
    out, status, overflow, capped = zip(*groups)
    return (torch.cat(out), torch.cat(status), None if overflow[0] is None else torch.cat(overflow),
            None if capped[0] is None else torch.cat(capped))


def _lk_pass_implicit(prev: Pyramid, nxt: Pyramid, pts: torch.Tensor, valid: torch.Tensor,
                      init: Optional[torch.Tensor], opts: LKOptions, capturable: bool, fb: Optional[FBArgs] = None):
    """:func:`_lk_pass` with ``grad_mode="implicit"``: the forward without a graph (the same code, so
    the same values), then :func:`.implicit._implicit_attach` on the lanes with status True that did
    not hit level 0's iteration budget."""
    P, Q = prev, nxt
    if _levels_have_tangent(prev, nxt):  # no_grad does not stop forward-mode AD: the forward on plain levels
        P, Q = _detached(prev), _detached(nxt)
    with torch.no_grad():
        out, status, overflow, capped = _lk_pass(P, Q, pts.detach(), valid, None if init is None else init.detach(),
                                                 dataclasses.replace(opts, grad_mode="unrolled"), capturable, True, fb)
    cap = torch.zeros_like(status) if capped is None else capped.view(status.shape)
    # the forward's own status (with fb the checked one: a lane that fails the check gets no gradient)
    out, _ = _implicit_attach(prev, nxt, pts, out, status & ~cap, opts)
    return out, status, overflow, None
