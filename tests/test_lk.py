"""Pyramidal Lucas–Kanade vs ``cv2.calcOpticalFlowPyrLK`` on real images, vs ground truth (homography
warps of real frames, Middlebury Motorcycle), batching, gradients.

Acceptance bars (issue 5): status agreement >= 99 %; among points both call valid, median
``|delta| <= 0.02`` px and 95th percentile ``<= 0.1`` px; median end-point error vs ground truth
``<= 1.1x`` OpenCV's own; false-valid rate (status 1, error > 1 px) printed, ``<= 1 %`` with the
forward–backward check where OpenCV's algorithm itself can reach it (see ``test_motorcycle_vs_gt``);
on the EuRoC temporal pairs >= 99 % of the points bit-identical to OpenCV (the fixed-point
emulation; without it 7.9 %, which only this bar detects). Larger motions (stereo, warps) need more
iterations, and the float summation order of the 2x2 systems then leaves 60-90 % bit-identical
(printed as ``bit-identical``), within the distance bars.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from tests.conftest import REPO, TEST_DATA, load_gray, sample_frames
from torch_frontend.errors import ConfigError
from torch_frontend.lk import track_lk
from torch_frontend.pyramid import build_pyramid

pytestmark = pytest.mark.usefixtures("single_thread")  # many small ops (conftest)

CRIT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)


# ----------------------------------------------------------------------------------------- helpers
def cv_lk(a, b, p, max_level=3, win=21, init=None):
    flags = 0
    nxt = None
    if init is not None:
        flags, nxt = cv2.OPTFLOW_USE_INITIAL_FLOW, init.reshape(-1, 1, 2).astype(np.float32).copy()
    out, st, _ = cv2.calcOpticalFlowPyrLK(a, b, p.reshape(-1, 1, 2).astype(np.float32), nxt,
                                          winSize=(win, win), maxLevel=max_level, criteria=CRIT, flags=flags)
    return out.reshape(-1, 2), st.ravel().astype(bool)


def cv_lk_fb(a, b, p, max_level=3, fb_max_level=3, use_initial=False):
    """VINS-Fusion FLOW_BACK with cv2 (spec §6.3)."""
    out, st = cv_lk(a, b, p, max_level)
    back, st2 = cv_lk(b, a, out, fb_max_level, init=p if use_initial else None)
    ok = st & st2 & (np.linalg.norm(back - p, axis=1) <= 0.5)
    return out, ok


def t_img(*imgs):
    return torch.from_numpy(np.stack(imgs))[:, None]


def t_pts(*pts):
    return torch.from_numpy(np.stack(pts).astype(np.float32))


def gftt(img, n=300, min_dist=10):
    return cv2.goodFeaturesToTrack(img, n, 0.01, min_dist).reshape(-1, 2).astype(np.float32)


def bit_identical(ours, st, ref, st_ref):
    """Fraction of points exactly as OpenCV: same status and, where both track, the same float32
    position bit for bit."""
    both = st & st_ref
    same_pos = np.all(ours.astype(np.float32) == ref.astype(np.float32), axis=1)
    return float(np.mean((st == st_ref) & (~both | same_pos)))


def fidelity(name, ours, st, ref, st_ref, min_bits=None):
    """The distance bars; with ``min_bits`` also a floor on the bit-identical fraction (uint8 images,
    fixed point, float32 points: a lost fixed-point emulation leaves ~8 % there)."""
    agree = float(np.mean(st == st_ref))
    both = st & st_ref
    d = np.linalg.norm(ours - ref, axis=1)[both]
    med, p95 = float(np.median(d)), float(np.percentile(d, 95))
    print(f"[{name}] n={len(st)} status agree={agree:.4f} valid={both.mean():.3f} "
          f"median|d|={med:.2e} p95|d|={p95:.2e} max|d|={d.max():.2e} "
          f"bit-identical={bit_identical(ours, st, ref, st_ref):.4f}")
    assert agree >= 0.99, (name, agree)
    assert med <= 0.02 and p95 <= 0.1, (name, med, p95)
    if min_bits is not None:
        assert bit_identical(ours, st, ref, st_ref) >= min_bits, (name, min_bits)
    return agree, med, p95


def vs_gt(name, ours, st, ref, st_ref, gt):
    e_t = np.linalg.norm(ours - gt, axis=1)
    e_cv = np.linalg.norm(ref - gt, axis=1)
    both = st & st_ref
    m_t, m_cv = float(np.median(e_t[both])), float(np.median(e_cv[both]))
    fv_t, fv_cv = float(np.mean(e_t[st] > 1)), float(np.mean(e_cv[st_ref] > 1))
    print(f"[{name}] median EPE ours={m_t:.4f} cv2={m_cv:.4f} ratio={m_t / max(m_cv, 1e-9):.3f} "
          f"false-valid ours={fv_t:.4f} cv2={fv_cv:.4f}")
    assert m_t <= 1.1 * m_cv + 1e-3, (name, m_t, m_cv)
    return m_t, m_cv, fv_t, fv_cv


def render_homography(img, H, ss=4):
    """Warp ``img`` by ``H`` (pixel-centre convention) with 4x supersampling + INTER_AREA."""
    h, w = img.shape
    big = cv2.resize(img, (w * ss, h * ss), interpolation=cv2.INTER_CUBIC)
    S = np.array([[ss, 0, (ss - 1) / 2], [0, ss, (ss - 1) / 2], [0, 0, 1.0]])
    wb = cv2.warpPerspective(big, S @ H @ np.linalg.inv(S), (w * ss, h * ss), flags=cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_REFLECT_101)
    return cv2.resize(wb, (w, h), interpolation=cv2.INTER_AREA)


def similarity(tx, ty, rot_deg, scale, centre):
    cx, cy = centre
    th = np.deg2rad(rot_deg)
    R = np.array([[scale * np.cos(th), -scale * np.sin(th), 0], [scale * np.sin(th), scale * np.cos(th), 0],
                  [0, 0, 1.0]])
    return np.array([[1, 0, cx + tx], [0, 1, cy + ty], [0, 0, 1.0]]) @ R @ np.array(
        [[1, 0, -cx], [0, 1, -cy], [0, 0, 1.0]])


@pytest.fixture(scope="module")
def cam0():
    return [load_gray(p) for p in sample_frames("cam0")]


@pytest.fixture(scope="module")
def cam1():
    return [load_gray(p) for p in sample_frames("cam1")]


# ------------------------------------------------------------------------------ fidelity vs cv2
# fraction of points bit-identical to cv2 on the EuRoC temporal pairs (the tracker's case): 99.2 %
# measured with the fixed-point emulation, 7.9 % without it (the other bars pass either way)
BIT_IDENTICAL_BAR = 0.99
# larger motions need more iterations and the float summation order of ``b`` then leaves fewer
# points bit-identical; floors ~7 points below the measured fractions (stereo 0.76-0.79, with the
# backward check 0.88-0.90; warps 0.70-0.88; Motorcycle 0.60 / 0.74; initial flow 0.905), far above
# the ~8 % of float interpolation: each of these tests also catches a lost fixed-point emulation
STEREO_BITS, STEREO_FB_BITS, WARP_BITS = 0.7, 0.8, 0.62
MOTORCYCLE_BITS, MOTORCYCLE_FB_BITS, INITIAL_FLOW_BITS = 0.53, 0.67, 0.83


# the capturable rows repeat the default rows' figures (the paths are equal bit for bit:
# tests/test_lk_capturable.py), so they only run with the slow tests
@pytest.mark.parametrize("fixed_point,capturable", [
    (None, False), (False, False),
    pytest.param(None, True, marks=pytest.mark.slow), pytest.param(False, True, marks=pytest.mark.slow)],
    ids=["fixed_point", "float_guard", "capturable", "capturable_float_guard"])
def test_euroc_temporal_vs_cv2_batched(cam0, fixed_point, capturable):
    """4 consecutive-frame pairs (one with a 3-frame gap) as B=4 streams in one call. At least 99 %
    of the points are bit-identical to OpenCV's, on the default (eager) and on the capturable
    path; the ``float_guard`` cases show that the bar fails when the fixed-point
    emulation is off (float interpolation still passes the distance bars)."""
    pairs = [(0, 1), (7, 8), (15, 16), (20, 23)]
    pts = [gftt(cam0[i]) for i, _ in pairs]
    n = min(len(p) for p in pts)
    pts = [p[:n] for p in pts]
    out, st = track_lk(t_img(*[cam0[i] for i, _ in pairs]), t_img(*[cam0[j] for _, j in pairs]), t_pts(*pts),
                       fixed_point=fixed_point, capturable=capturable)
    assert out.shape == (4, n, 2) and st.shape == (4, n) and st.dtype == torch.bool
    allo, alls, allr, allsr = [], [], [], []
    for b, (i, j) in enumerate(pairs):
        ref, st_ref = cv_lk(cam0[i], cam0[j], pts[b])
        allo.append(out[b].numpy()), alls.append(st[b].numpy()), allr.append(ref), allsr.append(st_ref)
    ours, status, ref, st_ref = (np.concatenate(x) for x in (allo, alls, allr, allsr))
    fidelity("euroc temporal", ours, status, ref, st_ref)
    bits = bit_identical(ours, status, ref, st_ref)
    if fixed_point is None:
        assert bits >= BIT_IDENTICAL_BAR, bits
    else:
        assert bits < BIT_IDENTICAL_BAR, bits  # the bar catches a lost fixed-point emulation


def test_euroc_stereo_vs_cv2(cam0, cam1):
    """Left -> right on two EuRoC stereo pairs (B=2 in one call), plain and VINS-Fusion stereo FB."""
    pts = [gftt(cam0[i], 300) for i in range(2)]
    n = min(len(p) for p in pts)
    pts = [p[:n] for p in pts]
    L, R, P = t_img(cam0[0], cam0[1]), t_img(cam1[0], cam1[1]), t_pts(*pts)
    out, st = track_lk(L, R, P)
    # VINS-Fusion stereo FLOW_BACK: backward maxLevel 3, no initial guess
    out_fb, st_fb = track_lk(L, R, P, forward_backward=True, fb_max_level=3, fb_use_initial_flow=False)
    for i in range(2):
        ref, st_ref = cv_lk(cam0[i], cam1[i], pts[i])
        fidelity(f"euroc stereo {i}", out[i].numpy(), st[i].numpy(), ref, st_ref, STEREO_BITS)
        ref, ok_ref = cv_lk_fb(cam0[i], cam1[i], pts[i], 3, 3, use_initial=False)
        fidelity(f"euroc stereo {i} FB", out_fb[i].numpy(), st_fb[i].numpy(), ref, ok_ref, STEREO_FB_BITS)


# mild warps: shifts up to 30 px, rotation, scale; "strong" ones only reported (+ fidelity/EPE ratio)
WARPS = {
    "shift(30,0)": (30, 0, 0, 1.0),
    "shift(-20,25)": (-20, 25, 0, 1.0),
    "rot3": (0, 0, 3, 1.0),
    "scale1.05": (4, -3, 0, 1.05),
    "sim(8,-6,2deg,0.96)": (8, -6, 2, 0.96),
}
STRONG = {"rot8": (0, 0, 8, 1.0), "sim(25,20,-6deg,1.1)": (25, 20, -6, 1.1)}


def _warp_case(img, params):
    h, w = img.shape
    H = similarity(*params, (w / 2, h / 2))
    return render_homography(img, H), H


def test_homography_warps_vs_cv2_and_gt(cam0):
    """All warps of one real frame as B streams in one call (plain, then VINS-Fusion temporal FB)."""
    img = cam0[3]
    p = gftt(img, 400, 8)
    cases = {**WARPS, **STRONG}
    warped, gts = [], []
    for prm in cases.values():
        w_img, H = _warp_case(img, prm)
        warped.append(w_img)
        gts.append(cv2.perspectiveTransform(p.reshape(-1, 1, 2).astype(np.float64), H).reshape(-1, 2))
    B = len(cases)
    prev, nxt, P = t_img(*[img] * B), t_img(*warped), t_pts(*[p] * B)
    out, st = track_lk(prev, nxt, P)
    # VINS-Fusion temporal FLOW_BACK: backward maxLevel 1 from the original points
    out_fb, st_fb = track_lk(prev, nxt, P, forward_backward=True, fb_max_level=1)
    fv_fb = []
    for b, name in enumerate(cases):
        ref, st_ref = cv_lk(img, warped[b], p)
        fidelity(f"warp {name}", out[b].numpy(), st[b].numpy(), ref, st_ref, WARP_BITS)
        vs_gt(f"warp {name}", out[b].numpy(), st[b].numpy(), ref, st_ref, gts[b])
        ref, ok_ref = cv_lk_fb(img, warped[b], p, 3, 1, use_initial=True)
        fidelity(f"warp {name} FB", out_fb[b].numpy(), st_fb[b].numpy(), ref, ok_ref, WARP_BITS)
        _, _, fv, _ = vs_gt(f"warp {name} FB", out_fb[b].numpy(), st_fb[b].numpy(), ref, ok_ref, gts[b])
        if name in WARPS:
            fv_fb.append(fv)
    print(f"[warps] false-valid with FB (mild warps): {np.round(fv_fb, 4).tolist()}")
    assert max(fv_fb) <= 0.01


def test_motorcycle_vs_gt():
    """Middlebury Motorcycle (disparities 8–60 px).

    OpenCV's own LK has a high false-valid rate here (occlusion boundaries, repetitive texture):
    ~35 % plain and ~18 % with the forward–backward check; ours reproduces it point for point, so
    the 1 % bar is asserted relative to OpenCV's rate (and printed).
    """
    L = cv2.cvtColor(cv2.imread(str(TEST_DATA / "motorcycle" / "motorcycle_left.png")), cv2.COLOR_BGR2GRAY)
    R = cv2.cvtColor(cv2.imread(str(TEST_DATA / "motorcycle" / "motorcycle_right.png")), cv2.COLOR_BGR2GRAY)
    disp = np.load(TEST_DATA / "motorcycle" / "motorcycle_disp.npz")["arr_0"]
    p = gftt(L, 500, 8)
    d = disp[p[:, 1].astype(int), p[:, 0].astype(int)]
    keep = np.isfinite(d)  # NaN / inf = no ground truth
    p, d = p[keep], d[keep]
    gt = p.copy()
    gt[:, 0] -= d
    ref, st_ref = cv_lk(L, R, p)
    out, st = track_lk(t_img(L), t_img(R), t_pts(p))
    fidelity("motorcycle", out[0].numpy(), st[0].numpy(), ref, st_ref, MOTORCYCLE_BITS)
    vs_gt("motorcycle", out[0].numpy(), st[0].numpy(), ref, st_ref, gt)
    ref, ok_ref = cv_lk_fb(L, R, p, 3, 3, use_initial=False)
    out, st = track_lk(t_img(L), t_img(R), t_pts(p), forward_backward=True, fb_max_level=3,
                       fb_use_initial_flow=False)
    fidelity("motorcycle FB", out[0].numpy(), st[0].numpy(), ref, ok_ref, MOTORCYCLE_FB_BITS)
    _, _, fv, fv_cv = vs_gt("motorcycle FB", out[0].numpy(), st[0].numpy(), ref, ok_ref, gt)
    assert fv <= fv_cv + 0.01


def test_border_points_vs_cv2(cam0):
    """Windows hanging over / outside every image edge: status and position as OpenCV."""
    a, b = cam0[0], cam0[1]
    h, w = a.shape
    xs = [-30, -21, -20.5, -11, -10.3, -3, 0, 0.5, 2, 5, 9.7, 10, 10.5]
    pts = [[x, y] for x in xs for y in (50.3, 200, 300.7)]
    pts += [[w - 1 - x, y] for x in xs for y in (50.3, 200, 300.7)]
    pts += [[x, y] for y in (-25, -10.5, 0, 3, h - 1, h - 10.2, h + 9.5, h + 10, h + 20) for x in (100, 300.5, 600)]
    p = np.array(pts, np.float32)
    shifted, _ = _warp_case(a, (-25, 20, 0, 1.0))
    for nxt in (b, shifted):
        ref, st_ref = cv_lk(a, nxt, p)
        out, st = track_lk(t_img(a), t_img(nxt), t_pts(p))
        assert np.array_equal(st[0].numpy(), st_ref)
        both = st_ref & st[0].numpy()
        assert np.abs(out[0].numpy() - ref)[both].max() <= 1e-3


def test_initial_flow_and_small_image_cap(cam0):
    a, b = cam0[5], cam0[6]
    p = gftt(a, 200)
    guess = p + np.float32([3.0, -2.0])
    ref, st_ref = cv_lk(a, b, p, max_level=1, init=guess)
    out, st = track_lk(t_img(a), t_img(b), t_pts(p), max_level=1, init_pts=t_pts(guess))
    fidelity("initial flow", out[0].numpy(), st[0].numpy(), ref, st_ref, INITIAL_FLOW_BITS)
    # 60x80 crop with win 21: OpenCV stops the pyramid at level 1 (30 px) < ... (15 px <= 21)
    ca, cb = np.ascontiguousarray(a[200:260, 300:380]), np.ascontiguousarray(b[200:260, 300:380])
    pc = gftt(ca, 30, 5)
    ref, st_ref = cv_lk(ca, cb, pc, max_level=3)
    out, st = track_lk(t_img(ca), t_img(cb), t_pts(pc), max_level=3)
    assert np.array_equal(st[0].numpy(), st_ref)
    assert np.abs(out[0].numpy() - ref)[st_ref].max() <= 1e-3


def test_batch_equals_separate_calls_and_modes(cam0, device, monkeypatch):
    """B streams x N points in one call == B separate calls; pyramid reuse, capturable=True and
    padded invalid lanes change nothing."""
    idx = [(0, 1), (9, 10), (17, 19)]
    crops = [(slice(100, 260), slice(200, 420))] * 3
    A = [np.ascontiguousarray(cam0[i][crops[k]]) for k, (i, _) in enumerate(idx)]
    Bn = [np.ascontiguousarray(cam0[j][crops[k]]) for k, (_, j) in enumerate(idx)]
    P = [gftt(x, 60, 6) for x in A]
    n = min(len(x) for x in P)
    P = [x[:n] for x in P]
    pts = t_pts(*P).to(device)
    valid = torch.ones(3, n, dtype=torch.bool, device=device)
    valid[1, ::3] = False
    tA, tB = t_img(*A).to(device), t_img(*Bn).to(device)
    out, st = track_lk(tA, tB, pts, valid)
    assert out.device == pts.device and st.device == pts.device
    for b in range(3):
        o1, s1 = track_lk(tA[b : b + 1], tB[b : b + 1], pts[b : b + 1], valid[b : b + 1])
        assert torch.equal(s1[0], st[b])
        assert (o1[0] - out[b]).abs().max() <= 1e-4
    assert not st[1, ::3].any()
    assert torch.equal(out[1, ::3], pts[1, ::3])  # padded lanes untouched
    # large CPU batches are processed in groups of streams: same results (group size forced to 1
    # here, on this test's device), for image and pyramid inputs, with the backward check too
    import dataclasses

    from torch_frontend import _tuning

    # (the tensor LK's stream groups: the fused LK has one kernel for every stream, tests/test_fused.py)
    out, st = track_lk(tA, tB, pts, valid, lk_backend="tensor")
    ref_fb = track_lk(tA, tB, pts, valid, forward_backward=True, lk_backend="tensor")
    with monkeypatch.context() as mp:
        mp.setitem(_tuning.STRATEGIES, device.type, dataclasses.replace(_tuning.CPU, lk_max_streams=1))
        og, sg = track_lk(tA, tB, pts, valid, lk_backend="tensor")
        assert torch.equal(sg, st) and torch.equal(og, out)
        qa, qb = build_pyramid(tA, 3, backend="tensor"), build_pyramid(tB, 3, backend="tensor")
        og, sg = track_lk(qa, qb, pts, valid, forward_backward=True, lk_backend="tensor")
        assert torch.equal(sg, ref_fb[1]) and torch.equal(og, ref_fb[0])
        # the padded levels (win 21 -> pad 22) are built once for the whole batch and stay on the
        # pyramids: the next image's are reused when it becomes the previous one
        assert (0, 22, 22, pts.dtype) in qb._padded and qb._padded[(0, 22, 22, pts.dtype)].shape[0] == 3
    # pyramids built once (as the tracker keeps them) and the sync-free fixed-iteration mode
    pa, pb = build_pyramid(tA, 3, backend="tensor"), build_pyramid(tB, 3, with_gradients=False, backend="tensor")
    o2, s2 = track_lk(pa, pb, pts, valid, capturable=True, lk_backend="tensor")
    assert torch.equal(s2, st) and (o2 - out).abs().max() <= 1e-5


def test_float_mode_close_to_cv2(cam0, dtype):
    """Float images -> plain float interpolation (no fixed-point emulation), still within the bars."""
    a, b = cam0[11], cam0[12]
    p = gftt(a, 300)
    ref, st_ref = cv_lk(a, b, p)
    out, st = track_lk(t_img(a).to(dtype), t_img(b).to(dtype), t_pts(p).to(dtype))
    assert out.dtype == dtype
    fidelity(f"float mode {dtype}", out[0].numpy(), st[0].numpy(), ref, st_ref)


def test_non_square_window_and_empty(cam0):
    a, b = cam0[2], cam0[3]
    p = gftt(a, 150)
    out, st = track_lk(t_img(a), t_img(b), t_pts(p), win_size=(15, 9), max_level=2)
    ref, st_ref, _ = cv2.calcOpticalFlowPyrLK(a, b, p.reshape(-1, 1, 2), None, winSize=(15, 9), maxLevel=2,
                                              criteria=CRIT)
    fidelity("win 15x9", out[0].numpy(), st[0].numpy(), ref.reshape(-1, 2), st_ref.ravel().astype(bool),
             BIT_IDENTICAL_BAR)
    out, st = track_lk(t_img(a, a), t_img(b, b), torch.zeros(2, 0, 2), forward_backward=True)
    assert out.shape == (2, 0, 2) and st.shape == (2, 0)


# ---------------------------------------------------------------------------------- gradients
def _smooth_pair(shift=(0.7, -0.4), size=24):
    y, x = torch.meshgrid(torch.arange(size, dtype=torch.float64), torch.arange(size, dtype=torch.float64),
                          indexing="ij")

    def f(xx, yy):
        return (120 + 50 * torch.sin(0.45 * xx + 0.2 * yy) + 40 * torch.cos(0.3 * yy - 0.25 * xx)
                + 30 * torch.exp(-((xx - 11) ** 2 + (yy - 13) ** 2) / 18.0))

    return f(x, y)[None, None], f(x - shift[0], y - shift[1])[None, None]


@pytest.mark.parametrize("max_level,win", [(0, 5), (1, 7)])
def test_gradcheck(max_level, win):
    I, J = _smooth_pair(size=24 if max_level == 0 else 32)
    I.requires_grad_()
    J.requires_grad_()
    pts = torch.tensor([[[10.3, 11.6], [13.2, 9.1]]], dtype=torch.float64, requires_grad=True)

    def f(I, J, pts):
        # the unrolled gradient is the derivative of this (unconverged) forward: gradcheck's target
        out, st = track_lk(I, J, pts, win_size=win, max_level=max_level, eps=1e-3, grad_mode="unrolled")
        assert st.all()
        return out

    assert torch.autograd.gradcheck(f, (I.detach(), J.detach(), pts), atol=1e-6, rtol=1e-4)
    assert torch.autograd.gradcheck(f, (I, J, pts.detach()), atol=1e-6, rtol=1e-4, fast_mode=True)


def test_finite_difference_real_crop(cam0):
    """Autograd (unrolled iterations) vs central differences on a real 64x64 crop, win 21, 2 levels."""
    a = torch.from_numpy(cam0[0][180:244, 330:394]).double()[None, None]
    b = torch.from_numpy(cam0[1][180:244, 330:394]).double()[None, None]
    # GFTT corners are integers: there the bilinear template is exactly at a kink (one-sided
    # derivative, central differences average both sides), so move them off the pixel grid
    p = torch.from_numpy(gftt(cam0[0][180:244, 330:394], 4, 8) + np.float32([0.37, 0.21])).double()[None]
    c = torch.randn_like(p, generator=torch.Generator().manual_seed(0))
    kw = dict(max_level=1, eps=1e-4, grad_mode="unrolled")  # what this test measures (the default is implicit)

    def loss(a, b, p):
        out, st = track_lk(a, b, p, **kw)
        assert st.all()
        return (out * c).sum()

    a.requires_grad_(), b.requires_grad_(), p.requires_grad_()
    ga, gb, gp = torch.autograd.grad(loss(a, b, p), (a, b, p))
    assert torch.isfinite(ga).all() and torch.isfinite(gb).all() and torch.isfinite(gp).all()
    with torch.no_grad():
        h = 1e-4
        for k in range(p.shape[1]):
            for d in range(2):
                e = torch.zeros_like(p)
                e[0, k, d] = h
                fd = (loss(a, b, p + e) - loss(a, b, p - e)) / (2 * h)
                assert abs(fd - gp[0, k, d]) <= 1e-3 * (1 + abs(fd)), (k, d, fd, gp[0, k, d])
        # pixels with the largest gradient of each image
        for img, g, which in ((a, ga, 0), (b, gb, 1)):
            for flat in g.abs().flatten().topk(4).indices.tolist():
                e = torch.zeros_like(img).flatten()
                e[flat] = 1e-2
                e = e.view_as(img)
                args_p = (a + e, b, p) if which == 0 else (a, b + e, p)
                args_m = (a - e, b, p) if which == 0 else (a, b - e, p)
                fd = (loss(*args_p) - loss(*args_m)) / 2e-2
                assert abs(fd - g.flatten()[flat]) <= 1e-3 * (1 + abs(fd)), (which, flat, fd)


def test_uint8_straight_through_gradient(cam0):
    """Fixed-point mode still gives (straight-through) gradients w.r.t. the points."""
    a, b = t_img(cam0[0]), t_img(cam0[1])
    p = t_pts(gftt(cam0[0], 20)).requires_grad_()
    out, st = track_lk(a, b, p)
    (g,) = torch.autograd.grad(out[st].sum(), p)
    assert torch.isfinite(g).all() and g.abs().sum() > 0


# ------------------------------------------------------------------------------ input checking
def test_bad_inputs():
    img = torch.zeros(1, 1, 40, 40, dtype=torch.uint8)
    with pytest.raises(ValueError, match="pts"):
        track_lk(img, img, torch.zeros(1, 5, 3))
    with pytest.raises(ValueError, match="batch"):
        track_lk(img, img, torch.zeros(2, 5, 2))
    with pytest.raises(ConfigError):
        track_lk(img, img, torch.zeros(1, 5, 2), win_size=2)
    with pytest.raises(ValueError, match="sizes differ"):
        track_lk(img, torch.zeros(1, 1, 40, 41, dtype=torch.uint8), torch.zeros(1, 5, 2))
    # textureless image: every point fails the eigenvalue test
    out, st = track_lk(img, img, torch.full((1, 5, 2), 20.0))
    assert not st.any() and torch.isfinite(out).all()


def test_early_exit_keyword_is_deprecated(cam0):
    """The old ``early_exit`` keyword still works, as ``capturable = not early_exit``, with a
    ``DeprecationWarning``."""
    a, b = (np.ascontiguousarray(x[150:230, 300:420]) for x in cam0[:2])
    p = t_pts(gftt(a, 20, 6))
    kw = dict(max_level=1)
    for early_exit in (True, False):
        with pytest.warns(DeprecationWarning, match="capturable"):
            got = track_lk(t_img(a), t_img(b), p, early_exit=early_exit, **kw)
        ref = track_lk(t_img(a), t_img(b), p, capturable=not early_exit, **kw)
        assert torch.equal(got[0], ref[0]) and torch.equal(got[1], ref[1]) and ref[1].sum() >= 10
    with pytest.warns(DeprecationWarning):  # early_exit decides when both are given
        got = track_lk(t_img(a), t_img(b), p, capturable=True, early_exit=True, **kw)
    assert torch.equal(got[0], track_lk(t_img(a), t_img(b), p, capturable=False, **kw)[0])


def test_compile_step_is_per_call_and_per_tracker():
    """The compiled iteration kernel is an option of the call (``LKOptions.compile_step``), set by
    ``FeatureTracker.compile()`` on a default-path tracker in that tracker's params only: another
    tracker, and every other call, keep the eager kernel."""
    from torch_frontend import FeatureTracker
    from torch_frontend.lk import LKOptions, eager

    assert LKOptions().compile_step is False and eager._step_kernel(LKOptions()) is eager._lk_step
    o = LKOptions(compile_step={"backend": "eager"})
    assert o.compile_step == (("backend", "eager"), ("dynamic", True)) and hash(o) == hash(LKOptions(**o.__dict__))
    assert LKOptions(compile_step=True).compile_step == (("dynamic", True),)
    with pytest.raises(ConfigError, match="compile_step"):
        LKOptions(compile_step={"options": {"a": 1}})  # not hashable
    a, b = FeatureTracker(REPO / "configs" / "euroc.yaml"), FeatureTracker(REPO / "configs" / "euroc.yaml")
    a.compile(backend="eager")
    assert a.params.lk_options.compile_step == (("backend", "eager"), ("dynamic", True))
    assert b.params.lk_options.compile_step is False and a.params.capturable is False
    assert eager._step_kernel(b.params.lk_options) is eager._lk_step
    assert eager._step_kernel(a.params.lk_options) is eager._step_kernel(a.params.lk_short_options) \
        is not eager._lk_step  # one compiled kernel per setting
    hash(a.params)  # the params stay hashable (static for the compiler)
    a.compile(False)
    assert a.params.lk_options.compile_step is False and a.params == b.params


@pytest.mark.slow
def test_compiled_step_gives_the_same_results(cam0):
    """A call with the compiled iteration kernel (dynamo, eager backend: ~7 s) equals the eager call
    bit for bit."""
    a, b = (np.ascontiguousarray(x[150:230, 300:420]) for x in cam0[:2])
    p = t_pts(gftt(a, 20, 6))
    ref = track_lk(t_img(a), t_img(b), p, max_level=1)
    got = track_lk(t_img(a), t_img(b), p, max_level=1, compile_step={"backend": "eager"})
    assert torch.equal(got[0], ref[0]) and torch.equal(got[1], ref[1]) and ref[1].sum() >= 10
