"""Shared input checks and small tensor helpers used by every kernel.

Kernels call the checks at their public boundary (the checked door over each ``_impl``) so that a
wrong shape or type fails early with a message that names the argument, the expected shape and the
given one (a ``ValueError``), rather than deep inside a ``conv2d`` or an ``index_select``. The
``_impl`` layer calls none of them: a pipeline validates its inputs once and calls it directly.
The slot helpers at the end (:func:`valid_first_order`, :func:`gather_slots`) are tensor code, not
checks.
"""

from __future__ import annotations

from typing import Optional, Sequence, Union

import torch

Shape = Sequence[Union[int, str, None]]


def check_shape(t: torch.Tensor, shape: Shape, name: str) -> None:
    """Check ``t`` against a shape pattern.

    ``shape`` entries are ints (exact size), strings (named sizes that must agree with each other
    across the same pattern, e.g. ``("B", "N", 2)``) or ``None`` (any size). A leading ``"*"``
    allows any number of leading dimensions.

    Raises:
        ValueError: naming ``name``, the expected pattern and the given shape.
    """
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(t).__name__}")
    pattern = list(shape)
    dims = list(t.shape)
    if pattern and pattern[0] == "*":
        pattern = pattern[1:]
        ok = len(dims) >= len(pattern)
        dims_tail = dims[len(dims) - len(pattern):] if ok else dims
    else:
        ok = len(dims) == len(pattern)
        dims_tail = dims
    named: dict = {}
    if ok:
        for want, got in zip(pattern, dims_tail):
            if want is None:
                continue
            if isinstance(want, str):
                if want in named and named[want] != got:
                    ok = False
                    break
                named[want] = got
            elif want != got:
                ok = False
                break
    if not ok:
        parts = ["*" if p == "*" else ("?" if p is None else str(p)) for p in shape]
        want_s = "(" + ", ".join(parts) + ("," if len(parts) == 1 else "") + ")"
        raise ValueError(f"{name}: expected shape {want_s}, got {tuple(dims)}")


def available_devices() -> list:
    """The devices this process can use: ``cpu``, every ``cuda:i``, ``mps`` where present."""
    out = ["cpu"]
    if torch.cuda.is_available():
        out += [f"cuda:{i}" for i in range(torch.cuda.device_count())]
    mps = getattr(torch.backends, "mps", None)
    if mps is not None and mps.is_available():
        out.append("mps")
    return out


def check_device(device, name: str = "device") -> torch.device:
    """``torch.device(device)``, refused with a ``ValueError`` naming it and the available devices
    when this process cannot allocate on it (a torch built without CUDA, no GPU, ``cuda:3`` on a
    one-GPU machine, ``mps`` off a Mac) instead of torch's raw ``AssertionError`` /
    ``RuntimeError`` from deep inside the first allocation.

    The probe is a 0-element allocation (no host sync, no data), so a device torch cannot name
    (``cuda`` on a CPU build) but a dispatch mode provides (a simulated or fake CUDA) passes."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise ValueError(f"{name}: {device!r} is not a device ({str(exc).splitlines()[0][:200]}); available here: "
                         f"{', '.join(available_devices())}") from None
    if dev.type in ("cpu", "meta"):
        return dev
    try:
        torch.empty(0, device=dev)
    except (AssertionError, RuntimeError, NotImplementedError) as exc:
        if dev.type == "cuda" and not torch.version.cuda and not getattr(torch.version, "hip", None):
            why = f"this torch {torch.__version__} is built without CUDA"
        elif dev.type == "cuda" and not torch.cuda.is_available():
            why = "no CUDA device is visible"
        elif dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
            why = f"this machine has {torch.cuda.device_count()} CUDA device(s)"
        elif dev.type == "mps":
            why = "MPS needs Apple silicon and a torch built with it"
        else:
            why = f"this torch cannot allocate on {dev.type}: {type(exc).__name__}: {str(exc).splitlines()[0][:120]}"
        raise ValueError(f"{name} {str(dev)!r} is not available on this machine ({why}); available here: "
                         f"{', '.join(available_devices())}") from None
    return dev


def check_int(value, name: str, minimum: int = 0) -> int:
    """Check that ``value`` is an integer (an int, or a number equal to one) ``>= minimum``;
    returns it as an ``int``.

    Raises:
        ValueError: naming ``name``, what was expected and the value given.
    """
    if int(value) != value or value < minimum:
        want = {0: "a non-negative integer", 1: "a positive integer"}.get(minimum, f"an integer >= {minimum}")
        raise ValueError(f"{name}: expected {want}, got {value!r}")
    return int(value)


def as_image_batch(img: torch.Tensor, name: str = "img") -> torch.Tensor:
    """Return ``img`` as a ``(B, 1, H, W)`` tensor.

    Accepts ``(B, 1, H, W)`` or ``(B, H, W)``; uint8 or floating point in 0..255. The dtype is
    kept (callers decide whether they need float); only the layout is normalised.
    """
    if not isinstance(img, torch.Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(img).__name__}")
    if img.dim() == 3:
        img = img.unsqueeze(1)
    if img.dim() != 4 or img.shape[1] != 1:
        raise ValueError(f"{name}: expected shape (B, 1, H, W) or (B, H, W), got {tuple(img.shape)}")
    if not (img.dtype == torch.uint8 or img.is_floating_point()):
        raise TypeError(f"{name}: expected uint8 or floating point, got {img.dtype}")
    return img


def as_float_image(img: torch.Tensor, name: str = "img") -> torch.Tensor:
    """``as_image_batch`` then convert to floating point (grey levels 0..255 are kept, not rescaled):
    a float image keeps its dtype, uint8 becomes float32."""
    img = as_image_batch(img, name)
    return img if img.is_floating_point() else img.to(torch.float32)


def check_points(pts: torch.Tensor, name: str = "pts") -> None:
    """Points are ``(B, N, 2)`` floating point pixels ``(x, y)``."""
    check_shape(pts, ("B", "N", 2), name)
    if not pts.is_floating_point():
        raise TypeError(f"{name}: expected a floating point tensor, got {pts.dtype}")


def default_valid(pts: torch.Tensor, valid: Optional[torch.Tensor], name: str = "valid") -> torch.Tensor:
    """Return a ``(B, N)`` bool mask, all True when ``valid`` is None."""
    if valid is None:
        return torch.ones(pts.shape[:-1], dtype=torch.bool, device=pts.device)
    check_shape(valid, tuple(pts.shape[:-1]), name)
    return valid.to(torch.bool)


def valid_first_order(valid: torch.Tensor) -> torch.Tensor:
    """``(B, K)`` slot order that moves each row's valid slots to the front, keeping their order
    (a stable compaction, VINS's ``reduceVector``).

    A stable descending sort of the bool mask itself: the order of a stable ascending sort of
    ``~valid`` (equal keys keep their order either way), in one kernel instead of three (``~``,
    the cast, the sort)."""
    return torch.sort(valid.to(torch.bool), dim=-1, descending=True, stable=True).indices


def gather_slots(t: torch.Tensor, order: torch.Tensor) -> torch.Tensor:
    """Permute the slots (dim 1) of ``t (B, K, ...)`` by ``order (B, K')``."""
    idx = order.reshape(order.shape + (1,) * (t.dim() - 2))
    return torch.gather(t, 1, idx.expand(*order.shape, *t.shape[2:]))
