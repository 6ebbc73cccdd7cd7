"""The fused Triton kernels (``fused/_triton_pyramid.py``, ``fused/_triton_lk.py``) without a GPU.

Convention:
    Two kinds of checks, each in its own subprocess (``TRITON_INTERPRET`` is read when ``@triton.jit``
    decorates, so a process either interprets or compiles every kernel):

    * PTX (``TRITON_INTERPRET`` unset): every kernel compiled for sm_90 (:func:`ptx_sm90`) has no
      FMA, no approximate or flush-to-zero float instruction, and every float add / sub / mul
      carries ``.rn`` (without a rounding modifier ptxas may contract a mul and an add into an FMA).
    * Interpreter (``TRITON_INTERPRET=1``, CPU tensors, slow): the pyramid equals ``cv2.pyrDown`` +
      ``cv2.copyMakeBorder(BORDER_REFLECT_101)`` and the LK equals ``cv2.calcOpticalFlowPyrLK``
      (winSize 21, COUNT | EPS 30 / 0.01) bit for bit on crops of the sample EuRoC frames: status,
      and the float32 positions of every lane cv2 tracks (status 0 too: cv2's ``nextPts`` of a lost
      point is the contract's). Lanes cv2 has no notion of (``valid`` False, a non-finite ``init``)
      are checked against the contract's rule. The points were chosen (with an instrumented model
      of the contract) to cover its branches; each case says which.

    A scenario runs in the subprocess as ``_scenario_<name>()`` of this module, asserts there and
    prints ``PASS <name>``; the test asserts on the subprocess's exit status and output.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

if os.environ.get("TORCH_FRONTEND_REQUIRE_TRITON") == "1":  # make test-all / CI: never skip
    import triton  # noqa: F401
else:
    pytest.importorskip("triton", reason="the fused CUDA kernels are Triton kernels: triton is not installed "
                                         "(make test-all installs it: pip install -e '.[triton]')")
cv2 = pytest.importorskip("cv2", reason="the reference is OpenCV's calcOpticalFlowPyrLK")

REPO = Path(__file__).resolve().parents[1]
FRAMES = sorted((REPO / "torch_frontend" / "data" / "euroc_mini" / "mav0" / "cam0" / "data").glob("*.png"))

#: VINS's LK: window 21 x 21, COUNT | EPS criteria (30 iterations, eps 0.01), OpenCV's min-eigenvalue
WIN = 21
MAX_ITERS = 30
EPS = 0.01
MIN_EIG = 1e-4
PAD = WIN + 1
CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, MAX_ITERS, EPS)

#: seconds a scenario subprocess may take (the interpreter runs ~0.1-0.3 s per LK iteration of a block)
_TIMEOUT = 600


# ------------------------------------------------------------------------------- subprocess driver
def _run(code: str, interpret: bool) -> str:
    """Run ``code`` in a fresh interpreter from the repo root; returns its stdout (asserts exit 0)."""
    env = dict(os.environ)
    env.pop("TRITON_INTERPRET", None)
    if interpret:
        env["TRITON_INTERPRET"] = "1"
    env.setdefault("OMP_NUM_THREADS", "1")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=_TIMEOUT)
    assert proc.returncode == 0, \
        f"subprocess failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr[-6000:]}"
    return proc.stdout


def _run_scenario(name: str) -> None:
    out = _run(f"import tests.test_fused_triton as t; t._scenario_{name}()", interpret=True)
    assert f"PASS {name}" in out, out


# ----------------------------------------------------------------------------------- PTX (no GPU)
_PTX_SCRIPT = r"""
import json, re
from torch_frontend.fused._triton_lk import ptx_sm90
ptx = ptx_sm90()
# float arithmetic, and conversions of integers to floats (both must round to nearest even)
FLOAT_OP = re.compile(r"^\s*(?:@!?%p\d+\s+)?((?:add|sub|mul|div|sqrt|rcp|fma|mad)(?:\.\w+)*\.f(?:32|64)"
                      r"|cvt(?:\.\w+)*\.f(?:32|64)\.[su](?:8|16|32|64))\b", re.M)
report = {}
for name, text in ptx.items():
    ops = FLOAT_OP.findall(text)
    report[name] = {
        "fma": sorted({o for o in ops if o.startswith(("fma", "mad"))}),
        "approx": text.count(".approx"),
        "div_full": text.count("div.full"),
        "ftz": text.count(".ftz"),
        "no_rn": sorted({o for o in ops if ".rn." not in o}),
        "n_float_ops": len(ops),
    }
print(json.dumps(report))
"""


def test_ptx_sm90_has_only_correctly_rounded_float_ops():
    """Every kernel's sm_90 PTX: no FMA, no ``.approx``, no ``div.full``, no ``.ftz``, and every
    float add / sub / mul / div / sqrt and int-to-float conversion rounded ``.rn`` (bit-identity with
    OpenCV's SSE2 arithmetic; an add or mul without a rounding modifier may be contracted by ptxas)."""
    import json

    t0 = time.time()
    out = _run(_PTX_SCRIPT, interpret=False)
    report = json.loads(out.strip().splitlines()[-1])
    assert set(report) == {"lk", "lk_init", "lk_back", "pyramid_level0", "pyramid_down", "clahe_lut",
                           "clahe_blend", "mask_decide", "mask_draw", "ransac_score",
                           "ransac_score_state", "corners_response", "corners_candidates",
                           "pinhole_lift", "pinhole_lift_f64"}, sorted(report)
    for name, r in report.items():
        assert r["fma"] == [], (name, r)
        assert r["approx"] == 0 and r["div_full"] == 0 and r["ftz"] == 0, (name, r)
        assert r["no_rn"] == [], (name, r)
    # the LK really is float code (the checks above are not vacuous)
    assert report["lk"]["n_float_ops"] > 100, report["lk"]
    assert report["ransac_score"]["n_float_ops"] > 50, report["ransac_score"]
    assert report["pinhole_lift"]["n_float_ops"] > 20, report["pinhole_lift"]
    assert time.time() - t0 < _TIMEOUT


# ------------------------------------------------------------------------- scenario helpers (child)
def _frame(i: int) -> np.ndarray:
    img = cv2.imread(str(FRAMES[i]), cv2.IMREAD_GRAYSCALE)
    assert img is not None, FRAMES[i]
    return img


def _crop_pair(i: int, y0: int, x0: int, h: int, w: int, dy: int = 0, dx: int = 0, gap: int = 1):
    """Frame ``i``'s ``h x w`` crop at ``(y0, x0)`` and frame ``i + gap``'s crop shifted by ``(dy, dx)``."""
    a = np.ascontiguousarray(_frame(i)[y0:y0 + h, x0:x0 + w])
    b = np.ascontiguousarray(_frame(i + gap)[y0 + dy:y0 + dy + h, x0 + dx:x0 + dx + w])
    return a, b


def _packed_cv2(img: np.ndarray, max_level: int, pad: int) -> np.ndarray:
    """The packed pyramid row (``fused/layout.py``) built with ``cv2.pyrDown`` + ``cv2.copyMakeBorder``."""
    levels = [img]
    for _ in range(max_level):
        levels.append(cv2.pyrDown(levels[-1]))
    return np.concatenate([cv2.copyMakeBorder(lv, pad, pad, pad, pad, cv2.BORDER_REFLECT_101).ravel()
                           for lv in levels])


def _cv2_top_cap(h: int, w: int, win: int = WIN) -> int:
    """The largest maxLevel cv2's buildOpticalFlowPyramid keeps for an ``h x w`` image (it stops at the
    level whose next level would be ``<= win``): a test's ``top`` must not exceed it."""
    level = 0
    while True:
        h, w = (h + 1) // 2, (w + 1) // 2
        if h <= win or w <= win:
            return level
        level += 1


def _cv2_lk(a, b, pts, top, init=None):
    """``cv2.calcOpticalFlowPyrLK`` with VINS's parameters: ``(N, 2)`` float32 positions, ``(N,)`` bool."""
    assert top <= _cv2_top_cap(*a.shape)
    if init is None:
        r, st, _ = cv2.calcOpticalFlowPyrLK(a, b, pts, None, winSize=(WIN, WIN), maxLevel=top,
                                            criteria=CRITERIA)
    else:
        r, st, _ = cv2.calcOpticalFlowPyrLK(a, b, pts, init.copy(), winSize=(WIN, WIN), maxLevel=top,
                                            criteria=CRITERIA, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    return r.reshape(-1, 2), st.ravel().astype(bool)


def _cv2_lk_fb(a, b, pts, top, init, fb_top, threshold, from_pts):
    """The forward-backward reference: forward, then backward from the result (starting at ``pts``
    when ``from_pts``); ``status & back_status & |back - pts| <= threshold`` (float64)."""
    fwd, st = _cv2_lk(a, b, pts, top, init)
    back, bst = _cv2_lk(b, a, fwd, fb_top, pts if from_pts else None)
    ex = (back[:, 0] - pts[:, 0]).astype(np.float64)  # float32 differences, then double
    ey = (back[:, 1] - pts[:, 1]).astype(np.float64)
    return fwd, st & bst & (np.sqrt(ex * ex + ey * ey) <= threshold)


def _lk(prev_rows, next_rows, pts, valid, init, h, w, top, fb_top=-1, fb_threshold=0.0, fb_from_pts=False):
    """:func:`lk_cuda` on numpy inputs (CPU tensors: run under the interpreter); numpy outputs. Every
    output of every lane is first checked equal, bit for bit, to the CPU kernel's (the numba kernel
    behind ``torch_frontend::lk`` on CPU tensors): positions (also of lanes with status 0), status,
    ``capped``."""
    import torch

    from torch_frontend.fused._triton_lk import lk_cuda
    from torch_frontend.fused.ops import lk_op

    t = lambda x: None if x is None else torch.from_numpy(np.ascontiguousarray(x))  # noqa: E731
    args = (h, w, PAD, PAD, top, WIN, WIN, MAX_ITERS, EPS, MIN_EIG, fb_top, fb_threshold, fb_from_pts)
    out, st, cp = lk_cuda(t(prev_rows), t(next_rows), t(pts), t(valid), t(init), *args)
    c_out, c_st, c_cp = lk_op(t(prev_rows), t(next_rows), t(pts), t(valid), t(init), *args)
    assert torch.equal(out.view(torch.int32), c_out.view(torch.int32)), "positions differ from the CPU kernel"
    assert torch.equal(st, c_st) and torch.equal(cp, c_cp), "status / capped differ from the CPU kernel"
    return out.numpy(), st.numpy(), cp.numpy()


def _assert_same(name, got, ref_pos, ref_st, lanes):
    """Lanes ``lanes`` of one stream: status equal, positions bit-equal (NaN == NaN)."""
    pos, st = got
    np.testing.assert_array_equal(st[lanes], ref_st, err_msg=f"{name}: status")
    a = pos[lanes].view(np.int32)
    b = np.ascontiguousarray(ref_pos, dtype=np.float32).view(np.int32)
    nan = np.isnan(pos[lanes]) & np.isnan(ref_pos)
    bad = (a != b) & ~nan
    assert not bad.any(), f"{name}: positions differ at lanes {np.asarray(lanes)[bad.any(1)]}:\n" \
                          f"{pos[lanes][bad.any(1)]}\nvs cv2\n{ref_pos[bad.any(1)]}"


def _setup():
    import torch

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    return time.time()


# ------------------------------------------------------------------------------------- scenarios
#: the pyramid cases: (H, W, max_level, pad): a real crop, odd sizes with levels smaller than the pad
#: (repeated reflection), 1- and 2-pixel levels, pad 0
PYRAMID_CASES = [(80, 96, 1, PAD), (37, 51, 3, PAD), (13, 17, 3, 5), (5, 7, 3, PAD), (2, 3, 2, 4),
                 (1, 1, 2, 3), (3, 1, 1, 0)]


def _scenario_pyramid():
    import torch

    from torch_frontend.fused._triton_pyramid import pyramid_cuda
    from torch_frontend.fused.layout import PyramidLayout

    t0 = _setup()
    rng = np.random.default_rng(7)
    for h, w, lv, pad in PYRAMID_CASES:
        real = _frame(2)[100:100 + h, 200:200 + w]
        imgs = np.stack([real, rng.integers(0, 256, (h, w), dtype=np.uint8)])
        out = pyramid_cuda(torch.from_numpy(imgs), lv, pad).numpy()
        assert out.shape == (2, PyramidLayout(h, w, lv, pad).total), (h, w, lv, pad, out.shape)
        if pad >= 3:  # the op's domain (the CPU kernel reads 3 pixels out); the CUDA kernel takes any pad
            from torch_frontend.fused.ops import pyramid_op

            np.testing.assert_array_equal(out, pyramid_op(torch.from_numpy(imgs), lv, pad).numpy(),
                                          err_msg=f"{(h, w, lv, pad)}: the CPU kernel")
        for s in range(2):
            np.testing.assert_array_equal(out[s], _packed_cv2(imgs[s], lv, pad), err_msg=f"{(h, w, lv, pad)}")
    print(f"PASS pyramid {time.time() - t0:.1f}s")


# Forward LK, no initial flow, two streams of 96 x 80 crops (top 1: cv2's cap for this size).
# Stream 0: frames 0 -> 1, a flat grey square painted into both crops.
FWD0 = dict(i=0, y0=200, x0=300, dy=0, dx=0, flat=(48, 78, 5, 36, 90))
FWD0_PTS = [
    (64.4354, 16.0578),  # converges at level 1, oscillation stop at level 0 (nx -= dx / 2)
    (97.25, -2.5),  # level 1 fails the min-eigenvalue test (a coarse level abandoned), level 0 tracks
    (100.75, 76.5),  # level 1 hits the iteration cap (capped stays False: not level 0)
    (-3.75, 84.75),  # oscillation stops at both levels
    (40.0, 30.0),  # ordinary
    (16.5, 82.75),  # 30 iterations at level 0 without converging: capped, status 1
    (20.0, 62.0),  # the flat square: level 1 tracks, level 0 fails the min-eigenvalue test
    (-40.0, 30.0),  # template window outside at every level (abandoned at level 1, then at level 0)
    (-11.25, -6.0),  # level 1 fails the min-eigenvalue test, level 0's template window is outside
    (92.75, -10.0),  # fails the min-eigenvalue test at both levels
    (float("nan"), 20.0),  # NaN point: outside everywhere (cv2: status 0, NaN position)
    (float("inf"), 20.0),  # inf point: likewise
    (70.25, 50.75),  # valid False: keeps its start, status False
]
FWD0_TRACKED, FWD0_LOST, FWD0_INVALID, FWD0_CAPPED = range(0, 6), range(6, 12), [12], [5]
# Stream 1: frames 3 -> 4 shifted by (3, -4) px: iterations that leave the image, and the cap.
FWD1 = dict(i=3, y0=100, x0=100, dy=3, dx=-4, flat=None)
FWD1_PTS = [
    (91.0, 60.0),  # 30 iterations at level 0 without converging: capped
    (92.0, 38.0),  # capped
    (85.6241, 50.6963),  # capped
    (92.0, 43.0),  # leaves the image during level 0's iterations (iteration 22)
    (91.5815, 44.3120),  # leaves at level 0 (iteration 14)
    (101.8732, 35.8447),  # leaves at level 1 (iteration 19), starts outside at level 0
    (50.8122, -2.7507),  # above the image: capped, status 1
]
FWD1_CAPPED, FWD1_LEFT = [0, 1, 2, 6], [3, 4, 5]


def _fwd_inputs(spec, pts, h=80, w=96):
    a, b = _crop_pair(spec["i"], spec["y0"], spec["x0"], h, w, spec["dy"], spec["dx"])
    if spec["flat"] is not None:
        r0, r1, c0, c1, grey = spec["flat"]
        a = a.copy()
        b = b.copy()
        a[r0:r1, c0:c1] = grey
        b[r0:r1, c0:c1] = grey
    return a, b, np.asarray(pts, np.float32)


def _scenario_forward():
    t0 = _setup()
    top, h, w = 1, 80, 96
    a0, b0, p0 = _fwd_inputs(FWD0, FWD0_PTS)
    a1, b1, p1 = _fwd_inputs(FWD1, FWD1_PTS)
    n = max(len(p0), len(p1))
    pts = np.zeros((2, n, 2), np.float32)
    valid = np.zeros((2, n), bool)
    pts[0, :len(p0)], pts[1, :len(p1)] = p0, p1
    valid[0, :len(p0)], valid[1, :len(p1)] = True, True
    valid[0, FWD0_INVALID] = False
    prev = np.stack([_packed_cv2(a0, top, PAD), _packed_cv2(a1, top, PAD)])
    nxt = np.stack([_packed_cv2(b0, top, PAD), _packed_cv2(b1, top, PAD)])
    out, st, cp = _lk(prev, nxt, pts, valid, None, h, w, top)
    for s, (a, b, p) in enumerate([(a0, b0, p0), (a1, b1, p1)]):
        tracked = np.flatnonzero(valid[s, :len(p)])
        r, rst = _cv2_lk(a, b, p[tracked], top)
        _assert_same(f"stream {s}", (out[s], st[s]), r, rst, tracked)
    # invalid lanes (and the padding lanes of stream 0): start kept, status and capped False
    off = ~valid
    np.testing.assert_array_equal(out[off].view(np.int32), pts[off].view(np.int32))
    assert not st[off].any() and not cp[off].any()
    # the branches the points were chosen for
    exp_cap = np.zeros((2, n), bool)
    exp_cap[0, FWD0_CAPPED] = True
    exp_cap[1, FWD1_CAPPED] = True
    np.testing.assert_array_equal(cp, exp_cap)
    assert st[0, FWD0_TRACKED].all() and not st[0, FWD0_LOST].any()
    assert st[1, FWD1_CAPPED].all() and not st[1, FWD1_LEFT].any()
    print(f"PASS forward {time.time() - t0:.1f}s")


# Initial flow (OPTFLOW_USE_INITIAL_FLOW), 4 levels (top 3: cv2's cap for this size): a 200 x 184 crop
# of frames 5 -> 6, the second crop taken (dy, dx) = (-3, 4) px off, so that the content moves by
# (-4, +3) px; the guesses are that motion plus noise.
INIT = dict(i=5, y0=150, x0=250, dy=-3, dx=4, flat=None)


def _scenario_init():
    t0 = _setup()
    top, h, w = 3, 184, 200
    a, b, _ = _fwd_inputs(INIT, [], h, w)
    corners = cv2.goodFeaturesToTrack(a, 8, 0.01, 10).reshape(-1, 2).astype(np.float32)
    pts = np.concatenate([corners, np.float32([[100.5, 90.25], [3.0, 180.0], [150.0, 20.0], [60.0, 60.0],
                                               [120.0, 140.0], [30.0, 100.0]])]).astype(np.float32)
    n = len(pts)
    rng = np.random.default_rng(3)
    # content at (x, y) in a is at (x - dx, y - dy) in b
    init = (pts + np.float32([-INIT["dx"], -INIT["dy"]]) + rng.normal(0, 1.5, pts.shape)).astype(np.float32)
    k_far, k_nan, k_inf, k_invalid = n - 4, n - 3, n - 2, n - 1
    init[k_far] = (-150.0, 60.0)  # the start is outside at every level: stops at once, status 0
    init[k_nan, 1] = np.nan  # a non-finite guess: not tracked, position = the point
    init[k_inf, 0] = np.inf
    valid = np.ones(n, bool)
    valid[k_invalid] = False  # not tracked, position = its (finite) guess
    prev, nxt = _packed_cv2(a, top, PAD)[None], _packed_cv2(b, top, PAD)[None]
    out, st, cp = _lk(prev, nxt, pts[None], valid[None], init[None], h, w, top)
    cv_lanes = np.array([k for k in range(n) if k not in (k_nan, k_inf, k_invalid)])
    r, rst = _cv2_lk(a, b, pts[cv_lanes], top, init[cv_lanes])
    _assert_same("init", (out[0], st[0]), r, rst, cv_lanes)
    assert not st[0, k_far] and rst[:len(corners)].sum() >= len(corners) - 1
    for k, start in [(k_nan, pts[k_nan]), (k_inf, pts[k_inf]), (k_invalid, init[k_invalid])]:
        assert out[0, k].view(np.int32).tolist() == start.view(np.int32).tolist(), (k, out[0, k], start)
        assert not st[0, k] and not cp[0, k]
    print(f"PASS init {time.time() - t0:.1f}s")


def _scenario_fb_from_pts():
    """Forward-backward, the backward pass starting at the points (VINS-Fusion's flow_back), with an
    initial flow, top 2 / fb_top 1 on a 150 x 120 crop of frames 8 -> 9, threshold 0.05 px (two corners
    come back 0.11 and 0.13 px away)."""
    t0 = _setup()
    top, fb_top, thr, h, w = 2, 1, 0.05, 120, 150
    a, b = _crop_pair(8, 180, 320, h, w, 2, -2)
    pts = np.concatenate([cv2.goodFeaturesToTrack(a, 10, 0.01, 8).reshape(-1, 2),
                          np.float32([[75.3, 60.6], [5.0, 115.0], [149.0, 2.0]])]).astype(np.float32)
    n = len(pts)
    init = (pts + np.float32([2.0, -2.0])).astype(np.float32)
    valid = np.ones(n, bool)
    valid[1] = False
    prev, nxt = _packed_cv2(a, top, PAD)[None], _packed_cv2(b, top, PAD)[None]
    out, st, cp = _lk(prev, nxt, pts[None], valid[None], init[None], h, w, top, fb_top, thr, True)
    lanes = np.flatnonzero(valid)
    r, rst = _cv2_lk_fb(a, b, pts[lanes], top, init[lanes], fb_top, thr, True)
    _assert_same("fb from pts", (out[0], st[0]), r, rst, lanes)
    assert out[0, 1].view(np.int32).tolist() == init[1].view(np.int32).tolist() and not st[0, 1]
    fwd_only, fwd_st = _cv2_lk(a, b, pts[lanes], top, init[lanes])
    assert (fwd_st & ~rst).any(), "no lane lost by the forward-backward check alone: the case covers nothing"
    print(f"PASS fb_from_pts {time.time() - t0:.1f}s")


def _scenario_fb_from_result():
    """Forward-backward from the forward result (no start), no initial flow, top 1 / fb_top 0, on a
    96 x 80 crop of frames 12 -> 13 shifted by (1, 3) px, threshold 0.1 px; the pyramids built by
    :func:`pyramid_cuda` (the two kernels together)."""
    import torch

    from torch_frontend.fused._triton_pyramid import pyramid_cuda

    t0 = _setup()
    top, fb_top, thr, h, w = 1, 0, 0.1, 80, 96
    a, b = _crop_pair(12, 60, 420, h, w, 1, 3)
    pts = np.concatenate([cv2.goodFeaturesToTrack(a, 10, 0.01, 8).reshape(-1, 2),
                          np.float32([[47.5, 40.5], [0.5, 0.5], [95.0, 60.0]])]).astype(np.float32)
    n = len(pts)
    prev = pyramid_cuda(torch.from_numpy(a)[None], top, PAD).numpy()
    nxt = pyramid_cuda(torch.from_numpy(b)[None], top, PAD).numpy()
    np.testing.assert_array_equal(prev[0], _packed_cv2(a, top, PAD))
    out, st, cp = _lk(prev, nxt, pts[None], np.ones((1, n), bool), None, h, w, top, fb_top, thr, False)
    r, rst = _cv2_lk_fb(a, b, pts, top, None, fb_top, thr, False)
    _assert_same("fb from result", (out[0], st[0]), r, rst, np.arange(n))
    fwd, fwd_st = _cv2_lk(a, b, pts, top)
    assert (fwd_st & ~rst).any(), "no lane lost by the forward-backward check alone: the case covers nothing"
    print(f"PASS fb_from_result {time.time() - t0:.1f}s")


# ----------------------------------------------------------------------------- interpreter tests
@pytest.mark.slow
def test_pyramid_matches_cv2_interpreted():
    """Packed pyramid == cv2.pyrDown levels + copyMakeBorder(REFLECT_101), odd and tiny sizes, any pad."""
    _run_scenario("pyramid")


@pytest.mark.slow
def test_lk_forward_matches_cv2_interpreted():
    """Two streams, no initial flow: oscillation, cap, leaving the image, outside windows, a flat
    patch, NaN / inf points, an invalid lane."""
    _run_scenario("forward")


@pytest.mark.slow
def test_lk_initial_flow_matches_cv2_interpreted():
    """OPTFLOW_USE_INITIAL_FLOW on 4 levels; a start outside the image, NaN / inf guesses, an invalid lane."""
    _run_scenario("init")


@pytest.mark.slow
def test_lk_forward_backward_from_pts_matches_cv2_interpreted():
    _run_scenario("fb_from_pts")


@pytest.mark.slow
def test_lk_forward_backward_from_result_matches_cv2_interpreted():
    _run_scenario("fb_from_result")


def _scenario_mask():
    """setMask (``_triton_mask.py``) == the CPU kernel == the tensor kernel, bit for bit: a small
    real-corner case with ties (two streams, one shared base and one per stream), the self-check's
    case, .5 centres, borders, NaN / inf, invalid slots, float64 points and int32 counts."""
    import math

    import torch

    from torch_frontend.fused import selfcheck
    from torch_frontend.fused._triton_mask import set_mask_cuda
    from torch_frontend.fused.mask_op import disc_r2, set_mask_op
    from torch_frontend.masks import _distance_mask_impl

    t0 = _setup()
    H, W = 60, 80
    crops = [_frame(k)[200:200 + H, 300:300 + W] for k in (0, 7)]
    rng = np.random.default_rng(9)
    N = 40
    pts = np.full((2, N, 2), -5.0, np.float32)
    for b, c in enumerate(crops):
        cs = cv2.goodFeaturesToTrack(c, 28, 0.01, 3).reshape(-1, 2)
        pts[b, :len(cs)] = cs + rng.normal(0, 1.0, cs.shape)
    pts[:, 28:34] = [[0.5, 0.5], [-0.5, 10], [W - 0.5, 20], [30.5, H - 0.5], [np.nan, 5], [6, np.inf]]
    cnt = rng.integers(1, 4, (2, N))
    valid = rng.random((2, N)) > 0.1
    base = np.full((2, H, W), 255, np.uint8)
    base[1, :, :5] = 254
    base[0, 40:, 60:] = 0
    cases = []
    for dt, it in ((torch.float32, torch.int64), (torch.float64, torch.int32)):
        for bm in (base[:1], base):
            for radius in (0.0, 6.0, 9.5, 25.0):
                cases.append((torch.from_numpy(pts).to(dt), torch.from_numpy(cnt).to(it), torch.from_numpy(valid),
                              torch.from_numpy(np.ascontiguousarray(bm)), radius))
    c = {k: v for k, v in selfcheck.case().items()}
    p = torch.cat((c["pts"], c["init"]), 1)
    cases.append((p, (torch.arange(48).view(2, 24) * 7) % 4, torch.cat((c["valid"], c["valid"]), 1),
                  torch.full((1, 72, 104), 255, dtype=torch.uint8), 17.0))
    for k, (p, q, v, bm, radius) in enumerate(cases):
        r2 = disc_r2(radius, bm.shape[1], bm.shape[2])
        keep, mask = set_mask_cuda(p, q, v, bm, r2, math.isqrt(r2))
        ck, cm = set_mask_op(p, q, v, bm, radius)
        tk, tm = _distance_mask_impl(p, q, v, radius, bm.expand(p.shape[0], -1, -1).clone())[:2]
        assert torch.equal(keep, ck) and torch.equal(mask, cm), f"case {k}: differs from the CPU kernel"
        assert torch.equal(keep, tk) and torch.equal(mask, tm), f"case {k}: differs from the tensor kernel"
        assert keep.any() or radius == 0.0
    print(f"PASS mask {time.time() - t0:.1f}s")


@pytest.mark.slow
def test_set_mask_matches_the_cpu_kernel_interpreted():
    """setMask's decide and draw kernels under the interpreter: the CPU kernel's bits on every case."""
    _run_scenario("mask")


# ------------------------------------------------------------------------------- F-RANSAC scoring
def _scenario_ransac():
    """``torch_frontend::ransac_score``'s Triton kernel (interpreted) equals the CPU kernel on every
    output: the self-check case, fresh and with a running state, and a block of real 7-point models
    (two problems of 40 and 30 planted points, one of 12: passed through) at thresholds 1 and 0.5."""
    import torch

    from torch_frontend.fused._triton_ransac import ransac_score_cuda
    from torch_frontend.fused.ransac_op import ransac_score_op, selfcheck_case
    from torch_frontend.ransac.bounds import _niters_table
    from torch_frontend.ransac.capturable import _front_capturable
    from torch_frontend.ransac.samples import OPENCV_SEED, _state_of

    from ._ransac_cases import _plant, _scatter, _synthetic_scenes

    cases = [(selfcheck_case(), 1.0)]
    rng = np.random.default_rng(2)
    sets = [(a[:k], _plant(a[:k], c[:k], 0.3, rng)[0]) for (a, c), k in
            zip(_synthetic_scenes(k=3, n=40, noise=0.3, seed=4), (40, 30, 12))]
    p1, p2, valid, _ = _scatter(sets, 44, rng)
    sp = _front_capturable(p1.float(), p2.float(), valid, 0.99, 12, [_state_of(OPENCV_SEED)] * 3, None)
    for thr2 in (1.0, 0.25):
        cases.append(((sp.Fm, sp.fok, sp.x12, sp.eff, sp.n, _niters_table(44, 1000, 0.99)), thr2))
    for args, thr2 in cases:
        B = args[0].shape[0]
        state = (torch.full((B,), 4, dtype=torch.int64), torch.full((B,), 8, dtype=torch.int64),
                 torch.full((B,), 30, dtype=torch.int64), torch.full((B,), 1, dtype=torch.int64))
        for st in ((None,) * 4, state):
            ref = ransac_score_op(*args, *st, thr2)
            got = ransac_score_cuda(*args, *st, thr2)
            for r, g in zip(ref, got):
                assert torch.equal(r, g), (thr2, st[0] is None, r, g)
    # slots in several lane blocks (N = 40 in blocks of 16: the count and mask loops over chunks)
    import torch_frontend.fused._triton_ransac as tr

    tr._MAX_BLOCK = 16
    args = selfcheck_case()
    for r, g in zip(ransac_score_op(*args, None, None, None, None, 1.0),
                    ransac_score_cuda(*args, None, None, None, None, 1.0)):
        assert torch.equal(r, g), ("chunks", r, g)
    print("PASS ransac")


def test_ransac_score_matches_cpu_interpreted():
    _run_scenario("ransac")
