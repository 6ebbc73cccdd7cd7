"""``torch.func`` support of :func:`~torch_frontend.track_lk` through public extension points only
(``docs/lk.md``, "torch.func").

``grad``, ``vjp``, ``jacrev``, ``jvp``, ``jacfwd``, ``hessian`` and forward-AD dual tensors need
nothing here: every kernel asks of its own tensors whether a derivative is carried
(``_autodiff.derivative_wanted``) and takes its differentiable reference form then, and the
per-size caches keep plain tensors (``_cache.cached``). ``vmap`` does: the eager LK sizes its work
by host syncs and ``nonzero``, which vmap cannot batch. Streams and points are independent, so the
vmapped dimension is *folded* into the call instead:

* :class:`_FoldVmap`, a gateway ``torch.autograd.Function`` over the LK's tensor arguments. Its
  ``forward`` (reached when no argument is batched by a vmap) returns only an empty marker ("no
  fold"). Its ``vmap`` staticmethod, which functorch runs one level below the vmap, folds the
  vmapped dimension into the batch (``(V, B, ...) -> (V B, ...)``: an image is batched; the others
  are repeated) or into the points (``(V, B, N, 2) -> (B, V N, 2)``: shared images, neither copied
  nor rebuilt) and returns the folded, unbatched tensors with a marker of shape ``(V, into_batch)``.
  An outer ``grad`` / ``jvp`` records the folding ops themselves (they run at its level).
* the LK then runs on the folded tensors; nested vmaps fold one level per gateway call (functorch
  passes a call with nothing batched at the innermost level down to the next one), until the
  marker says "no fold";
* :class:`_UnfoldVmap`, given the fold's inputs as witnesses (so that functorch runs its ``vmap``
  rule at the level of that fold), maps the results back to ``(V, B, N, ...)`` batched at that level.

The values are those of one call per ``v`` bit for bit (every lane is computed by the same per-lane
code whatever the lane set). The gateways' ``backward`` / ``jvp`` are reached only when a
derivative transform runs *inside* the vmap (``vmap(grad(f))``, ``vmap(jvp(f))``: per-sample
derivatives) and a derivative flows through the folded call, which this cannot give: they raise
``NotImplementedError``. A call with no wrapped tensor does not go through the gateways at all.
"""

from __future__ import annotations

from typing import Any, Callable, List, NamedTuple, Optional, Sequence, Tuple

import torch

from .._autodiff import is_wrapper
from ..pyramid import Pyramid

__all__ = ["has_wrapped_tensor"]

VMAP_OVER_DERIVATIVE = (
    "track_lk: vmap over the primals of a derivative transform (vmap(grad(f)), vmap(jvp(f)), "
    "vmap(vjp(f))) is not supported: the vmapped dimension is folded into the LK's batch, whose "
    "derivative the transform inside the vmap would see whole. Put vmap inside the derivative "
    "(grad(vmap(f))), or take the derivative of the loss summed over the batch: the streams are independent.")


def has_wrapped_tensor(*args: Any) -> bool:
    """Some argument (a tensor, a :class:`Pyramid`'s levels; None ignored) is a ``torch.func``
    transform's wrapper, so a transform may batch it. ~0.1 us a tensor."""
    for x in args:
        if isinstance(x, Pyramid):
            if any(is_wrapper(t) for t in x.levels):
                return True
        elif isinstance(x, torch.Tensor) and is_wrapper(x):
            return True
    return False


class _Spec(NamedTuple):
    """How the LK's arguments ``(prev, next, pts, valid, init_pts)`` lie in the gateway's flat
    tensor list: per image argument the number of tensors (``None``: a tensor, else a pyramid's
    level count) and ``rounded``; whether ``valid`` and ``init_pts`` are given."""

    images: Tuple[Tuple[Optional[int], bool], ...]
    has_valid: bool
    has_init: bool


def _flatten(args: Sequence[Any]) -> Tuple[_Spec, List[torch.Tensor]]:
    flat: List[torch.Tensor] = []
    images = []
    for x in args[:2]:
        if isinstance(x, Pyramid):
            images.append((len(x.levels), x.rounded))
            flat.extend(x.levels)
        else:
            images.append((None, False))
            flat.append(x)
    flat.append(args[2])
    for x in args[3:]:
        if x is not None:
            flat.append(x)
    return _Spec(tuple(images), args[3] is not None, args[4] is not None), flat


def _unflatten(spec: _Spec, flat: Sequence[torch.Tensor], old: Sequence[Any]) -> tuple:
    """The arguments of ``flat`` (the fold's outputs); a pyramid whose levels all came back
    unchanged is the given one (with its padded-level cache)."""
    out: List[Any] = []
    i = 0
    for (n, rounded), x in zip(spec.images, old):
        if n is None:
            out.append(flat[i])
            i += 1
        else:
            levels = list(flat[i:i + n])
            i += n
            same = all(a is b for a, b in zip(levels, x.levels))
            out.append(x if same else Pyramid(levels, None, rounded))
    out.append(flat[i])
    i += 1
    for given in (spec.has_valid, spec.has_init):
        out.append(flat[i] if given else None)
        i += given
    return tuple(out)


def _fold(spec: _Spec, V: int, in_dims: Sequence[Optional[int]], flat: Sequence[torch.Tensor]):
    """The folded flat tensors (see the module notes) and whether the fold is into the batch."""
    in_dims = list(in_dims)
    n_img = sum(1 if n is None else n for n, _ in spec.images)
    into_batch = any(d is not None for d in in_dims[:n_img])

    def rep(x, d):  # dimension d moved to 0, or x repeated along a new dim 0 of size V (a view)
        return x.movedim(d, 0) if d is not None else x.unsqueeze(0).expand(V, *x.shape)

    out = []
    for k, (x, d) in enumerate(zip(flat, in_dims)):
        if k < n_img:  # images / pyramid levels: folded only into the batch
            out.append(rep(x, d).flatten(0, 1) if into_batch else x)
        else:  # pts (V, B, N, 2), valid (V, B, N), init_pts (V, B, N, 2)
            x = rep(x, d)
            out.append(x.flatten(0, 1) if into_batch else x.movedim(0, 1).flatten(1, 2))
    return out, into_batch


def _unfold(y: torch.Tensor, V: int, into_batch: bool) -> torch.Tensor:
    """An output ``(V B, N, ...)`` (into the batch) or ``(B, V N, ...)`` as ``(V, B, N, ...)``."""
    return y.unflatten(0, (V, -1)) if into_batch else y.unflatten(1, (V, -1)).movedim(1, 0)


class _FoldVmap(torch.autograd.Function):
    """Gateway: ``apply(spec, *flat) -> (marker,)`` outside vmap (``marker.dim() == 1``: no fold);
    under a vmap that batches some of ``flat``, ``(*folded, marker)`` with ``marker`` of shape
    ``(V, into_batch)``."""

    @staticmethod
    def forward(spec: _Spec, *flat: torch.Tensor):
        return (flat[0].new_empty(0),)

    @staticmethod
    def setup_context(ctx, inputs, output):
        marker = output[-1]
        ctx.folded = marker.dim() == 2
        ctx.n_inputs = len(inputs)
        ctx.mark_non_differentiable(marker)

    @staticmethod
    def vmap(info, in_dims, spec: _Spec, *flat: torch.Tensor):
        folded, into_batch = _fold(spec, info.batch_size, in_dims[1:], flat)
        marker = flat[0].new_empty(info.batch_size, int(into_batch))
        return (*folded, marker), (None,) * (len(folded) + 1)

    @staticmethod
    def backward(ctx, *grads):
        if ctx.folded:
            raise NotImplementedError(VMAP_OVER_DERIVATIVE)
        return (None,) * ctx.n_inputs

    @staticmethod
    def jvp(ctx, *tangents):
        if ctx.folded:
            raise NotImplementedError(VMAP_OVER_DERIVATIVE)
        return (None,)


class _UnfoldVmap(torch.autograd.Function):
    """Gateway: ``apply(V, into_batch, n, *outputs, *witnesses)``: the ``n`` outputs of a folded call
    as ``(V, B, N, ...)``, batched at the level of the fold whose inputs are ``witnesses``."""

    @staticmethod
    def forward(V: int, into_batch: bool, n: int, *tensors: torch.Tensor):
        raise RuntimeError("track_lk: a folded call's outputs reached no vmap level (internal error)")

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.mark_non_differentiable(*(t for t in output if not t.is_floating_point()))

    @staticmethod
    def vmap(info, in_dims, V: int, into_batch: bool, n: int, *tensors: torch.Tensor):
        if info.batch_size != V or any(d is not None for d in in_dims[3:3 + n]):
            raise RuntimeError("track_lk: a folded call's outputs reached another vmap level (internal error)")
        return tuple(_unfold(y, V, into_batch) for y in tensors[:n]), (0,) * n

    @staticmethod
    def backward(ctx, *grads):
        raise NotImplementedError(VMAP_OVER_DERIVATIVE)

    @staticmethod
    def jvp(ctx, *tangents):
        raise NotImplementedError(VMAP_OVER_DERIVATIVE)


def track_transformed(args: Sequence[Any], call: Callable[..., Tuple[torch.Tensor, ...]]) -> Tuple[torch.Tensor, ...]:
    """``call(*args)`` (``args = (prev, next, pts, valid, init_pts)``, ``call`` the checked LK
    returning a tuple of ``(B, N, ...)`` tensors) with every vmapped dimension of the arguments
    folded into the call and unfolded from its results (see the module notes)."""
    folds = []
    while True:
        spec, flat = _flatten(args)
        res = _FoldVmap.apply(spec, *flat)
        marker = res[-1]
        if marker.dim() == 1:
            break
        V, into_batch = marker.shape[0], bool(marker.shape[1])
        folds.append((flat, V, into_batch))
        args = _unflatten(spec, res[:-1], args)
    out = tuple(call(*args))
    for flat, V, into_batch in reversed(folds):
        out = _UnfoldVmap.apply(V, into_batch, len(out), *out, *flat)
    return out
