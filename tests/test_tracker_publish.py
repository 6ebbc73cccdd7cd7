"""Work only where VINS works: the capturable mono step's variant is chosen on the host from a mirror
of the publish clock (``clock.HostClock``, ``clock.publish_plan``), so unpublished frames run no
rejectWithF, setMask or detection kernels, and a batch whose streams are out of phase runs those
stages on a sub-batch of the publishing streams; the outputs are the same bits in every case."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

import torch_frontend as tf
from torch_frontend.testing.dispatch_count import OpCounter, _site
from torch_frontend.tracker import FeatureTracker, TrackerParams
from torch_frontend.tracker.clock import HostClock, count_published, lane_sizes, mono_clock, publish_plan
from torch_frontend.tracker.state import ClockState
from torch_frontend.tracker.track_step import check_inputs, step_impl

from . import _golden as g
from .conftest import REPO, load_gray, sample_frames

CFG = REPO / "configs" / "euroc.yaml"
#: a crop that keeps the LK's four pyramid levels and CLAHE's 8x8 tiles (the capturable step's
#: kernels do not depend on the size; the crop keeps the CPU time of these tests small)
CROP = (192, 256)
#: where the publish-only stages' kernels live (rejectWithF's RANSAC, setMask's disc mask, GFTT)
PUBLISH_ONLY = ("ransac/", "corners/", "masks.py")


# ---------------------------------------------------------------------------------------------
# the host mirror of the clock


def _device_clock(stamps, actives, params):
    """``publish (n, B)`` and the clock fields after each step, from the device rules."""
    B = len(stamps[0])
    clock = ClockState.initial(B, "cpu")
    out = []
    for t, a in zip(stamps, actives):
        clock, d = mono_clock(clock, torch.tensor(t, dtype=torch.float64), torch.tensor(a), params)
        clock, _ = count_published(clock, d.publish)
        out.append((d.publish.numpy().copy(), clock))
    return out


def _host_clock(stamps, actives, params):
    clock = HostClock.initial(len(stamps[0]))
    out = []
    for t, a in zip(stamps, actives):
        clock, pub = clock.step(np.asarray(t, np.float64), np.asarray(a, bool), params)
        out.append((pub, clock))
    return out


def _assert_same_clock(stamps, actives, params, where):
    for k, ((pd, cd), (ph, ch)) in enumerate(zip(_device_clock(stamps, actives, params),
                                                 _host_clock(stamps, actives, params))):
        assert np.array_equal(pd, ph), f"{where} step {k}: publish {pd.tolist()} (device) vs {ph.tolist()} (host)"
        for f in dataclasses.fields(HostClock):
            dev, host = getattr(cd, f.name).numpy(), getattr(ch, f.name)
            assert dev.dtype == host.dtype and np.array_equal(dev, host), f"{where} step {k}: {f.name} differs"


def _random_stamps(rng, B, n):
    """Clocks that exercise every rule: 15..40 Hz with jitter, epoch or small start times,
    duplicate stamps, gaps over 1 s, time going backwards, streams that pause."""
    t = np.where(rng.random(B) < 0.5, 1.4e9 + rng.random(B) * 1e6, rng.random(B) * 10)
    hz = rng.choice([15.0, 20.0, 25.0, 30.0, 40.0, 20.0 * (1 + 1e-3 * rng.standard_normal())], B)
    stamps, actives = [], []
    for _ in range(n):
        u = rng.random(B)
        dt = 1.0 / hz * (1 + 0.02 * rng.standard_normal(B))
        dt = np.where(u < 0.04, 0.0, np.where(u < 0.07, 1.5, np.where(u < 0.10, -0.3, dt)))
        t = t + dt
        stamps.append(t.tolist())
        actives.append((rng.random(B) > 0.1).tolist())
    return stamps, actives


@pytest.mark.parametrize("freq", [10, 7, 100])
def test_host_clock_decides_as_the_device_clock(freq):
    """The mirror (numpy, float64) and the device's rules (torch, float64): the same publish masks
    and the same clock after every step, over random clocks with every rule in play."""
    params = TrackerParams(freq=freq)
    rng = np.random.default_rng(freq)
    for trial in range(6):
        stamps, actives = _random_stamps(rng, 8, 120)
        _assert_same_clock(stamps, actives, params, f"freq {freq} trial {trial}")


@pytest.mark.parametrize("scenario", ["mono", "mono8", "flight", "kb_fisheye"])
def test_host_clock_on_the_golden_clocks(scenario):
    """The golden mono scenarios' stamps and ``active`` (restarts after a gap and after time going
    backwards, a paused stream): the mirror's decisions are the device's."""
    steps = g.SCENARIOS[scenario].steps()
    stamps = [list(s.timestamps) for s in steps]
    actives = [list(s.active) if s.active is not None else [True] * len(s.timestamps) for s in steps]
    _assert_same_clock(stamps, actives, TrackerParams(), scenario)
    # the 20 Hz EuRoC stamps publish every other frame; the restarts put the two streams out of phase
    pub = [p for p, _ in _host_clock(stamps, actives, TrackerParams())]
    assert any(p.all() for p in pub) and any(not p.any() for p in pub)
    if len(stamps[0]) > 1:
        assert any(p.any() and not p.all() for p in pub)


def test_lane_sizes_and_plans():
    assert lane_sizes(1) == (1,) and lane_sizes(16) == (1, 2, 4, 8, 16) and lane_sizes(5) == (1, 2, 4, 5)
    assert [publish_plan(n, 16).lanes for n in range(17)] == [0, 1, 2, 4, 4] + [8] * 4 + [16] * 8
    assert [publish_plan(n, 16).name for n in (0, 3, 9)] == ["track", "sub4", "all"]
    assert publish_plan(1, 1).name == "all"
    with pytest.raises(ValueError):
        publish_plan(3, 2)


# ---------------------------------------------------------------------------------------------
# the step variants


def _crop_cfg():
    H, W = CROP
    return dataclasses.replace(tf.load_config(CFG), image_width=W, image_height=H)


def _frames():
    H, W = CROP
    return [(int(f.stem) * 1e-9, load_gray(f)[:H, :W].copy()) for f in sample_frames("cam0")]


class _SiteCounter(OpCounter):
    """OpCounter that also records the source file of every kernel."""

    def __init__(self):
        super().__init__()
        self.files = set()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        before = self.kernels
        out = super().__torch_dispatch__(func, types, args, kwargs)
        if self.kernels != before:
            self.files.add(_site().split(":")[0])
        return out


def _counted(tr, state, img, stamps, plan):
    img_v, t, act, _ = check_inputs(state, tr.params, img, stamps)
    with _SiteCounter() as c:
        out = step_impl(state, img_v, t, tr.params, right=None, active=act, plan=plan)
    return out, c


def _same(a, b, where):
    la, lb = torch.utils._pytree.tree_leaves(a), torch.utils._pytree.tree_leaves(b)
    assert len(la) == len(lb), where
    for x, y in zip(la, lb):
        if isinstance(x, torch.Tensor):
            assert x.dtype == y.dtype and x.shape == y.shape and torch.equal(x, y), where


#: kernels of the per-stream pyramid select that a step whose plan knows every stream is tracked
#: skips: one ``where`` on the packed pyramid (the fused kernels' pyramid, the default; the tensor
#: pyramid: one per level and per cached padded level, 8)
PYRAMID_SELECT_KERNELS = 1


def test_an_unpublished_step_runs_no_publish_kernels_and_publishes_the_same_frames():
    """At every step of the sample (B = 2, in phase): the host's plan, counted on the pure step,
    against the every-stream variant (``plan=None``) on the same inputs. Both give the same state
    and frame bit for bit; after warm-up, track-only steps launch no kernel of RANSAC, setMask or
    GFTT, no step syncs, and each variant has one kernel count."""
    tr = FeatureTracker(_crop_cfg(), num_streams=2, capturable=True)
    frames = _frames()[:7]
    counts = {}
    for k, (t, img) in enumerate(frames):
        img = torch.from_numpy(np.stack((img, img)))[:, None]
        stamps = [t, t + 100.0]
        plan, _ = tr._plan(tr.state, torch.tensor(stamps, dtype=torch.float64), torch.ones(2, dtype=torch.bool))
        (new, frame), c = _counted(tr, tr.state, img, stamps, plan)
        (ref_new, ref_frame), c_all = _counted(tr, tr.state, img, stamps, None)
        _same((new, frame), (ref_new, ref_frame), f"step {k} ({plan.name})")
        assert tr.track(img, stamps).published.tolist() == frame.published.tolist()
        if k < 3:  # the first steps build the cached constants (uploads) of their stages once
            continue
        assert c.syncs == 0, c.summary()
        assert bool(frame.published.any()) == (plan.lanes > 0)
        touched = sorted(f for f in c.files if f.startswith(PUBLISH_ONLY))
        # in phase, no gap: from the second frame on every stream is tracked, and the plan says so
        # (this frame's pyramid kept as it is: one where per level and per cached padded level less)
        assert plan.every_tracked
        if plan.lanes == 0:
            assert not touched, f"step {k}: track-only step launched kernels in {touched}"
            # (a bound relative to the step: the fused stages shrink both counts, 128 vs 495 with the fused lift)
            assert 2 * c.kernels < c_all.kernels, (c.kernels, c_all.kernels)
            print(f"kernels per step: track-only {c.kernels}, every stream {c_all.kernels}")
        else:
            assert plan.lanes == plan.batch and touched
            assert c.kernels == c_all.kernels - PYRAMID_SELECT_KERNELS, (c.kernels, c_all.kernels)
        counts.setdefault(plan.name, set()).add(c.kernels)
    assert set(counts) == {"track_every", "all_every"} and all(len(v) == 1 for v in counts.values()), counts


def _mixed_streams(frames, n):
    """Four streams out of phase: stream 0 from the start, stream 1 one frame later (inactive at
    step 0), stream 2 at 30 Hz (every third frame), stream 3 with a 2 s gap at step 5 (a restart).
    Returns ``[(images (4, H, W), stamps, active)]``."""
    out = []
    for k in range(n):
        t, img = frames[k]
        t3 = t + (2.0 if k >= 5 else 0.0)
        stamps = [t, t + 10.0, 50.0 + k / 30.0, t3]
        imgs = np.stack([frames[k][1], frames[max(k - 1, 0)][1], frames[(k + 3) % len(frames)][1], img])
        out.append((imgs, stamps, [True, k > 0, True, True]))
    return out


@pytest.mark.slow  # slow, and CI (make test-all) runs it: keeps make test within ~5 min
def test_mixed_phase_batch_equals_per_stream_runs():
    """A batch whose streams publish at different steps runs the publish stages on sub-batches
    (1, 2 or 4 lanes) and gives each stream the bits of a tracker of its own (and, for the frames,
    of the default path)."""
    cfg = _crop_cfg()
    steps = _mixed_streams(_frames(), 10)
    batch = FeatureTracker(cfg, num_streams=4, capturable=True)
    default = FeatureTracker(cfg, num_streams=4)
    singles = [FeatureTracker(cfg, num_streams=1, capturable=True) for _ in range(4)]
    plans = []
    for k, (imgs, stamps, active) in enumerate(steps):
        plans.append(batch._plan(batch.state, torch.tensor(stamps, dtype=torch.float64), torch.tensor(active))[0])
        fb = batch.track(torch.from_numpy(imgs)[:, None], stamps, active=active)
        fd = default.track(torch.from_numpy(imgs)[:, None], stamps, active=active)
        _same(fb, fd, f"step {k}: capturable vs default")
        for b in range(4):
            if not active[b]:
                continue
            fs = singles[b].track(torch.from_numpy(imgs[b:b + 1])[:, None], stamps[b:b + 1])
            rows = {f.name: getattr(fb, f.name)[b:b + 1] for f in dataclasses.fields(fb)
                    if isinstance(getattr(fb, f.name), torch.Tensor)}
            _same(dataclasses.replace(fb, **rows), fs, f"step {k} stream {b}")
        assert not bool(fb.overflow.any())
    names = {p.name for p in plans}
    assert {"sub1", "sub2", "track"} <= names, names


@pytest.mark.slow  # slow, and CI (make test-all) runs it: keeps make test within ~5 min
def test_sub_batch_variants_share_one_kernel_count():
    """The sub-batch variant is shape-static: the same kernels for 1, 2 and 4 lanes (only the
    bytes of the publish stages scale with the lanes), no sync; every lane count gives the same bits."""
    cfg = _crop_cfg()
    steps = _mixed_streams(_frames(), 6)
    tr = FeatureTracker(cfg, num_streams=4, capturable=True)
    for imgs, stamps, active in steps[:5]:
        tr.track(torch.from_numpy(imgs)[:, None], stamps, active=active)
    imgs, stamps, active = steps[5]
    plan, _ = tr._plan(tr.state, torch.tensor(stamps, dtype=torch.float64), torch.tensor(active))
    assert 0 < plan.lanes < 4, plan
    img = torch.from_numpy(imgs)[:, None]
    img_v, t, act, _ = check_inputs(tr.state, tr.params, img, stamps, active=active)
    kernels, outs = {}, {}
    for lanes in sorted({plan.lanes, 2, 3, 4}):
        p = plan._replace(lanes=lanes)
        step_impl(tr.state, img_v, t, tr.params, right=None, active=act, plan=p)  # its lanes' RANSAC tables, once
        with OpCounter() as c:
            outs[lanes] = step_impl(tr.state, img_v, t, tr.params, right=None, active=act, plan=p)
        assert c.syncs == 0, c.summary()
        kernels[p.name] = c.kernels
        _same(outs[lanes], outs[plan.lanes], f"{lanes} lanes")
    subs = {v for k, v in kernels.items() if k.startswith("sub")}
    assert len(subs) == 1 and kernels["all"] < min(subs) < kernels["all"] + 40, kernels


def test_a_step_from_another_state_reads_its_clock_back():
    """The mirror follows the states the tracker returned; a step from any other state (a saved
    one, a branch) reads that state's clock back and plans from it: the same frames as before."""
    cfg = _crop_cfg()
    frames = _frames()[:6]
    tr = FeatureTracker(cfg, capturable=True)
    states, out = [tr.state], []
    for t, img in frames:
        states.append(tr.step(states[-1], torch.from_numpy(img)[None, None], [t])[0])
    for k in (2, 3, 1):  # replay single steps from saved states, out of order
        t, img = frames[k]
        new, frame = tr.step(states[k], torch.from_numpy(img)[None, None], [t])
        _same(new.features, states[k + 1].features, f"replayed step {k}")
        out.append(bool(frame.published[0]))
    assert out == [True, False, False]  # the sample publishes steps 2, 4, ...


def test_fusion_and_the_default_path_take_no_plan(monkeypatch):
    """Fusion publishes (and detects) every frame and the default path skips unpublished work on
    its own (syncs that cost nothing on the CPU): neither plans on the host."""
    import torch_frontend.tracker.feature_tracker as ftm

    seen = []
    real = ftm.step_impl

    def spy(*a, plan=None, **k):
        seen.append(plan)
        return real(*a, plan=plan, **k)

    monkeypatch.setattr(ftm, "step_impl", spy)
    t, img = _frames()[0]
    for kw in (dict(mode="fusion", capturable=True), dict(capturable=False)):
        tr = FeatureTracker(_crop_cfg(), **kw)
        tr.track(torch.from_numpy(img)[None, None], [t])
        assert not tr._plans and tr._mirror is None
    assert seen == [None, None]


@pytest.mark.slow  # dynamo traces the whole step once per variant (~1 min each on this CPU)
def test_compile_captures_each_variant_once():
    cfg = _crop_cfg()
    frames = _frames()[:5]
    ref = FeatureTracker(cfg, capturable=True)
    tr = FeatureTracker(cfg, capturable=True)
    tr.compile(backend="eager", regions=False)  # the whole step, one graph per variant (CUDA's default)
    torch._dynamo.reset()
    for t, img in frames:
        x = torch.from_numpy(img)[None, None]
        _same(ref.track(x, [t]), tr.track(x, [t]), f"t={t}")
    assert tr._compiled.failed is None and tr._compiled.regions is None
    fns = tr._compiled.variants
    # the first frame (no stream tracked: the plain track-only variant), then every stream tracked:
    # track-only and publishing steps that keep this frame's pyramid as it is (PublishPlan.every_tracked)
    assert {p.name for p in fns} == {"track", "track_every", "all_every"}
    codes = {p.name: fn._torchdynamo_orig_callable.__code__ for p, fn in fns.items()}
    assert codes["track_every"] is not codes["all_every"] and codes["track_every"].co_name == "_step_track_every"


@pytest.mark.slow  # dynamo traces each part once (~20 s in all on this CPU)
def test_compile_regions_compile_each_part_once_for_every_variant():
    """``compile(regions=True)`` (the CPU's default): the mono step's parts (track, publish,
    finish) are compiled each once and shared by the step variants; the outputs are the eager
    step's, and later steps of every variant compile nothing new."""
    cfg = _crop_cfg()
    frames = _frames()[:8]
    graphs = []

    def counting(gm, example_inputs):  # dynamo's graphs, run as traced
        graphs.append(gm)
        return gm.forward

    ref = FeatureTracker(cfg, capturable=True)
    tr = FeatureTracker(cfg, capturable=True)
    tr.compile(backend=counting)
    torch._dynamo.reset()
    for t, img in frames[:5]:
        x = torch.from_numpy(img)[None, None]
        _same(ref.track(x, [t]), tr.track(x, [t]), f"t={t}")
    assert tr._compiled.failed is None
    parts = tr._compiled.regions.parts
    assert set(parts) == {"track", "publish", "finish_unnumbered", "finish_unnumbered_every", "finish_numbered_every"}
    assert {p.name for p in tr._compiled.variants} == {"track", "track_every", "all_every"}
    # one graph per part: the first frame's track part is every later one's (a primed pyramid of
    # the first image stands for the missing previous one, lk.track._prime_next_pyramid)
    assert len(graphs) == len(parts)
    for t, img in frames[5:]:
        x = torch.from_numpy(img)[None, None]
        _same(ref.track(x, [t]), tr.track(x, [t]), f"t={t}")
    assert len(graphs) == len(parts)
    _same(ref.state, tr.state, "state")


@pytest.mark.slow  # dynamo traces the whole step once per variant
def test_cuda_graph_outputs_keep_the_pyramid_padded_levels():
    """With CUDA graphs the compiled step clones its outputs out of the graph's pool; the new
    state's pyramid keeps its padded levels (cloned too), so the next step neither pads the
    previous levels again nor fails the graph's guard on them (a recompile). Emulated on the CPU:
    the clone path switched on (``cuda_graphs``), dynamo's graphs run as traced."""
    cfg = _crop_cfg()
    frames = _frames()[:6]
    graphs = []

    def counting(gm, example_inputs):
        graphs.append(gm)
        return gm.forward

    ref = FeatureTracker(cfg, capturable=True)
    tr = FeatureTracker(cfg, capturable=True)
    tr.compile(backend=counting, regions=False)
    tr._compiled.cuda_graphs = True  # the clone out of the pool (cudagraph_mark_step_begin: a no-op here)
    torch._dynamo.reset()
    for t, img in frames:
        x = torch.from_numpy(img)[None, None]
        _same(ref.track(x, [t]), tr.track(x, [t]), f"t={t}")
        p = tr.state.prev_pyramid  # the fused pyramid carries its border in its packed tensor (a pytree leaf)
        assert p.packed is not None or p._padded, "the state's pyramid lost its padded levels"
    assert len(graphs) == len(tr._compiled.variants) == 3  # one graph per variant, no recompile
    _same(ref.state, tr.state, "state")
