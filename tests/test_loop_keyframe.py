"""Keyframes (spec §7.1–7.3, §7.11) and VINS's BRIEF matching ``searchByBRIEFDes`` (§7.6).

``match_brief`` is compared with a plain Python loop that follows the spec's words (first index with
the smallest distance among those < 128, accepted iff < 80), on random descriptors with planted
ties and near-duplicates and on real FAST/BRIEF descriptors of two EuRoC frames (distances by numpy
popcount, independent of ``hamming``). Keyframe contents are checked against ``cv2.FAST`` and the
camera model.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from torch_frontend.camera import PinholeCamera
from torch_frontend.errors import DataError
from torch_frontend.loop.features import brief, fast
from torch_frontend.loop.keyframe import KeyFrame, describe_keyframes, match_brief

from .conftest import load_gray, sample_frames

# EuRoC cam0 intrinsics (radial-tangential), so that lift() is not a plain affine map
EUROC = dict(k1=-0.28340811, k2=0.07395907, p1=0.00019359, p2=1.76187114e-05,
             fx=458.654, fy=457.296, cx=367.215, cy=248.375)


def _camera(device="cpu"):
    return PinholeCamera(**EUROC, width=752, height=480, device=device)


# ------------------------------------------------------------------------------ reference
def _np_hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, 4) int64, (M, 4) int64 -> (N, M) popcount(a ^ b), by numpy bit unpacking."""
    x = a[:, None, :] ^ b[None, :, :]
    return np.unpackbits(x.view(np.uint8).reshape(*x.shape[:2], -1), axis=-1).sum(-1).astype(np.int64)


def _reference_match(wd, od, wv, ov, accept=80, search=128):
    """The spec's loop, literally: per window descriptor, scan the old ones in order."""
    B, N, _ = wd.shape
    idx = np.full((B, N), -1, dtype=np.int64)
    dist = np.full((B, N), search, dtype=np.int64)
    for b in range(B):
        D = _np_hamming(wd[b], od[b])
        for i in range(N):
            if not wv[b, i]:
                continue
            best, best_j = search, -1
            for j in range(od.shape[1]):
                if ov[b, j] and D[i, j] < best:
                    best, best_j = int(D[i, j]), j
            dist[b, i] = best
            if best_j >= 0 and best < accept:
                idx[b, i] = best_j
    return idx, dist


def _random_desc(rng, shape):
    return rng.integers(np.iinfo(np.int64).min, np.iinfo(np.int64).max, size=shape, dtype=np.int64, endpoint=True)


def _flip_bits(rng, d: np.ndarray, n: int) -> np.ndarray:
    """Copy of descriptor ``d (4,)`` with ``n`` distinct random bits flipped."""
    out = d.copy()
    for bit in rng.choice(256, size=n, replace=False):
        out[bit // 64] ^= np.int64(1) << np.int64(bit % 64) if bit % 64 < 63 else np.int64(np.iinfo(np.int64).min)
    return out


# ---------------------------------------------------------------------------------- match
def test_match_brief_equals_loop_reference_random(device):
    rng = np.random.default_rng(0)
    B, N, M = 3, 40, 70
    wd = _random_desc(rng, (B, N, 4))
    od = _random_desc(rng, (B, M, 4))
    for b in range(B):
        for i in range(0, N, 2):
            # near-duplicates at various distances around the 80 / 128 bounds, some planted twice
            # (equal distances at two old indices: the first must win)
            k = int(rng.integers(0, 140))
            j1, j2 = rng.choice(M, size=2, replace=False)
            od[b, j1] = _flip_bits(rng, wd[b, i], k)
            if i % 4 == 0:
                od[b, j2] = _flip_bits(rng, wd[b, i], k)
        # exact ties: the same old descriptor twice
        od[b, 5] = od[b, 60]
        wd[b, 1] = od[b, 60]
        wd[b, 3] = _flip_bits(rng, od[b, 5], 79)  # accept bound: 79 in, 80 out
        wd[b, 5] = _flip_bits(rng, od[b, 7], 80)
    wv = rng.random((B, N)) > 0.1
    ov = rng.random((B, M)) > 0.1
    ov[2] = False  # stream 2: few valid old corners, so some window rows find nothing below 128
    ov[:, 5] = ov[:, 60] = ov[:, 7] = True
    wv[:, [1, 3, 5]] = True
    ref_idx, ref_dist = _reference_match(wd, od, wv, ov)
    t = lambda a: torch.from_numpy(a).to(device)  # noqa: E731
    idx, dist, matched = match_brief(t(wd), t(od), t(wv), t(ov))
    assert idx.device.type == device.type
    np.testing.assert_array_equal(idx.cpu().numpy(), ref_idx)
    np.testing.assert_array_equal(dist.cpu().numpy(), ref_dist)
    np.testing.assert_array_equal(matched.cpu().numpy(), ref_idx >= 0)
    assert (idx[:, 1] == 5).all()  # tie -> first index
    assert (idx[:, 3] >= 0).all() and (dist[:, 3] <= 79).all()
    # planted data exercises every branch: accepted, found-but-rejected, nothing below 128
    assert (ref_idx >= 0).sum() > 15
    assert ((ref_idx < 0) & (ref_dist < 128) & wv).sum() > 5
    assert ((ref_dist == 128) & wv).sum() > 5
    assert (idx[~t(wv)] == -1).all()


def test_match_brief_many_to_one_and_empty():
    rng = np.random.default_rng(1)
    old = torch.from_numpy(_random_desc(rng, (1, 5, 4)))
    win = old[:, [2, 2, 2]].clone()  # three window points, the same old corner: all match it
    idx, dist, matched = match_brief(win, old)
    assert idx.tolist() == [[2, 2, 2]] and dist.tolist() == [[0, 0, 0]] and matched.all()
    idx, dist, matched = match_brief(win, old[:, :0])
    assert (idx == -1).all() and (dist == 128).all() and not matched.any()
    # custom bounds
    idx, _, _ = match_brief(win, old, accept=0)
    assert (idx == -1).all()


def test_match_brief_bad_input():
    d = torch.zeros(2, 3, 4, dtype=torch.int64)
    with pytest.raises(ValueError, match="old_desc"):
        match_brief(d, torch.zeros(3, 3, 4, dtype=torch.int64))
    with pytest.raises(ValueError, match="window_desc"):
        match_brief(torch.zeros(3, 4, dtype=torch.int64), d)
    with pytest.raises(TypeError, match="int64"):
        match_brief(d.int(), d)
    with pytest.raises(ValueError, match="window_valid"):
        match_brief(d, d, window_valid=torch.ones(2, 4, dtype=torch.bool))


def test_match_brief_real_euroc_frames():
    """Window = Shi-Tomasi corners of frame 0, old = FAST corners of frame 12 (real BRIEF)."""
    from torch_frontend.corners import good_features_to_track

    frames = sample_frames("cam0")
    imgs = torch.from_numpy(np.stack([load_gray(frames[0]), load_gray(frames[12])]))[:, None]
    pts, valid = good_features_to_track(imgs, 150, 0.01, 30)
    d = describe_keyframes(imgs, _camera(), pts, valid)
    wd, wv = d["window_brief"][:1], valid[:1]
    od, ov = d["brief"][1:], d["keypoints_valid"][1:]
    idx, dist, matched = match_brief(wd, od, wv, ov)
    ref_idx, ref_dist = _reference_match(wd.numpy(), od.numpy(), wv.numpy(), ov.numpy())
    np.testing.assert_array_equal(idx.numpy(), ref_idx)
    np.testing.assert_array_equal(dist.numpy(), ref_dist)
    # the MAV barely moves in these frames: most window points find their own corner again
    n = int(matched.sum())
    assert n > 60
    kp = d["keypoints"][1][idx[0][matched[0]]]
    close = (kp - pts[0][matched[0]]).norm(dim=-1) < 3
    assert int(close.sum()) > 0.7 * n


# -------------------------------------------------------------------------------- describe
def test_describe_keyframes_batched_equals_single(device):
    frames = sample_frames("cam0")
    imgs = torch.from_numpy(np.stack([load_gray(frames[0])[:200, :300], load_gray(frames[5])[100:300, 200:500]]))
    imgs = imgs[:, None].to(device)
    rng = np.random.default_rng(2)
    uv = torch.from_numpy(rng.uniform([0, 0], [299, 199], size=(2, 30, 2))).to(device)
    valid = torch.from_numpy(rng.random((2, 30)) > 0.2).to(device)
    cam = _camera(device)
    d = describe_keyframes(imgs, cam, uv, valid)
    for b in range(2):
        s = describe_keyframes(imgs[b:b + 1], cam, uv[b:b + 1], valid[b:b + 1])
        K = int(s["keypoints_valid"].sum())
        kv = d["keypoints_valid"][b]
        assert int(kv.sum()) == K
        assert torch.equal(d["keypoints"][b][kv], s["keypoints"][0][:K])
        assert torch.equal(d["keypoints_norm"][b][kv], s["keypoints_norm"][0][:K])
        assert torch.equal(d["brief"][b][kv], s["brief"][0][:K])
        assert torch.equal(d["window_brief"][b], s["window_brief"][0])
        assert (d["brief"][b][~kv] == 0).all() and (d["keypoints_norm"][b][~kv] == 0).all()
    assert (d["window_brief"][~valid] == 0).all()
    assert d["keypoints"].dtype == torch.float32 and d["keypoints_norm"].dtype == torch.float64
    # max_keypoints keeps the strongest
    m = describe_keyframes(imgs, cam, uv, valid, max_keypoints=10)
    assert m["keypoints"].shape[1] == 10 and m["keypoints_valid"].all()
    with pytest.raises(ValueError, match="pts_uv"):
        describe_keyframes(imgs, cam, uv[:1])


# ------------------------------------------------------------------------------ KeyFrame
def _points(n=40, seed=3):
    rng = np.random.default_rng(seed)
    uv = rng.uniform([30, 30], [720, 450], size=(n, 2)).astype(np.float32)
    p3 = rng.normal(size=(n, 3))
    return uv, p3, np.arange(100, 100 + n)


def test_keyframe_create_contents():
    img = load_gray(sample_frames("cam0")[3])
    cam = _camera()
    uv, p3, ids = _points()
    T = np.array([1.0, 2.0, 3.0])
    R = cv2.Rodrigues(np.array([0.1, -0.2, 0.3]))[0]
    kf = KeyFrame.create(12.5, img, T, R, p3, uv, ids, cam, sequence=2)
    assert kf.time == 12.5 and kf.sequence == 2 and kf.index == -1 and not kf.has_loop and kf.loop_index == -1
    assert kf.image is None
    # FAST exactly as OpenCV (threshold 20, non-max suppression) on the raw image, raster order
    cvk = cv2.FastFeatureDetector_create(20, True).detect(img)
    ref = np.array(sorted((k.pt for k in cvk), key=lambda p: (p[1], p[0])), dtype=np.float32)
    np.testing.assert_array_equal(kf.keypoints.numpy(), ref)
    assert kf.num_keypoints == len(ref) > 300
    # normalized coordinates through the camera model
    P = cam.lift(kf.keypoints.double())
    assert torch.equal(kf.keypoints_norm, P[:, :2] / P[:, 2:])
    P = cam.lift(torch.from_numpy(uv).double())
    assert torch.equal(kf.point_2d_norm, P[:, :2] / P[:, 2:])
    # descriptors = loop.features.brief on the raw image
    im = torch.from_numpy(img)[None, None]
    assert torch.equal(kf.brief, brief(im, kf.keypoints[None])[0])
    assert torch.equal(kf.window_brief, brief(im, torch.from_numpy(uv)[None])[0])
    # dtypes, shapes, poses
    assert kf.point_3d.dtype == torch.float64 and kf.point_2d_uv.dtype == torch.float32
    assert kf.point_id.dtype == torch.int64 and kf.point_id.tolist() == ids.tolist()
    assert kf.num_points == 40 and kf.window_brief.shape == (40, 4)
    for a in ("origin_vio_T", "vio_T", "T_w_i"):
        np.testing.assert_array_equal(getattr(kf, a).numpy(), T)
    for a in ("origin_vio_R", "vio_R", "R_w_i"):
        np.testing.assert_array_equal(getattr(kf, a).numpy(), R)
    assert kf.vio_T.data_ptr() != kf.origin_vio_T.data_ptr() != kf.T_w_i.data_ptr()
    assert kf.loop_info.shape == (8,) and kf.loop_info.dtype == torch.float64 and not kf.loop_info.any()
    # pose updates (VINS updateVioPose / updatePose) never touch the origin pose
    kf.update_vio_pose(torch.zeros(3, dtype=torch.float64), torch.eye(3, dtype=torch.float64))
    assert not kf.T_w_i.any() and kf.origin_vio_T.tolist() == T.tolist()
    kf.update_pose(torch.ones(3, dtype=torch.float64), torch.eye(3, dtype=torch.float64))
    assert kf.T_w_i.tolist() == [1, 1, 1] and not kf.vio_T.any()


def test_keyframe_create_options():
    img = load_gray(sample_frames("cam0")[0])[:240, :320]
    uv, p3, ids = _points(10)
    uv = uv % np.array([319, 239], dtype=np.float32)
    norm = np.random.default_rng(4).normal(size=(10, 2))
    kf = KeyFrame.create(1.0, torch.from_numpy(img), torch.zeros(3), torch.eye(3), p3, uv, ids, _camera(),
                         point_2d_norm=norm, fast_threshold=40, save_image=True)
    np.testing.assert_array_equal(kf.point_2d_norm.numpy(), norm)
    n40 = len(cv2.FastFeatureDetector_create(40, True).detect(img))
    assert kf.num_keypoints == n40
    assert kf.image is not None and torch.equal(kf.image, torch.from_numpy(img))
    assert kf.origin_vio_T.dtype == torch.float64  # float32 input poses are stored as float64


@pytest.mark.parametrize("case", ["no_points", "nan_pose", "inf_point", "nan_uv", "mismatch", "mismatch_norm",
                                  "image_3d", "image_float"])
def test_keyframe_create_errors(case):
    img = load_gray(sample_frames("cam0")[0])[:120, :160]
    uv, p3, ids = _points(8)
    uv = uv % np.array([159, 119], dtype=np.float32)
    T, R, norm = np.zeros(3), np.eye(3), None
    msg = "nan or inf"
    if case == "no_points":
        uv, p3, ids = uv[:0], p3[:0], ids[:0]
        msg = "needs tracked features with 3D points"
    elif case == "nan_pose":
        T = np.array([0.0, np.nan, 0.0])
    elif case == "inf_point":
        p3[3, 1] = np.inf
    elif case == "nan_uv":
        uv[2, 0] = np.nan
    elif case == "mismatch":
        ids = ids[:5]
        msg = "different lengths"
    elif case == "mismatch_norm":
        norm = np.zeros((7, 2))
        msg = "different lengths"
    elif case == "image_3d":
        img = np.stack([img, img], -1)
        msg = "2-D uint8"
    elif case == "image_float":
        img = img.astype(np.float32)
        msg = "2-D uint8"
    with pytest.raises(DataError, match=f"(?i)time 7.250000.*{msg}"):
        KeyFrame.create(7.25, img, T, R, p3, uv, ids, _camera(), point_2d_norm=norm)


def test_keyframe_loaded():
    rng = np.random.default_rng(5)
    kp = rng.uniform(0, 700, size=(12, 2))
    kn = rng.normal(size=(12, 2))
    desc = torch.from_numpy(_random_desc(rng, (12, 4)))
    info = np.arange(8, dtype=np.float64)
    R = cv2.Rodrigues(np.array([0.0, 0.0, 0.5]))[0]
    kf = KeyFrame.loaded(7, 3.5, [1.0, 2.0, 3.0], R, kp, kn, desc, loop_index=2, loop_info=info)
    assert kf.sequence == 0 and kf.index == 7 and kf.time == 3.5
    assert kf.has_loop and kf.loop_index == 2 and kf.loop_info.tolist() == info.tolist()
    for a in ("origin_vio_T", "vio_T", "T_w_i"):
        assert getattr(kf, a).tolist() == [1.0, 2.0, 3.0]
    for a in ("origin_vio_R", "vio_R", "R_w_i"):
        np.testing.assert_array_equal(getattr(kf, a).numpy(), R)
    assert kf.num_points == 0 and kf.point_3d.shape == (0, 3) and kf.window_brief.shape == (0, 4)
    assert kf.point_2d_uv.shape == (0, 2) and kf.point_id.shape == (0,)
    assert kf.keypoints.dtype == torch.float32 and kf.keypoints_norm.dtype == torch.float64
    assert torch.equal(kf.brief, desc) and kf.num_keypoints == 12
    plain = KeyFrame.loaded(0, 0.0, np.zeros(3), np.eye(3), kp[:0], kn[:0], desc[:0])
    assert not plain.has_loop and plain.loop_index == -1 and not plain.loop_info.any()
    with pytest.raises(DataError, match="different lengths"):
        KeyFrame.loaded(0, 0.0, np.zeros(3), np.eye(3), kp, kn[:3], desc)
    with pytest.raises(DataError, match="nan or inf|NaN or inf"):
        KeyFrame.loaded(0, 0.0, np.full(3, np.nan), np.eye(3), kp, kn, desc)


def test_keyframe_device(device):
    img = torch.from_numpy(load_gray(sample_frames("cam0")[0])[:240, :320]).to(device)
    uv, p3, ids = _points(10)
    uv = torch.from_numpy(uv % np.array([319, 239], dtype=np.float32)).to(device)
    kf = KeyFrame.create(1.0, img, torch.zeros(3), torch.eye(3), torch.from_numpy(p3).to(device), uv,
                         torch.from_numpy(ids).to(device), _camera(device))
    for a in ("point_3d", "keypoints", "brief", "window_brief", "T_w_i", "loop_info", "keypoints_norm"):
        assert getattr(kf, a).device.type == device.type, a
    pts, _, valid = fast(img[None, None].cpu(), 20, True)
    assert kf.num_keypoints == int(valid.sum())
