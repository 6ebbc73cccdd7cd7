"""Image pyramid and Scharr derivatives vs OpenCV (``cv2.pyrDown`` chains, ``cv2.Scharr``)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from tests.conftest import load_gray, sample_frames
from torch_frontend.pyramid import (
    Pyramid,
    _build_pyramid_impl,
    build_pyramid,
    pad_reflect101,
    pyr_down,
    scharr_gradients,
)

pytestmark = pytest.mark.usefixtures("single_thread")  # many small ops (conftest)


@pytest.fixture(scope="module")
def frame():
    return load_gray(sample_frames("cam0")[0])


# full frame, odd sizes (751x479 and small odd crops), tiny images (multiple reflections)
CROPS = [(480, 752), (479, 751), (37, 41), (6, 3), (2, 1)]


@pytest.mark.parametrize("hw", CROPS, ids=[f"{h}x{w}" for h, w in CROPS])
def test_pyr_down_matches_cv2(frame, hw, device):
    h, w = hw
    img = np.ascontiguousarray(frame[:h, :w])
    ref = cv2.pyrDown(img)
    out = pyr_down(torch.from_numpy(img).to(device)[None, None])
    assert out.dtype == torch.float32
    assert tuple(out.shape) == (1, 1) + ref.shape == (1, 1, (h + 1) // 2, (w + 1) // 2)
    out = out[0, 0].cpu().numpy()
    assert np.abs(out - ref).max() <= 0.5  # unrounded float vs OpenCV's rounded 8-bit
    assert np.array_equal(np.floor(out + 0.5).astype(np.uint8), ref)  # OpenCV: (sum + 128) >> 8


@pytest.mark.parametrize("hw", CROPS[:3], ids=[f"{h}x{w}" for h, w in CROPS[:3]])
def test_build_pyramid_uint8_identical_to_cv2_chain(frame, hw, device):
    h, w = hw
    img = np.ascontiguousarray(frame[:h, :w])
    pyr = build_pyramid(torch.from_numpy(img).to(device)[None, None], max_level=4)
    assert isinstance(pyr, Pyramid) and pyr.rounded and pyr.max_level == 4
    ref = img
    for l in range(5):
        if l:
            ref = cv2.pyrDown(ref)
        lv = pyr.levels[l][0, 0].cpu().numpy()
        assert lv.shape == ref.shape
        assert np.array_equal(lv, ref.astype(np.float32)), f"level {l}"
        gx = cv2.Scharr(ref, cv2.CV_16S, 1, 0)
        gy = cv2.Scharr(ref, cv2.CV_16S, 0, 1)
        g = pyr.grads[l][0].cpu().numpy()
        assert np.array_equal(g[0], gx) and np.array_equal(g[1], gy), f"level {l} gradients"
    # cv2.buildOpticalFlowPyramid (what calcOpticalFlowPyrLK uses) gives the same levels
    n, cvpyr = cv2.buildOpticalFlowPyramid(img, (5, 5), 4, withDerivatives=False)
    for l in range(n + 1):
        assert np.array_equal(pyr.levels[l][0, 0].cpu().numpy(), cvpyr[l].astype(np.float32))


def test_build_pyramid_float_within_half_grey_level(frame, dtype):
    img = frame[:479, :751]
    pyr = build_pyramid(torch.from_numpy(img).to(dtype)[None], max_level=3, with_gradients=False)
    assert not pyr.rounded and pyr.grads is None and pyr.levels[0].dtype == dtype
    ref = img
    for l in range(1, 4):
        ref = cv2.pyrDown(ref)
        diff = np.abs(pyr.levels[l][0, 0].numpy() - ref)
        # OpenCV rounds each level (error <= 0.5) and the normalised positive kernel does not amplify
        # what it inherits, so the unrounded chain stays within 0.5 grey level per level
        assert diff.max() <= 0.5 * l, (l, diff.max())
        assert np.mean(diff) < 0.3
    assert pyr.with_gradients().grads is not None
    # float input holding 8-bit values + round_levels=True reproduces OpenCV exactly
    pr = build_pyramid(torch.from_numpy(img).to(dtype)[None], max_level=3, round_levels=True)
    assert pr.rounded and np.array_equal(pr.levels[3][0, 0].numpy(), ref)


def test_scharr_matches_cv2(frame, dtype):
    img = frame[100:160, 200:290]
    g = scharr_gradients(torch.from_numpy(img).to(dtype)[None, None])
    assert g.shape == (1, 2, 60, 90) and g.dtype == dtype
    assert np.array_equal(g[0, 0].numpy(), cv2.Scharr(img, cv2.CV_16S, 1, 0))
    assert np.array_equal(g[0, 1].numpy(), cv2.Scharr(img, cv2.CV_16S, 0, 1))
    # the LK template derivative is BORDER_REFLECT_101 inside the image, like cv2.Scharr's default
    ref101 = cv2.Scharr(img, cv2.CV_16S, 1, 0, borderType=cv2.BORDER_REFLECT_101)
    assert np.array_equal(g[0, 0].numpy(), ref101)


def test_batch_and_layouts(frame):
    imgs = np.stack([frame[:100, :120], frame[50:150, 100:220], frame[200:300, 300:420]])
    t = torch.from_numpy(imgs)  # (B, H, W) accepted
    pb = build_pyramid(t, max_level=2)
    for b in range(3):
        single = build_pyramid(t[b : b + 1, None], max_level=2)
        for l in range(3):
            assert torch.equal(pb.levels[l][b], single.levels[l][0])
            assert torch.equal(pb.grads[l][b], single.grads[l][0])
    assert pb.sizes() == [(100, 120), (50, 60), (25, 30)]


def test_grouped_build_and_padded_cache(frame, monkeypatch):
    """Large CPU batches are built in groups of streams: same levels and gradients as one pass.
    Padded levels are cached per (level, pad, dtype) and come along with select()."""
    import dataclasses

    from torch_frontend import _tuning

    imgs = torch.from_numpy(np.stack([frame[:100, :120], frame[50:150, 100:220], frame[200:300, 300:420]]))
    whole = build_pyramid(imgs, max_level=2)
    assert _tuning.CPU.pyramid_streams(3, 100, 120) is None  # small batch: one pass on the CPU, too
    groups = dataclasses.replace(_tuning.CPU, pyramid_batch_pixels=100, pyramid_group_pixels=100 * 120)
    assert groups.pyramid_streams(3, 100, 120) == 1  # one stream per group
    monkeypatch.setitem(_tuning.STRATEGIES, "cpu", groups)
    grouped = build_pyramid(imgs, max_level=2)
    for l in range(3):
        assert torch.equal(grouped.levels[l], whole.levels[l])
        assert torch.equal(grouped.grads[l], whole.grads[l])
    p = grouped.padded(1, 3, 4)
    assert p.shape == (3, 1, 56, 68)
    assert torch.equal(p, pad_reflect101(grouped.levels[1], 3, 4))
    assert grouped.padded(1, 3, 4) is p  # cached
    assert grouped.padded(1, 3, 4, torch.float64).dtype == torch.float64
    sub = grouped.select(slice(1, 3))
    assert torch.equal(sub.padded(1, 3, 4), p[1:3])


def test_pad_reflect101_matches_cv2():
    x = np.arange(12, dtype=np.float32).reshape(3, 4)
    for p in (1, 2, 5, 9):  # pads larger than the image need repeated reflection
        ref = cv2.copyMakeBorder(x, p, p, p, p, cv2.BORDER_REFLECT_101)
        out = pad_reflect101(torch.from_numpy(x)[None, None], p, p)[0, 0].numpy()
        assert np.array_equal(out, ref), p


def test_gradients_flow():
    img = (torch.rand(1, 1, 9, 11, dtype=torch.float64) * 255).requires_grad_()
    assert torch.autograd.gradcheck(lambda x: pyr_down(x), (img,))
    assert torch.autograd.gradcheck(lambda x: scharr_gradients(x), (img,))
    assert torch.autograd.gradcheck(lambda x: build_pyramid(x, 2).levels[2], (img,))


def test_bad_inputs():
    from torch_frontend.errors import ConfigError

    with pytest.raises(ValueError, match=r"\(B, 1, H, W\)"):
        pyr_down(torch.zeros(1, 3, 8, 8))
    with pytest.raises(ConfigError):
        build_pyramid(torch.zeros(1, 1, 8, 8), max_level=-1)


@pytest.mark.parametrize("hw", CROPS, ids=[f"{h}x{w}" for h, w in CROPS])
def test_conv_pyramid_equals_separable_and_cv2(frame, hw, monkeypatch):
    """``Strategy.pyramid_conv`` (a device's form: one strided 5x5 conv2d with bias 0.5 per level,
    level 0 a view into the padded image) == the separable CPU form == the cv2.pyrDown chain."""
    import dataclasses

    from torch_frontend import _tuning
    from torch_frontend.testing.dispatch_count import OpCounter

    h, w = hw
    imgs = np.stack([frame[:h, :w], frame[-h:, -w:]])
    x = torch.from_numpy(imgs)[:, None]
    ref = build_pyramid(x, max_level=3, backend="tensor")
    fused = build_pyramid(x, max_level=3, backend="fused")  # one op, uint8 levels (tests/test_fused.py)
    monkeypatch.setitem(_tuning.STRATEGIES, "cpu", dataclasses.replace(_tuning.CPU, pyramid_conv=True))
    _build_pyramid_impl(x, 3, False, True)  # warm-up: cached taps
    with OpCounter() as c:
        _build_pyramid_impl(x, 3, False, True)
    assert c.syncs == 0, c.summary()
    if min(h, w) >= 16:  # pads smaller than every level: one reflection_pad2d each (else a gather)
        assert c.kernels == 10, c.summary()  # pad, convert; 3 x (conv, floor); 2 pads
    got = build_pyramid(x, max_level=3, backend="tensor")
    assert got.rounded and fused.rounded and fused.packed is not None
    for l in range(4):
        assert got.levels[l].dtype == torch.float32 and torch.equal(got.levels[l], ref.levels[l]), l
        assert fused.levels[l].dtype == torch.uint8 and torch.equal(fused.levels[l].float(), ref.levels[l]), l
        assert torch.equal(got.grads[l], ref.grads[l]) and torch.equal(fused.grads[l], ref.grads[l]), l
        assert torch.equal(got.padded(l, 3, 4), ref.padded(l, 3, 4)), l
        assert torch.equal(fused.padded(l, 3, 4, torch.float32), ref.padded(l, 3, 4)), l
    for b in range(2):
        c = imgs[b]
        for l in range(1, 4):
            c = cv2.pyrDown(c)
            assert np.array_equal(got.levels[l][b, 0].numpy(), c.astype(np.float32)), (b, l)
    # float input and unrounded levels keep the separable form (their sums need not be exact)
    assert torch.equal(build_pyramid(x.float(), max_level=2).levels[2], build_pyramid(x.float(), 2).levels[2])
