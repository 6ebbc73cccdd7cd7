"""The kernel contract (docs/CONTRIBUTING.md, "The kernel contract"): every kernel's private
``_<name>_impl`` takes a keyword-only ``capturable`` flag and returns, on both paths, the same
``NamedTuple`` whose last field is ``overflow``: a ``(B,)`` bool tensor on the capturable path, None
on the default path. Tiny inputs, both paths, and the same values wherever ``overflow`` is False."""

from __future__ import annotations

import importlib
import inspect
import sys

import numpy as np
import pytest
import torch

from ._layers import LAYERS

B = 2


def _images(h=32, w=40, seed=0):
    """``(B, 1, h, w)`` uint8: smooth random texture (corners, a trackable shift)."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(B, 1, h // 4, w // 4, generator=g) * 255
    return torch.nn.functional.interpolate(x, size=(h, w), mode="bilinear", align_corners=False).round().to(torch.uint8)


def _clahe():
    from torch_frontend.equalize import _clahe_impl

    src = _images()[:, 0].contiguous()
    return _clahe_impl, lambda cap: _clahe_impl(src, 3.0, 2, 2, capturable=cap)


def _clahe_fused():
    from torch_frontend.equalize import _clahe_impl

    src = _images()[:, 0].contiguous()
    return _clahe_impl, lambda cap: _clahe_impl(src, 3.0, 2, 2, capturable=cap, backend="fused")


def _corners():
    from torch_frontend.corners import _good_features_impl

    img, mc = _images(), torch.tensor([6, 3])
    return _good_features_impl, lambda cap: _good_features_impl(img, mc, 0.01, 3.0, None, False, 3, 0.04, 6,
                                                                capturable=cap)


def _corners_fused():
    from torch_frontend.corners import _good_features_impl

    img, mc = _images(), torch.tensor([6, 3])
    return _good_features_impl, lambda cap: _good_features_impl(img, mc, 0.01, 3.0, None, False, 3, 0.04, 6,
                                                                capturable=cap, backend="fused")


def _masks(backend="tensor"):
    from torch_frontend.masks import _distance_mask_impl

    g = torch.Generator().manual_seed(1)
    pts = torch.rand(B, 8, 2, generator=g) * 20
    pri = torch.randint(1, 4, (B, 8), generator=g)
    valid = torch.ones(B, 8, dtype=torch.bool)
    return _distance_mask_impl, lambda cap: _distance_mask_impl(
        pts, pri, valid, 3.0, torch.full((B, 20, 20), 255, dtype=torch.uint8), capturable=cap, backend=backend)


def _lk():
    from torch_frontend.lk import LKOptions
    from torch_frontend.lk import _track_lk_impl as impl
    from torch_frontend.pyramid import _build_pyramid_impl

    a = _images(seed=2)
    b = torch.roll(a, 1, dims=-1)
    P, Q = (_build_pyramid_impl(x, 1, False, True) for x in (a, b))
    pts = torch.tensor([[[12.0, 12.0], [20.0, 16.0]]]).expand(B, 2, 2).contiguous()
    valid = torch.ones(B, 2, dtype=torch.bool)
    opts = LKOptions(win_size=(7, 7), max_level=1, max_iters=10)
    return impl, lambda cap: impl(P, Q, pts, valid, None, opts, capturable=cap)


def _ransac():
    from torch_frontend import ransac

    g = torch.Generator().manual_seed(3)
    p1 = torch.rand(B, 16, 2, generator=g, dtype=torch.float64) * 100
    p2 = p1 + torch.tensor([2.0, 0.5], dtype=torch.float64) + torch.rand(B, 16, 2, generator=g, dtype=torch.float64)
    valid = torch.ones(B, 16, dtype=torch.bool)
    states = ransac._seeds(B, seed=7)
    impl = ransac._find_fundamental_impl
    return impl, lambda cap: impl(p1, p2, valid, 1.0, 0.99, 50, states, None, capturable=cap)


# kernel module -> the builder of its ``_impl`` and a call on tiny inputs (a new kernel adds a line)
KERNELS = {
    "equalize": ("torch_frontend.equalize", _clahe),
    "equalize:fused": ("torch_frontend.equalize", _clahe_fused),  # the fused op behind the same _impl
    "corners": ("torch_frontend.corners", _corners),
    "corners:fused": ("torch_frontend.corners", _corners_fused),  # the fused op behind the same _impl
    "masks": ("torch_frontend.masks", _masks),
    "lk": ("torch_frontend.lk", _lk),
    "ransac": ("torch_frontend.ransac", _ransac),
}


# the same contract for a kernel's other backends (the fused ops behind an ``_impl``)
BACKEND_VARIANTS = {
    "masks[fused]": ("torch_frontend.masks", lambda: _masks("fused")),
}


def _static_names(module: str):
    """Callables named ``*_static`` in a kernel module and its submodules (the contract's one name
    for the concept is ``*_capturable``)."""
    mods = [m for name, m in list(sys.modules.items()) if name == module or name.startswith(module + ".")]
    return sorted({n for m in mods for n in vars(m) if n.endswith("_static") and callable(getattr(m, n))})


def test_every_kernel_is_listed():
    """Every kernel of the kernel layer (the plan, ``tests/_layers.py``) is checked here."""
    kernels = dict(LAYERS)["kernels"]
    # _tuning: strategies; pyramid: one form on both paths; fused: the custom ops behind the pyramid and
    # the LK (their doors are those kernels', tests/test_fused.py)
    assert sorted(k for k in kernels if k not in ("_tuning", "pyramid", "fused")) == \
        sorted({k.split(":")[0] for k in KERNELS})  # "module:variant": another backend of the module's _impl


@pytest.mark.parametrize("kernel", list(KERNELS) + list(BACKEND_VARIANTS))
def test_impl_follows_the_kernel_contract(kernel):
    module, build = {**KERNELS, **BACKEND_VARIANTS}[kernel]
    importlib.import_module(module)
    old = _static_names(module)
    assert not old, f"{module}: capturable helpers must be named *_capturable, not {old}"
    impl, call = build()
    param = inspect.signature(impl).parameters.get("capturable")
    assert param is not None and param.kind is inspect.Parameter.KEYWORD_ONLY, \
        f"{impl.__qualname__}: capturable must be a keyword-only parameter"
    assert param.default in (False, None)  # None: LK's "as its options say" (LKOptions.capturable=False)

    default, capturable = call(False), call(True)
    for res in (default, capturable):
        assert isinstance(res, tuple) and hasattr(type(res), "_fields"), f"{impl.__qualname__}: not a NamedTuple"
        assert res._fields[-1] == "overflow", f"{impl.__qualname__}: last field {res._fields[-1]!r}"
    assert type(default) is type(capturable)  # the same fields on both paths
    assert default.overflow is None
    ovf = capturable.overflow
    if ovf is not None:  # None on both paths: a kernel without budgets (CLAHE)
        assert isinstance(ovf, torch.Tensor) and ovf.dtype == torch.bool and ovf.shape == (B,)
    bools = [v for v in default[:-1] if isinstance(v, torch.Tensor) and v.dtype == torch.bool]
    assert all(bool(m.any()) for m in bools), "the tiny input selects nothing: a vacuous comparison"
    # the same values wherever the capturable path did not overflow (these inputs fit every budget)
    assert ovf is None or not bool(ovf.any())
    for name, a, b in zip(default._fields[:-1], default[:-1], capturable[:-1]):
        if isinstance(a, torch.Tensor):
            if a.is_floating_point():
                np.testing.assert_allclose(a.numpy(), b.numpy(), rtol=1e-9, atol=1e-9, err_msg=name)
            else:
                assert torch.equal(a, b), name
