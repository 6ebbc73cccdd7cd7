"""The capturable detection kernels (issue 18): CLAHE, goodFeaturesToTrack and setMask with
``capturable=True`` give the default path's results (and OpenCV's), make no host sync, launch a
number of kernels independent of B and of the data, and flag ``overflow`` where their fixed budget
is too small (and only there: wherever the flag is False the result is the default path's)."""

from __future__ import annotations

import glob

import cv2
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torch_frontend.corners import (
    GFTT_BUDGET,
    GreedyBudget,
    _gftt_from_response,
    _good_features_impl,
    _harris_impl,
    _min_eigen_impl,
    _response_impl,
)
from torch_frontend.equalize import _clahe_impl
from torch_frontend.masks import MASK_ROUNDS, _distance_mask_impl, fisheye_mask
from torch_frontend.testing.dispatch_count import OpCounter

from .conftest import SHARED_DATA, load_gray, sample_frames

_CLAHE = cv2.createCLAHE(3.0, (8, 8))


def _frames(camera="cam0", n=24):
    return [load_gray(p) for p in sample_frames(camera)[:n]]


@pytest.fixture(scope="module")
def eq_frames():
    return np.stack([_CLAHE.apply(f) for f in _frames()])


def _gftt(x, mc, md=30.0, mask=None, cap=150, harris=False, **kw):
    return _good_features_impl(x, mc, 0.01, float(md), mask, harris, 3, 0.04, cap, **kw)


def _same(a, b):
    return all(torch.equal(u.cpu(), v.cpu()) for u, v in zip(a, b))


def _tracked_mask(frames, device, md=30, seed=1):
    """The tracker's steady state in kernels: OpenCV corners of the next frames, jittered, random
    track counts, setMask -> (n_max, mask, keep, inputs)."""
    rng = np.random.default_rng(seed)
    cs = [cv2.goodFeaturesToTrack(f, 150, 0.01, md)[:, 0] for f in frames]
    N = max(len(c) for c in cs)
    pts = np.zeros((len(frames), N, 2), np.float32)
    val = np.zeros((len(frames), N), bool)
    for b, c in enumerate(cs):
        pts[b, :len(c)] = c + rng.normal(0, 2.0, c.shape)
        val[b, :len(c)] = True
    cnt = rng.integers(1, 8, val.shape)
    args = (torch.from_numpy(pts).to(device), torch.from_numpy(cnt).to(device), torch.from_numpy(val).to(device))
    return args


# ---------------------------------------------------------------------------------------------
# CLAHE


@pytest.mark.parametrize("wh", [(752, 480), (749, 477), (752, 477), (749, 480)])
def test_clahe_capturable_equals_default_and_opencv(device, wh):
    w, h = wh
    batch = np.stack([f[:h, :w] for f in _frames(n=3)])
    x = torch.from_numpy(batch).to(device)
    res, dflt = _clahe_impl(x, 3.0, 8, 8, capturable=True), _clahe_impl(x, 3.0, 8, 8)
    assert res.overflow is None and dflt.overflow is None  # no budget: exact on both paths
    got = res.image
    assert got.dtype == torch.uint8 and torch.equal(got, dflt.image)
    ref = np.stack([_CLAHE.apply(np.ascontiguousarray(b)) for b in batch])
    assert np.array_equal(got.cpu().numpy(), ref)
    assert torch.equal(_clahe_impl(x[1:2], 3.0, 8, 8, capturable=True).image, got[1:2])  # B = 1 = its row


@pytest.mark.parametrize("clip,grid", [(2.0, (4, 4)), (40.0, (8, 8)), (0.0, (8, 8)), (3.0, (6, 5))])
def test_clahe_capturable_other_parameters(clip, grid):
    x = torch.from_numpy(np.stack([f[100:300, 50:350] for f in _frames(n=2)]))
    assert torch.equal(_clahe_impl(x, clip, *grid, capturable=True).image, _clahe_impl(x, clip, *grid).image)


def test_clahe_capturable_no_sync_and_kernels_independent_of_batch(device):
    f = _frames(n=4)
    counts = []
    for B in (1, 16):
        x = torch.from_numpy(np.stack([f[b % 4][:120, :160] for b in range(B)])).to(device)
        _clahe_impl(x, 3.0, 8, 8, capturable=True)  # warm-up: cached geometry
        with OpCounter() as c:
            _clahe_impl(x, 3.0, 8, 8, capturable=True)
        assert c.syncs == 0, c.summary()
        counts.append(c.kernels)
    assert counts[0] == counts[1]


# ---------------------------------------------------------------------------------------------
# goodFeaturesToTrack


def test_gftt_capturable_equals_default_and_opencv(eq_frames, device, dtype):
    """Mixed batch (per-stream counts incl. 0), uint8 and float images, vs default and cv2."""
    imgs = eq_frames[:4]
    x = torch.from_numpy(imgs)[:, None].to(device)
    if dtype == torch.float64:
        x = x.to(dtype)  # float64 response: the sort path of the ranking
    mc = torch.tensor([150, 37, 0, 150], device=device)
    pts, valid, ovf = _gftt(x, mc, capturable=True)
    assert pts.shape == (4, 150, 2) and valid.shape == (4, 150) and ovf.shape == (4,) and not ovf.any()
    ref = _gftt(x, mc)
    assert ref.overflow is None and _same((pts, valid), ref[:2])
    for b in (0, 1):
        ref = cv2.goodFeaturesToTrack(imgs[b], int(mc[b]), 0.01, 30)[:, 0]
        assert np.array_equal(pts[b][valid[b]].cpu().numpy(), ref)
    assert not valid[2].any() and not pts[2].any()
    one = _gftt(x[1:2], mc[1:2], capturable=True)  # B = 1 equals its row of the batch
    assert _same(one, (pts[1:2], valid[1:2], ovf[1:2]))


def test_gftt_capturable_with_vins_mask(eq_frames, device):
    """The tracker's use: setMask (capturable too), then GFTT(n_max = MAX_CNT - kept, mask)."""
    imgs = eq_frames[:4]
    pts, cnt, val = _tracked_mask(eq_frames[1:5], device)
    mask = torch.full((4, 480, 752), 255, dtype=torch.uint8, device=device)
    keep, m, movf = _distance_mask_impl(pts, cnt, val, 30.0, mask.clone(), capturable=True)
    ref = _distance_mask_impl(pts, cnt, val, 30.0, mask.clone())
    assert not movf.any() and ref.overflow is None and _same((keep, m), ref[:2])
    n_max = (150 - keep.sum(1)).clamp_min(0)
    x = torch.from_numpy(imgs)[:, None].to(device)
    got = _gftt(x, n_max, mask=m != 0, capturable=True)
    assert not got[2].any() and _same(got[:2], _gftt(x, n_max, mask=m != 0))
    for b in range(4):
        ref = cv2.goodFeaturesToTrack(imgs[b], int(n_max[b]), 0.01, 30, mask=m[b].cpu().numpy())
        assert np.array_equal(got[0][b][got[1][b]].cpu().numpy(), ref[:, 0])


def test_gftt_capturable_edge_cases(eq_frames):
    crop = torch.from_numpy(np.ascontiguousarray(eq_frames[3][100:160, 150:250]))[None, None]
    x = torch.cat([crop, crop.flip(-1)])
    # capacity far above the candidates; tiny image (block > pixels); Harris; min_distance < 1
    for kw in (dict(cap=400, mc=torch.tensor([400, 3])), dict(cap=60, mc=torch.tensor([60, 60]), harris=True),
               dict(cap=50, mc=torch.tensor([50, 50]), md=0.5), dict(cap=30, mc=torch.tensor([30, 5]), md=7.6)):
        mc = kw.pop("mc")
        got = _gftt(x, mc, capturable=True, **kw)
        assert not got.overflow.any() and _same(got[:2], _gftt(x, mc, **kw)[:2]), kw
    # other box sizes of the response (its stacked box sums), non-integer float grey levels
    xf = x.to(torch.float32) + torch.rand(x.shape, generator=torch.Generator().manual_seed(0))
    for block, img in ((1, x.double()), (2, xf), (5, xf.double())):
        assert torch.equal(_min_eigen_impl(img, block, True), _min_eigen_impl(img, block))
        assert torch.equal(_harris_impl(img, block, 0.04, True), _harris_impl(img, block, 0.04))
        mc = torch.tensor([40, 40])
        got = _good_features_impl(img, mc, 0.01, 10.0, None, False, block, 0.04, 40, capturable=True)
        assert not got.overflow.any() and _same(got[:2], _good_features_impl(img, mc, 0.01, 10.0, None, False,
                                                                             block, 0.04, 40)[:2])
    # max_corners 0 everywhere, capacity 0
    p, v, o = _gftt(x, torch.zeros(2, dtype=torch.long), capturable=True)
    assert not v.any() and not o.any()
    p, v, o = _gftt(x, torch.zeros(2, dtype=torch.long), cap=0, capturable=True)
    assert p.shape == (2, 0, 2) and v.shape == (2, 0) and not o.any()
    # empty mask: nothing, no overflow
    p, v, o = _gftt(x, torch.tensor([10, 10]), mask=torch.zeros(2, 60, 100, dtype=torch.bool), capturable=True)
    assert not v.any() and not o.any()
    with pytest.raises(ValueError, match="capacity"):
        _gftt(x, torch.tensor([10, 10]), cap=None, capturable=True)


def _shared_frames(rel, n=None):
    paths = sorted(glob.glob(str(SHARED_DATA / rel / "*.png")))
    if not paths:
        pytest.skip(f"../shared/data not found beside the repo (looked for {SHARED_DATA / rel}); this test needs it")
    return [load_gray(p) for p in paths[:n]]


def _flight_frame(k):
    from torch_frontend.testing.flight import synthetic_flight

    return synthetic_flight(k + 1)[0][k]


def test_integral_covariance_sums_equal_the_float_ones():
    """A uint8 image's stacked sums (exact-integer passes: windowed [1, 2, 1] and box reductions,
    products written into the padded stack) give the float path's responses bit for bit, for
    every box size it takes (1..4; 5: the float path), on random, extreme (0 / 255 checkerboards:
    the largest derivatives and sums) and tiny images."""
    from torch_frontend.corners.responses import _covariance_sums, _covariance_sums_stacked

    g = torch.Generator().manual_seed(0)
    imgs = []
    for h, w in ((2, 2), (3, 3), (4, 7), (2, 9), (9, 2), (17, 23), (48, 64)):
        imgs.append(torch.randint(0, 256, (2, 1, h, w), dtype=torch.uint8, generator=g))
        cb = ((torch.arange(h)[:, None] + torch.arange(w)[None]) % 2 * 255).to(torch.uint8)
        stripes = (torch.arange(w)[None].expand(h, w) % 2 * 255).to(torch.uint8)
        imgs.append(torch.stack([cb[None], stripes[None]]))
        imgs.append((torch.rand(2, 1, h, w, generator=g) > 0.5).to(torch.uint8) * 255)
    for x in imgs:
        h, w = x.shape[-2:]
        for block in range(1, 6):
            if max(block // 2, block - 1 - block // 2) >= min(h, w):
                continue
            xf = x.float()
            assert torch.equal(_min_eigen_impl(x, block, True), _min_eigen_impl(xf, block)), (x.shape, block)
            assert torch.equal(_harris_impl(x, block, 0.04, True), _harris_impl(xf, block, 0.04)), (x.shape, block)
            got, ref = _covariance_sums_stacked(x, block), _covariance_sums(xf, block)
            assert all(torch.equal(u, v) for u, v in zip(got[:3], ref[:3])) and got[3] == ref[3]


def test_top_keys_equal_an_int64_topk():
    """``_top_keys`` (two int32 top-k and a sort of the winners) == the int64 top-k of ``bits *
    2**ib + raster``, lane for lane, with heavy ties (a few distinct values, +inf's bits, all
    zero) at every k."""
    from torch_frontend.corners.selection_capturable import _top_keys

    g = torch.Generator().manual_seed(0)
    for trial in range(200):
        B, HW = int(torch.randint(1, 4, (1,), generator=g)), int(torch.randint(1, 300, (1,), generator=g))
        ib = max(1, (HW - 1).bit_length())
        nv = int(torch.randint(1, 6, (1,), generator=g))
        vals = torch.cat((torch.zeros(1, dtype=torch.int32),
                          torch.randint(1, 0x7F800001, (nv,), generator=g, dtype=torch.int32)))
        if trial % 3 == 0:
            vals[1:] = 0x7F800000
        bits = vals[torch.randint(0, nv + 1, (B, HW), generator=g)]
        if trial % 5 == 0:
            bits.zero_()
        k = int(torch.randint(1, HW + 1, (1,), generator=g))
        ref = torch.topk(bits.long() * (1 << ib) + torch.arange(HW), k, dim=1)
        idx, cvalid = _top_keys(bits, k, ib)
        assert torch.equal(idx, ref.indices) and torch.equal(cvalid, ref.values >= (1 << ib)), trial


def test_nms_windows_equal_nms_candidates():
    """The windowed 3x3 maximum's candidates == the pairwise maxima's, with plateaus, zeros of
    both signs and negative values."""
    from torch_frontend.corners.selection import _nms_candidates

    g = torch.Generator().manual_seed(0)
    for h, w in ((1, 5), (2, 2), (3, 3), (4, 9), (17, 11), (40, 50)):
        for levels in (2, 5, 1000):
            t = torch.randint(-2, levels, (3, h, w), generator=g).float()
            t[torch.rand(t.shape, generator=g) > 0.7] = -0.0
            assert torch.equal(_nms_candidates(t, windowed=True), _nms_candidates(t)), (h, w, levels)


def test_select_finite_response_same_as_thresholded():
    """``finite=True`` (NMS on the response itself, no thresholded copy) selects what the
    thresholded form selects, output for output, overflow included: signed responses with
    plateaus, masks (also ones whose maximum is negative), quality 0, 0.01 and 1, small budgets."""
    from torch_frontend.corners.selection_capturable import _select_corners_capturable

    rng = np.random.default_rng(0)
    for trial in range(60):
        h, w = int(rng.integers(3, 30)), int(rng.integers(3, 30))
        r = torch.from_numpy(rng.integers(-6, 8, (3, h, w)).astype(np.float32))
        if trial % 4 == 0:
            r = -r.abs()  # no positive response: nothing passes
        m = torch.from_numpy(rng.random((3, h, w)) > 0.4) if trial % 2 else None
        mc = torch.tensor([20, 5, 0])
        bud = GreedyBudget(int(rng.integers(1, h * w + 1)), 8, 2, 4, 2, 2)
        for q in (0.0, 0.01, 1.0):
            for md in (0.5, 3.0):
                a = _select_corners_capturable(r, mc, q, md, m, 20, bud, finite=True)
                b = _select_corners_capturable(r, mc, q, md, m, 20, bud, finite=False)
                assert _same(a, b), (trial, q, md)


def test_gftt_budget_holds_on_the_worst_measured_frames():
    """The frames behind GFTT_BUDGET's measured maxima: no overflow, the default path's corners;
    a block one candidate short of the measured need trips the flag."""
    flight = _CLAHE.apply(_flight_frame(2))  # candidate rank 2,763 and 283 survivors at min_dist 30
    x = torch.from_numpy(flight)[None, None]
    mc = torch.tensor([150])
    got = _gftt(x, mc, capturable=True)
    assert not got[2].any() and _same(got[:2], _gftt(x, mc))
    short = _gftt(x, mc, capturable=True, budget=GFTT_BUDGET._replace(block=2762))
    assert short[2].all()
    tight = _gftt(x, mc, capturable=True, budget=GFTT_BUDGET._replace(block=2763))
    assert not tight[2].any() and _same(tight[:2], got[:2])
    cam1 = _shared_frames("sequences/euroc_v1_01_easy_micro/mav0/cam1/data", 30)
    # 13 first-stage rounds (raw, min_dist 25) and 11 second-stage rounds (CLAHE, min_dist 25)
    for img in (cam1[24], _CLAHE.apply(cam1[29])):
        x = torch.from_numpy(img)[None, None]
        got = _gftt(x, mc, 25, capturable=True)
        assert not got[2].any() and _same(got[:2], _gftt(x, mc, 25))


def test_gftt_overflow_for_small_budgets(eq_frames):
    x = torch.from_numpy(eq_frames[:2])[:, None]
    mc = torch.tensor([150, 150])
    ref = _gftt(x, mc)
    for budget in (GFTT_BUDGET._replace(block=512), GFTT_BUDGET._replace(rounds_first=2),
                   GFTT_BUDGET._replace(first=256, survivors=16), GFTT_BUDGET._replace(first=256, rounds=1)):
        p, v, o = _gftt(x, mc, capturable=True, budget=budget)
        assert o.all(), budget
        assert not _same((p, v), ref)


def test_gftt_capturable_no_sync_and_kernels_independent_of_batch_and_data(eq_frames, device):
    counts = []
    for B, off in ((1, 0), (16, 0), (1, 7)):  # B and the frames change, the op sequence does not
        x = torch.from_numpy(np.stack([eq_frames[(off + b) % 24][:120, :160] for b in range(B)]))[:, None].to(device)
        mc = torch.arange(B, device=device) % 3 * 20
        mask = torch.ones(B, 120, 160, dtype=torch.bool, device=device)
        _gftt(x, mc, mask=mask, capturable=True)  # warm-up: cached constants
        with OpCounter() as c:
            _gftt(x, mc, mask=mask, capturable=True)
        assert c.syncs == 0, c.summary()
        counts.append(c.kernels)
    assert counts[0] == counts[1] == counts[2]


# random response maps with ties / plateaus / negative values, a generous and a random (small)
# budget: wherever overflow is False the result is the default path's
@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    h=st.integers(3, 40),
    w=st.integers(3, 48),
    levels=st.integers(2, 50),
    md=st.sampled_from([0.5, 1.0, 2.0, 3.0, 4.4, 5.0, 7.6, 12.0]),
    max_corners=st.integers(0, 60),
    use_mask=st.booleans(),
    signed=st.booleans(),
    f64=st.booleans(),
    budget=st.tuples(st.integers(1, 2000), st.integers(1, 64), st.integers(0, 6), st.integers(1, 64),
                     st.integers(0, 6)),
)
def test_gftt_capturable_property(seed, h, w, levels, md, max_corners, use_mask, signed, f64, budget):
    rng = np.random.default_rng(seed)
    resp = rng.integers(0, levels, (3, h, w)).astype(np.float32)
    if signed:
        resp -= levels / 2.0
    r = torch.from_numpy(resp).to(torch.float64 if f64 else torch.float32)
    mask = torch.from_numpy(rng.random((3, h, w)) > 0.3) if use_mask else None
    mc = torch.tensor([max_corners, max_corners // 2, 0])
    q = -0.5 if signed else 0.01
    ref = _gftt_from_response(r, mc, q, md, mask, 60)
    for bud in (GreedyBudget(block=h * w, first=h * w, rounds_first=64, survivors=1, rounds=0), GreedyBudget(*budget)):
        p, v, o = _gftt_from_response(r, mc, q, md, mask, 60, capturable=True, budget=bud)
        assert not o[2]  # max_corners 0
        for b in range(3):
            if not o[b]:
                assert torch.equal(p[b], ref[0][b]) and torch.equal(v[b], ref[1][b]), (b, bud)


# ---------------------------------------------------------------------------------------------
# setMask


@pytest.mark.parametrize("radius", [0, 1, 12, 12.5, 30])
def test_distance_mask_capturable_equals_default(device, radius):
    rng = np.random.default_rng(int(radius * 10))
    B, N, H, W = 4, 200, 120, 160
    pts = rng.uniform(-3, [W + 3, H + 3], (B, N, 2)).astype(np.float32)
    pts[:, :20] = np.round(pts[:, :20]) + 0.5  # exact .5: round half to even
    pts[0, 3] = np.nan
    pts[1, 4, 1] = np.inf
    pri = rng.integers(1, 5, (B, N))
    val = rng.random((B, N)) > 0.1
    base = fisheye_mask(H, W, radius=75).to(device).expand(B, H, W)
    args = (torch.from_numpy(pts).to(device), torch.from_numpy(pri).to(device), torch.from_numpy(val).to(device),
            float(radius))
    keep, mask, ovf = _distance_mask_impl(*args, base.clone(), capturable=True, rounds=N)
    assert not ovf.any() and _same((keep, mask), _distance_mask_impl(*args, base.clone())[:2])
    one = _distance_mask_impl(*(a[2:3] for a in args[:3]), float(radius), base[2:3].clone(), capturable=True,
                              rounds=N)
    assert _same(one, (keep[2:3], mask[2:3], ovf[2:3]))


def test_distance_mask_capturable_real_and_budget(eq_frames, device):
    pts, cnt, val = _tracked_mask(eq_frames[:6], device, md=20)
    base = torch.full((6, 480, 752), 255, dtype=torch.uint8, device=device)
    base[:, :, :40] = 254  # not exactly 255: dropped
    ref = _distance_mask_impl(pts, cnt, val, 30.0, base.clone())
    got = _distance_mask_impl(pts, cnt, val, 30.0, base.clone(), capturable=True)  # MASK_ROUNDS
    assert MASK_ROUNDS >= 3 and not got[2].any() and _same(got[:2], ref)
    # a chain of points 10 px apart, radius 12: every one waits for the previous -> one round each
    chain = torch.stack([torch.arange(20.0) * 10 + 5, torch.full((20,), 50.0)], -1)[None].to(device)
    pri = torch.arange(20, 0, -1, device=device)[None]
    ones = torch.ones(1, 20, dtype=torch.bool, device=device)
    m0 = torch.full((1, 100, 210), 255, dtype=torch.uint8, device=device)
    k, m, o = _distance_mask_impl(chain, pri, ones, 12.0, m0.clone(), capturable=True, rounds=3)
    assert o.all()
    k, m, o = _distance_mask_impl(chain, pri, ones, 12.0, m0.clone(), capturable=True, rounds=20)
    assert not o.any() and _same((k, m), _distance_mask_impl(chain, pri, ones, 12.0, m0.clone())[:2])
    assert k[0].tolist() == [i % 2 == 0 for i in range(20)]


def test_distance_mask_capturable_no_sync_and_kernels_independent_of_batch(device):
    rng = np.random.default_rng(3)
    counts = []
    for B in (1, 16):
        pts = torch.from_numpy(rng.uniform(0, [752, 480], (B, 150, 2)).astype(np.float32)).to(device)
        pri = torch.from_numpy(rng.integers(1, 5, (B, 150))).to(device)
        val = torch.from_numpy(rng.random((B, 150)) > 0.2).to(device)
        base = torch.full((B, 480, 752), 255, dtype=torch.uint8, device=device)
        _distance_mask_impl(pts, pri, val, 30.0, base.clone(), capturable=True)  # warm-up
        with OpCounter() as c:
            _distance_mask_impl(pts, pri, val, 30.0, base, capturable=True)
        assert c.syncs == 0, c.summary()
        counts.append(c.kernels)
    assert counts[0] == counts[1]


# ---------------------------------------------------------------------------------------------
# the budget on the sequences (first frames: every frame, no features; steady state in kernels)


#: The sequences the budgets were measured on. The default suite runs the repo's stereo frames;
#: the rest is slow (make test and CI run it too).
_SEQUENCES = ["mini_cam1"] + [pytest.param(n, marks=pytest.mark.slow)
                              for n in ("mini_cam0", "micro_cam0", "micro_cam1", "middlebury", "flight")]


def _sequence(name):
    """The frames of one sequence (micro: every 4th / 3rd; skips where ../shared/data is absent)."""
    if name.startswith("mini_"):
        return _frames(name[5:])
    if name == "flight":
        from torch_frontend.testing.flight import synthetic_flight

        return synthetic_flight(16)[0]
    if name == "middlebury":
        return _shared_frames("flow/middlebury2014_motorcycle_stereo")
    cam = name[6:]
    return _shared_frames(f"sequences/euroc_v1_01_easy_micro/mav0/{cam}/data")[::4 if cam == "cam0" else 3]


def _response(img):
    """``img``'s min-eigenvalue response (1, H, W) as both paths of ``_good_features_impl`` compute it
    (the default one by CPU stream groups, the capturable one with stacked box sums: equal bit for
    bit), so that the selections below see what the detector's two paths see."""
    x = torch.from_numpy(img)[None, None]
    resp = _response_impl(x, False, 3, 0.0)[:, 0]
    assert torch.equal(_min_eigen_impl(x.float(), 3, True)[:, 0], resp)
    return resp


@pytest.mark.parametrize("name", _SEQUENCES)
def test_gftt_budget_never_overflows_on_the_sequences(name):
    """Every frame of a sequence the budgets were measured on, as a first frame (150 corners, no
    mask; CLAHE and raw) and in the steady state (setMask of the previous frame's corners,
    jittered), min_dist 30 / 25 / 20: no overflow (GFTT and setMask), the default path's corners.
    The selection runs on each frame's response, computed once (it depends on neither min_dist nor
    the mask)."""
    mc = torch.tensor([150])
    for eq in (True, False):
        imgs = [_CLAHE.apply(f) if eq else f for f in _sequence(name)]
        for k, img in enumerate(imgs):
            resp = _response(img)
            for md in (30, 25, 20):
                got = _gftt_from_response(resp, mc, 0.01, md, None, 150, capturable=True)
                ref = _gftt_from_response(resp, mc, 0.01, md, None, 150)
                assert not got.overflow.any() and _same(got[:2], ref[:2]), (name, eq, md, k)
                if k == 0 or not eq:
                    continue
                pts, cnt, val = _tracked_mask([imgs[k - 1]], "cpu", md=md, seed=k)
                H, W = img.shape
                keep, m, movf = _distance_mask_impl(pts, cnt, val, float(md),
                                                    torch.full((1, H, W), 255, dtype=torch.uint8), capturable=True)
                n_max = 150 - keep.sum(1)
                got = _gftt_from_response(resp, n_max, 0.01, md, m != 0, 150, capturable=True)
                ref = _gftt_from_response(resp, n_max, 0.01, md, m != 0, 150)
                assert not movf.any() and not got.overflow.any(), (name, md, k)
                assert _same(got[:2], ref[:2]), (name, md, k)
