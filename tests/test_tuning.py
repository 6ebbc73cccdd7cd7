"""The kernels' two layers and their CPU tuning (``torch_frontend._tuning``).

* every kernel's checked public door gives bit for bit what its ``_impl`` gives on the normalised
  arguments, and the ``_impl`` layer performs no input check (a pipeline validates once);
* every fast (in-place) form equals its reference (out-of-place, differentiable) form bit for bit,
  and the values with gradients recorded equal those without (the gradients themselves are checked
  against finite differences by the gradchecks in ``test_pyramid``, ``test_corners``, ``test_lk``);
* the CPU strategies (blocks, groups of streams, host checks) give the results of one pass, which
  is what every other device runs.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
import torch

from torch_frontend import _tuning, corners, equalize, lk, masks, pyramid, ransac
from torch_frontend.errors import ConfigError

from .conftest import load_gray, sample_frames


@pytest.fixture(scope="module")
def frames():
    return [load_gray(p) for p in sample_frames("cam0")]


def _corners(img, n=150, min_dist=10):
    return cv2.goodFeaturesToTrack(img, n, 0.01, min_dist).reshape(-1, 2).astype(np.float32)


def _lk_case(frames, B=3, crop=(slice(60, 300), slice(120, 520))):
    prev = np.stack([np.ascontiguousarray(frames[2 * b][crop]) for b in range(B)])
    nxt = np.stack([np.ascontiguousarray(frames[2 * b + 1][crop]) for b in range(B)])
    pts = [_corners(p, 80, 6) for p in prev]
    n = min(len(p) for p in pts)
    P = torch.from_numpy(np.stack([p[:n] for p in pts]))
    valid = torch.ones(B, n, dtype=torch.bool)
    valid[1, ::4] = False
    return torch.from_numpy(prev)[:, None], torch.from_numpy(nxt)[:, None], P, valid


def _equal(a, b):
    if isinstance(a, (tuple, list)):
        return len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b))
    return torch.equal(a, b)


# --------------------------------------------------------------------------- strategies
def test_strategy_by_device():
    assert _tuning.for_device(torch.device("cpu")) is _tuning.CPU
    assert _tuning.for_device("cpu") is _tuning.CPU
    for dev in ("cuda", "cuda:1"):
        assert _tuning.for_device(dev) is _tuning.CUDA
    assert _tuning.for_device(torch.device("meta")) is _tuning.ONE_PASS
    # the fused pyramid and LK where they have kernels (numba, Triton); the tensor kernels elsewhere
    assert (_tuning.CPU.lk_backend, _tuning.CUDA.lk_backend, _tuning.ONE_PASS.lk_backend) == ("fused", "fused", "tensor")
    assert (_tuning.CPU.clahe_backend, _tuning.CUDA.clahe_backend, _tuning.ONE_PASS.clahe_backend) == \
        ("fused", "fused", "tensor")
    assert (_tuning.CPU.ransac_backend, _tuning.CUDA.ransac_backend, _tuning.ONE_PASS.ransac_backend) == \
        ("fused", "fused", "tensor")
    assert (_tuning.CPU.corner_backend, _tuning.CUDA.corner_backend, _tuning.ONE_PASS.corner_backend) == (
        "fused", "fused", "tensor")
    assert (_tuning.CPU.lift_backend, _tuning.CUDA.lift_backend, _tuning.ONE_PASS.lift_backend) == (
        "fused", "fused", "tensor")
    assert dataclasses.replace(_tuning.CUDA, lk_backend="tensor", clahe_backend="tensor",
                               ransac_backend="tensor", corner_backend="tensor",
                               lift_backend="tensor") == _tuning.ONE_PASS
    one = _tuning.ONE_PASS
    assert one.clahe_rows(64 * 480, 752) == [(0, 64 * 480)]
    assert one.pyramid_streams(64, 480, 752) is None
    assert one.corner_streams(64, 480, 752) is None
    assert one.lk_streams(64, 1000) is None
    assert not one.host_checks_free
    cpu = _tuning.CPU
    assert cpu.clahe_rows(1000, 1 << 16) == [(r, r + 2) for r in range(0, 1000, 2)]
    assert cpu.pyramid_streams(16, 480, 752) is None and cpu.pyramid_streams(64, 480, 752) == 1
    assert cpu.corner_streams(1, 480, 752) is None and cpu.corner_streams(8, 480, 752) == 1
    assert cpu.lk_streams(6, 150) is None and cpu.lk_streams(8, 150) == 6 and cpu.lk_streams(8, 1000) == 1
    assert cpu.lk_streams(64, 20) == 8
    with pytest.raises(dataclasses.FrozenInstanceError):
        cpu.lk_max_lanes = 1


def test_lk_grouped_on_cpu_equals_one_pass(frames, monkeypatch):
    """The CPU grouping of streams (pyramids padded once, groups as views) == one pass, forward,
    with an initial guess and with the backward check."""
    prev, nxt, pts, valid = _lk_case(frames)
    guess = pts + torch.tensor([1.5, -0.75])

    def calls():  # the tensor LK's grouping (the fused LK's threads: tests/test_fused.py)
        kw = dict(lk_backend="tensor")
        return [lk.track_lk(prev, nxt, pts, valid, **kw), lk.track_lk(prev, nxt, pts, valid, init_pts=guess,
                                                                      max_level=1, **kw),
                lk.track_lk(prev, nxt, pts, valid, forward_backward=True, fb_max_level=1, **kw)]

    monkeypatch.setitem(_tuning.STRATEGIES, "cpu", _tuning.ONE_PASS)
    one = calls()
    for lanes, streams in ((1, 8), (pts.shape[1], 1), (2 * pts.shape[1], 8)):
        grouped = dataclasses.replace(_tuning.CPU, lk_max_lanes=lanes, lk_max_streams=streams)
        assert grouped.lk_streams(3, pts.shape[1]) is not None  # really grouped
        monkeypatch.setitem(_tuning.STRATEGIES, "cpu", grouped)
        assert _equal(calls(), one), (lanes, streams)


# ---------------------------------------------------------------- fast forms == reference
def _float_images(frames, dtype):
    """Real frames plus a non-integer offset field: sums are inexact, so an operation order change
    would show."""
    x = torch.from_numpy(np.stack([frames[0][:97, :131], frames[5][200:297, 300:431]]))[:, None].to(dtype)
    g = torch.Generator().manual_seed(0)
    return x + torch.rand(x.shape, generator=g, dtype=dtype) * 0.37


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_pyramid_fast_forms_equal_reference(frames, dtype):
    x = _float_images(frames, dtype)
    u8 = torch.from_numpy(np.stack([frames[0][:97, :131], frames[5][200:297, 300:431]]))[:, None]
    for img, rnd in ((x, False), (x, True), (u8, True)):
        fast = pyramid._build_pyramid_impl(img, 3, True, rnd)
        with _tuning.reference_forms():
            ref = pyramid._build_pyramid_impl(img, 3, True, rnd)
        assert _equal(fast.levels, ref.levels) and _equal(fast.grads, ref.grads)
    # the reference form with autograd gives the same values
    xg = x.clone().requires_grad_()
    withgrad = pyramid._build_pyramid_impl(xg, 3, True, False)
    fast = pyramid._build_pyramid_impl(x, 3, True, False)
    assert _equal([t.detach() for t in withgrad.levels], fast.levels)
    assert _equal([t.detach() for t in withgrad.grads], fast.grads)
    assert withgrad.levels[3].requires_grad and withgrad.grads[2].requires_grad


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_corner_fast_forms_equal_reference(frames, dtype):
    x = _float_images(frames, dtype)
    for harris in (False, True):
        fast = corners._response_impl(x, harris, 3, 0.04)
        with _tuning.reference_forms():
            ref = corners._response_impl(x, harris, 3, 0.04)
        withgrad = corners._response_impl(x.clone().requires_grad_(), harris, 3, 0.04)
        assert torch.equal(fast, ref) and torch.equal(withgrad.detach(), fast) and withgrad.requires_grad


def test_lk_fast_forms_equal_reference_uint8(frames):
    """Fixed point (8-bit images): the in-place steps, the window-view gather, the folded template
    and the skipped straight-through estimator give the reference values bit for bit; so do
    points that require a gradient (reference forms, straight-through)."""
    prev, nxt, pts, valid = _lk_case(frames)
    for kw in ({}, {"capturable": True}, {"forward_backward": True}):
        fast = lk.track_lk(prev, nxt, pts, valid, **kw)
        with _tuning.reference_forms():
            ref = lk.track_lk(prev, nxt, pts, valid, **kw)
        assert _equal(fast, ref), kw
    fast = lk.track_lk(prev, nxt, pts, valid)
    pg = pts.clone().requires_grad_()
    out, st = lk.track_lk(prev, nxt, pg, valid)
    assert out.requires_grad and torch.equal(out.detach(), fast[0]) and torch.equal(st, fast[1])
    (g,) = torch.autograd.grad(out[st].sum(), pg)
    assert torch.isfinite(g).all() and g.abs().sum() > 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_lk_fast_forms_equal_reference_float(frames, dtype):
    """Float images (float interpolation; non-integer grey levels): fast == reference, and images
    and points that require gradients give the same values."""
    prev, nxt, pts, valid = _lk_case(frames, B=2)
    g = torch.Generator().manual_seed(1)
    a = prev.to(dtype) + torch.rand(prev.shape, generator=g, dtype=dtype) * 0.37
    b = nxt.to(dtype) + torch.rand(nxt.shape, generator=g, dtype=dtype) * 0.37
    p = pts.to(dtype)
    fast = lk.track_lk(a, b, p, valid)
    with _tuning.reference_forms():
        ref = lk.track_lk(a, b, p, valid)
    assert _equal(fast, ref)
    out, st = lk.track_lk(a.clone().requires_grad_(), b.clone().requires_grad_(), p.clone().requires_grad_(), valid)
    assert out.requires_grad and torch.equal(out.detach(), fast[0]) and torch.equal(st, fast[1])


def test_lk_reference_kernels_bitwise():
    """The LK's small kernels one by one: fast == reference on non-integer data."""
    g = torch.Generator().manual_seed(2)
    f = torch.rand(40, 9 * 13, generator=g) * 255
    w = torch.rand(4, 40, generator=g)
    init = torch.rand(40, 1, generator=g)
    n, pitch = 7 * 13, 13
    fast = (lk._interp_flat(f, w, n, pitch), lk._interp_flat(f, w, n, pitch, 1, init), lk._scharr_flat(f, pitch, n))
    with _tuning.reference_forms():
        ref = (lk._interp_flat(f, w, n, pitch), lk._interp_flat(f, w, n, pitch, 1, init), lk._scharr_flat(f, pitch, n))
    assert _equal(fast, ref)
    fi = f.int()  # the int32 derivative windows of the fixed-point template
    with _tuning.reference_forms():
        ref_i = lk._scharr_flat(fi, pitch, n)
    assert torch.equal(lk._scharr_flat(fi, pitch, n), ref_i) and ref_i.dtype == torch.int32
    # the straight-through estimator: the value of ``hard`` exactly (also far from ``soft``, where
    # ``soft + (hard - soft)`` would round), the gradient of ``soft``
    soft = (torch.rand(1000, generator=g) * 1000).requires_grad_()
    hard = torch.floor(soft.detach() / 97.0) / 3.0
    v = lk._ste(soft, hard)
    assert torch.equal(v.detach(), hard)
    (gs,) = torch.autograd.grad(v.sum(), soft)
    assert torch.equal(gs, torch.ones_like(gs))


# ------------------------------------------------------------------- doors == _impl layer
_CHECK_NAMES = ("as_image_batch", "as_float_image", "check_points", "check_shape", "default_valid")


def _forbid_checks(monkeypatch):
    def boom(*a, **k):
        raise AssertionError("an _impl called an input check")

    for mod in (equalize, pyramid, corners, masks, lk, ransac):
        for name in _CHECK_NAMES:
            if hasattr(mod, name):
                monkeypatch.setattr(mod, name, boom)


def test_impl_layer_equals_doors_and_checks_nothing(frames, monkeypatch):
    """A tracker step's kernels through the ``_impl`` layer (validated once, as a pipeline does):
    bit for bit the public functions' results, with no visit to the input checks."""
    imgs = torch.from_numpy(np.stack([frames[0], frames[3]]))[:, None]
    nxt_imgs = torch.from_numpy(np.stack([frames[1], frames[4]]))[:, None]
    B, _, H, W = imgs.shape
    pts = torch.from_numpy(np.stack([_corners(frames[0], 120)[:100], _corners(frames[3], 120)[:100]]))
    valid = torch.ones(B, 100, dtype=torch.bool)
    valid[0, -7:] = False
    cnt = torch.arange(100).flip(0).expand(B, 100).contiguous()
    n_max = torch.tensor([40, 25])
    fv = valid.clone()
    guess = pts + 0.5

    def doors():
        eq, eq2 = equalize.clahe(imgs), equalize.clahe(nxt_imgs)
        P, Q = pyramid.build_pyramid(eq, 3, with_gradients=False), pyramid.build_pyramid(eq2, 3, with_gradients=False)
        out, st = lk.track_lk(P, Q, pts, valid)
        out1, st1 = lk.track_lk(P, Q, pts, valid, init_pts=guess, max_level=1, forward_backward=True, fb_max_level=1)
        res = ransac.find_fundamental(pts.double(), out.double(), fv & st, threshold=1.0, confidence=0.99, seed=7)
        keep, mask = masks.distance_mask(out, cnt, st, 30, height=H, width=W)
        gp, gv = corners.good_features_to_track(eq2, n_max, 0.01, 30, mask=mask)
        return [eq, eq2, *P.levels, out, st, out1, st1, res.F, res.inliers, res.ok, res.num_iters, keep, mask, gp, gv]

    ref = doors()
    states = ransac._seeds(B, seed=7)
    opts = lk.LKOptions(21, 3, 30, 0.01, 1e-4, True, False, backend="fused")  # the doors resolve "fused" here
    opts1 = dataclasses.replace(opts, max_level=1)
    _forbid_checks(monkeypatch)
    with pytest.raises(AssertionError, match="input check"):
        doors()
    eq, eq2 = (equalize._clahe_impl(x[:, 0], 3.0, 8, 8).image[:, None] for x in (imgs, nxt_imgs))
    P, Q = (pyramid._build_pyramid_impl(x, 3, False, True, pad=22, backend="fused") for x in (eq, eq2))
    out, st, _ = lk._track_lk_impl(P, Q, pts, valid, None, opts)
    # the forward-backward check: the door's one op (both passes) == the two calls a stage makes
    out1, st1, _ = lk._track_lk_impl(P, Q, pts, valid, guess, opts1)
    st1 = lk._forward_backward_impl(P, Q, pts, out1, st1, opts1, 1, 0.5, True).status
    res = ransac._find_fundamental_impl(pts.double(), out.double(), fv & st, 1.0, 0.99, 1000, states, None)
    keep, mask, _ = masks._distance_mask_impl(out, cnt, st, 30.0, torch.full((B, H, W), 255, dtype=torch.uint8))
    gp, gv, _ = corners._good_features_impl(eq2, n_max, 0.01, 30.0, mask != 0, False, 3, 0.04, None)
    got = [eq, eq2, *P.levels, out, st, out1, st1, res.F, res.inliers, res.ok, res.num_iters, keep, mask, gp, gv]
    assert len(got) == len(ref)
    for k, (a, b) in enumerate(zip(got, ref)):
        assert torch.equal(a, b) or (a.is_floating_point() and torch.equal(a.isnan(), b.isnan())
                                     and torch.equal(a.nan_to_num(), b.nan_to_num())), k


def test_lk_options_checked_and_normalised():
    o = lk.LKOptions(15, 2, 500, -1.0, 1e-3, 1, 1)
    assert o.win_size == (15, 15) and o.max_iters == 100 and o.eps == 0.0
    assert o.fixed_point is True and o.capturable is True and isinstance(o.min_eig_threshold, float)
    assert lk.LKOptions((21, 9)).win_size == (21, 9)
    assert dataclasses.replace(o, max_level=0).win_size == (15, 15)
    with pytest.raises(ConfigError, match="win_size"):
        lk.LKOptions((21, 2))
    with pytest.raises(ConfigError, match="max_level"):
        lk.LKOptions(21, -1)
    with pytest.raises(dataclasses.FrozenInstanceError):
        o.max_level = 1


def test_ransac_seeds_once():
    assert ransac._seeds(3) == [2**64 - 1] * 3  # OpenCV's own state
    assert ransac._seeds(2, seed=[0, 5]) == [2**64 - 1, 5]
    assert ransac._seeds(2, seed=-2) == [2**64 - 2] * 2
    g1, g2 = torch.Generator().manual_seed(4), torch.Generator().manual_seed(4)
    assert ransac._seeds(2, generator=g1) == ransac._seeds(2, generator=g2)
