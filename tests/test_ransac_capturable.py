"""Tests of the capturable F-RANSAC path (``_find_fundamental_impl(..., capturable=True)``).

Oracle: the default path (whose masks are ``cv2.findFundamentalMat``'s, see ``test_ransac.py``) and
cv2 itself where ``test_ransac.py`` compares with it. Contract: wherever ``overflow`` is False the
capturable path gives the default path's ``inliers``, ``ok``, ``num_iters`` and ``method`` exactly and
its ``F`` up to rounding (a factorisation-free null space); after a warm-up call with the same
states, N, max_iters and confidence it makes no host sync, and its kernel count depends neither on
B nor on the data.
"""

from __future__ import annotations

import threading

import numpy as np
import torch

from torch_frontend import ransac
from torch_frontend.ransac import capturable, find_fundamental, samples
from torch_frontend.testing.dispatch_count import OpCounter

from ._ransac_cases import _cv_mask, _plant, _reference_F, _scatter, _synthetic_scenes, _tie_problem

OPENCV = samples._state_of(ransac.OPENCV_SEED)
RATES = [0.0, 0.10, 0.25, 0.40]


def _both(p1, p2, valid, states=None, block=None, threshold=1.0, confidence=0.99, max_iters=1000):
    """(default result, capturable result) of the same call."""
    states = [OPENCV] * valid.shape[0] if states is None else states
    args = (p1, p2, valid, threshold, confidence, max_iters, states)
    return (ransac._find_fundamental_impl(*args, None),
            ransac._find_fundamental_impl(*args, block, capturable=True))


def _assert_same(ref, got, rows=None):
    """The capturable result equals the default one (F to rounding) on ``rows`` (default all)."""
    rows = slice(None) if rows is None else rows
    assert torch.equal(got.inliers[rows], ref.inliers[rows])
    assert torch.equal(got.ok[rows], ref.ok[rows])
    assert torch.equal(got.num_iters[rows], ref.num_iters[rows])
    assert torch.equal(got.method[rows], ref.method[rows])
    assert got.F.dtype == ref.F.dtype and got.inliers.dtype == torch.bool and got.overflow.dtype == torch.bool
    assert ref.overflow is None and got.overflow.shape == got.ok.shape  # the kernel contract's last field
    tol = 1e-9 if ref.F.dtype == torch.float64 else 1e-6
    assert torch.allclose(got.F[rows], ref.F[rows], atol=tol, rtol=0, equal_nan=True)
    assert torch.isnan(got.F[rows][~got.ok[rows]]).all()


def _planted(k=4, n=150, seed=5):
    rng = np.random.default_rng(seed)
    base = _synthetic_scenes(k=k, n=n, noise=0.3, seed=seed)
    sets = []
    for rate in RATES:
        for a, c in base:
            sets.append((a, _plant(a, c, rate, rng, _reference_F(a, c))[0]))
    return sets


def test_planted_scenes_equal_default_and_opencv(device, dtype):
    """Synthetic scenes with 0/10/25/40 % planted outliers (B = 16, NaN padding scattered): the
    default path's results, and cv2's masks; the default block never overflows."""
    sets = _planted()
    p1, p2, valid, slots = _scatter(sets, 160, np.random.default_rng(1), device)
    ref, got = _both(p1.to(dtype), p2.to(dtype), valid)
    _assert_same(ref, got)
    assert not got.overflow.any() and got.ok.all() and (got.method == ransac.METHOD_RANSAC).all()
    assert got.num_iters.max() > 300  # 40 % outliers: a deep replay of OpenCV's bound
    for b, ((a, c), s) in enumerate(zip(sets, slots)):
        assert np.array_equal(got.inliers[b, s].cpu().numpy(), _cv_mask(a, c)), b
        assert not got.inliers[b].sum() > len(s)


def test_point_counts_mixed_batch(device):
    """Rows with < 8, 8..14 (LMedS) and >= 15 (RANSAC) points, a degenerate row and NaN padding in
    one batch: the default path's results; cv2's masks at 14 and 15 points (where the default path
    has them)."""
    rng = np.random.default_rng(3)
    base = _synthetic_scenes(k=3, n=150, noise=0.2, seed=9)
    counts = [0, 3, 7, 8, 10, 14, 15, 30, 150, 14, 15, 40]
    sets = []
    for i, n in enumerate(counts):
        a, c = base[i % 3]
        c, _ = _plant(a, c, 0.25, rng)
        sets.append((a[:n], c[:n]))
    sets.append((np.full((30, 2), 5.0), np.full((30, 2), 5.0)))  # all points identical: no model
    p1, p2, valid, slots = _scatter(sets, 150, rng, device)
    ref, got = _both(p1, p2, valid)
    _assert_same(ref, got)
    assert not got.overflow.any()
    assert got.method.tolist() == [0, 0, 0, 1, 1, 1, 2, 2, 2, 1, 2, 2, 2]
    assert not got.ok[:3].any() and got.ok[3:-1].all() and not got.ok[-1]
    assert torch.equal(got.inliers[:3], valid[:3]) and got.inliers[-1].sum() == 30
    assert got.num_iters[-1] == 1000 and (got.num_iters[3:6] == 300).all()
    for b, n in enumerate(counts):
        if n in (14, 15):
            assert np.array_equal(got.inliers[b, slots[b]].cpu().numpy(), _cv_mask(*sets[b])), b


def test_per_problem_states_and_small_N():
    """Per-problem ``cv::RNG`` states (one table set per distinct state; repeated states share one)
    and N < 15 (LMedS only) or N < 8 (nothing to estimate): the default path's results."""
    rng = np.random.default_rng(8)
    base = _synthetic_scenes(k=6, n=60, noise=0.2, seed=2)
    sets = [(a, _plant(a, c, 0.2, rng)[0]) for a, c in base]
    p1, p2, valid, _ = _scatter(sets, 64, rng)
    states = [samples._state_of(s) for s in (1, 2, 3, 1, -1, 2)]
    ref, got = _both(p1, p2, valid, states=states)
    _assert_same(ref, got)
    assert len({tuple(r.tolist()) for r in got.inliers}) == 6
    for N, n in ((14, 12), (10, 9), (7, 7)):
        q1, q2, v, _ = _scatter([(a[:n], c[:n]) for a, c in sets[:3]], N, rng)
        ref, got = _both(q1, q2, v)
        _assert_same(ref, got)
        assert not got.overflow.any()


def test_degenerate_and_empty():
    """All points identical (every sample degenerate), NaN in valid slots, B = 0 and N = 0."""
    p = torch.full((1, 30, 2), 5.0, dtype=torch.float64)
    ref, got = _both(p, p.clone(), torch.ones(1, 30, dtype=torch.bool))
    _assert_same(ref, got)
    assert not got.ok.item() and got.inliers.all() and got.num_iters.item() == 1000
    a, c = _synthetic_scenes(k=1, n=40)[0]
    p1, p2 = torch.tensor(a[None]), torch.tensor(c[None])
    p1[0, 7] = float("nan")  # valid but not finite: treated as masked out
    p2[0, 9] = float("inf")
    ref, got = _both(p1, p2, torch.ones(1, 40, dtype=torch.bool))
    _assert_same(ref, got)
    assert got.ok.item() and not got.inliers[0, [7, 9]].any()
    for B, N in ((0, 20), (2, 0)):
        z = torch.zeros(B, N, 2)
        got = find_fundamental(z, z, capturable=True)
        assert got.F.shape == (B, 3, 3) and got.inliers.shape == (B, N) and got.overflow.shape == (B,)
        assert not got.ok.any()


def test_masks_equal_opencv_on_ties_and_tracker_like_calls():
    """The constructed ties of ``test_ransac.py`` (OpenCV keeps the first of two models with equal
    counts) and tracker-like problems (float32, 140..150 of 150 slots valid, 10 % outliers), each
    batched into one capturable call: every mask is cv2's."""
    sets = [_tie_problem(seed)[:2] for seed in range(6)]
    p1 = torch.from_numpy(np.stack([a for a, _ in sets]))
    p2 = torch.from_numpy(np.stack([c for _, c in sets]))
    got = find_fundamental(p1, p2, capturable=True)
    for b, (a, c) in enumerate(sets):
        assert np.array_equal(got.inliers[b].numpy(), _cv_mask(a, c)), b
    rng = np.random.default_rng(17)
    p1 = torch.full((6, 150, 2), float("nan"))
    p2 = p1.clone()
    valid = torch.zeros(6, 150, dtype=torch.bool)
    cases = []
    for i, (a, c) in enumerate(_synthetic_scenes(k=6, n=150, noise=0.3, seed=12)):
        c, _ = _plant(a, c, 0.1, rng)
        n = int(rng.integers(140, 151))
        p1[i, :n], p2[i, :n], valid[i, :n] = torch.from_numpy(a[:n]).float(), torch.from_numpy(c[:n]).float(), True
        cases.append((a[:n].astype(np.float32), c[:n].astype(np.float32)))
    got = find_fundamental(p1, p2, valid, seed=0, capturable=True)
    assert got.F.dtype == torch.float32 and not got.overflow.any()
    for i, (a, c) in enumerate(cases):
        assert np.array_equal(got.inliers[i, : len(a)].numpy(), _cv_mask(a, c)), i


def test_no_syncs_and_kernels_independent_of_batch_and_data():
    """After a warm-up call: 0 host syncs; the same kernel count for B = 1 and 4 (one problem of
    each outlier rate) and for easy and hard data (the count is also reported: it is each call's
    launch count on CUDA)."""
    sets = _planted(k=4, n=150)
    p1, p2, valid, _ = _scatter(sets, 150, np.random.default_rng(2))
    counts = {}
    for name, rows in (("B1 clean", [0]), ("B1 hard", [15]), ("B4", [1, 6, 11, 14])):
        args = (p1[rows].float(), p2[rows].float(), valid[rows], 1.0, 0.99, 1000, [OPENCV] * len(rows), None)
        ransac._find_fundamental_impl(*args, capturable=True)  # warm-up: tables, device constants
        with OpCounter() as c:
            res = ransac._find_fundamental_impl(*args, capturable=True)
        assert c.syncs == 0, c.summary()
        assert c.uploads == 0
        counts[name] = c.kernels
        assert not res.overflow.any()
    assert len(set(counts.values())) == 1, counts
    assert counts["B4"] <= 400, counts  # a budget: the whole tracker step has ~2,500
    # per-problem states (3 distinct, N = 40: short table builds): one kernel more (the state
    # offset), independent of B
    st = [samples._state_of(s % 3 + 1) for s in range(16)]
    per_state = {}
    for B in (2, 16):
        args = (p1[:B, :40], p2[:B, :40], valid[:B, :40], 1.0, 0.99, 1000, st[:B], None)
        ransac._find_fundamental_impl(*args, capturable=True)
        with OpCounter() as c:
            ransac._find_fundamental_impl(*args, capturable=True)
        assert c.syncs == 0, c.summary()
        per_state[B] = c.kernels
    assert per_state[2] == per_state[16] == counts["B4"] + 1, (per_state, counts)


def test_scoring_groups_same_result(monkeypatch):
    """Scoring the block in groups of problems (``capturable._SCORE_PAIRS``, a memory knob: one
    group up to B = 18 at 150 points) gives the one-group result (every field, F to the bit); no
    host sync, and 8 kernels more per extra group (bmm, square, sums, minimum, two tests, and, count)."""
    sets = _planted(k=2, n=150)[:5]
    p1, p2, valid, _ = _scatter(sets, 150, np.random.default_rng(7))
    args = (p1.float(), p2.float(), valid, 1.0, 0.99, 1000, [OPENCV] * valid.shape[0], None)
    kernels = {}
    for pairs in (capturable._SCORE_PAIRS, 2 * 3000 * 150):  # 1 group; 3 groups of <= 2 problems
        monkeypatch.setattr(capturable, "_SCORE_PAIRS", pairs)
        ransac._find_fundamental_impl(*args, capturable=True, backend="tensor")  # warm-up
        with OpCounter() as c:  # the tensor scoring's groups (the fused op has none)
            res = ransac._find_fundamental_impl(*args, capturable=True, backend="tensor")
        assert c.syncs == 0 and c.uploads == 0, c.summary()
        kernels[pairs] = (c.kernels, res)
    (k1, one), (k3, grouped) = kernels.values()
    for a, b in zip(one, grouped):
        assert torch.equal(a, b) or torch.equal(a.isnan(), b.isnan()) and torch.equal(a.nan_to_num(), b.nan_to_num())
    assert not one.overflow.any()
    assert k3 == k1 + 2 * 8, kernels


def test_overflow_flag():
    """A block smaller than OpenCV needs: ``overflow`` is True exactly where OpenCV would draw more
    samples (an all-outlier scene needs all 1000; LMedS needs 300); elsewhere the result is exact."""
    rng = np.random.default_rng(4)
    clean = _synthetic_scenes(k=1, n=100, noise=0.1, seed=6)[0]
    outliers = (rng.uniform(0, 500, (100, 2)), rng.uniform(0, 500, (100, 2)))
    lmeds = _synthetic_scenes(k=1, n=12, noise=0.1, seed=7)[0]
    p1, p2, valid, _ = _scatter([clean, outliers, lmeds], 100, rng)
    ref, got = _both(p1, p2, valid, block=48)
    assert int(ref.num_iters[0]) <= 48 and int(ref.num_iters[1]) == 1000
    assert got.overflow.tolist() == [False, True, True]
    _assert_same(ref, got, rows=slice(0, 1))
    assert got.num_iters.tolist()[1:] == [48, 48]
    ref, got = _both(p1, p2, valid)  # the default block: exact everywhere
    _assert_same(ref, got)
    assert not got.overflow.any()


def test_threads_share_one_table_build():
    """Cold tables built by two threads at once: both get the single-threaded result."""
    rng = np.random.default_rng(9)
    sets = [(a, _plant(a, c, 0.2, rng)[0]) for a, c in _synthetic_scenes(k=2, n=40, noise=0.2, seed=3)]
    p1, p2, valid, _ = _scatter(sets, 41, rng)
    capturable._tables_capturable.cache_clear()
    samples._state_samples.cache_clear()
    out = [None, None]

    def run(i):
        out[i] = ransac._find_fundamental_impl(p1, p2, valid, 1.0, 0.99, 1000, [OPENCV] * 2, None, capturable=True)

    threads = [threading.Thread(target=run, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    ref = ransac._find_fundamental_impl(p1, p2, valid, 1.0, 0.99, 1000, [OPENCV] * 2, None)
    for got in out:
        _assert_same(ref, got)
