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

__all__ = ["has_tangent", "derivative_wanted", "straight_through"]


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
