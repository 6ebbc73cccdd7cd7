"""``FeatureTracker.state_dict`` / ``load_state_dict`` (``tracker/checkpoint.py``): a tracker saved
mid-sequence and loaded into a new one continues bit for bit as the uninterrupted tracker, on the
default and the capturable path, mono and fusion; states of another version, config, stream count
or mode are refused naming what differs."""

from __future__ import annotations

import dataclasses
import io

import numpy as np
import pytest
import torch
import torch.utils._pytree as pytree

import torch_frontend as tf
from tests._helpers import crop, small_config
from tests.conftest import load_gray, sample_frames

pytestmark = pytest.mark.usefixtures("single_thread")

SPLIT = 7  # frames tracked before the save (past the first published frames)


@pytest.fixture(scope="module")
def cfg(tmp_path_factory):
    return tf.load_config(small_config(tmp_path_factory.mktemp("ckcfg")))


@pytest.fixture(scope="module")
def frames():
    """``(images (N, 2, 1, H, W) uint8, stamps (N, 2) float64 s)``: two streams, the second a
    reversed copy of the first (different tracks), and ``active`` with stream 1 pausing."""
    imgs = np.stack([crop(load_gray(f)) for f in sample_frames("cam0")[:14]])
    two = np.stack([imgs, imgs[::-1]], axis=1)[:, :, None]
    t = np.array([int(f.stem) for f in sample_frames("cam0")[:14]], dtype=np.int64) * 1e-9
    stamps = np.stack([t, t], axis=1)
    active = np.ones((len(imgs), 2), bool)
    active[3:5, 1] = False  # a stream that waits (its state is kept exactly)
    return torch.from_numpy(two), torch.from_numpy(stamps), torch.from_numpy(active)


def _saved(tracker) -> dict:
    """``state_dict`` through ``torch.save`` / ``torch.load(weights_only=True)``, as a user would."""
    buf = io.BytesIO()
    torch.save(tracker.state_dict(), buf)
    buf.seek(0)
    return torch.load(buf, weights_only=True, map_location="cpu")


def _same(a, b) -> bool:
    la, lb = pytree.tree_leaves(a), pytree.tree_leaves(b)
    return len(la) == len(lb) and all(
        (torch.equal(x, y) and x.dtype == y.dtype) if isinstance(x, torch.Tensor) else x == y for x, y in zip(la, lb))


@pytest.mark.parametrize("capturable, mode", [
    pytest.param(False, "mono", id="default-mono"), pytest.param(False, "fusion", id="default-fusion"),
    pytest.param(True, "mono", id="capturable-mono"),
    pytest.param(True, "fusion", id="capturable-fusion", marks=pytest.mark.slow),
])
def test_round_trip_mid_sequence_continues_bit_identical(cfg, frames, mode, capturable):
    images, stamps, active = frames
    kw = dict(num_streams=2, mode=mode, capturable=capturable)
    whole = tf.FeatureTracker(cfg, **kw)
    part = tf.FeatureTracker(cfg, **kw)
    for k in range(SPLIT):
        part.track(images[k], stamps[k], active=active[k])
    resumed = tf.FeatureTracker(cfg, **kw)
    resumed.load_state_dict(_saved(part))
    assert _same(resumed.state, part.state)
    published = 0
    for k in range(len(images)):
        f = whole.track(images[k], stamps[k], active=active[k])
        if k >= SPLIT:
            g = resumed.track(images[k], stamps[k], active=active[k])
            assert _same(f, g), f"frame {k}: the resumed tracker differs from the uninterrupted one"
            published += int(f.valid.sum())
    assert published > 0, "the frames after the split must publish features (else nothing is compared)"
    assert _same(whole.state, resumed.state)


def test_state_dict_is_a_copy_on_the_cpu(cfg, frames):
    images, stamps, _ = frames
    tr = tf.FeatureTracker(cfg, num_streams=2)
    for k in range(3):
        tr.track(images[k], stamps[k])
    d = tr.state_dict()
    assert d["version"] == tf.tracker.checkpoint.STATE_DICT_VERSION
    tensors = [x for x in d["leaves"] if isinstance(x, torch.Tensor)]
    assert tensors and all(x.device.type == "cpu" for x in tensors)
    before = [x.clone() for x in tensors]
    tr.track(images[3], stamps[3])
    assert all(torch.equal(x, y) for x, y in zip(before, tensors)), "the dict must not follow later steps"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (saved on CUDA, loaded on the CPU)")
def test_saved_on_cuda_loads_on_cpu(cfg, frames):  # pragma: no cover - GPU machines
    images, stamps, active = frames
    gpu = tf.FeatureTracker(cfg, num_streams=2, device="cuda", capturable=False)
    cpu = tf.FeatureTracker(cfg, num_streams=2)
    for k in range(SPLIT):
        gpu.track(images[k], stamps[k], active=active[k])
        cpu.track(images[k], stamps[k], active=active[k])
    loaded = tf.FeatureTracker(cfg, num_streams=2)
    loaded.load_state_dict(_saved(gpu))
    assert all(x.device.type == "cpu" for x in pytree.tree_leaves(loaded.state) if isinstance(x, torch.Tensor))
    f, g = cpu.track(images[SPLIT], stamps[SPLIT]), loaded.track(images[SPLIT], stamps[SPLIT])
    assert torch.equal(f.ids, g.ids) and torch.equal(f.valid, g.valid)


def test_restart_watch_survives_the_round_trip(cfg, frames):
    images, _, _ = frames
    tr = tf.FeatureTracker(cfg, num_streams=2)
    ns = torch.arange(10, dtype=torch.float64) * 5e7  # nanoseconds given as seconds: every step restarts
    with pytest.warns(UserWarning, match="restarted"):
        for k in range(4):
            tr.track(images[k], ns[k].repeat(2))
    loaded = tf.FeatureTracker(cfg, num_streams=2)
    loaded.load_state_dict(_saved(tr))
    assert loaded._restarts.warned == {0, 1}  # warned once per stream: not again after loading
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        loaded.track(images[4], ns[4].repeat(2))


# ---------------------------------------------------------------------------------------------- refusals


def test_refuses_another_version(cfg):
    d = tf.FeatureTracker(cfg).state_dict()
    d["version"] = 99
    with pytest.raises(ValueError, match="version 99.*version 1"):
        tf.FeatureTracker(cfg).load_state_dict(d)


@pytest.mark.parametrize("other,needle", [
    (dict(num_streams=3), "num_streams 2.*3"),
    (dict(num_streams=2, mode="fusion"), "mode 'mono'.*'fusion'"),
])
def test_refuses_another_stream_count_or_mode(cfg, other, needle):
    d = tf.FeatureTracker(cfg, num_streams=2).state_dict()
    with pytest.raises(ValueError, match=needle):
        tf.FeatureTracker(cfg, **other).load_state_dict(d)


def test_refuses_another_config_naming_the_key(cfg):
    d = tf.FeatureTracker(cfg).state_dict()
    with pytest.raises(ValueError, match=r"another config: max_cnt \(saved: 60, this tracker: 61\)"):
        tf.FeatureTracker(dataclasses.replace(cfg, max_cnt=61)).load_state_dict(d)


def test_refuses_another_camera_naming_the_parameter(cfg, tmp_path):
    d = tf.FeatureTracker(cfg).state_dict()
    text = small_config(tmp_path).read_text().replace("cx: 115.0", "cx: 116.0")
    other = tmp_path / "other.yaml"
    other.write_text(text)
    with pytest.raises(ValueError, match=r"camera\.cx \(saved: 115\.0, this tracker: 116\.0\)"):
        tf.FeatureTracker(tf.load_config(other)).load_state_dict(d)


def test_same_config_elsewhere_is_the_same_config(cfg, tmp_path):
    d = tf.FeatureTracker(cfg).state_dict()
    tf.FeatureTracker(tf.load_config(small_config(tmp_path))).load_state_dict(d)  # another path: accepted


def test_refuses_what_is_not_a_state_dict(cfg):
    with pytest.raises(ValueError, match="not a FeatureTracker state_dict"):
        tf.FeatureTracker(cfg).load_state_dict({"weights": 1})
