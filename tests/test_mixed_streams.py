"""Per-stream configs (``FeatureTracker([cfg_0, ..., cfg_{B-1}])``): stream b of a mixed batch gives
exactly the frames of a one-stream tracker of config b on the same images, every step, on every
path; mixed image sizes as a list or a padded batch with ``sizes``."""

from __future__ import annotations

import dataclasses

import pytest
import torch

import torch_frontend as tf
from torch_frontend import FeatureTracker
from torch_frontend.testing.flight import synthetic_flight
from torch_frontend.tracker import TrackerState

from .conftest import REPO, load_gray, sample_frames, shared_data_or_skip

pytestmark = pytest.mark.usefixtures("single_thread")

#: the five VINS-Mono configs of the issue: pinhole 752x480, Kannala-Brandt 512x512 fisheye,
#: pinhole 640x480, MEI equalize 0 (freq 20), Kannala-Brandt 752x480
SHIPPED_MONO = ("euroc/euroc_config.yaml", "tum/tum_config.yaml", "realsense/realsense_color_config.yaml",
                "3dm/3dm_config.yaml", "cla/cla_config.yaml")
#: frames per stream: the first published frame is the third, detection again on the fifth
N_FRAMES = 5
_PER_STREAM = ("published", "sent", "restarted", "tracked", "timestamps", "overflow")


def _shipped_mono():
    root = shared_data_or_skip("vins_configs", "vins_mono")
    cfgs = [tf.load_config(root / n) for n in SHIPPED_MONO]
    # a smaller max_cnt in one stream: K is the largest, that stream never fills more
    cfgs[2] = dataclasses.replace(cfgs[2], max_cnt=90)
    return cfgs


def _repo_mono():
    """Configs in the repo (no skip): pinhole 752x480, Kannala-Brandt 512x512 fisheye, and the
    pinhole with other VINS keys."""
    a = tf.load_config(REPO / "configs" / "euroc.yaml")
    b = tf.load_config(REPO / "configs" / "tum_vi.yaml")
    c = dataclasses.replace(a, max_cnt=80, min_dist=20, F_threshold=2.0, equalize=not a.equalize)
    return [a, b, c]


def _flights(cfgs, n=N_FRAMES):
    """Each stream's images at its config's size (the synthetic flight over the package photo)."""
    cache = {}
    out = []
    for c in cfgs:
        size = (c.image_height, c.image_width)
        if size not in cache:
            cache[size] = [torch.as_tensor(im) for im in synthetic_flight(n, size)[0]]
        out.append(cache[size])
    return out


def assert_stream_equal(frame, b, single, K):
    """Stream ``b`` of the mixed ``frame`` equals the one-stream tracker's ``single`` bit for bit; slots
    beyond its own ``max_cnt`` are empty."""
    k = single.ids.shape[1]
    for f in dataclasses.fields(single):
        want, got = getattr(single, f.name), getattr(frame, f.name)
        if want is None:
            assert got is None or not got[b].any(), f.name
            continue
        row = got[b:b + 1]
        if f.name not in _PER_STREAM:
            assert row.shape[1] == K
            assert not row[:, k:].any() if f.name != "ids" else (row[:, k:] == -1).all(), f.name
            row = row[:, :k]
        assert torch.equal(row, want), f"stream {b}: {f.name} differs"


def _run_equal(cfgs, n=N_FRAMES, **kw):
    seqs = _flights(cfgs, n)
    mixed = FeatureTracker(cfgs, **kw)
    singles = [FeatureTracker(c, **kw) for c in cfgs]
    published = 0
    for i in range(n):
        ts = [0.05 * i + 0.003 * b for b in range(len(cfgs))]
        frame = mixed.track([s[i] for s in seqs], ts)
        for b, tr in enumerate(singles):
            assert_stream_equal(frame, b, tr.track(seqs[b][i][None, None], ts[b:b + 1]), mixed.K)
        published += int(frame.valid.sum())
    assert published > 0  # features were published: the comparison saw tracks
    return mixed


@pytest.mark.parametrize("path", ["default", "capturable"])
def test_repo_configs_each_stream_equals_its_tracker(path):
    mixed = _run_equal(_repo_mono(), capturable=path == "capturable")
    assert mixed.mixed and len(mixed.groups) == 3 and mixed.K == 150


@pytest.mark.parametrize("path", ["default", pytest.param("capturable", marks=pytest.mark.slow), "differentiable"])
def test_five_shipped_configs_each_stream_equals_its_tracker(path):
    kw = {"capturable": path == "capturable", "differentiable": path == "differentiable"}
    mixed = _run_equal(_shipped_mono(), **kw)
    models = {type(c).__name__ for c in mixed.cameras}
    assert models == {"PinholeCamera", "KannalaBrandtCamera", "MeiCamera"}
    assert {(c.image_width, c.image_height) for c in mixed.configs} == {(752, 480), (512, 512), (640, 480)}


def test_padded_batch_with_sizes_equals_list():
    cfgs = _repo_mono()
    seqs = _flights(cfgs, 3)
    a, b = FeatureTracker(cfgs), FeatureTracker(cfgs)
    H = max(c.image_height for c in cfgs)
    W = max(c.image_width for c in cfgs)
    sizes = [(c.image_height, c.image_width) for c in cfgs]
    for i in range(3):
        ts = [0.05 * i] * 3
        padded = torch.full((3, 1, H, W), 7, dtype=torch.uint8)
        for s, (h, w) in enumerate(sizes):
            padded[s, 0, :h, :w] = seqs[s][i]
        fa = a.track([s[i] for s in seqs], ts)
        fb = b.track(padded, ts, sizes=sizes)
        for f in dataclasses.fields(fa):
            va, vb = getattr(fa, f.name), getattr(fb, f.name)
            assert (va is None and vb is None) or torch.equal(va, vb), f.name


def test_fusion_two_stereo_configs_each_stream_equals_its_tracker():
    mei = tf.load_config(REPO / "configs" / "euroc_stereo_mei.yaml")
    pin_path = shared_data_or_skip("vins_configs", "vins_fusion", "euroc", "euroc_stereo_config.yaml")
    pin = dataclasses.replace(tf.load_config(pin_path), max_cnt=100, min_dist=20)
    left = [torch.as_tensor(load_gray(p)) for p in sample_frames("cam0")[:4]]
    right = [torch.as_tensor(load_gray(p)) for p in sample_frames("cam1")[:4]]
    cfgs = [mei, pin]
    mixed = FeatureTracker(cfgs, mode="fusion")
    singles = [FeatureTracker(c, mode="fusion") for c in cfgs]
    assert mixed.mixed
    for i in range(4):
        ts = [0.05 * i, 0.05 * i]
        # stream 1 sees the images upside down: the streams differ in content as in calibration
        imgs = [left[i], left[i].flip(0)]
        rights = [right[i], right[i].flip(0)]
        frame = mixed.track(imgs, ts, right=rights)
        for b, tr in enumerate(singles):
            single = tr.track(imgs[b][None, None], ts[b:b + 1], right=rights[b][None, None])
            assert_stream_equal(frame, b, single, mixed.K)
        assert frame.right_valid.any()
    # the estimator's hooks reach the right group
    ids = frame.ids[1][frame.valid[1]][:3].tolist()
    mixed.remove(1, ids)
    singles[1].remove(0, ids)
    assert torch.equal(mixed.state.groups[1].features.ids, singles[1].state.features.ids)


def test_identical_configs_are_one_group():
    cfg = tf.load_config(REPO / "configs" / "euroc.yaml")
    tr = FeatureTracker([cfg, REPO / "configs" / "euroc.yaml"])
    assert not tr.mixed and tr.B == 2 and tr.params.max_cnt == cfg.max_cnt
    assert isinstance(tr.state, TrackerState)


def test_mixed_errors_name_the_stream():
    cfgs = _repo_mono()
    with pytest.raises(ValueError, match="num_streams: 2 differs from the 3 per-stream configs"):
        FeatureTracker(cfgs, num_streams=2)
    tr = FeatureTracker(cfgs)
    imgs = [torch.zeros(480, 752, dtype=torch.uint8)] * 3
    with pytest.raises(ValueError, match=r"images\[1\]: image size 752x480 differs from stream 1's config .*tum_vi"):
        tr.track(imgs, [0.0] * 3)
    with pytest.raises(ValueError, match=r"images: expected 3 images"):
        tr.track(imgs[:2], [0.0] * 3)
    with pytest.raises(ValueError, match=r"sizes\[1\]: \(H, W\) = \(512, 512\) does not fit"):
        tr.track(torch.zeros(3, 1, 480, 752, dtype=torch.uint8), [0.0] * 3, sizes=[(480, 752), (512, 512), (480, 752)])
    with pytest.raises(AttributeError, match="per-stream configs"):
        _ = tr.params
    with pytest.raises(ValueError, match="timestamps: expected"):
        tr.track([torch.zeros(c.image_height, c.image_width, dtype=torch.uint8) for c in cfgs], [0.0, 1.0])


def _focal(cam) -> str:
    return "fx" if "fx" in cam.param_names else "mu"  # Kannala-Brandt: mu


def _other_fx(cfg, scale):
    cam = cfg.camera
    p = {**cam.params_dict(), _focal(cam): cam.params_dict()[_focal(cam)] * scale}
    return dataclasses.replace(cfg, camera=type(cam).from_params(p, width=cam.width, height=cam.height))


@pytest.mark.parametrize("path", ["default", pytest.param("capturable", marks=pytest.mark.slow)])
def test_rig_of_calibrations_is_one_group_with_a_camera_batch(path):
    """Four cameras of one model and size with their own calibrations (a rig): one group, its camera
    a CameraBatch, the homogeneous step's launches; each stream equals its own tracker."""
    euroc = tf.load_config(REPO / "configs" / "euroc.yaml")
    cfgs = [euroc] + [_other_fx(euroc, s) for s in (1.01, 0.98, 1.03)]
    mixed = _run_equal(cfgs, capturable=path == "capturable")
    assert not mixed.mixed and len(mixed.groups) == 1
    assert isinstance(mixed.camera, tf.CameraBatch) and len(mixed.camera) == 4
    with pytest.raises(AttributeError, match="per-stream configs"):
        _ = mixed.config


def test_rig_in_a_mixed_batch_groups_by_model_and_settings():
    euroc = tf.load_config(REPO / "configs" / "euroc.yaml")
    tum = tf.load_config(REPO / "configs" / "tum_vi.yaml")
    cfgs = [euroc, tum, _other_fx(euroc, 1.02), _other_fx(tum, 0.99)]
    tr = FeatureTracker(cfgs)
    assert [s for s, _ in tr.groups] == [(0, 2), (1, 3)]
    assert all(isinstance(m.camera, tf.CameraBatch) for _, m in tr.groups)
    batch = tr.groups[0][1].camera
    assert [batch[i].params_dict()["fx"] for i in (0, 1)] == \
        [euroc.camera.params_dict()["fx"], euroc.camera.params_dict()["fx"] * 1.02]
