"""Corner responses and goodFeaturesToTrack vs OpenCV on real EuRoC frames (CPU/CUDA)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torch_frontend.corners import (
    _gftt_from_response,
    good_features_to_track,
    harris_response,
    min_eigen_response,
)
from torch_frontend.masks import distance_mask

from .conftest import load_gray, sample_frames

_CLAHE = cv2.createCLAHE(3.0, (8, 8))


def _equalized(n=24):
    # VINS (EuRoC config, equalize 1) detects on the CLAHE image
    return np.stack([_CLAHE.apply(load_gray(p)) for p in sample_frames("cam0")[:n]])


@pytest.fixture(scope="module")
def frames():
    return _equalized(24)


def _rel_err(ours, ref):
    return float(np.abs(ours.astype(np.float64) - ref).max() / np.abs(ref).max())


def test_responses_match_opencv(frames, device, dtype):
    imgs = frames[:3]
    x = torch.from_numpy(imgs)[:, None].to(device)
    if dtype == torch.float64:
        x = x.to(dtype)  # float grey levels 0..255 give the same (8-bit scaled) response
    me = min_eigen_response(x).cpu().numpy()[:, 0]
    hr = harris_response(x, 3, 0.04).cpu().numpy()[:, 0]
    assert me.dtype == (np.float64 if dtype == torch.float64 else np.float32)
    for b, im in enumerate(imgs):
        # documented scale: Sobel derivatives * 1 / (4 * 3 * 255) as in OpenCV, no rescaling here
        assert _rel_err(me[b], cv2.cornerMinEigenVal(im, 3, 3)) <= 1e-4
        assert _rel_err(hr[b], cv2.cornerHarris(im, 3, 3, 0.04)) <= 1e-4


@pytest.mark.parametrize("block", [2, 5])
def test_response_other_block_sizes(frames, block):
    im = frames[0][100:200, 200:360]
    me = min_eigen_response(torch.from_numpy(im)[None], block).numpy()[0, 0]
    assert _rel_err(me, cv2.cornerMinEigenVal(im, block, 3)) <= 1e-4


def test_responses_gradcheck():
    g = torch.Generator().manual_seed(0)
    x = (torch.rand(1, 1, 5, 6, generator=g, dtype=torch.float64) * 255).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: min_eigen_response(t), (x,), fast_mode=True)
    assert torch.autograd.gradcheck(lambda t: harris_response(t), (x,), fast_mode=True)
    flat = torch.full((1, 1, 5, 5), 7.0, dtype=torch.float64, requires_grad=True)
    min_eigen_response(flat).sum().backward()  # sqrt at 0 in flat regions: finite gradient
    assert torch.isfinite(flat.grad).all()


def _compare_sets(pts, valid, refs):
    """Fraction of OpenCV corners reproduced (same integer pixel), count differences, exact order."""
    same = total = 0
    worst_count = 0
    exact = True
    for b, ref in enumerate(refs):
        ours = pts[b][valid[b]].cpu().numpy()
        ref = np.zeros((0, 2), np.float32) if ref is None else ref[:, 0]
        so, sr = set(map(tuple, ours.astype(int))), set(map(tuple, ref.astype(int)))
        same += len(so & sr)
        total += len(sr)
        worst_count = max(worst_count, abs(len(ours) - len(ref)))
        exact &= len(ours) == len(ref) and bool((ours == ref).all())
    return same / max(total, 1), worst_count, exact


def test_gftt_matches_opencv_24_frames(frames, device):
    x = torch.from_numpy(frames)[:, None].to(device)
    pts, valid = good_features_to_track(x, 150, 0.01, 30)
    assert pts.shape == (24, 150, 2) and valid.shape == (24, 150)
    refs = [cv2.goodFeaturesToTrack(im, 150, 0.01, 30) for im in frames]
    frac, dcount, exact = _compare_sets(pts, valid, refs)
    # bar: >= 98 % identical pixels, count within +-1. Measured: identical, same order.
    assert frac >= 0.98 and dcount <= 1
    assert exact


def test_gftt_with_vins_mask_and_per_stream_counts(frames, device):
    """The tracker's use: setMask (distance_mask) then GFTT(n_max = MAX_CNT - kept, mask)."""
    B = 8
    imgs = frames[:B]
    prev = frames[1 : B + 1]
    rng = np.random.default_rng(1)
    # tracked features: OpenCV corners of the next frame, jittered, random track counts
    tracked = []
    for im in prev:
        c = cv2.goodFeaturesToTrack(im, 150, 0.01, 20)[:, 0]
        tracked.append(c + rng.normal(0, 2.0, c.shape).astype(np.float32))
    N = max(len(t) for t in tracked)
    pts = np.zeros((B, N, 2), np.float32)
    val = np.zeros((B, N), bool)
    for b, t in enumerate(tracked):
        pts[b, : len(t)] = t
        val[b, : len(t)] = True
    cnt = rng.integers(1, 8, (B, N))
    keep, mask = distance_mask(torch.from_numpy(pts).to(device), torch.from_numpy(cnt).to(device),
                               torch.from_numpy(val).to(device), 30, height=480, width=752)
    n_max = (150 - keep.sum(1)).clamp_min(0)
    x = torch.from_numpy(imgs)[:, None].to(device)
    got, gvalid = good_features_to_track(x, n_max, 0.01, 30, mask=mask)
    assert got.shape[1] == int(n_max.max())
    mask_np = mask.cpu().numpy()
    refs = [cv2.goodFeaturesToTrack(imgs[b], int(n_max[b]), 0.01, 30, mask=mask_np[b]) for b in range(B)]
    frac, dcount, exact = _compare_sets(got, gvalid, refs)
    assert frac >= 0.98 and dcount <= 1
    assert exact
    # per-stream counts and masks in one call equal separate calls
    for b in (0, 5):
        p1, v1 = good_features_to_track(x[b : b + 1], int(n_max[b]), 0.01, 30, mask=mask[b : b + 1])
        k = int(v1.sum())
        assert torch.equal(got[b, :k], p1[0, :k]) and int(gvalid[b].sum()) == k


def test_gftt_ties_later_raster_first():
    """Exact response ties (a grid of identical squares): OpenCV puts later raster positions first."""
    im = np.zeros((120, 160), np.uint8)
    for y in range(10, 110, 20):
        for x in range(10, 150, 20):
            im[y : y + 10, x : x + 10] = 200
    ref = cv2.goodFeaturesToTrack(im, 40, 0.01, 5)[:, 0]
    resp = cv2.cornerMinEigenVal(im, 3, 3)
    assert len(set(resp[ref[:, 1].astype(int), ref[:, 0].astype(int)])) == 1  # all tied
    pts, valid = good_features_to_track(torch.from_numpy(im)[None], 40, 0.01, 5)
    assert np.array_equal(pts[0][valid[0]].numpy(), ref)


def test_gftt_harris_and_edge_cases(frames):
    im = np.ascontiguousarray(frames[3][100:340, 150:526])
    x = torch.from_numpy(im)[None, None]
    pts, valid = good_features_to_track(x, 100, 0.01, 10, use_harris=True, k=0.04)
    ref = cv2.goodFeaturesToTrack(im, 100, 0.01, 10, useHarrisDetector=True, k=0.04)
    frac, dcount, _ = _compare_sets(pts, valid, [ref])
    assert frac >= 0.98 and dcount <= 1
    # max_corners <= 0: no corners; capacity pads
    p0, v0 = good_features_to_track(x, 0)
    assert p0.shape == (1, 0, 2) and not v0.any()
    p2, v2 = good_features_to_track(torch.cat([x, x]), torch.tensor([0, 5]), capacity=8)
    assert p2.shape == (2, 8, 2) and v2.sum(1).tolist() == [0, 5]
    # empty mask -> nothing
    p3, v3 = good_features_to_track(x, 10, mask=torch.zeros(240, 376, dtype=torch.uint8))
    assert not v3.any()
    # min_distance < 1: the first max_corners candidates, like OpenCV
    p4, v4 = good_features_to_track(x, 50, 0.01, 0)
    ref4 = cv2.goodFeaturesToTrack(im, 50, 0.01, 0)[:, 0]
    assert np.array_equal(p4[0][v4[0]].numpy(), ref4)


# ---- property tests on random response maps against a sequential reference -----------------

def _reference_select(resp, max_corners, q, md, mask):
    """OpenCV goodFeaturesToTrack after the response, written as the sequential C++ loop."""
    H, W = resp.shape
    m = np.ones((H, W), bool) if mask is None else mask != 0
    max_val = resp[m].max() if m.any() else 0.0
    thr = np.float32(np.float64(max_val) * q)
    t = np.where(resp > thr, resp, 0).astype(np.float32)
    pad = np.pad(t, 1, constant_values=-np.inf)
    dil = np.max([pad[dy : dy + H, dx : dx + W] for dy in range(3) for dx in range(3)], axis=0)
    cands = [(t[y, x], y * W + x) for y in range(1, H - 1) for x in range(1, W - 1)
             if t[y, x] != 0 and t[y, x] == dil[y, x] and m[y, x]]
    cands.sort(key=lambda c: (-c[0], -c[1]))
    out = []
    if md < 1:
        return [(i % W, i // W) for _, i in cands[:max_corners]]
    cell = int(round(md))
    for _, i in cands:
        x, y = i % W, i // W
        good = True
        for ax, ay in out:
            if abs(x // cell - ax // cell) <= 1 and abs(y // cell - ay // cell) <= 1 and (x - ax) ** 2 + (y - ay) ** 2 < md * md:
                good = False
                break
        if good:
            out.append((x, y))
            if len(out) == max_corners:
                break
    return out


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    h=st.integers(3, 40),
    w=st.integers(3, 48),
    levels=st.integers(2, 50),
    md=st.sampled_from([0.5, 1.0, 2.0, 3.0, 4.4, 5.0, 7.6, 12.0]),
    max_corners=st.integers(1, 60),
    use_mask=st.booleans(),
)
def test_gftt_selection_property(seed, h, w, levels, md, max_corners, use_mask):
    rng = np.random.default_rng(seed)
    # few levels -> many exact ties and plateaus
    resp = rng.integers(0, levels, (2, h, w)).astype(np.float32)
    mask = (rng.random((2, h, w)) > 0.3).astype(np.uint8) if use_mask else None
    mc = torch.tensor([max_corners, max(1, max_corners // 2)])
    pts, valid, overflow = _gftt_from_response(torch.from_numpy(resp), mc, 0.01, md,
                                               None if mask is None else torch.from_numpy(mask), None)
    assert overflow is None  # the default path is exact
    for b in range(2):
        ours = [tuple(p) for p in pts[b][valid[b]].long().tolist()]
        ref = _reference_select(resp[b], int(mc[b]), 0.01, md, None if mask is None else mask[b])
        assert ours == ref
        if md >= 1 and float(md).is_integer():  # invariant (exact for integer distances)
            a = np.array(ours, dtype=np.int64).reshape(-1, 2)
            d2 = ((a[:, None] - a[None]) ** 2).sum(-1) + np.eye(len(a), dtype=np.int64) * 10**9
            assert (d2 >= md * md).all()


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), md=st.integers(2, 15))
def test_gftt_min_distance_invariant_images(seed, md):
    rng = np.random.default_rng(seed)
    im = cv2.GaussianBlur(rng.integers(0, 256, (48, 64)).astype(np.uint8), (3, 3), 0)
    pts, valid = good_features_to_track(torch.from_numpy(im)[None], 200, 0.01, md)
    a = pts[0][valid[0]].numpy().astype(np.int64)
    d2 = ((a[:, None] - a[None]) ** 2).sum(-1) + np.eye(len(a), dtype=np.int64) * 10**9
    assert (d2 >= md * md).all()
    ref = cv2.goodFeaturesToTrack(im, 200, 0.01, md)
    ref = np.zeros((0, 2)) if ref is None else ref[:, 0]
    assert abs(len(a) - len(ref)) <= 1 and math.isfinite(float(a.sum()))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gftt_selection_signed_responses(dtype):
    """Negative responses and ties (Harris-like): the packed-key sort (float32) and the general
    two-sort path (float64) both give the sequential reference."""
    rng = np.random.default_rng(5)
    for trial in range(6):
        r = (rng.integers(-40, 40, (2, 23, 31)) / 4.0 - (60.0 if trial % 2 else 0.0)).astype(np.float32)
        q = [0.0, 0.01, -0.5][trial % 3]
        pts, valid, _ = _gftt_from_response(torch.from_numpy(r).to(dtype), 30, q, 3, None, None)
        for b in range(2):
            ours = [tuple(int(c) for c in p) for p in pts[b][valid[b]].tolist()]
            assert ours == _reference_select(r[b], 30, q, 3, None)


def test_cpu_stream_blocks_equal_one_block(frames, monkeypatch):
    """The CPU grouping of streams (cache-sized blocks) does not change any result."""
    import dataclasses

    from torch_frontend import _tuning

    x = torch.from_numpy(frames[:3, :96, :128].copy())[:, None]
    ref_r = min_eigen_response(x)
    ref_h = harris_response(x)
    ref_p, ref_v = good_features_to_track(x, 40, 0.01, 7)
    blocks = dataclasses.replace(_tuning.CPU, corner_block_pixels=1)
    assert blocks.corner_streams(3, 96, 128) == 1
    monkeypatch.setitem(_tuning.STRATEGIES, "cpu", blocks)  # one stream per block
    assert torch.equal(min_eigen_response(x), ref_r) and torch.equal(harris_response(x), ref_h)
    p, v = good_features_to_track(x, 40, 0.01, 7)
    assert torch.equal(p, ref_p) and torch.equal(v, ref_v)
