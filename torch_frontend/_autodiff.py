"""Autodiff helpers of the kernels: does a tensor carry a derivative, and straight-through roundings.

Convention:
    A tensor *carries a derivative* when reverse mode may record through it (``requires_grad``:
    autograd, and ``torch.func.grad`` / ``vjp`` / ``jacrev``, whose tracked tensors set it) or it
    has a forward-mode tangent at the current level (``torch.autograd.forward_ad`` dual tensors
    and ``torch.func.jvp`` / ``jacfwd``, whose tensors leave ``requires_grad`` False). Both are read
    through public APIs (``Tensor.requires_grad``, ``forward_ad.unpack_dual``). A kernel that
    chooses between a fast form and a differentiable reference form asks this of the tensors it
    works on (``_tuning.inplace_ok``), never whether some transform is active somewhere: the
    choice then follows the data, and a transform that differentiates something else (a camera's
    parameters) keeps the fast forms of the image kernels.
"""

from __future__ import annotations

from typing import Optional

import torch
import torch.autograd.forward_ad as fwAD

__all__ = ["has_tangent", "derivative_wanted", "straight_through", "is_wrapper", "is_vmapped"]


def has_tangent(t: torch.Tensor) -> bool:
    """``t`` has a forward-mode tangent at the current forward-AD level (integer tensors never
    do). ~0.3 us when no forward-AD level is open."""
    return t.is_floating_point() and fwAD.unpack_dual(t).tangent is not None


def derivative_wanted(*tensors: Optional[torch.Tensor]) -> bool:
    """Some derivative may be recorded through these tensors: one requires a gradient or has a
    forward-mode tangent. ``None`` entries are ignored."""
    return any(t is not None and (t.requires_grad or has_tangent(t)) for t in tensors)


def straight_through(soft: torch.Tensor, hard: torch.Tensor) -> torch.Tensor:
    """Value of ``hard`` with the derivative of ``soft`` (the straight-through estimator of the 8-bit
    emulation's roundings). With a derivative wanted through ``soft`` it is ``hard.detach() + (soft -
    soft.detach())``, whose added term is exactly 0 for finite ``soft``, so the value is ``hard`` bit
    for bit; otherwise it is ``hard`` itself (no kernels)."""
    if not derivative_wanted(soft):
        return hard
    return hard.detach() + (soft - soft.detach())


def is_wrapper(t: torch.Tensor) -> bool:
    """``t`` is a ``torch.func`` transform's wrapper (``grad``/``jvp``/``vmap`` levels wrap the
    tensors they see; a wrapper owns no storage, which is how the public API tells). ~0.1 us for a
    plain tensor. A wrapper must not outlive its transform (no cache may keep one)."""
    try:
        t.untyped_storage()
    except (RuntimeError, NotImplementedError):
        return True
    return False


class _VmapProbe(torch.autograd.Function):
    """``apply(x)``: an empty marker of shape ``(0,)``, or ``(1,)`` when a ``torch.func.vmap``
    batches ``x``: functorch runs this public ``vmap`` staticmethod instead of ``forward`` then. No
    derivative flows through the marker."""

    @staticmethod
    def forward(x):
        return x.new_empty(0)

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.mark_non_differentiable(output)

    @staticmethod
    def vmap(info, in_dims, x):
        return x.new_empty(1), None

    @staticmethod
    def backward(ctx, grad):
        return None

    @staticmethod
    def jvp(ctx, tangent):
        return None


def is_vmapped(x) -> bool:
    """``x`` is a tensor batched by ``torch.func.vmap`` at the current level. A plain tensor is not
    (~0.1 us); a wrapper is asked through a gateway ``autograd.Function`` whose ``vmap`` rule
    answers (public extension points only)."""
    return isinstance(x, torch.Tensor) and is_wrapper(x) and _VmapProbe.apply(x).shape[0] > 0
