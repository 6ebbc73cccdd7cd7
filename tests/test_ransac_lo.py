"""Tests of LO-RANSAC (``find_fundamental(..., method="lo")``, issue 22) and the ``F_method`` key.

Oracle: exact ground truth (synthetic two-view scenes with known F and planted outliers), the
``"opencv"`` path (whose masks are cv2's, see ``test_ransac.py``) as the baseline it must beat, and
the default LO path as the oracle of the capturable one. Contract: the capturable path gives the
default path's ``inliers``, ``ok``, ``num_iters`` and ``method`` wherever ``overflow`` is False (and
its ``F``: bit for bit on RANSAC rows on the CPU, to rounding on LMedS rows); a problem's result
is the same in any batch; no host sync and a kernel count independent of B and of the data.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

import torch_frontend as tf
from torch_frontend import ransac
from torch_frontend.errors import ConfigError
from torch_frontend.ransac import find_fundamental, refit, refit_fundamental, samples
from torch_frontend.ransac import lo as ransac_lo
from torch_frontend.ransac.consts import _consts
from torch_frontend.testing.dispatch_count import OpCounter
from torch_frontend.testing.two_view import line_distances, planted_scenes

from ._ransac_cases import _cv_mask, _plant, _scatter, _synthetic_scenes
from .conftest import REPO

OPENCV = samples._state_of(ransac.OPENCV_SEED)
RATES = [0.0, 0.10, 0.25, 0.40]
def _gt_scenes(k: int, rate: float, seed: int, n: int = 150, noise: float = 0.3):
    """``k`` planted scenes (``torch_frontend.testing.two_view``) as ``p1, p2, g1, g2, F, planted``."""
    s = planted_scenes(k, rate, seed, n=n, noise=noise)
    return [s[name] for name in ("p1", "p2", "g1", "g2", "F", "planted")]


_line_dists = line_distances


def _f_error(F, g1, g2):
    """The benchmark's F error: ``max(d1, d2)`` of the noise-free correspondences, px."""
    return np.maximum(*_line_dists(F, g1, g2))


def _both(p1, p2, valid, states=None, block=None, max_iters=1000):
    states = [OPENCV] * valid.shape[0] if states is None else states
    args = (p1, p2, valid, 1.0, 0.99, max_iters, states, block)
    return (ransac._find_fundamental_impl(*args, method="lo"),
            ransac._find_fundamental_impl(*args, capturable=True, method="lo"))


def _mixed_batch(device="cpu"):
    """Rows with < 8, 8..14 (LMedS) and >= 15 points, 0..40 % planted outliers, an all-identical
    (degenerate) row, scattered among NaN slots."""
    rng = np.random.default_rng(3)
    base = _synthetic_scenes(k=3, n=150, noise=0.3, seed=9)
    sets = []
    for i, n in enumerate([0, 3, 7, 8, 10, 14, 15, 30, 150, 14, 15, 40, 150, 100]):
        a, c = base[i % 3]
        c, _ = _plant(a, c, RATES[i % 4], rng)
        sets.append((a[:n], c[:n]))
    sets.append((np.full((30, 2), 5.0), np.full((30, 2), 5.0)))
    p1, p2, valid, slots = _scatter(sets, 150, rng, device)
    return p1, p2, valid, slots, sets


# ----------------------------------------------------------------------------------------------
# accuracy on planted scenes (fixed seeds)
# ----------------------------------------------------------------------------------------------
def test_lo_recall_precision_and_F_error_on_planted_scenes():
    """8 scenes per outlier rate (150 matches, 0.3 px noise in both images): "lo" keeps >= 95 % of
    the true inliers (the ground-truth F itself keeps ~97.7 % under OpenCV's 1 px test, "opencv"
    ~87 %), rejects as many planted outliers as "opencv" (within 1 point), and its F is within
    0.12 px of the truth (median over the true correspondences), less than half "opencv"'s error.
    "opencv" (explicit) is the default call, and its masks are cv2's."""
    for rate in RATES:
        P1, P2, G1, G2, Fs, planted = _gt_scenes(8, rate, seed=40 + int(rate * 100))
        p1, p2 = torch.from_numpy(P1), torch.from_numpy(P2)
        cv = find_fundamental(p1, p2)
        assert torch.equal(find_fundamental(p1, p2, method="opencv").inliers, cv.inliers)
        lo = find_fundamental(p1, p2, method="lo")
        assert lo.ok.all() and (lo.method == ransac.METHOD_RANSAC).all() and not lo.overflow.any()
        assert (lo.num_iters <= cv.num_iters).all()  # the bound from the (higher) LO counts
        stats = {}
        for name, r in (("opencv", cv), ("lo", lo)):
            m, F = r.inliers.numpy(), r.F.numpy()
            err = np.concatenate([_f_error(F[b], G1[b][~planted[b]], G2[b][~planted[b]]) for b in range(len(F))])
            stats[name] = ((m & ~planted).sum() / (~planted).sum(),
                           (~m & planted).sum() / max(planted.sum(), 1), float(np.median(err)))
        print(rate, {k: tuple(round(float(x), 4) for x in v) for k, v in stats.items()})
        (rec, orec, err), (rec_cv, orec_cv, err_cv) = stats["lo"], stats["opencv"]
        assert rec >= 0.95 and rec >= rec_cv + 0.05, (rate, stats)
        assert orec >= orec_cv - 0.01 and (rate == 0 or orec >= 0.99), (rate, stats)
        assert err <= 0.12 and err <= 0.5 * err_cv, (rate, stats)
        for b in range(2):
            assert np.array_equal(cv.inliers[b].numpy(), _cv_mask(P1[b], P2[b])), (rate, b)


# ----------------------------------------------------------------------------------------------
# the capturable path, batches, the budgets
# ----------------------------------------------------------------------------------------------
def test_capturable_lo_equals_default(device, dtype):
    """A mixed batch (every point-count regime, NaN padding, a degenerate row), one seed for all
    and per-problem seeds: wherever ``overflow`` is False the capturable path gives the default
    path's masks, ``ok``, ``num_iters`` and ``method``; its F bit for bit on the RANSAC rows (CPU),
    to rounding on the LMedS rows (their 7-point models come from another solver)."""
    p1, p2, valid, _, _ = _mixed_batch(device)
    B = valid.shape[0]
    for states in ([OPENCV] * B, [OPENCV if s % 2 else samples._state_of(2) for s in range(B)]):
        ref, got = _both(p1.to(dtype), p2.to(dtype), valid, states)
        keep = ~got.overflow
        assert keep.sum() >= B - 2 and ref.overflow is None
        assert torch.equal(got.inliers[keep], ref.inliers[keep])
        assert torch.equal(got.ok, ref.ok) and torch.equal(got.method, ref.method)
        assert torch.equal(got.num_iters[keep], ref.num_iters[keep])
        assert got.ok.tolist() == [False] * 3 + [True] * 11 + [False]
        assert got.F.dtype == dtype and torch.isnan(got.F[~got.ok]).all() and torch.equal(got.inliers[~got.ok], valid[~got.ok])
        tol = 1e-9 if dtype == torch.float64 else 1e-6
        assert torch.allclose(got.F[keep], ref.F[keep], atol=tol, rtol=0, equal_nan=True)
        rows = keep & (got.method == ransac.METHOD_RANSAC)
        if device.type == "cpu":
            assert torch.equal(got.F[rows].nan_to_num(7.0), ref.F[rows].nan_to_num(7.0))


def test_overflow_flags():
    """The capturable path's budgets: a block too small for OpenCV's loop (all-outlier data needs
    all 1000 samples) and too few locally optimised models (``_LO_EVENTS = 0``: only the best
    hypothesis is optimised) set ``overflow``; everywhere else the result is the default path's,
    and even an overflowing problem ends with its best hypothesis optimised."""
    rng = np.random.default_rng(4)
    clean = _synthetic_scenes(k=1, n=100, noise=0.1, seed=6)[0]
    noise = (rng.uniform(0, 500, (100, 2)), rng.uniform(0, 500, (100, 2)))
    P1, P2, _, _, _, planted = _gt_scenes(6, 0.25, seed=11)
    sets = [clean, noise] + [(P1[b], P2[b]) for b in range(6)]
    p1, p2, valid, _ = _scatter(sets, 150, rng)
    ref, got = _both(p1, p2, valid, block=48)
    assert got.overflow[1] and int(ref.num_iters[1]) == 1000 and int(got.num_iters[1]) == 48
    keep = ~got.overflow
    assert keep[0] and torch.equal(got.inliers[keep], ref.inliers[keep])
    mp = torch.from_numpy(np.pad(planted, ((2, 0), (0, 0))))
    saved = ransac_lo._LO_EVENTS
    try:
        ransac_lo._LO_EVENTS = 0
        _, few = _both(p1, p2, valid)
    finally:
        ransac_lo._LO_EVENTS = saved
    assert few.overflow[2:].sum() >= 3  # 25 % outliers: OpenCV's loop accepts several models
    keep = ~few.overflow
    assert torch.equal(few.inliers[keep], ref.inliers[keep]) and torch.equal(few.num_iters[keep], ref.num_iters[keep])
    # the overflowing ones: still the planted outliers rejected, ~all true inliers kept
    lost = (~few.inliers[2:] & ~mp[2:]).sum() / (~mp[2:]).sum()
    assert not (few.inliers[2:] & mp[2:]).sum() > 2 and lost < 0.05


def test_batch_equals_single_calls():
    """Each problem of a mixed batch (per-problem seeds) equals its single call bit for bit, with
    the same slots, on both paths; and on its valid points alone (another N), masks, ``ok`` and
    ``num_iters`` are the same (F to rounding: another padding, other sums)."""
    p1, p2, valid, slots, sets = _mixed_batch()
    B = valid.shape[0]
    states = [samples._state_of(7919 * s - 5) for s in range(B)]
    for cap, blocks in ((False, (64, 256)), (True, (64, 64))):  # default path: any round size
        res = ransac._find_fundamental_impl(p1, p2, valid, 1.0, 0.99, 1000, states, blocks[0], capturable=cap,
                                            method="lo")
        assert not cap or res.overflow.any()  # (a 64-sample block: some overflow, flags compared too)
        for b in range(B):
            one = ransac._find_fundamental_impl(p1[b : b + 1], p2[b : b + 1], valid[b : b + 1], 1.0, 0.99, 1000,
                                                states[b : b + 1], blocks[1], capturable=cap, method="lo")
            assert torch.equal(one.F.nan_to_num(7.0)[0], res.F.nan_to_num(7.0)[b]), (cap, b)
            for f in ("inliers", "ok", "num_iters", "method") + (("overflow",) if cap else ()):
                assert torch.equal(getattr(one, f)[0], getattr(res, f)[b]), (cap, b, f)
            assert cap or (one.overflow is None and res.overflow is None)  # the default path is exact
            if not cap and len(sets[b][0]):
                a, c = sets[b]
                lone = find_fundamental(torch.tensor(a[None]), torch.tensor(c[None]), seed=7919 * b - 5, method="lo")
                assert torch.equal(lone.inliers[0], res.inliers[b, slots[b]]), b
                assert lone.ok[0] == res.ok[b] and lone.num_iters[0] == res.num_iters[b]
                assert torch.allclose(lone.F[0], res.F[b], atol=1e-9, equal_nan=True)


def test_capturable_lo_no_syncs_and_kernels_independent_of_batch_and_data():
    """After a warm-up call: 0 host syncs and uploads; the same kernel count for B = 1 and 16 and
    for clean and 40 %-outlier data (60 matches; the count is reported: each call's launch count
    on CUDA)."""
    P1, P2, _, _, _, _ = _gt_scenes(16, 0.4, seed=3, n=60)
    C1, C2, _, _, _, _ = _gt_scenes(1, 0.0, seed=4, n=60)
    cases = {"B1 clean": (C1, C2), "B1 hard": (P1[:1], P2[:1]), "B16": (P1, P2)}
    counts = {}
    for name, (a, c) in cases.items():
        p1, p2 = torch.from_numpy(a).float(), torch.from_numpy(c).float()
        valid = torch.ones(p1.shape[:2], dtype=torch.bool)
        valid[:, -3:] = False
        args = (p1, p2, valid, 1.0, 0.99, 1000, [OPENCV] * len(p1), None)
        ransac._find_fundamental_impl(*args, capturable=True, method="lo")  # warm-up: tables, constants
        with OpCounter() as cnt:
            res = ransac._find_fundamental_impl(*args, capturable=True, method="lo")
        assert cnt.syncs == 0 and cnt.uploads == 0, cnt.summary()
        assert res.ok.all()
        counts[name] = cnt.kernels
    print("capturable LO kernels per call", counts)
    assert len(set(counts.values())) == 1, counts
    assert counts["B16"] <= 1450, counts  # a budget (the OpenCV path: ~300)


# ----------------------------------------------------------------------------------------------
# the final refit and its solvers
# ----------------------------------------------------------------------------------------------
def _lo_state(p1, p2, valid):
    """The state ``_lo_final`` gets in a default-path call (captured), and the call's result."""
    seen = {}
    orig = ransac_lo._lo_final

    def spy(*args):
        seen["args"] = args
        return orig(*args)

    ransac_lo._lo_final = spy
    try:
        res = find_fundamental(p1, p2, valid, method="lo")
    finally:
        ransac_lo._lo_final = orig
    return seen["args"], res


def test_final_refit_gradcheck():
    """The final refit is differentiable w.r.t. the points (float64 gradcheck, the mask and the
    weights' model held fixed); through ``find_fundamental`` gradients reach the valid slots only
    and are finite (masked-out slots hold NaN)."""
    P1, P2, G1, G2, _, planted = _gt_scenes(1, 0.1, seed=12, n=24)
    p1, p2 = torch.from_numpy(P1), torch.from_numpy(P2)
    (_, _, eff, st, ctx), res = _lo_state(p1, p2, None)
    assert res.ok.all() and not (res.inliers & torch.from_numpy(planted)).any()
    # the points' OpenCV errors under the final model are far from the threshold (no flip under eps)
    d = np.maximum(*_line_dists(res.F[0].numpy(), P1[0], P2[0]))
    assert ((d < 0.9) | (d > 1.1)).all()

    def final_F(a, c):
        return ransac_lo._lo_final(a, c, eff, st, ctx)[0]

    a = p1.clone().requires_grad_(True)
    c = p2.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(final_F, (a, c), eps=1e-6, atol=1e-6, rtol=1e-4)
    x1 = torch.full((1, 30, 2), float("nan"), dtype=torch.float64)
    x2 = x1.clone()
    x1[0, :24], x2[0, :24] = p1[0], p2[0]
    x1.requires_grad_(True)
    F = find_fundamental(x1, x2, torch.arange(30)[None] < 24, method="lo").F
    assert torch.allclose(F.detach(), res.F, atol=1e-12)
    F.square().sum().backward()
    assert torch.isfinite(x1.grad).all() and (x1.grad[0, 24:] == 0).all() and x1.grad[0, :24].abs().sum() > 0


def test_sync_free_solvers_match_eigh():
    """The host-sync-free eigensolvers of the refit (inverse iteration, the adjugate's rank-2
    projection) give ``refit_fundamental``'s eigh-based F to 1e-9 on non-degenerate scenes, whatever
    the warm start's error; ``_rank2`` is the closest rank-2 matrix (SVD) and has rank 2."""
    P1, P2, _, _, _, _ = _gt_scenes(6, 0.0, seed=21, n=80)
    p1, p2 = torch.from_numpy(P1), torch.from_numpy(P2)
    w = torch.rand(6, 80, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) + 0.2
    k = _consts(torch.device("cpu"))
    ref = refit_fundamental(p1, p2, w)
    warm = ref + 0.05 * torch.randn(ref.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    got = refit._refit_impl(p1, p2, w, warm=warm, k=k)
    assert torch.allclose(got, ref, atol=1e-9, rtol=0)
    F = torch.randn(64, 3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    U, S, Vh = torch.linalg.svd(F)
    S[:, 2] *= 0.05  # near rank 2, as a refit before the projection
    F = U @ torch.diag_embed(S) @ Vh
    best = U @ torch.diag_embed(S * torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64)) @ Vh
    r2 = refit._rank2(F, k)
    assert torch.allclose(r2, best, atol=1e-12)
    assert (torch.linalg.svdvals(r2)[:, 2] < 1e-14).all()


def test_method_argument():
    z = torch.zeros(1, 20, 2)
    with pytest.raises(ValueError, match="method"):
        find_fundamental(z, z, method="magsac")
    with pytest.raises(ValueError, match="method"):
        ransac._find_fundamental_impl(z, z, torch.ones(1, 20, dtype=torch.bool), 1.0, 0.99, 1000, [OPENCV], None,
                                      method="LO")
    for cap in (False, True):  # empty inputs: no problem to solve
        for B, N in ((0, 20), (2, 0), (2, 5)):
            q = torch.zeros(B, N, 2)
            r = find_fundamental(q, q, capturable=cap, method="lo")
            assert r.F.shape == (B, 3, 3) and r.inliers.shape == (B, N) and not r.ok.any()


# ----------------------------------------------------------------------------------------------
# the config key
# ----------------------------------------------------------------------------------------------
def test_config_F_method(tmp_path):
    """``F_method`` in a VINS config: absent -> "opencv", "lo" or lo (plain or quoted) -> "lo"; any
    other value is a ``ConfigError`` naming the file and the key; a ``TrackerConfig`` built or
    replaced by hand is checked too."""
    src = (REPO / "configs" / "euroc.yaml").read_text()
    assert tf.load_config(REPO / "configs" / "euroc.yaml").F_method == "opencv"
    for text, want in (("lo", "lo"), ('"lo"', "lo"), ('"opencv"', "opencv")):
        p = tmp_path / f"cfg_{len(text)}_{want}.yaml"
        p.write_text(src + f"\nF_method: {text}\n")
        cfg = tf.load_config(p)
        assert cfg.F_method == want and cfg.camera is not None
    for text, why in (('"magsac"', "expected one of 'opencv', 'lo'"), ("3", "expected a string")):
        p = tmp_path / "bad.yaml"
        p.write_text(src + f"\nF_method: {text}\n")
        with pytest.raises(ConfigError, match="F_method") as exc:
            tf.load_config(p)
        assert str(p) in str(exc.value) and why in str(exc.value)
    cfg = tf.load_config(REPO / "configs" / "euroc.yaml")
    assert dataclasses.replace(cfg, F_method="lo").F_method == "lo"
    with pytest.raises(ConfigError, match="F_method"):
        dataclasses.replace(cfg, F_method="ransac")
    assert "F_method lo" in dataclasses.replace(cfg, F_method="lo").summary()
    assert "F_method" not in cfg.summary()
    assert Path(tf.config.__file__).name == "config.py"
