"""distance_mask (VINS setMask) vs a sequential reference and cv2.circle; fisheye_mask vs the JPEG."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torch_frontend.masks import disc_offsets, distance_mask, fisheye_mask

from .conftest import SHARED_DATA, load_gray, sample_frames, shared_data_or_skip

#: setMask's kernels: the tensor kernel and the fused op (``fused/mask_op.py``); the same bits
BACKENDS = ["tensor", "fused"]


def _reference(pts, pri, val, r, base):
    """VINS setMask written sequentially (stable sort by -track_cnt, cv2.circle discs)."""
    m = base.copy()
    H, W = m.shape
    order = sorted((i for i in range(len(pts)) if val[i]), key=lambda i: -pri[i])
    keep = np.zeros(len(pts), bool)
    for i in order:
        x, y = np.round(pts[i].astype(np.float64)).astype(int)  # half to even, like cvRound
        if 0 <= x < W and 0 <= y < H and m[y, x] == 255:
            keep[i] = True
            cv2.circle(m, (int(x), int(y)), int(r), 0, -1)
    return keep, m


def _check(pts, pri, val, r, base, device, backend="tensor"):
    B = pts.shape[0]
    keep, mask = distance_mask(torch.from_numpy(pts).to(device), torch.from_numpy(pri).to(device),
                               torch.from_numpy(val).to(device), r, torch.from_numpy(base).to(device), backend=backend)
    assert keep.shape == pri.shape and mask.dtype == torch.uint8 and mask.shape == (B,) + base.shape
    edge = 0
    for b in range(B):
        k, m = _reference(pts[b], pri[b], val[b], r, base)
        assert np.array_equal(keep[b].cpu().numpy(), k)
        edge += int((mask[b].cpu().numpy() != m).sum())
    return edge


@pytest.mark.parametrize("backend", BACKENDS)
def test_distance_mask_random(device, backend):
    rng = np.random.default_rng(0)
    B, N, H, W = 4, 200, 120, 160
    pts = rng.uniform(-3, [W + 3, H + 3], (B, N, 2)).astype(np.float32)
    pts[:, :20] = np.round(pts[:, :20]) + 0.5  # exact .5: round half to even
    pri = rng.integers(1, 5, (B, N))  # many ties: stable order by index
    val = rng.random((B, N)) > 0.1
    base = fisheye_mask(H, W, radius=75).numpy()
    edge = _check(pts, pri, val, 12, base, device, backend)
    assert edge == 0  # the disc equals cv2.circle pixel for pixel (see test below)


@pytest.mark.parametrize("backend", BACKENDS)
def test_distance_mask_real(device, backend):
    """Tracked features = OpenCV corners of EuRoC frames, jittered; VINS radius 30; JPEG-like mask."""
    rng = np.random.default_rng(2)
    frames = [load_gray(p) for p in sample_frames("cam0")[:4]]
    cs = [cv2.goodFeaturesToTrack(f, 200, 0.01, 10)[:, 0] for f in frames]
    N = max(len(c) for c in cs)
    pts = np.zeros((4, N, 2), np.float32)
    val = np.zeros((4, N), bool)
    for b, c in enumerate(cs):
        pts[b, : len(c)] = c + rng.normal(0, 3, c.shape)
        val[b, : len(c)] = True
    pri = rng.integers(1, 10, (4, N))
    base = np.full((480, 752), 255, np.uint8)
    base[:, :40] = 254  # "JPEG ring" values: not exactly 255 -> point dropped
    edge = _check(pts, pri, val, 30, base, device, backend)
    assert edge == 0


@pytest.mark.parametrize("backend", BACKENDS)
@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(0, 40), r=st.integers(0, 20))
def test_distance_mask_property(backend, seed, n, r):
    rng = np.random.default_rng(seed)
    H, W = 40, 50
    pts = rng.uniform(-2, [W + 2, H + 2], (2, n, 2)).astype(np.float32)
    pri = rng.integers(0, 3, (2, n))
    val = rng.random((2, n)) > 0.2
    base = (rng.random((H, W)) > 0.05).astype(np.uint8) * 255
    assert _check(pts, pri, val, r, base, "cpu", backend) == 0


def test_disc_equals_cv2_circle():
    """Filled cv2.circle vs dx² + dy² <= r² for radii 0..60 and sub-image clipping."""
    diff = 0
    for r in range(0, 61):
        m = np.full((131, 131), 255, np.uint8)
        cv2.circle(m, (65, 65), r, 0, -1)
        off = disc_offsets(r).numpy()
        ours = np.full_like(m, 255)
        ours[65 + off[:, 1], 65 + off[:, 0]] = 0
        diff += int((ours != m).sum())
    assert diff <= 8  # documented bound for "edge pixels"; measured: 0
    assert diff == 0
    # clipped at the border, batched
    keep, mask = distance_mask(torch.tensor([[[2.0, 3.0]], [[158.4, 118.6]]]), torch.ones(2, 1, dtype=torch.long),
                               None, 25, height=120, width=160)
    for b, c in enumerate([(2, 3), (158, 119)]):
        m = np.full((120, 160), 255, np.uint8)
        cv2.circle(m, c, 25, 0, -1)
        assert np.array_equal(mask[b].numpy(), m)
    assert keep.all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_distance_mask_rules(backend):
    # priority order wins, then index; .5 rounds to even; outside the image is dropped
    pts = torch.tensor([[[10.0, 10.0], [20.0, 10.0], [10.5, 40.5], [-0.6, 5.0], [60.0, 60.0]]])
    pri = torch.tensor([[1, 3, 2, 9, 3]])
    keep, mask = distance_mask(pts, pri, None, 10, height=64, width=64, backend=backend)
    assert keep.tolist() == [[False, True, True, False, True]]
    assert mask[0, 40, 10] == 0 and mask[0, 40, 21] == 255 and mask[0, 40, 20] == 0  # centre (10, 40)
    with pytest.raises(ValueError):
        distance_mask(pts, pri, None, 10)  # no size given
    with pytest.raises(ValueError):
        distance_mask(pts, pri[:, :3], None, 10, height=64, width=64)


def test_fisheye_mask_vs_vins_jpeg():
    p = shared_data_or_skip("vins_configs", "vins_mono", "fisheye_mask.jpg")
    jpg = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
    ours = fisheye_mask(512, 512).numpy()
    agree = float(((ours == 255) == (jpg == 255)).mean())
    assert agree >= 0.99  # measured 0.9913 (JPEG soft edge ring of 1..254 values)
    p2 = SHARED_DATA / "vins_configs" / "vins_mono" / "fisheye_mask_752x480.jpg"
    if p2.exists():
        jpg2 = cv2.imread(str(p2), cv2.IMREAD_GRAYSCALE)
        ours2 = fisheye_mask(480, 752, radius=279.5).numpy()
        assert float(((ours2 == 255) == (jpg2 == 255)).mean()) >= 0.99
    m = fisheye_mask(480, 752)
    assert m.dtype == torch.uint8 and set(m.unique().tolist()) == {0, 255}
