"""The capturable tracker step: shape-static, no host syncs, a launch count independent
of B, identical results to the CPU-tuned path, one graph for the compiler."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
import torch

import torch_frontend as tf
from torch_frontend.testing.dispatch_count import OpCounter
from torch_frontend.tracker import FeatureTracker, TrackerParams, TrackerState
from torch_frontend.tracker.track_step import check_inputs, step_impl

from .conftest import DEVICES, REPO, load_gray, sample_frames

CFG = REPO / "configs" / "euroc.yaml"
STEREO = REPO / "configs" / "euroc_stereo_mei.yaml"
FIELDS = ("ids", "uv", "xy", "velocity", "track_count", "valid", "present", "published", "sent", "restarted",
          "tracked", "prev_uv", "prev_valid", "right_uv", "right_xy", "right_velocity", "right_valid")
#: launch budget of one capturable mono EuRoC step (752x480, 150 features, 4 levels x 30 LK iterations),
#: counted with OpCounter; see benchmarks/results/capturable.md for the breakdown
KERNEL_BOUND = 4600


def _frames(cam="cam0"):
    return [(int(f.stem) * 1e-9, load_gray(f)) for f in sample_frames(cam)]


def _warp(img, k, b):
    """A moving affine warp of ``img`` (frame k of stream b): rotation, zoom and shift that change
    over time and differ per stream, so that tracks move by several pixels per frame."""
    h, w = img.shape
    ang = 0.6 * np.sin(0.3 * k + b)
    scale = 1.0 + 0.01 * np.sin(0.2 * k + 0.5 * b)
    M = cv2.getRotationMatrix2D((w / 2, h / 2), ang, scale)
    M[:, 2] += (2.5 * k * np.cos(b), 1.5 * k * np.sin(0.7 * b + 0.3))
    return cv2.warpAffine(img, M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)


def _sequence(kind, B, n):
    """``n`` steps of ``(images (B,1,H,W) uint8, stamps (B,) list)``."""
    frames = _frames()
    steps = []
    for k in range(n):
        imgs, stamps = [], []
        for b in range(B):
            i = (k + 5 * b) % len(frames)
            t, img = frames[i]
            if kind == "warp":
                img = _warp(frames[(3 * b) % len(frames)][1], k, b)
            imgs.append(img)
            stamps.append(1403715273.0 + 0.05 * k if kind != "sample" else frames[k % len(frames)][0] + 3.0 * (k // len(frames)))
        steps.append((torch.from_numpy(np.stack(imgs))[:, None], stamps))
    return steps


def _equal_frames(fa, fb, where=""):
    for name in FIELDS:
        a, b = getattr(fa, name), getattr(fb, name)
        if a is None or b is None:
            assert a is None and b is None, f"{where}{name}: present on one path only"
            continue
        a, b = a.cpu(), b.cpu()
        assert a.dtype == b.dtype and a.shape == b.shape, f"{where}{name}: {a.dtype}{tuple(a.shape)} vs {b.dtype}{tuple(b.shape)}"
        assert torch.equal(a, b), f"{where}{name}: {(a != b).sum().item()} of {a.numel()} values differ"


def _run_both(cfg, steps, B, mode="mono", actives=None, right=None, device="cpu"):
    ref = FeatureTracker(cfg, num_streams=B, mode=mode, capturable=False)
    cap = FeatureTracker(cfg, num_streams=B, mode=mode, capturable=True, device=device)
    n_pub = 0
    for k, (img, stamps) in enumerate(steps):
        act = None if actives is None else actives[k]
        r = None if right is None else right[k]
        fa = ref.track(img, stamps, active=act, right=r)
        fb = cap.track(img.to(device), stamps, active=act, right=None if r is None else r.to(device))
        assert not bool(fb.overflow.any()), f"step {k}: a capturable budget overflowed in streams {fb.overflow.nonzero().flatten().tolist()}"
        assert not bool(fa.overflow.any())
        _equal_frames(fa, fb, f"step {k}: ")
        n_pub += int(fa.published.sum())
    return n_pub


def test_capturable_default_follows_the_device():
    assert FeatureTracker(CFG).capturable is False
    assert FeatureTracker(CFG, capturable=True).params.capturable is True
    assert FeatureTracker(CFG, capturable=True).params.lk_options.capturable is True


@pytest.mark.slow  # the golden battery's capturable cases cover the sample in the default suite
@pytest.mark.parametrize("device", DEVICES)
def test_identical_on_the_euroc_sample(device):
    cfg = tf.load_config(CFG)
    steps = _sequence("sample", 1, 30)  # the 24 sample frames, then again after a 3 s gap (a restart)
    assert _run_both(cfg, steps, 1, device=device) > 5


@pytest.mark.parametrize("n", [pytest.param(6, id="6 steps"), pytest.param(14, id="14 steps", marks=pytest.mark.slow)])
def test_identical_on_warped_motion(n):
    """Two streams moving by several pixels per frame (more LK iterations than the sample needs)."""
    cfg = tf.load_config(CFG)
    steps = _sequence("warp", 2, n)
    assert _run_both(cfg, steps, 2) > (2 if n < 10 else 5)


@pytest.mark.slow  # the golden battery's mono cases: other images, a pause and restarts per stream
def test_identical_on_a_mixed_batch():
    """Streams that differ: other sequences, a stream that pauses (``active``), one that restarts."""
    cfg = tf.load_config(CFG)
    B, n = 4, 16
    steps = _sequence("sample", B, n)
    warped = _sequence("warp", B, n)
    actives = []
    for k in range(n):
        img, stamps = steps[k]
        img = img.clone()
        img[1] = warped[k][0][1]
        stamps = list(stamps)
        if k >= 9:
            stamps[3] += 2.0  # stream 3 jumps by 2 s: restart
        steps[k] = (img, stamps)
        actives.append(torch.tensor([True, True, not 4 <= k < 7, True]))
    assert _run_both(cfg, steps, B, actives=actives) > 10


@pytest.mark.slow  # the golden battery's stereo/capturable case is the same comparison
def test_identical_in_fusion_stereo():
    cfg = tf.load_config(STEREO)
    left, right = _frames("cam0"), _frames("cam1")
    n = min(len(left), len(right), 8)
    steps = [(torch.from_numpy(left[k][1])[None, None], [left[k][0]]) for k in range(n)]
    rights = [torch.from_numpy(right[k][1])[None, None] for k in range(n)]
    assert _run_both(cfg, steps, 1, mode="fusion", right=rights) == n


def _count_steps(B, n_warm=3, n=2, crop=None):
    """OpCounter figures of ``n`` capturable steps (the pure step on validated inputs, after warm-up);
    ``crop``: ``(H, W)`` top-left crops of the frames with the config's size and principal point
    moved along (the capturable step is shape-static: its kernel count depends on no size)."""
    cfg = tf.load_config(CFG)
    steps = _sequence("warp", B, n_warm + n)
    if crop is not None:
        H, W = crop
        cfg = dataclasses.replace(cfg, image_width=W, image_height=H)  # top-left crops: the same camera
        steps = [(img[..., :H, :W].contiguous(), stamps) for img, stamps in steps]
    tr = FeatureTracker(cfg, num_streams=B, capturable=True)
    for img, stamps in steps[:n_warm]:
        tr.track(img, stamps)
    out = []
    state = tr.state
    for img, stamps in steps[n_warm:]:
        img_v, t, act, _ = check_inputs(state, tr.params, img, stamps)
        with OpCounter() as c:
            state, _ = step_impl(state, img_v, t, tr.params, right=None, active=act)
        out.append(c)
    return out


#: a crop that keeps the LK's four pyramid levels (level 3 is 24 x 32 > the 21-px window)
COUNT_CROP = (192, 256)


@pytest.mark.parametrize("B", [4, pytest.param(16, marks=pytest.mark.slow)])
def test_capturable_step_has_no_syncs_and_a_launch_count_independent_of_b(B):
    """0 syncs; the same kernels per step at B = 1 and B (on crops: the count depends on no size,
    as the full-frame B = 1 count shows) and on every step (the data)."""
    full = _count_steps(1)
    one, many = _count_steps(1, crop=COUNT_CROP), _count_steps(B, crop=COUNT_CROP)
    for c in full + one + many:
        assert c.syncs == 0, c.summary()
    kf, k1, kb = ([c.kernels for c in cs] for cs in (full, one, many))
    assert len(set(kf)) == 1, f"kernels per step vary with the data: {kf}"
    assert k1 == kf, f"kernels per step depend on the image size: full {kf}, {COUNT_CROP} crops {k1}"
    assert kb == k1, f"kernels per step depend on B: B=1 {k1}, B={B} {kb}"
    assert kf[0] <= KERNEL_BOUND, full[0].summary()


def test_the_default_cpu_path_is_unchanged_by_the_flag():
    """capturable=False is the tuned path: LK with early exit (host syncs allowed there)."""
    p = TrackerParams.from_config(tf.load_config(CFG))
    assert p.capturable is False and p.lk_options.capturable is False


def _explain(B=1):
    cfg = tf.load_config(CFG)
    tr = FeatureTracker(cfg, num_streams=B, capturable=True)
    steps = _sequence("warp", B, 5)
    for img, stamps in steps[:4]:
        tr.track(img, stamps)
    img, stamps = steps[4]
    img_v, t, act, _ = check_inputs(tr.state, tr.params, img, stamps)

    def fn(state, img, t, active):
        return step_impl(state, img, t, tr.params, right=None, active=active)

    torch._dynamo.reset()
    return torch._dynamo.explain(fn)(tr.state, img_v, t, act)


@pytest.mark.slow  # slow, and CI (make test-all) runs it: keeps make test within ~5 min
def test_capturable_step_is_one_graph():
    ex = _explain()
    reasons = "; ".join(str(b.reason)[:200] for b in ex.break_reasons[:5])
    assert ex.graph_break_count == 0, f"{ex.graph_break_count} graph breaks: {reasons}"
    assert ex.graph_count == 1


@pytest.mark.slow  # ~60 s of dynamo tracing; test_capturable_step_is_one_graph traces the step by default
def test_compile_runs_the_whole_step_with_an_eager_fallback():
    cfg = tf.load_config(CFG)
    steps = _sequence("warp", 1, 4)
    ref = FeatureTracker(cfg, capturable=True)
    tr = FeatureTracker(cfg, capturable=True)
    tr.compile(backend="eager")  # dynamo's whole-step graph, run eagerly (inductor takes minutes on CPU)
    torch._dynamo.reset()
    from torch_frontend._cache import clear_caches

    clear_caches()  # a cold start: the compiled step's first trace meets no cached constant (it failed so)
    for img, stamps in steps:
        out = tr.track(img, stamps)  # before the eager tracker, which would fill the caches
        _equal_frames(ref.track(img, stamps), out)
    assert tr._compiled.failed is None
    # a compiler failure falls back to eager with a warning, and the step's result is the eager one
    def broken_backend(gm, example_inputs):
        raise RuntimeError("this backend always fails")

    bad = FeatureTracker(cfg, capturable=True)
    bad.compile(backend=broken_backend)
    with pytest.warns(RuntimeWarning, match="running eager"):
        fb = bad.track(*steps[0])
    _equal_frames(FeatureTracker(cfg, capturable=True).track(*steps[0]), fb)
    assert bad._compiled.failed is not None
    bad.compile(enable=False)
    assert bad._compiled is None
    strict = FeatureTracker(cfg, capturable=True)
    strict.compile(backend=broken_backend, fallback=False)
    with pytest.raises(Exception, match="always fails"):
        strict.track(*steps[0])


def test_state_is_a_pytree_with_the_same_leaves_on_both_paths():
    cfg = tf.load_config(CFG)
    a, b = FeatureTracker(cfg, capturable=False), FeatureTracker(cfg, capturable=True)
    for img, stamps in _sequence("sample", 1, 3):
        a.track(img, stamps)
        b.track(img, stamps)
    la = torch.utils._pytree.tree_leaves(a.state)
    lb = torch.utils._pytree.tree_leaves(b.state)
    assert [tuple(x.shape) for x in la if isinstance(x, torch.Tensor)] == \
        [tuple(x.shape) for x in lb if isinstance(x, torch.Tensor)]
    assert isinstance(b.state, TrackerState) and dataclasses.is_dataclass(b.state)


def test_an_lk_iteration_budget_trades_launches_for_an_overflow_flag():
    """``lk_iter_budget``: fewer launches per step; exact (and no overflow) on the EuRoC sample, where
    points need at most 12 iterations per level; a budget that is too small says so per stream."""
    cfg = tf.load_config(CFG)
    steps = _sequence("sample", 1, 8)
    # the tensor LK's budgets (a budget runs the tensor LK: the fused one always runs OpenCV's count)
    ref = FeatureTracker(cfg, capturable=False, lk_backend="tensor")
    short = FeatureTracker(cfg, capturable=True, lk_iter_budget=(16, 14, 12, 10), lk_backend="tensor")
    tiny = FeatureTracker(cfg, capturable=True, lk_iter_budget=2, lk_backend="tensor")
    tripped = []
    for img, stamps in steps:
        fr = ref.track(img, stamps)
        fs = short.track(img, stamps)
        assert not bool(fs.overflow.any())
        _equal_frames(fr, fs)
        tripped.append(bool(tiny.track(img, stamps).overflow.any()))
    assert any(tripped) and not tripped[0]  # the first frame tracks nothing
    counts = []
    for tr in (FeatureTracker(cfg, capturable=True, lk_backend="tensor"),
               FeatureTracker(cfg, capturable=True, lk_iter_budget=(16, 14, 12, 10), lk_backend="tensor")):
        state = tr.state
        for img, stamps in steps[:3]:
            state, _ = tr.step(state, img, stamps)
        img_v, t, act, _ = check_inputs(state, tr.params, *steps[3])
        with OpCounter() as c:
            step_impl(state, img_v, t, tr.params, right=None, active=act)
        counts.append(c.kernels)
    assert counts[1] < counts[0] - 1000, counts


def test_lo_ransac_in_the_tracker_on_both_paths():
    """``F_method: lo`` through rejectWithF: the capturable step equals the default path
    (no overflow on the sample), and an unknown estimator is refused by name."""
    cfg = dataclasses.replace(tf.load_config(CFG), F_method="lo")
    assert TrackerParams.from_config(cfg).F_method == "lo"
    steps = _sequence("sample", 1, 10)
    assert _run_both(cfg, steps, 1) > 3
    with pytest.raises(ValueError, match="F_method"):
        TrackerParams(F_method="magsac")
