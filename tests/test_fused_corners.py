"""The fused detection (``torch_frontend::good_features``, ``fused/corners_op.py``): every corner and its
order equal to the tensor path's and to ``cv2.goodFeaturesToTrack``'s, as VINS calls it (quality 0.01,
block 3, min eigenvalue, setMask-style masks).

Convention:
    Frames: the repo's EuRoC sample (cam0 / cam1, raw and CLAHE 3.0 / 8x8 as VINS-Mono equalises),
    ``../shared``'s V1_01 excerpt and Middlebury pair (skipped, saying so, when absent). Masks: 255
    with filled discs of radius ``min_dist`` at random points (what setMask leaves), and VINS's
    fisheye-like disc. The Triton kernels run in Triton's interpreter in a child process
    (``TRITON_INTERPRET`` is read when ``@triton.jit`` decorates).
"""

from __future__ import annotations

import os
import subprocess
import sys

import cv2
import numpy as np
import pytest
import torch

from torch_frontend import _tuning, fused
from torch_frontend.corners import _good_features_impl
from torch_frontend.errors import ConfigError
from torch_frontend.fused.corners_op import good_features_op
from torch_frontend.testing.dispatch_count import OpCounter

from .conftest import REPO, load_gray, sample_frames, shared_data_or_skip

_CLAHE = cv2.createCLAHE(3.0, (8, 8))


def _frames(camera="cam0", n=3, clahe=False):
    out = [load_gray(f) for f in sample_frames(camera)[:n]]
    return [_CLAHE.apply(f) for f in out] if clahe else out


def _disc_mask(shape, n, radius, seed):
    """255 with ``n`` filled discs of ``radius`` at random points (setMask's mask), uint8."""
    h, w = shape
    m = np.full((h, w), 255, np.uint8)
    rng = np.random.default_rng(seed)
    for x, y in zip(rng.integers(0, w, n), rng.integers(0, h, n)):
        cv2.circle(m, (int(x), int(y)), int(radius), 0, -1)
    return m


def _check(imgs, max_corners, min_dist, masks=None, quality=0.01):
    """fused == tensor == cv2 for a batch of frames (each stream its own max_corners / mask)."""
    x = torch.from_numpy(np.stack(imgs))
    B = x.shape[0]
    mc = torch.as_tensor(max_corners).expand(B).contiguous()
    K = int(mc.max())
    m = None if masks is None else torch.from_numpy(np.stack(masks) != 0)
    pts, valid, ovf = good_features_op(x, mc, m, K, quality, float(min_dist))
    assert not bool(ovf.any())
    ref = _good_features_impl(x[:, None], mc, quality, float(min_dist), m, False, 3, 0.04, K, backend="tensor")
    assert torch.equal(pts, ref.pts) and torch.equal(valid, ref.valid)
    for b in range(B):
        want = cv2.goodFeaturesToTrack(imgs[b], int(mc[b]), quality, float(min_dist),
                                       mask=None if masks is None else masks[b])
        want = np.zeros((0, 2), np.float32) if want is None else want.reshape(-1, 2)
        got = pts[b][valid[b]].numpy()
        np.testing.assert_array_equal(got, want, err_msg=f"stream {b}: max_corners {int(mc[b])}, min_dist {min_dist}")
        assert bool(valid[b, :len(want)].all()) and not bool(valid[b, len(want):].any())
    return valid.sum(1)


@pytest.mark.parametrize("camera,clahe", [("cam0", False), ("cam0", True), ("cam1", True)])
def test_fused_equals_tensor_and_cv2_on_sample_frames(camera, clahe):
    """VINS's first frame (no mask, 150 corners, MIN_DIST 30) on three frames as one batch of streams."""
    imgs = _frames(camera, 3, clahe)
    n = _check(imgs, 150, 30)
    assert int(n.min()) > 40


@pytest.mark.parametrize("max_corners,min_dist", [(37, 30), (300, 20), (80, 25.5), (500, 10), (60, 0.5), (40, 1.4)])
def test_fused_with_setmask_masks(max_corners, min_dist):
    """The steady state: masks with discs around tracked features; other counts and distances (25.5:
    OpenCV's grid cell rounds to 26; 0.5: no distance test; 1.4: a cell of 1)."""
    imgs = _frames("cam0", 2, clahe=True)
    masks = [_disc_mask(imgs[0].shape, 90, 30, seed=b) for b in range(2)]
    _check(imgs, max_corners, min_dist, masks)


def test_streams_are_independent():
    """B = 4 streams with their own counts and masks (one empty) equal four B = 1 calls."""
    imgs = _frames("cam0", 4, clahe=True)
    masks = [_disc_mask(imgs[0].shape, 40 * b, 25, seed=b) for b in range(4)]
    masks[3][:] = 0  # an empty mask: maxVal 0, no corner
    mc = torch.tensor([150, 20, 0, 75])
    x = torch.from_numpy(np.stack(imgs))
    m = torch.from_numpy(np.stack(masks) != 0)
    pts, valid, _ = good_features_op(x, mc, m, 150, 0.01, 30.0)
    for b in range(4):
        p1, v1, _ = good_features_op(x[b:b + 1], mc[b:b + 1], m[b:b + 1], 150, 0.01, 30.0)
        assert torch.equal(p1[0], pts[b]) and torch.equal(v1[0], valid[b])
    assert int(valid[2].sum()) == 0 and int(valid[3].sum()) == 0
    _check(imgs[:3], [150, 20, 75], 30, masks[:3])


def test_thread_groups_give_the_same_bits():
    imgs = _frames("cam0", 4)
    x = torch.from_numpy(np.stack(imgs))
    mc = torch.full((4,), 150)
    one = good_features_op(x, mc, None, 150, 0.01, 30.0)
    n = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        two = good_features_op(x, mc, None, 150, 0.01, 30.0)
    finally:
        torch.set_num_threads(n)
    assert all(torch.equal(a, b) for a, b in zip(one, two))


def test_fused_on_shared_frames():
    """../shared: V1_01 frames (with and without a mask) and the Middlebury pair (741 x 500, odd width)."""
    seq = shared_data_or_skip("sequences", "euroc_v1_01_easy_micro", "mav0", "cam0", "data")
    files = sorted(seq.glob("*.png"))[::30][:3]
    imgs = [_CLAHE.apply(load_gray(f)) for f in files]
    _check(imgs, 150, 30)
    _check(imgs, 150, 30, [_disc_mask(imgs[0].shape, 70, 30, seed=10 + b) for b in range(len(imgs))])
    mid = shared_data_or_skip("flow", "middlebury2014_motorcycle_stereo")
    pair = [load_gray(mid / f"motorcycle_{s}.png") for s in ("left", "right")]
    _check(pair, 200, 20)


def test_small_and_flat_images():
    """Edges of the contract: 2 x 2 and 3 x 5 images (no interior), a flat image (no response), a
    tiny textured one; capacity 0."""
    rng = np.random.default_rng(3)
    for h, w in ((2, 2), (3, 5), (5, 3), (9, 11)):
        imgs = [rng.integers(0, 256, (h, w), dtype=np.uint8) for _ in range(2)]
        _check(imgs, 10, 1.0)
    _check([np.full((20, 30), 77, np.uint8)], 10, 3.0)
    x = torch.from_numpy(np.stack(_frames("cam0", 1)))
    pts, valid, ovf = good_features_op(x, torch.tensor([5]), None, 0, 0.01, 30.0)
    assert pts.shape == (1, 0, 2) and valid.shape == (1, 0) and ovf.shape == (1,)


def test_capturable_door_equals_tensor_capturable():
    """``_good_features_impl(capturable=True, backend="fused")`` (the tracker's capturable step on the
    CPU) equals the tensor capturable path where that one does not overflow; the op never does."""
    imgs = _frames("cam0", 2, clahe=True)
    x = torch.from_numpy(np.stack(imgs))[:, None]
    m = torch.from_numpy(np.stack([_disc_mask(imgs[0].shape, 60, 30, seed=b) for b in range(2)]) != 0)
    mc = torch.tensor([150, 64])
    a = _good_features_impl(x, mc, 0.01, 30.0, m, False, 3, 0.04, 150, capturable=True, backend="fused")
    b = _good_features_impl(x, mc, 0.01, 30.0, m, False, 3, 0.04, 150, capturable=True, backend="tensor")
    assert not bool(b.overflow.any()) and not bool(a.overflow.any())
    assert torch.equal(a.pts, b.pts) and torch.equal(a.valid, b.valid)
    d = _good_features_impl(x, mc, 0.01, 30.0, m, False, 3, 0.04, None, backend="fused")
    assert d.overflow is None and torch.equal(d.pts, a.pts)
    # where the fused op does not apply (Harris, another block, a float image) the tensor path runs
    h = _good_features_impl(x, mc, 0.01, 30.0, m, True, 3, 0.04, None, backend="fused")
    assert torch.equal(h.pts, _good_features_impl(x, mc, 0.01, 30.0, m, True, 3, 0.04, None).pts)


def test_one_op_no_sync():
    imgs = _frames("cam0", 2)
    x = torch.from_numpy(np.stack(imgs))[:, None]
    mc = torch.tensor([150, 150])
    m = torch.from_numpy(np.stack([_disc_mask(imgs[0].shape, 60, 30, seed=b) for b in range(2)]) != 0)
    _good_features_impl(x, mc, 0.01, 30.0, m, False, 3, 0.04, 150, capturable=True, backend="fused")
    with OpCounter() as c:
        _good_features_impl(x, mc, 0.01, 30.0, m, False, 3, 0.04, 150, capturable=True, backend="fused")
    # the op, and the view of the image's channel
    assert c.kernels == 1 and c.syncs == 0, c.summary()
    with OpCounter() as t:
        _good_features_impl(x, mc, 0.01, 30.0, m, False, 3, 0.04, 150, capturable=True, backend="tensor")
    assert t.kernels > 50, t.summary()


def test_resolver():
    assert _tuning.CPU.corner_backend == "fused" and _tuning.CUDA.corner_backend == "fused"
    assert fused.resolve_corner_backend(None, "cpu") == "fused"
    assert fused.resolve_corner_backend("tensor", "cpu") == "tensor"
    assert fused.resolve_corner_backend("auto", "meta") == "tensor"  # ONE_PASS: the tensor path
    with pytest.raises(ConfigError, match="corner_backend"):
        fused.resolve_corner_backend("numba", "cpu")
    with pytest.raises(ConfigError, match="corner_backend='fused' cannot run on meta"):
        fused.resolve_corner_backend("fused", "meta")


@pytest.mark.parametrize("capturable", [False, True])
def test_tracker_fused_equals_tensor_detection(capturable):
    """Frames of the sample through the tracker (EuRoC config: CLAHE, setMask) with each detection
    backend: the same features, frame by frame."""
    import torch_frontend as tf

    cfg = tf.load_config(REPO / "configs" / "euroc.yaml")
    a = tf.FeatureTracker(cfg, capturable=capturable)
    b = tf.FeatureTracker(cfg, capturable=capturable, corner_backend="tensor")
    assert a.corner_backend == "fused" and b.corner_backend == "tensor"
    assert a.params.corner_backend == "fused"
    for i, f in enumerate(sample_frames("cam0")[:5]):
        img = torch.from_numpy(load_gray(f))[None, None]
        fa, fb = a.track(img, [0.05 * i]), b.track(img, [0.05 * i])
        for name, x in vars(fa).items():
            y = getattr(fb, name)
            if isinstance(x, torch.Tensor):
                assert torch.equal(x, y), (i, name)


# ------------------------------------------------------------------------------- Triton (interpreter)
_INTERP = r"""
import numpy as np, torch, cv2, sys
sys.path.insert(0, {repo!r})
import torch_frontend.corners  # registers the selection
from torch_frontend.fused._triton_corners import good_features_cuda
from torch_frontend.fused.corners_op import _SELECTION, good_features_op
img = cv2.imread({frame!r}, cv2.IMREAD_GRAYSCALE)
x = torch.from_numpy(np.stack([img[100:100 + {h}, 200:200 + {w}], img[300:300 + {h}, 400:400 + {w}]])).contiguous()
B, H, W = x.shape
m = torch.ones(B, H, W, dtype=torch.bool); m[0, 5:15, 8:20] = False; m[1, :, :10] = False
for mask, md, mc in {cases}:
    mcs = torch.tensor(mc)
    a = good_features_cuda(x, mcs, m if mask else None, max(mc), 0.01, md, _SELECTION[0])
    b = good_features_op(x, mcs, m if mask else None, max(mc), 0.01, md)
    assert all(torch.equal(u, v) for u, v in zip(a, b)), (mask, md, mc, a, b)
    assert int(b[1].sum()) > 0
print("PASS")
"""


def _interpret(h, w, cases):
    pytest.importorskip("triton", reason="the fused CUDA kernels are Triton kernels: triton is not installed")
    env = dict(os.environ, TRITON_INTERPRET="1", OMP_NUM_THREADS="1")
    code = _INTERP.format(repo=str(REPO), frame=str(sample_frames("cam0")[1]), h=h, w=w, cases=cases)
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0 and "PASS" in proc.stdout, proc.stderr[-4000:]


def test_triton_equals_cpu_interpreted_small():
    """The Triton kernels + the capturable selection == the CPU kernel, a 24 x 32 crop, with a mask."""
    _interpret(24, 32, [(True, 5.0, [12, 7])])


@pytest.mark.slow
def test_triton_equals_cpu_interpreted():
    """Larger crops, with and without a mask, distances 10, 3 and 0.5 (no test)."""
    _interpret(60, 90, [(False, 10.0, [30, 12]), (True, 10.0, [30, 12]), (True, 3.0, [40, 40]),
                        (False, 0.5, [25, 5])])


def test_op_passes_opcheck_and_compiles_as_one_node():
    """``torch.library.opcheck`` (schema, fake, autograd registration, AOT dispatch) with and without a
    mask, and ``torch.compile(fullgraph=True)`` of a call: no graph break, the same bits."""
    imgs = _frames("cam0", 2)
    x = torch.from_numpy(np.stack(imgs))[:, 100:180, 200:320].contiguous()
    m = torch.ones(x.shape, dtype=torch.bool)
    m[:, 20:50, 30:70] = False
    mc = torch.tensor([20, 7])
    for mask in (None, m):
        res = torch.library.opcheck(good_features_op, (x, mc, mask, 20, 0.01, 10.0))
        assert all(v == "SUCCESS" for v in res.values()), res

    def fn(x, mc, m):
        return good_features_op(x, mc, m, 20, 0.01, 10.0)

    got = torch.compile(fn, backend="eager", fullgraph=True)(x, mc, m)
    assert all(torch.equal(a, b) for a, b in zip(got, fn(x, mc, m)))
