"""The fused kernels (``torch_frontend/fused``): the CPU kernels against OpenCV bit for bit, the ops'
registration and tools, the backend choice and its fallbacks, threads, the implicit gradient from the
fused forward, and where the tensor LK differs.

Bars (issue 40): the fused LK equals ``cv2.calcOpticalFlowPyrLK`` (OpenCV 4.x x86 wheels: status,
and float32 positions where status is 1) on every point of the repo's real pairs (>= 50,000 points:
150 Shi-Tomasi corners, 1,000 weak corners and 300 random points per pair, some outside the image)
and of ``../shared``'s; the fused pyramid equals ``cv2.pyrDown`` + ``cv2.copyMakeBorder`` on every
level and border; the tensor LK differs from the fused one only where it differs from cv2.
(The CUDA kernels against the CPU ones: ``tests/test_fused_triton.py``.)
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import warnings

import cv2
import numpy as np
import pytest
import torch

import torch_frontend as tf
from torch_frontend import fused
from torch_frontend.errors import ConfigError
from torch_frontend.fused import ops, selfcheck
from torch_frontend.fused.layout import PyramidLayout
from torch_frontend.lk import track_lk
from torch_frontend.pyramid import build_pyramid
from torch_frontend.testing.dispatch_count import OpCounter

from .conftest import REPO, TEST_DATA, load_gray, sample_frames, shared_data_or_skip

pytestmark = pytest.mark.usefixtures("single_thread")

CRIT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
#: points per pair: VINS's corners, weak corners, random points (some outside the image)
N_CORNERS, N_WEAK, N_RANDOM = 150, 1000, 300


# ----------------------------------------------------------------------------------------- helpers
def _points(img: np.ndarray, rng) -> np.ndarray:
    h, w = img.shape
    c = cv2.goodFeaturesToTrack(img, N_CORNERS, 0.01, 30).reshape(-1, 2)
    weak = cv2.goodFeaturesToTrack(img, N_WEAK, 1e-4, 3).reshape(-1, 2)
    rnd = rng.uniform([-40, -40], [w + 40, h + 40], (N_RANDOM, 2))
    return np.concatenate([c, weak, rnd]).astype(np.float32)


def _cv(a, b, pts, max_level=3, win=(21, 21), init=None):
    flags, guess = 0, None
    if init is not None:
        flags, guess = cv2.OPTFLOW_USE_INITIAL_FLOW, init.reshape(-1, 1, 2).astype(np.float32).copy()
    out, st, _ = cv2.calcOpticalFlowPyrLK(a, b, np.ascontiguousarray(pts).reshape(-1, 1, 2), guess, winSize=win,
                                          maxLevel=max_level, criteria=CRIT, flags=flags)
    return out.reshape(-1, 2), st.ravel().astype(bool)


def _mismatches(out, st, ref, st_ref) -> np.ndarray:
    """Lanes whose status differs, or whose float32 position differs where both track."""
    return (st != st_ref) | (st & st_ref & np.any(out != ref, axis=1))


def _fused_lk(a, b, pts, **kw):
    out, st = track_lk(torch.from_numpy(a)[None, None], torch.from_numpy(b)[None, None], torch.from_numpy(pts)[None],
                       lk_backend="fused", **kw)
    return out[0].numpy(), st[0].numpy()


def _check_pairs(pairs, rng, min_points=0):
    """Every point of every pair: the fused LK == cv2 (plain call). Returns the number of points."""
    n = 0
    for name, a, b in pairs:
        pts = _points(a, rng)
        ref, st_ref = _cv(a, b, pts)
        out, st = _fused_lk(a, b, pts)
        bad = np.nonzero(_mismatches(out, st, ref, st_ref))[0]
        assert bad.size == 0, (f"{name}: {bad.size} of {len(pts)} points differ from cv2, e.g. lane {bad[0]}: "
                               f"{pts[bad[0]]} -> {out[bad[0]]} st {st[bad[0]]}, cv2 {ref[bad[0]]} st {st_ref[bad[0]]}")
        n += len(pts)
    assert n >= min_points, n
    return n


def _sequence_pairs(files, label, stride=1):
    imgs = [load_gray(f) for f in files]
    return [(f"{label} {k}", imgs[k], imgs[k + stride]) for k in range(len(imgs) - stride)]


# ----------------------------------------------------------------------------------------- vs OpenCV
def test_fused_lk_equals_cv2_on_every_point_of_the_repos_real_pairs():
    """>= 50,000 points: the EuRoC sample's temporal pairs (cam0, cam1), its stereo pairs, the Middlebury
    Motorcycle stereo pair both ways."""
    rng = np.random.default_rng(0)
    cam0, cam1 = sample_frames("cam0"), sample_frames("cam1")
    pairs = _sequence_pairs(cam0, "cam0") + _sequence_pairs(cam1, "cam1") + _sequence_pairs(cam0, "cam0 +2", 2)
    pairs += [(f"stereo {k}", load_gray(l), load_gray(r)) for k, (l, r) in enumerate(zip(cam0[::6], cam1[::6]))]
    moto = [load_gray(TEST_DATA / "motorcycle" / f"motorcycle_{side}.png") for side in ("left", "right")]
    pairs += [("motorcycle l->r", moto[0], moto[1]), ("motorcycle r->l", moto[1], moto[0])]
    n = _check_pairs(pairs, rng, min_points=50_000)
    print(f"fused LK == cv2 on {n} points of {len(pairs)} real pairs")


@pytest.mark.slow  # 243,102 more points (10 s): the repo's pairs above run in the default suite
def test_fused_lk_equals_cv2_on_shared_sequences():
    root = shared_data_or_skip("sequences", "euroc_v1_01_easy_micro", "mav0")
    rng = np.random.default_rng(1)
    cam0, cam1 = sorted((root / "cam0" / "data").glob("*.png")), sorted((root / "cam1" / "data").glob("*.png"))
    pairs = _sequence_pairs(cam0, "V1_01 cam0") + _sequence_pairs(cam1, "V1_01 cam1")
    pairs += _sequence_pairs(cam0[::4], "V1_01 cam0 every 4th")  # larger motions: more iterations
    by_name = {f.name: f for f in cam1}
    pairs += [(f"V1_01 stereo {f.name}", load_gray(f), load_gray(by_name[f.name])) for f in cam0 if f.name in by_name]
    n = _check_pairs(pairs, rng)
    print(f"fused LK == cv2 on {n} points of {len(pairs)} pairs of ../shared")


def _warp(img, H):
    h, w = img.shape
    return cv2.warpPerspective(img, H, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)


@pytest.mark.parametrize("win, max_level", [((21, 21), 3), ((15, 9), 2), ((31, 31), 4), ((8, 21), 1), ((21, 21), 0)])
def test_fused_lk_equals_cv2_on_other_windows_guesses_and_warps(win, max_level):
    """Other window sizes and level counts (the lane rule of 8-pixel blocks + a scalar tail), an initial
    guess (OPTFLOW_USE_INITIAL_FLOW), a rotation + zoom warp (many iterations, oscillations)."""
    rng = np.random.default_rng(2)
    frames = [load_gray(f) for f in sample_frames("cam0")[:8]]
    a = frames[3]
    c = np.array([[376.0, 240.0]])
    R = cv2.getRotationMatrix2D((376.0, 240.0), 4.0, 1.03)
    warped = _warp(a, np.vstack([R, [0, 0, 1]]))
    for name, b in (("temporal", frames[5]), ("warp", warped)):
        pts = np.ascontiguousarray(_points(a, rng)[::3])
        for guess in (None, pts + np.array([1.5, -2.25], dtype=np.float32)):
            ref, st_ref = _cv(a, b, pts, max_level, win, guess)
            out, st = _fused_lk(a, b, pts, win_size=win, max_level=max_level,
                                init_pts=None if guess is None else torch.from_numpy(guess)[None])
            bad = np.nonzero(_mismatches(out, st, ref, st_ref))[0]
            assert bad.size == 0, (name, win, max_level, guess is not None, bad.size, bad[:5])
    del c


def test_fused_forward_backward_equals_two_cv2_calls():
    """VINS-Fusion's FLOW_BACK in one op == cv2 forward, cv2 backward (from pts, one level / from the
    result, three levels), ``status & back & |back - pts| <= 0.5`` in double."""
    rng = np.random.default_rng(3)
    cam0, cam1 = sample_frames("cam0"), sample_frames("cam1")
    for a, b, fb_level, from_pts in ((load_gray(cam0[4]), load_gray(cam0[5]), 1, True),
                                     (load_gray(cam0[3]), load_gray(cam1[3]), 3, False)):
        pts = _points(a, rng)
        ref, st_ref = _cv(a, b, pts)
        back, st_b = _cv(b, a, ref, fb_level, init=pts if from_pts else None)
        d = np.linalg.norm((back - pts).astype(np.float32).astype(np.float64), axis=1)
        want = st_ref & st_b & (d <= 0.5)
        out, st = _fused_lk(a, b, pts, forward_backward=True, fb_max_level=fb_level, fb_use_initial_flow=from_pts)
        assert np.array_equal(st, want), (fb_level, int((st != want).sum()))
        assert np.array_equal(out[st_ref], ref[st_ref])


@pytest.mark.parametrize("hw", [(480, 752), (479, 751), (37, 41), (6, 3), (2, 1), (1, 1)])
@pytest.mark.parametrize("pad", [3, 22, 40])
def test_fused_pyramid_equals_cv2(hw, pad):
    """Every level (``cv2.pyrDown`` chain) and its border (``BORDER_REFLECT_101``, repeated reflection
    where the pad exceeds the level), odd sizes, levels of one pixel."""
    h, w = hw
    frame = load_gray(sample_frames("cam0")[0])
    imgs = np.stack([frame[:h, :w], frame[-h:, -w:]])
    packed = ops.pyramid_op(torch.from_numpy(imgs), 3, pad).numpy()
    lay = PyramidLayout(h, w, 3, pad)
    assert packed.shape == (2, lay.total)
    for b in range(2):
        lv = imgs[b]
        for l, ((lh, lw), o) in enumerate(zip(lay.sizes, lay.offsets)):
            if l:
                lv = cv2.pyrDown(lv)
            assert lv.shape == (lh, lw)
            hp, wp = lay.padded_shape(l)
            iy = [fused.layout.reflect101(y, lh) for y in range(-pad, lh + pad)]
            ix = [fused.layout.reflect101(x, lw) for x in range(-pad, lw + pad)]
            want = lv[np.ix_(iy, ix)]
            assert np.array_equal(packed[b, o:o + hp * wp].reshape(hp, wp), want), (hw, pad, b, l)
    if min(h, w) > pad:  # OpenCV's own border where it takes it
        assert np.array_equal(packed[0, :(h + 2 * pad) * (w + 2 * pad)].reshape(h + 2 * pad, w + 2 * pad),
                              cv2.copyMakeBorder(imgs[0], pad, pad, pad, pad, cv2.BORDER_REFLECT_101))


# ----------------------------------------------------------------------------------------- the ops
def _case_args():
    c = selfcheck.case()
    P, Q = ops.pyramid_op(c["prev"], 2, 22), ops.pyramid_op(c["next"], 2, 22)
    return c, P, Q, (P, Q, c["pts"], c["valid"], c["init"], 72, 104, 22, 22, 2, 21, 21, 30, 0.01, 1e-4, 1, 0.5, True)


def test_ops_pass_opcheck_and_compile_as_one_node():
    """``torch.library.opcheck`` (schema, fake tensors, autograd registration, AOT dispatch) on both ops,
    and ``torch.compile(fullgraph=True)`` of a pyramid + LK call on the CPU (no graph break)."""
    c, P, Q, args = _case_args()
    for op, a in ((ops.pyramid_op, (c["prev"], 2, 22)), (ops.lk_op, args)):
        res = torch.library.opcheck(op, a)
        assert all(v == "SUCCESS" for v in res.values()), res

    def fn(a, b, p, v):
        return ops.lk_op(ops.pyramid_op(a, 2, 22), ops.pyramid_op(b, 2, 22), p, v, None, 72, 104, 22, 22, 2, 21, 21, 30,
                         0.01, 1e-4, -1, 0.5, True)

    got = torch.compile(fn, backend="eager", fullgraph=True)(c["prev"], c["next"], c["pts"], c["valid"])
    want = fn(c["prev"], c["next"], c["pts"], c["valid"])
    assert all(torch.equal(x, y) for x, y in zip(got, want))


def test_one_op_per_call_and_no_sync():
    """The pyramid is one op; ``track_lk`` on two fused pyramids is one op (both passes of the
    forward-backward variant too); no host sync."""
    frames = [load_gray(f) for f in sample_frames("cam0")[:2]]
    imgs = [torch.from_numpy(f)[None, None] for f in frames]
    pts = torch.from_numpy(_points(frames[0], np.random.default_rng(4)))[None]
    build_pyramid(imgs[0], 3, with_gradients=False)  # warm-up (the kernels' first load)
    with OpCounter() as c:
        P = build_pyramid(imgs[0], 3, with_gradients=False)
    assert c.kernels == 1 and c.syncs == 0, c.summary()
    Q = build_pyramid(imgs[1], 3, with_gradients=False)
    valid = torch.ones(pts.shape[:2], dtype=torch.bool)
    for kw in (dict(), dict(forward_backward=True, fb_max_level=1)):
        track_lk(P, Q, pts, valid, **kw)
        with OpCounter() as c:
            track_lk(P, Q, pts, valid, **kw)
        assert c.kernels == 1 and c.syncs == 0, (kw, c.summary())


def test_selfcheck_bits_are_the_cpu_kernels():
    """The CUDA self-check's stored bits are what the CPU kernels give (regenerate EXPECTED with
    ``python -m torch_frontend.fused.selfcheck`` when the kernels are meant to move bits)."""
    assert selfcheck.run_case("cpu") == selfcheck.EXPECTED


def test_selfcheck_reports_a_difference(monkeypatch):
    monkeypatch.setattr(selfcheck, "run_case", lambda device: "0" * 64)
    assert "other bits" in selfcheck.cuda_selfcheck("cpu")

    def boom(device):
        raise RuntimeError("no kernel image is available")

    monkeypatch.setattr(selfcheck, "run_case", boom)
    assert "failed their self-check (RuntimeError: no kernel image" in selfcheck.cuda_selfcheck("cpu")


@pytest.mark.slow  # a cold numba compile in a child (~12 s)
def test_numba_kernels_have_no_fma(tmp_path):
    """No fused multiply-add anywhere in the numba kernels' machine code (a contraction rounds once
    where OpenCV rounds twice): compiled afresh in a child (a cache hit cannot be inspected)."""
    import subprocess
    import sys

    code = ("import torch_frontend.fused.selfcheck as s, torch_frontend.fused._numba_lk as a, "
            "torch_frontend.fused._numba_pyramid as b; s.run_case('cpu'); "
            "asm = ''.join(a.lk_streams.inspect_asm().values()) + ''.join(b.pyramid_streams.inspect_asm().values()); "
            "print(len(asm), 'vfmadd' in asm or 'vfmsub' in asm or 'vfnmadd' in asm)")
    env = {**__import__("os").environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=REPO, timeout=600)
    assert res.returncode == 0, res.stderr
    size, has_fma = res.stdout.split()
    assert int(size) > 10_000 and has_fma == "False", res.stdout


# ----------------------------------------------------------------------------------------- backend
def test_backend_resolution_and_the_numba_fallback(monkeypatch):
    assert fused.resolve_backend(None, "cpu") == "fused" and fused.resolve_backend("auto", "cpu") == "fused"
    assert fused.resolve_backend("tensor", "cpu") == "tensor"
    assert fused.resolve_backend(None, "meta") == "tensor"  # no fused kernel there
    with pytest.raises(ConfigError, match="lk_backend"):
        fused.resolve_backend("numba", "cpu")
    # a machine where numba cannot load: the tensor LK, said once; asking for "fused" is an error naming why
    monkeypatch.setitem(fused._STATUS, "cpu", "numba cannot be loaded (ImportError: no module named numba)")
    monkeypatch.setattr(fused, "_WARNED", set())
    with pytest.warns(RuntimeWarning, match="numba cannot be loaded"):
        assert fused.resolve_backend(None, "cpu") == "tensor"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert fused.resolve_backend(None, "cpu") == "tensor"  # once
    with pytest.raises(ConfigError, match="numba cannot be loaded"):
        fused.resolve_backend("fused", "cpu")
    tr = tf.FeatureTracker(tf.load_config(REPO / "configs" / "euroc.yaml"))
    assert tr.lk_backend == "tensor" and tr.params.lk_options.backend == "tensor"


def test_cuda_labelled_tensors_without_a_runtime_run_the_cpu_kernels():
    """No CUDA runtime (the simulated device of count_step.py, fake tensors): the fused backend is
    chosen for "cuda" and the ops run their CPU kernels (the dispatch of such a device does)."""
    if torch.cuda.is_available():
        pytest.skip("a CUDA runtime is present: the self-check decides (tests/test_fused_triton.py)")
    assert fused.unavailable_reason("cuda") is None and fused.resolve_backend(None, "cuda") == "fused"


def test_checkpoints_record_the_backend():
    cfg = tf.load_config(REPO / "configs" / "euroc.yaml")
    a, b = tf.FeatureTracker(cfg), tf.FeatureTracker(cfg, lk_backend="tensor")
    img = torch.from_numpy(load_gray(sample_frames("cam0")[0]))[None, None]
    a.track(img, [0.0])
    d = a.state_dict()
    assert d["lk_backend"] == "fused"
    with pytest.raises(ValueError, match="lk_backend 'fused', this one has 'tensor'"):
        b.load_state_dict(d)
    old = {k: v for k, v in b.state_dict().items() if k != "lk_backend"}  # a dict from before the fused kernels
    with pytest.raises(ValueError, match="lk_backend 'tensor', this one has 'fused'"):
        a.load_state_dict(old)
    b.load_state_dict(old)


# ----------------------------------------------------------------------------------------- threads
def _batch(B=5, n=300):
    frames = [load_gray(f) for f in sample_frames("cam0")]
    rng = np.random.default_rng(5)
    prev = torch.from_numpy(np.stack([frames[2 * b] for b in range(B)]))[:, None]
    nxt = torch.from_numpy(np.stack([frames[2 * b + 1] for b in range(B)]))[:, None]
    pts = torch.from_numpy(np.stack([_points(frames[2 * b], rng)[:n] for b in range(B)]))
    return prev, nxt, pts


def test_threads_split_streams_without_changing_a_bit():
    """With 2 torch threads the kernels run over stream groups in a pool (nogil): the same bits as one
    thread, and each stream's as its own call."""
    prev, nxt, pts = _batch()
    one = track_lk(prev, nxt, pts, forward_backward=True)
    alone = [track_lk(prev[b:b + 1], nxt[b:b + 1], pts[b:b + 1], forward_backward=True) for b in range(5)]
    n = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        two = track_lk(prev, nxt, pts, forward_backward=True)
        pyr = build_pyramid(prev, 3, with_gradients=False)
        assert ops._POOL[1] == 2  # the pool ran them
    finally:
        torch.set_num_threads(n)
    assert all(torch.equal(x, y) for x, y in zip(one, two))
    assert torch.equal(pyr.packed, build_pyramid(prev, 3, with_gradients=False).packed)
    for b in range(5):
        assert torch.equal(alone[b][0][0], one[0][b]) and torch.equal(alone[b][1][0], one[1][b])


def _child_after_fork(q):
    prev, nxt, pts = _batch(3, 50)
    torch.set_num_threads(2)
    q.put(track_lk(prev, nxt, pts)[1].sum().item())


def test_a_child_forked_after_a_threaded_call_works():
    """The pool's threads do not exist in a forked child: it makes its own (no hang, no abort; numba's
    parallel layer, which aborts there, is not used)."""
    prev, nxt, pts = _batch(3, 50)
    n = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        want = track_lk(prev, nxt, pts)[1].sum().item()
    finally:
        torch.set_num_threads(n)
    ctx = multiprocessing.get_context("fork")
    q = ctx.Queue()
    p = ctx.Process(target=_child_after_fork, args=(q,))
    p.start()
    got = q.get(timeout=120)
    p.join(60)
    assert p.exitcode == 0 and got == want


# ----------------------------------------------------------------------------------------- vs the tensor LK
def test_the_tensor_lk_differs_only_where_it_differs_from_cv2():
    """On real pairs, every lane where the tensor LK and the fused LK disagree is one where the tensor
    LK disagrees with cv2 (the fused LK equals cv2 everywhere): the float sums' order."""
    rng = np.random.default_rng(6)
    frames = [load_gray(f) for f in sample_frames("cam0")]
    total = differ = 0
    for k in range(0, 20, 4):
        a, b = frames[k], frames[k + 2]
        pts = _points(a, rng)
        ref, st_ref = _cv(a, b, pts)
        fo, fs = _fused_lk(a, b, pts)
        t = track_lk(torch.from_numpy(a)[None, None], torch.from_numpy(b)[None, None], torch.from_numpy(pts)[None],
                     lk_backend="tensor")
        to, ts = t[0][0].numpy(), t[1][0].numpy()
        assert not _mismatches(fo, fs, ref, st_ref).any()
        d = (fs != ts) | (fs & ts & np.any(fo != to, axis=1))
        assert not (d & ~_mismatches(to, ts, ref, st_ref)).any()
        total, differ = total + len(pts), differ + int(d.sum())
    print(f"tensor LK differs from the fused LK (= cv2) on {differ} of {total} points")
    assert differ > 0  # the tensor LK's sums are not OpenCV's order (docs/kernels.md)


def test_implicit_gradient_from_the_fused_forward():
    """``grad_mode="implicit"``: the fused forward's converged points and level-0 caps, then the same
    implicit-function gradient as the tensor LK's (lanes whose forward results agree: bit for bit)."""
    frames = [load_gray(f) for f in sample_frames("cam0")[:2]]
    rng = np.random.default_rng(7)
    pts0 = torch.from_numpy(_points(frames[0], rng)[:200])[None]
    a = torch.from_numpy(frames[0])[None, None].float()
    b = torch.from_numpy(frames[1])[None, None].float()
    grads, outs = {}, {}
    for be in ("fused", "tensor"):
        pts = pts0.clone().requires_grad_()
        img = b.clone().requires_grad_()
        P, Q = (build_pyramid(x, 3, with_gradients=False, round_levels=True) for x in (a, img))
        out, st = track_lk(P, Q, pts, fixed_point=True, lk_backend=be)
        (out * torch.linspace(0.5, 1.5, out.numel()).view(out.shape)).sum().backward()
        grads[be], outs[be] = (pts.grad, img.grad), (out.detach(), st)
    same = (outs["fused"][1] == outs["tensor"][1]) & (outs["fused"][0] == outs["tensor"][0]).all(-1)
    assert same.float().mean() > 0.9 and outs["fused"][1].any()
    gf, gt = grads["fused"], grads["tensor"]
    assert torch.equal(gf[0][same], gt[0][same])  # per lane: the same attach on the same point
    assert gf[0].abs().sum() > 0 and gf[1].abs().sum() > 0
    rel = (gf[1] - gt[1]).norm() / gt[1].norm()  # the image gradient sums every lane: the few that differ
    assert rel < 0.05, float(rel)


def test_fused_lk_not_taken_outside_its_setting():
    """Float images without 8-bit levels, float64 points, an iteration budget, an unrolled gradient,
    a window narrower than 8: the tensor LK (the same call, its own results)."""
    frames = [load_gray(f) for f in sample_frames("cam0")[:2]]
    a, b = (torch.from_numpy(f)[None, None] for f in frames)
    pts = torch.from_numpy(_points(frames[0], np.random.default_rng(8))[:100])[None]
    from torch_frontend.lk import fused_path

    calls = []
    real = fused_path.lk_fused

    def spy(*args, **kw):
        calls.append(1)
        return real(*args, **kw)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("torch_frontend.lk.track.lk_fused", spy)
        track_lk(a, b, pts)
        assert len(calls) == 1
        for kw in (dict(prev=a.float() + 0.25, next=b.float()), dict(pts=pts.double()), dict(win_size=(7, 21)),
                   dict(pts=pts.clone().requires_grad_(), grad_mode="unrolled")):
            args = dict(prev=a, next=b, pts=pts)
            args.update(kw)
            track_lk(args.pop("prev"), args.pop("next"), args.pop("pts"), **args)
        assert len(calls) == 1
    opts = dataclasses.replace(tf.lk.LKOptions(backend="fused"), iter_budget=5)
    assert not fused_path.fused_applies(build_pyramid(a, 3), build_pyramid(b, 3), pts, None, opts)


def test_ranks_that_resolve_other_kernels_refuse_to_start(monkeypatch):
    """``torchrun``: every rank resolves the backend and gathers the others'; one rank without numba
    (the tensor LK) would give other bits, so every rank raises before any work, naming them."""
    from torch_frontend.pipelines.common import OptionError
    from torch_frontend.pipelines.sharded import _same_lk_backend

    class Job:
        def __init__(self, every):
            self.every = every

        def all_gather(self, obj):
            return self.every

    _same_lk_backend(Job(["fused", "fused"]), None, torch.device("cpu"))
    with pytest.raises(OptionError, match="rank 0: fused, rank 1: tensor"):
        _same_lk_backend(Job(["fused", "tensor"]), None, torch.device("cpu"))


@pytest.mark.parametrize("stage", ["clahe", "ransac", "corners", "lift"])
def test_a_stage_follows_the_fused_kernels_answer_without_caching_it(monkeypatch, stage):
    """Every fused stage resolves through one mechanism: where the fused kernels cannot run (numba
    stubbed away) the stage runs its tensor path, and once they can again the stage is fused: the
    LK's answer is never cached a second time under the stage's key."""
    resolve = {"clahe": fused.resolve_clahe_backend, "ransac": fused.resolve_ransac_backend,
               "corners": fused.resolve_corner_backend, "lift": fused.resolve_lift_backend}[stage]
    monkeypatch.setattr(fused, "_WARNED", set())
    with monkeypatch.context() as m:
        m.setitem(fused._STATUS, "cpu", "numba cannot be loaded (ImportError: no module named numba)")
        m.delitem(fused._STATUS, (stage, "cpu"), raising=False)
        with pytest.warns(RuntimeWarning, match="numba cannot be loaded"):
            assert resolve(None, "cpu") == "tensor"
        with pytest.raises(ConfigError, match="numba cannot be loaded"):
            resolve("fused", "cpu")
    assert fused.stage_unavailable_reason(stage, "cpu") is None
    assert resolve(None, "cpu") == "fused" and resolve("fused", "cpu") == "fused"
