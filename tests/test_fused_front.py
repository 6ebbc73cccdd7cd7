"""The fused front (``torch_frontend::front``, ``fused/front_op.py``): CLAHE -> pyramid -> LK of a frame,
a group of streams at a time on the CPU (``_tuning.Strategy.front_group``, issue 41 item 2).

Bars: the op equals the three stage ops (``clahe``, ``pyramid``, ``lk``) bit for bit for every group
size and thread count; the tracker's grouped step equals its stage-order step (``front_group=None``)
on every output of every frame, for several group sizes, batch sizes and thread counts, on the default
and the capturable CPU path, and the step really runs the op (once per step after the first).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

import torch_frontend as tf
from torch_frontend import _tuning
from torch_frontend.fused.clahe_op import clahe_op
from torch_frontend.fused.front_op import front_op
from torch_frontend.fused.ops import lk_op, pyramid_op
from torch_frontend.testing.dispatch_count import OpCounter
from torch_frontend.tracker import track_step

from .conftest import REPO, load_gray, sample_frames

pytestmark = pytest.mark.usefixtures("single_thread")

PAD, LEVELS, WIN = 22, 3, 21


def _bits(t: torch.Tensor) -> torch.Tensor:
    return t.view(torch.int32) if t.dtype == torch.float32 else t


def _case(B: int, n_pts: int = 60):
    """Crops of consecutive sample frames (prev, next) per stream, points on corners and at random."""
    frames = [load_gray(p)[40:200, 100:340] for p in sample_frames("cam0")[:B + 1]]
    prev_img = torch.from_numpy(np.stack(frames[:B]))
    img = torch.from_numpy(np.stack(frames[1:B + 1]))
    g = torch.Generator().manual_seed(B)
    pts = torch.rand(B, n_pts, 2, generator=g) * torch.tensor([245.0, 165.0]) - 2.0  # some outside
    valid = torch.rand(B, n_pts, generator=g) > 0.15
    prev = pyramid_op(clahe_op(prev_img, 3.0, 8, 8), LEVELS, PAD)
    return img, prev, pts, valid


def _stages(img, prev, pts, valid, top=LEVELS):
    eq = clahe_op(img, 3.0, 8, 8)
    packed = pyramid_op(eq, LEVELS, PAD)
    H, W = img.shape[1:]
    return (eq, packed) + tuple(lk_op(prev, packed, pts, valid, None, H, W, PAD, PAD, top, WIN, WIN, 30, 0.01, 1e-4,
                                      -1, 0.0, False))


def _front(img, prev, pts, valid, group, top=LEVELS):
    return front_op(img, prev, pts, valid, 3.0, 8, 8, LEVELS, PAD, top, WIN, WIN, 30, 0.01, 1e-4, group)


def _assert_equal(got, ref, what):
    names = ("eq", "packed", "next_pts", "status", "capped")
    for name, a, b in zip(names, got, ref):
        assert torch.equal(_bits(a), _bits(b)), f"{what}: {name} differs"


@pytest.mark.parametrize("B", [1, 3, 5])
def test_the_op_equals_the_three_stage_ops_for_every_group_and_thread_count(B):
    img, prev, pts, valid = _case(B)
    ref = _stages(img, prev, pts, valid)
    assert ref[3].any() and not ref[3].all()  # tracked and lost lanes both
    n = torch.get_num_threads()
    try:
        for threads in (1, 2, 3):
            torch.set_num_threads(threads)
            for group in (1, 2, 3, B, B + 4):
                _assert_equal(_front(img, prev, pts, valid, group), ref, f"B={B} group={group} threads={threads}")
    finally:
        torch.set_num_threads(n)
    _assert_equal(_front(img, prev, pts, valid, 2, top=1), _stages(img, prev, pts, valid, top=1), "top=1")


def test_one_op_no_sync_opcheck_compile_and_errors():
    img, prev, pts, valid = _case(2, 8)
    _front(img, prev, pts, valid, 1)  # warm-up
    with OpCounter() as c:
        _front(img, prev, pts, valid, 1)
    assert c.kernels == 1 and c.syncs == 0, c.summary()
    res = torch.library.opcheck(front_op, (img, prev, pts, valid, 3.0, 8, 8, LEVELS, PAD, LEVELS, WIN, WIN, 30, 0.01,
                                           1e-4, 1))
    assert all(v == "SUCCESS" for v in res.values()), res
    got = torch.compile(lambda *a: _front(*a, 1), backend="eager", fullgraph=True)(img, prev, pts, valid)
    _assert_equal(got, _stages(img, prev, pts, valid), "compiled")
    with pytest.raises(ValueError, match="prev must be the"):
        _front(img, prev[:, :-1], pts, valid, 1)
    with pytest.raises(ValueError, match="pts must be"):
        _front(img, prev, pts.double(), valid, 1)
    with pytest.raises(ValueError, match="group must be >= 1"):
        _front(img, prev, pts, valid, 0)


def _run_tracker(monkeypatch, B: int, group, threads: int = 1, n: int = 6, **kwargs):
    """Every frame's outputs of a mono EuRoC tracker over ``n`` steps of the sample (stream ``b`` starts
    ``2 b`` frames later; stream 1, when there is one, skips step 3), with ``front_group=group``, and
    the number of front op calls."""
    monkeypatch.setitem(_tuning.STRATEGIES, "cpu", dataclasses.replace(_tuning.CPU, front_group=group))
    calls = []
    real = track_step.front
    monkeypatch.setattr(track_step, "front", lambda *a, **k: (calls.append(a[-1]), real(*a, **k))[1])
    files = sample_frames("cam0")
    tr = tf.FeatureTracker(tf.load_config(REPO / "configs" / "euroc.yaml"), num_streams=B, **kwargs)
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    out = []
    try:
        for k in range(n):
            img = torch.from_numpy(np.stack([load_gray(files[(k + 2 * b) % len(files)]) for b in range(B)]))[:, None]
            active = torch.tensor([not (b == 1 and k == 3) for b in range(B)])
            f = tr.track(img, [1403715273.0 + 0.05 * k] * B, active=active)
            out.append([getattr(f, name).clone() for name in ("ids", "uv", "xy", "velocity", "track_count", "valid",
                                                                 "present", "published")])
    finally:
        torch.set_num_threads(old)
    return out, len(calls)


@pytest.mark.parametrize("B,capturable,variants", [
    (1, False, [(1, 1), (1, 2)]),
    (3, False, [(1, 1), (2, 2), (4, 1)]),  # (group, threads)
    (3, True, [(2, 2)]),  # the capturable CPU step is slow: one grouped variant
])
def test_the_grouped_step_equals_the_stage_order_step(monkeypatch, B, capturable, variants):
    ref, calls = _run_tracker(monkeypatch, B, None, capturable=capturable)
    assert calls == 0
    assert sum(int(f[5].sum()) for f in ref) > 0  # features published
    for group, threads in variants:
        got, calls = _run_tracker(monkeypatch, B, group, threads, capturable=capturable)
        assert calls == len(ref) - 1, (group, threads)  # every step but the first (no previous pyramid)
        for k, (a, b) in enumerate(zip(got, ref)):
            for x, y in zip(a, b):
                assert torch.equal(_bits(x), _bits(y)), (group, threads, k)
