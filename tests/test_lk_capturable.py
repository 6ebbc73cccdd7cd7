"""The capturable LK path (``LKOptions(capturable=True)``, the capturable tracker's): the same results
as the default (eager, early-exit) path bit for bit, no host sync, a launch count independent of the
batch, the iteration budget and its overflow flag, gradients."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
import torch

from tests.conftest import DTYPES, load_gray, sample_frames
from torch_frontend import lk
from torch_frontend.errors import ConfigError
from torch_frontend.lk import capturable as lk_capturable
from torch_frontend.pyramid import build_pyramid
from torch_frontend.testing.dispatch_count import OpCounter

#: aten ops (kernels) per iteration of the capturable path (fixed point, float32 points, no gradient):
#: searchsorted, the patch gather, 5 for the weights (OpenCV's iw11 by one ``mm``), conv2d +
#: floor_divide, 2 for b, 3 for the step, 2 for the step test, 2 for the oscillation test, the
#: window test's gather, 1 ``all``, 1 update (see the lk module notes)
OPS_PER_ITERATION = 21
#: aten ops per level of the full budget's tail split (lk.capturable._TAIL_FROM): the seat sort (2),
#: 10 gathers of the lanes' state, the flag of the lanes left without a seat (3), 3 write-backs, less
#: the 2 ops the split saves at the first tail iteration
TAIL_OPS = 16
#: aten ops per level of each further stage of the split (lk.capturable._split_plan): the same, plus
#: the write-back of the sub-batch's own flag of lanes left without a seat
STAGE_OPS = 17


@pytest.fixture(scope="module")
def frames():
    return [load_gray(p) for p in sample_frames("cam0")]


def _crop(img):
    return np.ascontiguousarray(img[120:300, 250:520])


def _warp(img, tx, ty, rot):
    h, w = img.shape
    M = cv2.getRotationMatrix2D((w / 2, h / 2), rot, 1.0)
    M[:, 2] += (tx, ty)
    return cv2.warpAffine(img, M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)


def _batch(frames, B=3, n=48):
    """``B`` streams of 180x270 crops: consecutive frames, then warps with growing motion (shifts to
    12 px, rotation): converged, oscillating and capped lanes; points at and beyond every border;
    an eigenvalue failure (a flat patch)."""
    prev, nxt, pts = [], [], []
    for b in range(B):
        a = _crop(frames[2 * b])
        c = _crop(frames[2 * b + 1]) if b == 0 else _warp(_crop(frames[2 * b + 1]), 5.0 * b + 2, -3.5 * b, 2.0 * b)
        if b == B - 1:
            a = a.copy()
            a[60:110, 100:150] = 128  # flat: fails the eigenvalue test
        g = cv2.goodFeaturesToTrack(a, n - 12, 0.01, 6).reshape(-1, 2).astype(np.float32)
        h, w = a.shape
        edge = np.float32([[-25, 40], [-10.3, 90], [0.5, 3], [w - 1, 60.2], [w + 9.5, 100], [120, -10.5],
                           [60, h - 0.5], [200, h + 10.5], [125, 85], [300, 20], [-21.0, 50], [w + 9.99, h + 9.99]])
        p = np.concatenate([g, edge])[:n]
        prev.append(a), nxt.append(c), pts.append(np.pad(p, ((0, n - len(p)), (0, 0)), constant_values=50.0))
    return (torch.from_numpy(np.stack(prev))[:, None], torch.from_numpy(np.stack(nxt))[:, None],
            torch.from_numpy(np.stack(pts)))


def _both(P, Q, pts, valid, init, opts, **kw):
    """``LKResult`` of the default and of the capturable path: the overflow flag is a ``(B,)``
    tensor on the capturable path always, on the default one when some budget is below
    ``max_iters`` (else None: exact)."""
    e = lk._track_lk_impl(P, Q, pts, valid, init, dataclasses.replace(opts, capturable=False, **kw))
    with lk.exact_float32(pts.device):  # CUDA: TF32 off, as the tracker's step (the convolution form)
        s = lk._track_lk_impl(P, Q, pts, valid, init, dataclasses.replace(opts, capturable=True, **kw))
    assert isinstance(e, lk.LKResult) and isinstance(s, lk.LKResult)
    assert (e.overflow is None) == (not dataclasses.replace(opts, **kw).inexact)
    assert s.overflow is not None and s.overflow.shape == (pts.shape[0],)
    return e, s


def _assert_same(e, s):
    """Bit for bit (a default-path overflow of None is the all-False flag: the full budget)."""
    e = e._replace(overflow=torch.zeros_like(s.overflow) if e.overflow is None else e.overflow)
    for name, a, b in zip(("next_pts", "status", "overflow"), e, s):
        assert a.dtype == b.dtype and a.shape == b.shape, name
        assert torch.equal(a.nan_to_num(7e7) if a.is_floating_point() else a,
                           b.nan_to_num(7e7) if b.is_floating_point() else b), \
            (name, (a != b).sum().item() if a.shape == b.shape else None)


@pytest.fixture
def every_stage(monkeypatch):
    """Every stage of the full budget's split at the tests' small batches (``_STAGE_MIN_SEATS`` 0)."""
    monkeypatch.setattr(lk_capturable, "_STAGE_MIN_SEATS", 0)


@pytest.mark.parametrize("mode", ["uint8", "float", "fixed_on_float"])
@pytest.mark.parametrize("dtype", DTYPES, ids=["f32", "f64"])
def test_capturable_equals_eager(frames, device, dtype, mode, every_stage):
    """Bit for bit, a mixed batch and one stream, without and with initial guesses (NaN and inf ones
    too), padded lanes, points at and beyond the borders: fixed point (8-bit images), float
    interpolation (float images) and fixed point on float images, float32 and float64 points."""
    prev, nxt, pts = _batch(frames)
    if mode != "uint8":
        prev, nxt = prev.to(dtype), nxt.to(dtype)
    prev, nxt, pts = prev.to(device), nxt.to(device), pts.to(device, dtype)
    P, Q = build_pyramid(prev, 3, with_gradients=False), build_pyramid(nxt, 3, with_gradients=False)
    valid = torch.ones(pts.shape[:2], dtype=torch.bool, device=device)
    valid[:, 7::11] = False
    init = pts + torch.tensor([3.0, -2.0], dtype=dtype, device=device)
    init[:, ::9] = float("nan")
    init[1, 4, 0] = float("inf")
    opts = lk.LKOptions(fixed_point=mode != "float")
    for i, (pp, qq, x, v, g) in enumerate([(P, Q, pts, valid, None), (P, Q, pts, valid, init),
                                           (P.select(slice(2, 3)), Q.select(slice(2, 3)), pts[2:], valid[2:], None)]):
        e, s = _both(pp, qq, x, v, g, opts)
        _assert_same(e, s)
        assert e.overflow is None and not s.overflow.any()  # full budget: exact
        if i == 0:
            assert e[1].sum() > 0.6 * e[1].numel() and not e[1].all()  # tracks, and lanes lost at the borders
    # one level, a non-square window, eps 0 (steps to the cap), few iterations; the one- and
    # two-level cases with a tail sub-batch of half the lanes (seats for every lane still running
    # after 8 iterations there: test_tail_split)
    for kw in (dict(max_level=0, tail_share=2), dict(max_level=1, win_size=(15, 9), tail_share=2),
               dict(eps=0.0, max_iters=7)):
        _assert_same(*_both(P, Q, pts, valid, init, dataclasses.replace(opts, **kw)))


def test_capturable_equals_eager_at_the_largest_derivatives(device):
    """Black and white squares: Scharr derivatives at their bound 16 x 255 = 4080 (the iterations
    hold them as int16), windows full of them, a sub-pixel shift; bit for bit."""
    yy, xx = np.mgrid[:96, :128]
    board = (((yy // 6) + (xx // 6)) % 2 * 255).astype(np.uint8)
    shifted = cv2.warpAffine(board, np.float32([[1, 0, 1.37], [0, 1, -0.61]]), (128, 96),
                             flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
    assert np.abs(cv2.Scharr(board, cv2.CV_16S, 1, 0)).max() == 16 * 255
    g = np.stack(np.meshgrid(np.arange(15.0, 113.0, 6.3), np.arange(15.0, 81.0, 5.7)), -1).reshape(1, -1, 2)
    pts = torch.from_numpy(g.astype(np.float32)).to(device)
    prev = torch.from_numpy(board)[None, None].to(device)
    nxt = torch.from_numpy(shifted)[None, None].to(device)
    P, Q = build_pyramid(prev, 3, with_gradients=False), build_pyramid(nxt, 3, with_gradients=False)
    valid = torch.ones(pts.shape[:2], dtype=torch.bool, device=device)
    # every lane every iteration: on a board most lanes oscillate for all 30 iterations, more than
    # the split's seats (the stream's overflow flag says so; never on the real frames measured)
    e, s = _both(P, Q, pts, valid, None, lk.LKOptions(tail_share=1))
    _assert_same(e, s)
    assert e.status.sum() > pts.shape[1] // 2  # most lanes track


def test_capturable_in_reference_forms_and_forward_backward(frames):
    """The reference (differentiable) forms and the backward check give the same results too."""
    from torch_frontend import _tuning

    prev, nxt, pts = _batch(frames)
    P, Q = build_pyramid(prev, 3, with_gradients=False), build_pyramid(nxt, 3, with_gradients=False)
    valid = torch.ones(pts.shape[:2], dtype=torch.bool)
    opts = lk.LKOptions()
    ref = _both(P, Q, pts, valid, None, opts)[0]
    with _tuning.reference_forms():
        _assert_same(ref, _both(P, Q, pts, valid, None, opts)[1])
    out, st = ref[:2]
    for lv, from_start in ((1, True), (3, False)):
        # the path by the keyword (it overrides opts.capturable) and by the options
        fb = [lk._forward_backward_impl(P, Q, pts, out, st, opts, lv, 0.5, from_start, capturable=c) for c in (False, True)]
        assert isinstance(fb[0], lk.FlowBackResult) and fb[0].overflow is None
        assert torch.equal(fb[0].status, fb[1].status) and not fb[1].overflow.any()
        assert torch.equal(fb[0].status, lk._forward_backward_impl(P, Q, pts, out, st, opts, lv, 0.5, from_start).status)
        on_opts = lk._forward_backward_impl(P, Q, pts, out, st, dataclasses.replace(opts, capturable=True), lv, 0.5,
                                            from_start)
        assert torch.equal(on_opts.status, fb[1].status) and torch.equal(on_opts.overflow, fb[1].overflow)


def test_budget_and_overflow(frames):
    """``iter_budget`` below the iterations a lane needs sets the overflow flag of its stream (never
    with the full budget); both paths agree bit for bit under any budget, and a stream whose flag
    is False has OpenCV's (the full budget's) exact results."""
    prev, nxt, pts = _batch(frames)
    P, Q = build_pyramid(prev, 3, with_gradients=False), build_pyramid(nxt, 3, with_gradients=False)
    valid = torch.ones(pts.shape[:2], dtype=torch.bool)
    opts = lk.LKOptions()
    full = _both(P, Q, pts, valid, None, opts)[1]
    assert not full[2].any()
    seen_mixed = False
    for budget in (0, 1, 3, 6, 30, 60):
        e, s = _both(P, Q, pts, valid, None, opts, iter_budget=budget)
        _assert_same(e, s)
        if budget >= 30:
            assert not s[2].any()
        elif budget <= 3:
            assert s[2].all()  # every stream has moving points
        exact = ~s[2]
        assert torch.equal(s[0][exact], full[0][exact]) and torch.equal(s[1][exact], full[1][exact])
        seen_mixed |= bool(s[2].any() and exact.any())
        if s[2].any():
            assert not torch.equal(s[0], full[0])  # the flag is not raised for nothing here
    # per-level budgets (level 0 first, the last entry for the levels above)
    for budget, inexact in (((2, 30), True), ((30, 2), True), ((30,), False), ([40, 35], False)):
        e, s = _both(P, Q, pts, valid, None, opts, iter_budget=budget)
        _assert_same(e, s)
        assert bool(s[2].any()) == inexact
        if not inexact:
            assert torch.equal(s[0], full[0]) and torch.equal(s[1], full[1])
    o = lk.LKOptions(iter_budget=[4, 9])
    assert o.iter_budget == (4, 9) and [o.budget_at(lv) for lv in range(4)] == [4, 9, 9, 9] and o.inexact
    assert lk.LKOptions(max_iters=20, iter_budget=50).budget == 20 and lk.LKOptions().budget == 30
    for bad in (-1, 2.5, True, (), (3, -1)):
        with pytest.raises(ConfigError, match="iter_budget"):
            lk.LKOptions(iter_budget=bad)
    # with a generous budget a single-stream subset can be exact while another overflows
    e, s = _both(P.select(slice(0, 2)), Q.select(slice(0, 2)), pts[:2], valid[:2], None, opts, iter_budget=12)
    _assert_same(e, s)
    assert seen_mixed or not s[2].all()


@pytest.mark.parametrize("dtype", DTYPES, ids=["f32", "f64"])
def test_tail_split(frames, dtype, every_stage):
    """The full budget's split (``tail_share``): after 8 iterations on every lane the rest run on a
    sub-batch, the running lanes first. With seats for every running lane the result is the eager
    path's bit for bit (lanes did need more than 8 iterations: an 8-iteration budget differs); a
    running lane left without a seat raises its stream's overflow flag, and the streams without
    the flag keep the exact results; ``tail_share=1`` runs every lane every iteration."""
    prev, nxt, pts = _batch(frames)
    pts = pts.to(dtype)
    # one level: the crops' shifts of up to 12 px keep dozens of lanes iterating past 8
    P, Q = build_pyramid(prev, 0, with_gradients=False), build_pyramid(nxt, 0, with_gradients=False)
    valid = torch.ones(pts.shape[:2], dtype=torch.bool)
    opts = lk.LKOptions(max_level=0)
    exact = _both(P, Q, pts, valid, None, opts, tail_share=1)
    _assert_same(*exact)
    e = exact[0]
    short = _both(P, Q, pts, valid, None, opts, iter_budget=8)[1]  # lanes that need more than 8
    flags = {}
    for share in (2, 4, 8):  # 72, 36, 18 seats of 144 lanes
        s = _both(P, Q, pts, valid, None, opts, tail_share=share)[1]
        keep = ~s.overflow
        assert torch.equal(s.pts[keep], e.pts[keep]) and torch.equal(s.status[keep], e.status[keep])
        if s.overflow.any():
            assert not torch.equal(s.pts[~keep], e.pts[~keep])  # the flag is not raised for nothing
        flags[share] = s.overflow
    # fewer seats, more flags; the tail made exact a stream whose lanes needed more than 8
    # iterations; with 18 seats some stream is left short
    assert (flags[2] <= flags[4]).all() and (flags[4] <= flags[8]).all() and flags[8].any()
    assert (short.overflow & ~flags[2]).any()
    # the tracker's four levels: the default split is exact on the same lanes (at most 3 a stream
    # still iterate after 8 iterations there)
    P4, Q4 = build_pyramid(prev, 3, with_gradients=False), build_pyramid(nxt, 3, with_gradients=False)
    e4, s4 = _both(P4, Q4, pts, valid, None, lk.LKOptions())
    _assert_same(e4, s4)
    for bad in (0, True, 1.5):
        with pytest.raises(ConfigError, match="tail_share"):
            lk.LKOptions(tail_share=bad)


@pytest.mark.parametrize("dtype", DTYPES, ids=["f32", "f64"])
def test_no_syncs_and_kernels_independent_of_batch(frames, dtype):
    """After a warm-up call (per-size constants cached): 0 host syncs for a whole forward and
    backward LK, the same kernel count for B = 1 and B = 16, and the per-iteration op count."""
    a, b = _crop(frames[0]), _crop(frames[1])
    p = cv2.goodFeaturesToTrack(a, 40, 0.01, 6).reshape(-1, 2).astype(np.float32)[:32]
    counts = {}
    for B in (1, 16):
        P = build_pyramid(torch.from_numpy(np.stack([a] * B))[:, None], 3, with_gradients=False)
        Q = build_pyramid(torch.from_numpy(np.stack([b] * B))[:, None], 3, with_gradients=False)
        pts = torch.from_numpy(np.stack([p] * B)).to(dtype)
        valid = torch.ones(pts.shape[:2], dtype=torch.bool)
        for budget in (2, 3) if B > 1 else (2, 3, None):
            opts = lk.LKOptions(capturable=True, iter_budget=budget)

            def call(P, Q, pts, valid, opts):
                out, st, ov = lk._track_lk_impl(P, Q, pts, valid, pts, opts)
                return lk._forward_backward_impl(P, Q, pts, out, st, opts, 1, 0.5, True)

            call(P, Q, pts, valid, opts)  # warm-up: caches
            with OpCounter() as c:
                call(P, Q, pts, valid, opts)
            assert c.syncs == 0, c.summary()
            counts[B, budget] = c.kernels
    for budget in (2, 3):
        assert counts[1, budget] == counts[16, budget]
    per_iteration = (counts[1, 3] - counts[1, 2]) / (4 + 2)  # 4 forward levels + 2 backward levels
    # float64 points: OpenCV's float32 weights cost two conversions, the step test none
    bound = OPS_PER_ITERATION + 2 * (dtype == torch.float64)
    assert per_iteration <= bound, per_iteration
    # linear in the budget: 27 more iterations on 6 levels (less the overflow bookkeeping), plus the
    # full budget's split on each level (32 lanes: 16 seats from iteration 8)
    from torch_frontend.lk.capturable import _split_plan

    stages = len(_split_plan(32, 30, lk.LKOptions().tail_share))
    full = counts[1, 3] + 27 * 6 * per_iteration + 6 * (TAIL_OPS + (stages - 1) * STAGE_OPS)
    assert full - 12 <= counts[1, None] <= full


@pytest.mark.parametrize("fixed", [False, True], ids=["float", "fixed_point"])
@pytest.mark.parametrize("dtype", DTYPES, ids=["f32", "f64"])
def test_capturable_gradients(frames, device, dtype, fixed):
    """Gradients of the capturable path w.r.t. the points are those of the default path bit for bit;
    w.r.t. float images they are equal to rounding (allclose, ~1e-7 relative in float32): the backward
    adds the per-iteration window gradients into the images in another order (all lanes every
    iteration vs the compacted lanes)."""
    a = torch.from_numpy(_crop(frames[0])[20:140, 40:200]).to(device, dtype)[None, None]
    b = torch.from_numpy(_crop(frames[1])[20:140, 40:200]).to(device, dtype)[None, None]
    p = cv2.goodFeaturesToTrack(_crop(frames[0])[20:140, 40:200], 10, 0.01, 8).reshape(-1, 2)
    p = torch.from_numpy(p + np.float32([0.37, 0.21])).to(device, dtype)[None]
    c = torch.randn(p.shape, generator=torch.Generator().manual_seed(0), dtype=dtype).to(device)
    res = []
    for cap in (False, True):
        A, B, X = a.clone().requires_grad_(), b.clone().requires_grad_(), p.clone().requires_grad_()
        out, st = lk.track_lk(A, B, X, max_level=1, capturable=cap, fixed_point=fixed)
        res.append((out.detach(), st) + torch.autograd.grad((out * c).sum(), (A, B, X)))
    (o1, s1, ga1, gb1, gp1), (o2, s2, ga2, gb2, gp2) = res
    assert torch.equal(o1, o2) and torch.equal(s1, s2) and s1.sum() >= 8
    assert torch.equal(gp1, gp2)
    tol = dict(rtol=1e-5, atol=1e-6) if dtype == torch.float32 else dict(rtol=1e-12, atol=1e-13)
    for g1, g2 in ((ga1, ga2), (gb1, gb2)):
        assert g1.abs().sum() > 0
        torch.testing.assert_close(g2, g1, **tol)


def test_split_plan():
    """The full budget's stages: ``1/tail_share`` of the lanes from iteration 8 (at least 16), a
    quarter of those from 12 (at least 8) from ``tail_share`` 8 up; a stage that would seat every
    lane of the one before is left out; none for ``tail_share`` 1, an odd rest or a short budget."""
    from torch_frontend.lk.capturable import _split_plan

    assert _split_plan(150, 30, 8) == ((8, 19),)  # the second stage only after 512 seats or more
    assert _split_plan(4096, 30, 8) == ((8, 512), (12, 128))
    assert _split_plan(9600, 30, 8) == ((8, 1200), (12, 300))
    assert _split_plan(9600, 30, 16) == ((8, 600), (12, 150))
    assert _split_plan(9600, 30, 2) == ((8, 4800),)  # a smaller share: the first stage only
    assert _split_plan(9600, 12, 8) == ((8, 1200),)
    assert _split_plan(8, 30, 8) == ()
    assert _split_plan(150, 30, 1) == () and _split_plan(150, 31, 8) == () and _split_plan(150, 8, 8) == ()
    with pytest.MonkeyPatch.context() as mp:  # every stage, whatever the seats (the tests' small batches)
        mp.setattr(lk_capturable, "_STAGE_MIN_SEATS", 0)
        assert _split_plan(150, 30, 8) == ((8, 19), (12, 8))
        assert _split_plan(24, 30, 8) == ((8, 16), (12, 8))
        assert _split_plan(16, 30, 8) == ((12, 8),)  # 16 seats would seat every lane
        assert _split_plan(144, 30, 2) == ((8, 72),)


def test_exact_float32_scopes_tf32_off_and_restores_it():
    """``lk.exact_float32``: on CUDA, matmul and cuDNN TF32 are off inside (the capturable LK's
    convolution form needs full float32 inputs: ``_exact_float32``) and the caller's settings come
    back after, also after an error; elsewhere a no-op. The flags are plain settings, so this runs
    without a GPU."""
    mm, cudnn = torch.backends.cuda.matmul, torch.backends.cudnn
    old = mm.allow_tf32, cudnn.allow_tf32
    try:
        mm.allow_tf32, cudnn.allow_tf32 = False, True
        assert not lk_capturable._exact_float32("cuda") and lk_capturable._exact_float32("cpu")
        with lk.exact_float32(torch.device("cuda")):
            assert (mm.allow_tf32, cudnn.allow_tf32) == (False, False) and lk_capturable._exact_float32("cuda")
        assert (mm.allow_tf32, cudnn.allow_tf32) == (False, True)
        with pytest.raises(RuntimeError, match="inside"):
            with lk.exact_float32(torch.device("cuda")):
                raise RuntimeError("inside")
        assert (mm.allow_tf32, cudnn.allow_tf32) == (False, True)
        with lk.exact_float32(torch.device("cpu")):
            assert cudnn.allow_tf32  # not touched for another device
    finally:
        mm.allow_tf32, cudnn.allow_tf32 = old
