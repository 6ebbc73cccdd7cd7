"""Keyframe features for loop closure (spec §5.6, §7.3): FAST vs cv2, the 8-bit Gaussian blur vs
cv2, BRIEF vs a plain-numpy implementation of the spec, Hamming vs a numpy popcount."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torch_frontend.errors import ConfigError
from torch_frontend.loop.features import (
    DEFAULT_PATTERN_PATH,
    brief,
    default_brief_pattern,
    fast,
    gaussian_blur_u8,
    hamming,
    load_brief_pattern,
    make_brief_pattern,
)

from .conftest import load_gray, sample_frames, shared_data_or_skip

cv2 = pytest.importorskip("cv2")


@pytest.fixture(scope="module")
def frames():
    paths = sample_frames("cam0")[:20]
    assert len(paths) == 20
    return np.stack([load_gray(p) for p in paths])


def _cv_fast(img, threshold, nonmax):
    kps = cv2.FastFeatureDetector_create(int(threshold), bool(nonmax)).detect(img)
    pts = np.array([k.pt for k in kps], dtype=np.float64).reshape(-1, 2)
    return pts, np.array([k.response for k in kps], dtype=np.float64)


def _compare_fast(imgs, threshold, nonmax, device):
    """Returns (keypoints found by both, total cv2 keypoints, worst relative count error)."""
    pts, score, valid, num = fast(torch.from_numpy(imgs).to(device), threshold, nonmax, return_count=True)
    pts, score, valid = pts.cpu().numpy(), score.cpu().numpy(), valid.cpu().numpy()
    same = total = 0
    worst = 0.0
    for i, im in enumerate(imgs):
        ref, ref_score = _cv_fast(im, threshold, nonmax)
        mine = pts[i][valid[i]]
        assert int(num[i]) == len(mine)
        total += len(ref)
        worst = max(worst, abs(len(mine) - len(ref)) / max(len(ref), 1))
        if len(ref) != len(mine) or not (ref == mine).all():
            same += len({tuple(p) for p in ref} & {tuple(p) for p in mine})
        else:
            same += len(ref)
            # raster order and, with NMS, OpenCV's response (= FAST score) agree too
            assert (np.diff(mine[:, 1]) >= 0).all()
            if nonmax:
                np.testing.assert_array_equal(score[i][valid[i]], ref_score)
    return same, total, worst


@pytest.mark.parametrize("nonmax", [True, False], ids=["nms", "no_nms"])
def test_fast_matches_cv2_on_euroc(frames, nonmax, device):
    same, total, worst = 0, 0, 0.0
    for chunk in (frames[:10], frames[10:]):  # two batched calls of 10 frames
        s, t, w = _compare_fast(chunk, 20, nonmax, device)
        same, total, worst = same + s, total + t, max(worst, w)
    assert total > 5000
    # acceptance: >= 99 % identical keypoints, counts within 1 % (measured: 100 %, exact counts)
    assert same / total >= 0.99, (same, total)
    assert worst <= 0.01


@pytest.mark.parametrize("threshold", [0, 7, 40])
def test_fast_matches_cv2_on_synthetic(threshold):
    # random noise (many corners), blocky images (score plateaus: NMS ties) and odd small sizes
    rng = np.random.default_rng(threshold)
    imgs = [rng.integers(0, 256, (31, 45), dtype=np.uint8)]
    blocks = rng.integers(0, 6, (8, 12)).astype(np.uint8) * 50
    imgs.append(np.kron(blocks, np.ones((4, 4), np.uint8))[:31, :45].copy())
    imgs.append(cv2.GaussianBlur(imgs[0], (5, 5), 1.5))
    imgs = np.stack(imgs)
    for nonmax in (True, False):
        same, total, worst = _compare_fast(imgs, threshold, nonmax, "cpu")
        assert same == total and worst == 0.0, (nonmax, same, total)


def test_fast_capacity_overflow_and_inputs(frames):
    img = torch.from_numpy(np.ascontiguousarray(frames[:2, :240, :376]))
    pts, score, valid, num = fast(img, return_count=True)
    cap = int(num.min()) // 2
    p2, s2, v2, n2 = fast(img, max_points=cap, return_count=True)
    assert p2.shape == (2, cap, 2) and v2.all()
    assert torch.equal(n2, num) and (n2 > cap).all()  # overflow is reported by num_found > K
    for i in range(2):
        sc = score[i][valid[i]]
        kth = torch.sort(sc, descending=True).values[cap - 1]
        assert (s2[i] >= kth).all() and (s2[i] > kth).sum() == (sc > kth).sum()
        # kept corners are a subset, still in raster order
        key_all = (pts[i][valid[i]] @ torch.tensor([1.0, 10000.0])).tolist()
        key_cap = (p2[i] @ torch.tensor([1.0, 10000.0]))
        assert set(key_cap.tolist()) <= set(key_all)
        assert (torch.diff(key_cap) > 0).all()
    # larger capacity pads with zeros; float images (and (B, H, W) layout) give the same corners
    p3, s3, v3 = fast(img.float().unsqueeze(1), max_points=int(num.max()) + 5, dtype=torch.float64)
    assert p3.dtype == torch.float64 and (~v3[:, -5:]).all() and (p3[~v3] == 0).all()
    for i in range(2):
        assert torch.equal(p3[i][v3[i]].float(), pts[i][valid[i]])
    # too small for the 3-pixel border: nothing, K = 0
    p4, s4, v4 = fast(torch.zeros(3, 6, 40, dtype=torch.uint8))
    assert p4.shape == (3, 0, 2) and v4.shape == (3, 0)
    with pytest.raises(ValueError):
        fast(torch.zeros(2, 3, 20, 20, dtype=torch.uint8))


def test_gaussian_blur_u8_bit_exact(frames, device):
    rng = np.random.default_rng(1)
    cases = [frames[:2]] + [rng.integers(0, 256, (2, h, w), dtype=np.uint8) for h, w in ((1, 7), (3, 5), (17, 40))]
    for imgs in cases:
        out = gaussian_blur_u8(torch.from_numpy(imgs).to(device)).cpu().numpy()[:, 0]
        for i, im in enumerate(imgs):
            ref = cv2.GaussianBlur(im, (9, 9), 2, 2, borderType=cv2.BORDER_REFLECT_101)
            np.testing.assert_array_equal(out[i], ref)


def _numpy_brief(img, pts, valid, pattern):
    """Spec §7.3 in plain numpy: blur, C truncation of float32 sums, bounds test, pack."""
    blur = cv2.GaussianBlur(img, (9, 9), 2, 2, borderType=cv2.BORDER_REFLECT_101)
    H, W = img.shape
    pts = pts.astype(np.float32)
    x1, y1, x2, y2 = (np.trunc(pts[:, None, j % 2] + pattern[j].astype(np.float32)).astype(np.int64) for j in range(4))
    inside = (x1 >= 0) & (x1 < W) & (y1 >= 0) & (y1 < H) & (x2 >= 0) & (x2 < W) & (y2 >= 0) & (y2 < H)
    v1 = blur[np.clip(y1, 0, H - 1), np.clip(x1, 0, W - 1)]
    v2 = blur[np.clip(y2, 0, H - 1), np.clip(x2, 0, W - 1)]
    bits = (v1 < v2) & inside & valid[:, None]
    n = pattern.shape[1]
    words = np.zeros((len(pts), n // 64), dtype=np.uint64)
    for i in range(n):
        words[:, i // 64] |= bits[:, i].astype(np.uint64) << np.uint64(i % 64)
    return words.view(np.int64)


def _keypoints(frames):
    """FAST corners plus float points near and beyond the borders (incl. -0.5 -> trunc 0)."""
    pts, _, valid = fast(torch.from_numpy(frames))
    B, H, W = frames.shape
    rng = np.random.default_rng(2)
    extra = rng.uniform(-30.0, W + 30.0, (B, 60, 2)).astype(np.float32)
    extra[:, :, 1] = rng.uniform(-30.0, H + 30.0, (B, 60))
    extra[:, 0] = (-0.5, -0.5)
    extra[:, 1] = (W - 1 + 0.99, H - 1 + 0.99)
    extra[:, 2] = (24.0, 24.0)
    ev = np.ones((B, 60), dtype=bool)
    ev[:, 3] = False  # an invalid lane: all-zero descriptor
    return torch.cat([pts, torch.from_numpy(extra)], 1), torch.cat([valid, torch.from_numpy(ev)], 1)


@pytest.mark.parametrize("which", ["vins", "default"])
def test_brief_bit_exact_vs_numpy(frames, which, device):
    if which == "vins":
        pattern = load_brief_pattern(shared_data_or_skip("vins_support", "brief_pattern.yml"))
    else:
        pattern = default_brief_pattern()
    imgs = frames[:3]
    pts, valid = _keypoints(imgs)
    desc = brief(torch.from_numpy(imgs).to(device), pts.to(device), valid.to(device), pattern=pattern).cpu()
    assert desc.shape == (3, pts.shape[1], 4) and desc.dtype == torch.int64
    for i in range(3):
        ref = _numpy_brief(imgs[i], pts[i].numpy(), valid[i].numpy(), pattern.numpy())
        np.testing.assert_array_equal(desc[i].numpy(), ref)
    assert (desc[~valid] == 0).all()
    assert (desc[valid] != 0).any(dim=-1).float().mean() > 0.9


def test_brief_patterns():
    p = load_brief_pattern(shared_data_or_skip("vins_support", "brief_pattern.yml"))
    assert p.shape == (4, 256) and p.dtype == torch.int64 and p.abs().max() <= 24
    d = default_brief_pattern()
    assert np.array_equal(d.numpy(), make_brief_pattern())  # the shipped file is reproducible
    assert DEFAULT_PATTERN_PATH.exists()
    # same statistics as VINS's pattern: centred Gaussian, sigma ~ 48 / 5, clipped to +-24
    assert d.abs().max() <= 24 and abs(d.float().std().item() - p.float().std().item()) < 1.0
    assert not ((d[0] == d[2]) & (d[1] == d[3])).any()
    with pytest.raises(ValueError):
        brief(torch.zeros(1, 20, 20, dtype=torch.uint8), torch.zeros(1, 1, 2), pattern=d[:3])


def test_load_brief_pattern_errors(tmp_path):
    bad = tmp_path / "bad.yml"
    bad.write_text("%YAML:1.0\nx1: [1, 2]\ny1: [1, 2]\nx2: [1, 2]\n")
    with pytest.raises(ConfigError, match="y2"):
        load_brief_pattern(bad)
    bad.write_text("%YAML:1.0\nx1: [1, 2]\ny1: [1, 2]\nx2: [1, 2]\ny2: [1, 2]\n")
    with pytest.raises(ConfigError, match="multiple of 64"):
        load_brief_pattern(bad)


def _numpy_hamming(a, b):
    ua = np.unpackbits(a.view(np.uint8), axis=-1)
    ub = np.unpackbits(b.view(np.uint8), axis=-1)
    return (ua[..., :, None, :] != ub[..., None, :, :]).sum(-1)


def test_hamming_exact(frames, device):
    pts, valid = _keypoints(frames[:2])
    desc = brief(torch.from_numpy(frames[:2]), pts, valid)[:, :300]
    rng = np.random.default_rng(3)
    extremes = torch.tensor([[0, 0, 0, 0], [-1, -1, -1, -1], [-(2**63), 2**63 - 1, 1, -2]], dtype=torch.int64)
    rand = torch.from_numpy(rng.integers(-(2**63), 2**63 - 1, (2, 50, 4), dtype=np.int64))
    a = torch.cat([desc, rand, extremes.expand(2, 3, 4)], 1)
    b = torch.cat([desc[:, :100].flip(0), rand.flip(1), extremes.expand(2, 3, 4)], 1)
    h = hamming(a.to(device), b.to(device)).cpu()
    assert h.shape == (2, a.shape[1], b.shape[1]) and h.dtype == torch.int64
    np.testing.assert_array_equal(h.numpy(), _numpy_hamming(a.numpy(), b.numpy()))
    # broadcasting over leading dims, unbatched use
    np.testing.assert_array_equal(hamming(a[0], b).numpy(), _numpy_hamming(a[0].numpy()[None], b.numpy()))
    np.testing.assert_array_equal(hamming(a[0], b[0]).numpy(), _numpy_hamming(a[0].numpy(), b[0].numpy()))
    with pytest.raises(ValueError):
        hamming(a, b[..., :3])
