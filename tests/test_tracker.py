"""FeatureTracker: VINS-Mono front end for B streams, against the OpenCV oracle.

Tolerances: per published frame the feature count within ±2 % of the oracle's, ≥ 95 % of
features within 0.1 px of an oracle feature, mean track length within 5 %, the same frames
published; against ground truth, median reprojection error ≤ 0.1 px.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

import torch_frontend as tf
from torch_frontend.testing import oracle as vins_oracle
from torch_frontend.testing.flight import reprojection_errors, synthetic_flight
from torch_frontend.tracker import FeatureTracker

from .conftest import REPO, TEST_DATA, load_gray, sample_frames

CFG_PATH = REPO / "configs" / "euroc.yaml"


def _stamp(path: Path) -> float:
    return int(path.stem) * 1e-9


def oracle_cfg(cfg: tf.TrackerConfig) -> dict:
    return {
        "max_cnt": cfg.max_cnt, "min_dist": cfg.min_dist, "freq": cfg.freq, "F_threshold": cfg.F_threshold,
        "equalize": int(cfg.equalize), "fisheye": int(cfg.fisheye), "image_width": cfg.image_width,
        "image_height": cfg.image_height, "camera": {"model_type": cfg.camera.model_type, **cfg.camera.params_dict()},
    }


def _euroc_sequence(n=None):
    files = sample_frames("cam0")[:n]
    return [(_stamp(f), load_gray(f)) for f in files]


def _run_torch(cfg, seq, mode="mono"):
    tr = FeatureTracker(cfg, num_streams=1, mode=mode)
    out = []
    for t, img in seq:
        out.append(tr.track(torch.from_numpy(img)[None, None], [t]))
    return out


def _run_oracle(cfg, seq):
    orc = vins_oracle.OracleMonoTracker(oracle_cfg(cfg))
    return [orc.process(img, t) for t, img in seq]


def _track_lengths(frames_ids_cnt):
    """Mean length (max track count) of the tracks published at least once."""
    best = {}
    for ids, cnt in frames_ids_cnt:
        for i, c in zip(ids.tolist(), cnt.tolist()):
            best[i] = max(best.get(i, 0), c)
    return np.mean(list(best.values())) if best else 0.0


def _compare_with_oracle(ours, theirs):
    pubs_ours = [bool(f.published[0]) for f in ours]
    pubs_theirs = [bool(o["pub_this_frame"]) for o in theirs]
    assert pubs_ours == pubs_theirs, "different frames published"
    matched = total = 0
    worst_count = 0.0
    lo, lt = [], []
    for f, o in zip(ours, theirs):
        if not o["pub_this_frame"]:
            continue
        v = f.valid[0].numpy()
        uv = f.uv[0].numpy()[v].astype(np.float64)
        ouv = o["uv"][o["published_mask"]].astype(np.float64)
        n_o, n_t = len(uv), len(ouv)
        if n_o or n_t:
            worst_count = max(worst_count, abs(n_o - n_t) / max(n_t, 1))
        if n_o and n_t:
            d = np.sqrt(((uv[:, None, :] - ouv[None, :, :]) ** 2).sum(-1)).min(1)
            matched += int((d <= 0.1).sum())
            total += n_o
        lo.append((f.ids[0].numpy()[v], f.track_count[0].numpy()[v]))
        lt.append((o["ids"][o["published_mask"]], o["track_cnt"][o["published_mask"]]))
    frac = matched / max(total, 1)
    ml_o, ml_t = _track_lengths(lo), _track_lengths(lt)
    return worst_count, frac, ml_o, ml_t, total


def test_mono_matches_oracle_on_euroc():
    cfg = tf.load_config(CFG_PATH)
    seq = _euroc_sequence()
    ours, theirs = _run_torch(cfg, seq), _run_oracle(cfg, seq)
    worst, frac, ml_o, ml_t, total = _compare_with_oracle(ours, theirs)
    print(f"EuRoC: count diff max {worst:.3%}, matched within 0.1 px {frac:.2%} of {total}, "
          f"mean track length {ml_o:.2f} vs oracle {ml_t:.2f}")
    assert total > 1000
    assert worst <= 0.02
    assert frac >= 0.95
    assert abs(ml_o - ml_t) <= 0.05 * ml_t


def test_mono_synthetic_flight_vs_oracle_and_truth():
    frames, Hs = synthetic_flight()
    cfg = dataclasses.replace(tf.load_config(CFG_PATH), image_width=640, image_height=400)
    seq = [(1.0 + 0.05 * k, f) for k, f in enumerate(frames)]
    ours, theirs = _run_torch(cfg, seq), _run_oracle(cfg, seq)
    worst, frac, ml_o, ml_t, total = _compare_with_oracle(ours, theirs)
    # ground truth: a feature born at uv0 in frame k0 is at H_k H_k0^-1 uv0 in frame k
    e_ours = reprojection_errors([(f.ids[0].numpy()[f.present[0].numpy()], f.uv[0].numpy()[f.present[0].numpy()])
                                  for f in ours], Hs)
    e_cv = reprojection_errors([(o["ids"], o["uv"]) if o["tracked"] else (np.zeros(0, int), np.zeros((0, 2)))
                                for o in theirs], Hs)
    med, med_cv = float(np.median(e_ours)), float(np.median(e_cv))
    print(f"synthetic: count diff max {worst:.3%}, matched {frac:.2%} of {total}, track length {ml_o:.2f} vs "
          f"{ml_t:.2f}, median reprojection error {med:.4f} px (OpenCV oracle {med_cv:.4f} px) over "
          f"{len(e_ours)} observations")
    assert total > 500 and len(e_ours) > 500
    assert worst <= 0.02
    assert frac >= 0.95
    assert abs(ml_o - ml_t) <= 0.05 * ml_t
    assert med <= 0.1
    assert med <= 1.1 * med_cv


def _frames_equal(a, b, tol=1e-4):
    assert torch.equal(a.published, b.published) and torch.equal(a.restarted, b.restarted)
    assert torch.equal(a.valid, b.valid) and torch.equal(a.present, b.present)
    assert torch.equal(a.ids, b.ids) and torch.equal(a.track_count, b.track_count)
    assert torch.allclose(a.uv, b.uv, atol=tol) and torch.allclose(a.velocity, b.velocity, atol=1e-3)


def test_batch_of_four_equals_single_trackers():
    cfg = tf.load_config(CFG_PATH)
    euroc = _euroc_sequence(14)
    imgs = [img for _, img in euroc]
    # 4 streams: different sequences (forward, shifted, reversed), different clocks, stream 3
    # restarts mid-way after a 2 s gap.
    seqs = [
        [(100.0 + 0.05 * k, imgs[k]) for k in range(14)],
        [(7.3 + 1 / 30 * k, imgs[(k + 5) % 14]) for k in range(14)],
        [(0.0 + 0.04 * k, imgs[13 - k]) for k in range(14)],
        [(50.0 + 0.05 * k + (2.0 if k >= 7 else 0.0), imgs[k]) for k in range(14)],
    ]
    batched = FeatureTracker(cfg, num_streams=4)
    singles = [FeatureTracker(cfg, num_streams=1) for _ in range(4)]
    restarted = []
    for k in range(14):
        fb = batched.track(torch.stack([torch.from_numpy(s[k][1])[None] for s in seqs]), [s[k][0] for s in seqs])
        restarted.append(fb.restarted.tolist())
        for b in range(4):
            fs = singles[b].track(torch.from_numpy(seqs[b][k][1])[None, None], [seqs[b][k][0]])
            sub = dataclasses.replace(
                fb, **{f.name: getattr(fb, f.name)[b:b + 1] for f in dataclasses.fields(fb)
                       if isinstance(getattr(fb, f.name), torch.Tensor)})
            _frames_equal(sub, fs)
    assert restarted[7] == [False, False, False, True]


def _timing_tracker(freq=10):
    cfg = dataclasses.replace(tf.load_config(CFG_PATH), image_width=64, image_height=48, freq=freq, equalize=False)
    return FeatureTracker(cfg)


def _run_clock(stamps, freq=10):
    tr = _timing_tracker(freq)
    rng = np.random.default_rng(0)
    img = torch.from_numpy(cv2.GaussianBlur(rng.integers(0, 255, (48, 64)).astype(np.uint8), (5, 5), 1.5))
    out = [tr.track(img[None, None], [t]) for t in stamps]
    return out


def _oracle_clock(stamps, freq=10):
    timing = vins_oracle.MonoTiming(freq)
    out = []
    for t in stamps:
        r = timing.step(t)
        if r["pub_this_frame"]:
            timing.published()
        out.append(r)
    return out


def test_timing_matches_vins_rules():
    for hz, expect_every in ((20, 2), (30, 3)):
        stamps = [1403715273.26 + k / hz for k in range(30)]
        pub = [bool(f.published[0]) for f in _run_clock(stamps)]
        ref = [r["pub_this_frame"] for r in _oracle_clock(stamps)]
        assert pub == ref
        assert [k for k, p in enumerate(pub) if p][:4] == [expect_every * i for i in range(1, 5)]
    # 25 Hz: C rounding (12.5 -> 13: not published); Python's round would publish frame 2
    stamps = [0.04 * k for k in range(40)]
    pub = [k for k, f in enumerate(_run_clock(stamps)) if bool(f.published[0])]
    assert pub[:6] == [3, 5, 8, 10, 13, 15]


def test_timing_duplicates_gaps_and_backwards():
    stamps = [0.0, 0.05, 0.1, 0.1, 0.15, 0.2, 2.5, 2.55, 2.6, 2.65, 2.5, 2.55, 2.6]
    out = _run_clock(stamps)
    ref = _oracle_clock(stamps)
    assert [bool(f.published[0]) for f in out] == [r["pub_this_frame"] for r in ref]
    assert [bool(f.restarted[0]) for f in out] == [r["restart"] for r in ref]
    assert [bool(f.tracked[0]) for f in out] == [r["tracked"] for r in ref]
    assert out[6].restarted[0] and not out[7].tracked[0] and out[8].tracked[0]  # gap: dropped, next is "first"
    assert out[10].restarted[0]  # time went backwards
    for f in out:
        assert torch.isfinite(f.velocity).all()


def test_feature_frame_converters_and_drawing():
    cfg = tf.load_config(CFG_PATH)
    seq = _euroc_sequence(6)
    out = _run_torch(cfg, seq)
    f = out[4]
    assert bool(f.published[0]) and bool(f.sent[0])
    pc = f.to_point_cloud(0)
    n = int(f.valid[0].sum())
    assert pc["points"].shape == (n, 3) and np.all(pc["points"][:, 2] == 1)
    assert set(pc) >= {"id", "u", "v", "vx", "vy"} and pc["id"].dtype == np.float32
    fus = f.to_vins_fusion(0)
    assert len(fus) == n and all(obs[0][0] == 0 and len(obs[0][1]) == 7 for obs in fus.values())
    assert list(fus) == sorted(fus)
    img = tf.draw_tracks(torch.from_numpy(seq[4][1]), f, 0)
    assert img.shape == (480, 752, 3) and img.dtype == np.uint8
    # blue-ish (new) and red-ish (old) circles exist only where features are drawn
    assert (img[..., 0].astype(int) - img[..., 1]).max() > 100


def test_mono_velocity_rule():
    cfg = tf.load_config(CFG_PATH)
    seq = _euroc_sequence(10)
    ours, theirs = _run_torch(cfg, seq), _run_oracle(cfg, seq)
    for f, o in zip(ours, theirs):
        v, cnt = f.velocity[0].numpy(), f.track_count[0].numpy()
        pres = f.present[0].numpy()
        assert np.all(v[pres & (cnt <= 2)] == 0)
        if o["tracked"] and len(o["ids"]):
            # same velocities as the oracle for the same ids
            ours_v = dict(zip(f.ids[0].numpy()[pres].tolist(), v[pres].tolist()))
            for i, ov in zip(o["ids"].tolist(), o["velocity"].tolist()):
                if i in ours_v:
                    assert np.allclose(ours_v[i], ov, atol=2e-3), (i, ours_v[i], ov)


def test_bad_input():
    cfg = tf.load_config(CFG_PATH)
    tr = FeatureTracker(cfg, num_streams=2)
    with pytest.raises(ValueError, match="752x480"):
        tr.track(torch.zeros(2, 1, 100, 100, dtype=torch.uint8), [0.0, 0.0])
    with pytest.raises(ValueError, match="2 streams"):
        tr.track(torch.zeros(3, 1, 480, 752, dtype=torch.uint8), [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="timestamps"):
        tr.track(torch.zeros(2, 1, 480, 752, dtype=torch.uint8), [0.0])
    with pytest.raises(ValueError, match="mode"):
        FeatureTracker(cfg, mode="stereo")


# ---------------------------------------------------------------------------------------------- fusion


def _fusion_cfg():
    return tf.load_config(REPO / "configs" / "euroc_stereo_mei.yaml")


def test_fusion_stereo_euroc_shares_ids():
    cfg = _fusion_cfg()
    tr = FeatureTracker(cfg, mode="fusion")
    left, right = sample_frames("cam0")[:6], sample_frames("cam1")
    n_right = []
    for lf, rf in zip(left, right):
        f = tr.track(torch.from_numpy(load_gray(lf))[None, None], [_stamp(lf)],
                     right=torch.from_numpy(load_gray(rf))[None, None])
        rv = f.right_valid[0]
        assert bool((rv <= f.valid[0]).all())  # right observations are of left features
        fus = f.to_vins_fusion(0)
        both = [i for i, obs in fus.items() if len(obs) == 2]
        assert len(both) == int(rv.sum())
        n_right.append(len(both))
    assert min(n_right[1:]) >= 20


def test_fusion_flow_back_removes_bad_tracks():
    """Plant bad tracks: a second frame where a patch is replaced; forward-backward drops them."""
    cfg = dataclasses.replace(_fusion_cfg(), num_of_cam=1, camera1=None)
    frames, _ = synthetic_flight(n_frames=3, size=(480, 752))
    tr = FeatureTracker(cfg, mode="fusion")
    f0 = tr.track(torch.from_numpy(frames[0])[None, None], [0.0])
    pts0 = f0.uv[0][f0.valid[0]].numpy()
    # corrupt the windows around half of the features in the next frame with unrelated texture
    bad = frames[1].copy()
    rng = np.random.default_rng(1)
    planted = []
    for j, (x, y) in enumerate(pts0):
        if j % 2 == 0 and 15 <= x < 752 - 15 and 15 <= y < 480 - 15:
            xi, yi = int(x), int(y)
            bad[yi - 12:yi + 13, xi - 12:xi + 13] = rng.integers(0, 255, (25, 25), dtype=np.uint8)
            planted.append(j)
    ids0 = f0.ids[0][f0.valid[0]].numpy()
    f1 = tr.track(torch.from_numpy(bad)[None, None], [0.05])
    survivors = set(f1.ids[0][f1.valid[0]].tolist())
    removed = sum(int(ids0[j]) not in survivors for j in planted)
    print(f"flow_back removed {removed}/{len(planted)} planted bad tracks")
    assert removed >= 0.9 * len(planted)


def test_fusion_stereo_motorcycle_disparity():
    left = cv2.imread(str(TEST_DATA / "motorcycle" / "motorcycle_left.png"), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(TEST_DATA / "motorcycle" / "motorcycle_right.png"), cv2.IMREAD_GRAYSCALE)
    disp = np.load(TEST_DATA / "motorcycle" / "motorcycle_disp.npz")["arr_0"]
    H, W = left.shape
    base = _fusion_cfg()
    cfg = dataclasses.replace(base, image_width=W, image_height=H, max_cnt=300, min_dist=15, flow_back=False)
    tr = FeatureTracker(cfg, mode="fusion")
    f = tr.track(torch.from_numpy(left)[None, None], [0.0], right=torch.from_numpy(right)[None, None])
    rv = f.right_valid[0].numpy()
    uvl = f.uv[0].numpy()[rv].astype(np.float64)
    uvr = f.right_uv[0].numpy()[rv].astype(np.float64)
    gt = disp[np.rint(uvl[:, 1]).astype(int), np.rint(uvl[:, 0]).astype(int)]
    ok = np.isfinite(gt)
    err_ours = np.abs((uvl[:, 0] - uvr[:, 0]) - gt)[ok]
    # OpenCV's LK on the same points
    cv_r, st, _ = cv2.calcOpticalFlowPyrLK(left, right, uvl.astype(np.float32).reshape(-1, 1, 2), None,
                                           winSize=(21, 21), maxLevel=3)
    st = st.ravel().astype(bool)
    err_cv = np.abs((uvl[:, 0] - cv_r.reshape(-1, 2)[:, 0]) - gt)[ok & st]
    print(f"motorcycle stereo: median disparity error ours {np.median(err_ours):.3f} px "
          f"({ok.sum()} pts), OpenCV {np.median(err_cv):.3f} px")
    assert ok.sum() > 100
    assert np.median(err_ours) <= 1.1 * np.median(err_cv)


def test_remove_and_prediction():
    cfg = dataclasses.replace(_fusion_cfg(), num_of_cam=1, camera1=None)
    seq = _euroc_sequence(3)
    tr = FeatureTracker(cfg, mode="fusion")
    f0 = tr.track(torch.from_numpy(seq[0][1])[None, None], [seq[0][0]])
    ids = f0.ids[0][f0.valid[0]]
    tr.remove(0, ids[:5].tolist())
    assert not bool(torch.isin(ids[:5], tr.state.features.ids[0][tr.state.features.valid[0]]).any())
    # predict the current positions (the scene is static): tracking must still work
    keep = tr.state.features.valid
    tr.set_prediction(tr.state.features.ids, tr.state.features.pts, keep)
    f1 = tr.track(torch.from_numpy(seq[1][1])[None, None], [seq[1][0]])
    surv = torch.isin(ids[5:], f1.ids[0][f1.valid[0]]).float().mean()
    assert surv > 0.9
    assert not bool(torch.isin(ids[:5], f1.ids[0]).any())


@pytest.mark.slow
def test_long_run_memory_flat():
    """10,000 frames (8 streams × 1,250 steps of small 64×48 frames with 20 features each): the
    process's peak memory does not grow after the first 250 steps."""
    import resource

    cfg = dataclasses.replace(tf.load_config(CFG_PATH), image_width=64, image_height=48, equalize=False,
                              max_cnt=20, min_dist=8)
    B, steps = 8, 1250
    tr = FeatureTracker(cfg, num_streams=B)
    rng = np.random.default_rng(0)
    tex = cv2.GaussianBlur(rng.integers(0, 255, (96, 128)).astype(np.uint8), (5, 5), 1.2)
    rss, published = [], 0
    for k in range(steps):
        imgs = []
        for b in range(B):
            dx, dy = 8 + 4 * np.sin(k / 50 + b), 8 + 4 * np.cos(k / 70 + b)
            M = np.float32([[1, 0, -dx], [0, 1, -dy]])
            imgs.append(cv2.warpAffine(tex, M, (64, 48), flags=cv2.INTER_LINEAR))
        f = tr.track(torch.from_numpy(np.stack(imgs))[:, None], [0.05 * k] * B)
        published += int(f.valid.sum())
        if k in (250, steps - 1):
            rss.append(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
    print(f"peak RSS after 2,000 frames {rss[0] / 1024:.1f} MiB, after 10,000 {rss[1] / 1024:.1f} MiB; "
          f"{published} features published, {int(tr.state.next_id.sum())} ids")
    assert rss[1] - rss[0] < 32 * 1024  # KiB: < 32 MiB growth over 8,000 frames
    assert published > 10_000


@pytest.mark.parametrize("mode", ["mono", "fusion"])
def test_inactive_stream_is_left_untouched(mode):
    """``active=False`` for a stream: its state does not change, as if the frame never came."""
    cfg = tf.load_config(CFG_PATH if mode == "mono" else REPO / "configs" / "euroc_mono_mei.yaml")
    seq = _euroc_sequence(8)
    pair = FeatureTracker(cfg, num_streams=2, mode=mode)
    single = FeatureTracker(cfg, num_streams=1, mode=mode)
    for k, (t, img) in enumerate(seq):
        alive1 = k not in (4, 5)
        x = torch.from_numpy(img)[None, None]
        f = pair.track(torch.cat([x, x]), [t, t], active=[True, alive1])
        if alive1:
            fs = single.track(x, [t])
            assert torch.equal(f.ids[1], fs.ids[0]) and torch.equal(f.valid[1], fs.valid[0])
            assert torch.allclose(f.uv[1], fs.uv[0], atol=1e-4)
        else:
            assert not bool(f.valid[1].any()) and not bool(f.published[1])
    assert int(pair.state.next_id[1]) == int(single.state.next_id[0])


def test_fusion_uses_the_actual_image_size():
    """VINS-Fusion tracks images of any size (the config's image_width/height are the estimator's)."""
    cfg = dataclasses.replace(tf.load_config(REPO / "configs" / "euroc_mono_mei.yaml"), num_of_cam=1, camera1=None)
    tr = FeatureTracker(cfg, mode="fusion")
    crop = [img[:400, :640] for _, img in _euroc_sequence(3)]
    for k, img in enumerate(crop):
        f = tr.track(torch.from_numpy(np.ascontiguousarray(img))[None, None], [0.05 * k])
    uv = f.uv[0][f.valid[0]]
    assert uv.shape[0] > 50 and float(uv[:, 0].max()) < 639 and float(uv[:, 1].max()) < 399


def test_prediction_survives_a_later_remove():
    """set_prediction() then remove(): each prediction stays with its feature (slots are compacted
    by remove), and predicted tracks land where the features are (a static scene)."""
    cfg = dataclasses.replace(_fusion_cfg(), num_of_cam=1, camera1=None)
    seq = _euroc_sequence(2)
    tr = FeatureTracker(cfg, mode="fusion")
    f0 = tr.track(torch.from_numpy(seq[0][1])[None, None], [seq[0][0]])
    ids0, uv0 = f0.ids[0][f0.valid[0]], f0.uv[0][f0.valid[0]]
    tr.set_prediction(tr.state.features.ids, tr.state.features.pts, tr.state.features.valid)
    tr.remove(0, ids0[:10].tolist())
    f1 = tr.track(torch.from_numpy(seq[1][1])[None, None], [seq[1][0]])
    ids1, uv1 = f1.ids[0][f1.valid[0]], f1.uv[0][f1.valid[0]]
    common = torch.isin(ids0[10:], ids1)
    assert common.float().mean() > 0.9
    pos1 = {int(i): p for i, p in zip(ids1, uv1)}
    moved = torch.stack([(pos1[int(i)] - p).norm() for i, p in zip(ids0[10:][common], uv0[10:][common])])
    assert float(moved.median()) < 0.5
    assert not bool(tr.state.has_prediction.any())  # consumed
