"""The fused F-RANSAC scoring op (``torch_frontend::ransac_score``, ``fused/ransac_op.py``): its CPU kernel
against an independent numpy statement of OpenCV's ``computeError`` / ``findInliers`` and RANSAC loop,
``find_fundamental``'s fused backend against the tensor backend and cv2 (masks, ``ok``, iterations, F
to the bit) on the RANSAC cases and on real tracked frames, batch independence, and the op counts of
the capturable path (one op, no sync, independent of B and the data). The Triton kernel is checked
in ``tests/test_fused_triton.py`` (interpreter, PTX).

Convention: ``_cases`` problems are ``(B, N, 2)`` float32 virtual-pinhole pixels as the tracker's.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torch_frontend import ransac
from torch_frontend.errors import ConfigError
from torch_frontend.fused import resolve_ransac_backend
from torch_frontend.fused.ransac_op import cuda_selfcheck, ransac_score_op, selfcheck_case
from torch_frontend.ransac import find_fundamental
from torch_frontend.ransac.bounds import _niters_table
from torch_frontend.ransac.samples import OPENCV_SEED, _state_of
from torch_frontend.testing.dispatch_count import OpCounter

from ._ransac_cases import _cv_mask, _plant, _scatter, _synthetic_scenes
from .conftest import load_gray, sample_frames

pytestmark = pytest.mark.usefixtures("single_thread")

OPENCV = _state_of(OPENCV_SEED)


# ------------------------------------------------------------------------------- the op's contract
def _np_errors(F: np.ndarray, x12: np.ndarray) -> np.ndarray:
    """OpenCV's ``computeError`` for one model ``F (9,)`` on ``x12 (N, 4)``: float32 ``(N,)``, numpy
    ufuncs one operation at a time (no contraction), in OpenCV's order."""
    x1, y1, x2, y2 = x12.T
    with np.errstate(all="ignore"):
        a = F[0] * x1 + F[1] * y1 + F[2]
        b = F[3] * x1 + F[4] * y1 + F[5]
        c = F[6] * x1 + F[7] * y1 + F[8]
        s2 = 1.0 / (a * a + b * b)
        d2 = x2 * a + y2 * b + c
        a = F[0] * x2 + F[3] * y2 + F[6]
        b = F[1] * x2 + F[4] * y2 + F[7]
        c = F[2] * x2 + F[5] * y2 + F[8]
        s1 = 1.0 / (a * a + b * b)
        d1 = x1 * a + y1 * b + c
        e1, e2 = d1 * d1 * s1, d2 * d2 * s2
        return np.where(e1 < e2, e2, e1).astype(np.float32)


def _np_op(F, fok, x12, eff, n, table, state, thr2):
    """The op's contract in plain Python (``fused/_numba_ransac.py``'s docstring)."""
    B, M = fok.shape
    N = x12.shape[1]
    t = np.float32(thr2)
    out = []
    for b in range(B):
        live, best, nit, done = (int(s[b]) for s in state) if state is not None else (M // 3, -1, int(table[n[b], 0]), 0)
        kb, mask = -1, np.zeros(N, bool)
        if n[b] >= 15:
            for i in range(live):
                for m in range(3 * i, 3 * i + 3):
                    if fok[b, m]:
                        inl = eff[b] & (_np_errors(F[b, m], x12[b]) <= t)
                        if int(inl.sum()) > max(best, 6):
                            best, kb, mask, nit = int(inl.sum()), m, inl, int(table[n[b], int(inl.sum()) + 1])
                done += 1
                if done >= nit:
                    break
        out.append((best, nit, done, kb, mask))
    return [np.array(v) for v in zip(*out)]


def _solved_block(sets, N, S, seed=0):
    """Real 7-point models: the first ``S`` OpenCV samples of each problem solved by the tensor
    solver, as the capturable path's front builds them (``F (B, 3S, 9)``, ``fok``, ``x12``, ``eff``, ``n``)."""
    from torch_frontend.ransac.capturable import _front_capturable

    p1, p2, valid, _ = _scatter(sets, N, np.random.default_rng(seed))
    sp = _front_capturable(p1.float(), p2.float(), valid, 0.99, S, [OPENCV] * len(sets), None)
    return sp.Fm, sp.fok, sp.x12, sp.eff, sp.n, p1, p2, valid


def _planted_sets(k=4, n=150, rate=0.3, seed=5):
    rng = np.random.default_rng(seed)
    return [(a, _plant(a, c, rate, rng)[0]) for a, c in _synthetic_scenes(k=k, n=n, noise=0.3, seed=seed)]


@pytest.mark.parametrize("thr", [1.0, 0.5, 3.0])
def test_op_is_the_contract(thr):
    """Every output of the CPU kernel equals the numpy statement of the contract: fresh blocks of
    real 7-point models (problems of 150, 60 and 12 points: the last is LMedS, passed through) and
    a running state (part of a block, a bound already lowered), and the built-in self-check case."""
    sets = _planted_sets(k=2) + [(a[:60], c[:60]) for a, c in _planted_sets(k=1, seed=8)] + \
        [(a[:12], c[:12]) for a, c in _planted_sets(k=1, seed=9)]
    F, fok, x12, eff, n, *_ = _solved_block(sets, 150, 40)
    table = _niters_table(150, 1000, 0.99)
    B = F.shape[0]
    state = (torch.tensor([40, 7, 3, 40]), torch.tensor([-1, 60, 6, -1]), torch.tensor([1000, 30, 1000, 1000]),
             torch.tensor([0, 5, 996, 0]))
    for st in (None, state):
        got = ransac_score_op(F, fok, x12, eff, n, table, *(st or (None,) * 4), thr * thr)
        want = _np_op(F.numpy(), fok.numpy(), x12.numpy(), eff.numpy(), n.numpy(), table.numpy(),
                      None if st is None else [s.numpy() for s in st], thr * thr)
        for g, w in zip(got, want):
            assert np.array_equal(g.numpy(), w), (st is None, g, w)
        assert got[3][B - 1] == -1 and not got[4][B - 1].any()  # LMedS problem: passed through
    if thr == 1.0:
        args = selfcheck_case()
        got = ransac_score_op(*args, None, None, None, None, 1.0)
        want = _np_op(*(a.numpy() for a in args), None, 1.0)
        assert all(np.array_equal(g.numpy(), w) for g, w in zip(got, want))
        assert got[3].tolist()[:2] != [-1, -1]


def test_op_fake_and_errors():
    """The fake gives the outputs' shapes (meta tensors); bad shapes and a partial state are errors."""
    F, fok, x12, eff, n, table = selfcheck_case()
    out = ransac_score_op(*(t.to("meta") for t in (F, fok, x12, eff, n, table)), None, None, None, None, 1.0)
    assert [tuple(o.shape) for o in out] == [(3,), (3,), (3,), (3,), (3, 40)]
    assert out[4].dtype == torch.bool and out[0].dtype == torch.int64
    with pytest.raises(ValueError, match="shapes"):
        ransac_score_op(F, fok[:, :-1], x12, eff, n, table, None, None, None, None, 1.0)
    with pytest.raises(ValueError, match="all of live"):
        ransac_score_op(F, fok, x12, eff, n, table, n, None, None, None, 1.0)
    assert cuda_selfcheck("cpu") is None  # the self-check's own comparison (CPU against CPU here)


def test_backend_resolution():
    assert resolve_ransac_backend(None, "cpu") == "fused"
    assert resolve_ransac_backend("tensor", "cpu") == "tensor"
    with pytest.raises(ConfigError, match="ransac_backend"):
        resolve_ransac_backend("numba", "cpu")


# ---------------------------------------------------------------- find_fundamental: fused == tensor
def _same(a, b):
    """Two FundamentalFits/Results equal: masks, ok, iterations, method and F to the bit."""
    assert torch.equal(a.inliers, b.inliers)
    assert torch.equal(a.ok, b.ok) and torch.equal(a.num_iters, b.num_iters) and torch.equal(a.method, b.method)
    assert torch.equal(a.F.isnan(), b.F.isnan()) and torch.equal(a.F.nan_to_num(), b.F.nan_to_num())


@pytest.mark.parametrize("capturable", [False, True])
def test_fused_equals_tensor_equals_cv2_on_ransac_cases(capturable):
    """Planted outliers at 0-40 % (plus a 14-point LMedS problem and one below 8 points) scattered over
    padded slots, B = 6: the fused and tensor backends give the same F (bits), masks, ok and
    iterations, and every mask is cv2's."""
    rng = np.random.default_rng(3)
    sets = []
    for rate, (a, c) in zip([0.0, 0.1, 0.25, 0.4], _synthetic_scenes(k=4, n=120, noise=0.3, seed=21)):
        sets.append((a, _plant(a, c, rate, rng)[0]))
    sets += [(sets[0][0][:14], sets[0][1][:14]), (sets[1][0][:5], sets[1][1][:5])]
    p1, p2, valid, slots = _scatter(sets, 140, rng)
    p1, p2 = p1.float(), p2.float()
    kw = dict(capturable=capturable)
    fused = find_fundamental(p1, p2, valid, backend="fused", **kw)
    tensor = find_fundamental(p1, p2, valid, backend="tensor", **kw)
    _same(fused, tensor)
    for b, (a, c) in enumerate(sets[:5]):
        assert np.array_equal(fused.inliers[b, slots[b]].numpy(), _cv_mask(a, c)), b
    assert not capturable or not fused.overflow.any()


def test_batch_independent():
    """A problem's fused result is its single call's, whatever the batch (B = 5 against B = 1)."""
    sets = _planted_sets(k=5, n=100, rate=0.25, seed=4)
    p1, p2, valid, slots = _scatter(sets, 110, np.random.default_rng(1))
    p1, p2 = p1.float(), p2.float()
    for cap in (False, True):
        batch = find_fundamental(p1, p2, valid, capturable=cap, backend="fused")
        for b in range(len(sets)):
            one = find_fundamental(p1[b:b + 1], p2[b:b + 1], valid[b:b + 1], capturable=cap, backend="fused")
            assert torch.equal(batch.inliers[b], one.inliers[0]) and torch.equal(batch.num_iters[b], one.num_iters[0])
            assert torch.equal(batch.F[b], one.F[0])


def test_real_tracked_frames():
    """Sample EuRoC frames, VINS's corners tracked by cv2's LK (gaps of 1 and 3 frames), lifted into
    the 460-px virtual pinhole: for the first n tracks, n = 15, 20, ..., all (both RANSAC paths), the
    fused backend equals the tensor one and cv2's mask."""
    import cv2

    from .test_ransac import D0, K0, _virtual

    frames = sample_frames("cam0")
    checked = 0
    for i, gap in ((0, 1), (6, 3)):
        a, b = load_gray(frames[i]), load_gray(frames[i + gap])
        pts = cv2.goodFeaturesToTrack(a, 150, 0.01, 30)
        nxt, st, _ = cv2.calcOpticalFlowPyrLK(a, b, pts, None, winSize=(21, 21), maxLevel=3)
        ok = st.ravel() == 1
        h, w = a.shape
        u0 = _virtual(cv2.undistortPoints(pts[ok].astype(np.float64), K0, D0).reshape(-1, 2), w, h).astype(np.float32)
        u1 = _virtual(cv2.undistortPoints(nxt[ok].astype(np.float64), K0, D0).reshape(-1, 2), w, h).astype(np.float32)
        ns = list(range(15, len(u0), 5)) + [len(u0)]
        N = len(u0)
        p1 = torch.zeros(len(ns), N, 2)
        p2 = torch.zeros(len(ns), N, 2)
        valid = torch.zeros(len(ns), N, dtype=torch.bool)
        for r, k in enumerate(ns):
            p1[r, :k], p2[r, :k], valid[r, :k] = torch.from_numpy(u0[:k]), torch.from_numpy(u1[:k]), True
        for cap in (False, True):
            fused = find_fundamental(p1, p2, valid, capturable=cap, backend="fused")
            _same(fused, find_fundamental(p1, p2, valid, capturable=cap, backend="tensor"))
            for r, k in enumerate(ns):
                assert np.array_equal(fused.inliers[r, :k].numpy(), _cv_mask(u0[:k], u1[:k])), (i, k)
                checked += 1
    assert checked >= 40


# ----------------------------------------------------------------------------------------- counts
def test_capturable_counts():
    """Capturable path: 0 syncs; the same kernels at B = 1 and 16 and for other data; the scoring is
    one op (the fused path has fewer kernels than the tensor one, which has ~8 for scoring + ~12
    for the replay)."""
    sets = _planted_sets(k=4, n=150, rate=0.3)
    p1, p2, valid, _ = _scatter(sets * 4, 150, np.random.default_rng(2))
    p1, p2 = p1.float(), p2.float()
    counts = {}
    for name, rows, backend in (("B1", slice(0, 1), "fused"), ("B16", slice(0, 16), "fused"),
                                ("B1b", slice(3, 4), "fused"), ("tensor", slice(0, 1), "tensor")):
        args = (p1[rows], p2[rows], valid[rows], 1.0, 0.99, 1000, [OPENCV] * p1[rows].shape[0], None)
        ransac._find_fundamental_impl(*args, capturable=True, backend=backend)  # warm-up (tables)
        with OpCounter() as c:
            ransac._find_fundamental_impl(*args, capturable=True, backend=backend)
        assert c.syncs == 0 and c.uploads == 0, c.summary()
        counts[name] = c.kernels
    assert counts["B1"] == counts["B16"] == counts["B1b"], counts
    assert counts["B1"] <= counts["tensor"] - 15, counts
    F, fok, x12, eff, n, table = selfcheck_case()
    with OpCounter() as c:
        ransac_score_op(F, fok, x12, eff, n, table, None, None, None, None, 1.0)
    assert c.kernels == 1 and c.syncs == 0, c.summary()
