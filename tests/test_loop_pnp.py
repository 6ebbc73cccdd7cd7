"""Batched PnP-RANSAC (torch_frontend.loop.pnp) against cv2.solvePnPRansac called as VINS does.

Synthetic problems (as the brief states): a random pose, 100 world points in front of the camera
(depth 2..10), projected with f = 460 into a 752 x 480 image (normalized = pixel / 460), 1 px
Gaussian noise, 30 % outliers (random normalized points inside the image).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from torch_frontend.errors import DataError
from torch_frontend.geometry import rodrigues
from torch_frontend.loop.pnp import PnPResult, p3p, pnp_ransac, refine_pnp

THR = 10.0 / 460.0
W2, H2 = 376.0 / 460.0, 240.0 / 460.0  # half image size in normalized units


def make_problems(seeds, n=100, rate=0.3, noise_px=1.0):
    """Stacked numpy problems: X (B, n, 3), p (B, n, 2), R (B, 3, 3), t (B, 3), gt inlier mask (B, n)."""
    out = []
    for seed in seeds:
        rng = np.random.default_rng(seed)
        R, _ = cv2.Rodrigues(rng.normal(0.0, 1.0, 3))
        t = rng.normal(0.0, 1.0, 3)
        z = rng.uniform(2.0, 10.0, n)
        uv = np.stack([rng.uniform(-W2, W2, n), rng.uniform(-H2, H2, n)], -1)
        X = (np.concatenate([uv * z[:, None], z[:, None]], -1) - t) @ R  # R^T (x_cam - t)
        p = uv + rng.normal(0.0, noise_px / 460.0, (n, 2))
        m = int(round(rate * n))
        out_idx = rng.choice(n, m, replace=False)
        p[out_idx] = np.stack([rng.uniform(-W2, W2, m), rng.uniform(-H2, H2, m)], -1)
        # an "outlier" that lands within 2 thresholds of its true projection is no outlier: redraw
        near = np.linalg.norm(p[out_idx] - uv[out_idx], axis=-1) < 2 * THR
        while near.any():
            p[out_idx[near]] = np.stack([rng.uniform(-W2, W2, near.sum()), rng.uniform(-H2, H2, near.sum())], -1)
            near = np.linalg.norm(p[out_idx] - uv[out_idx], axis=-1) < 2 * THR
        gt = np.ones(n, bool)
        gt[out_idx] = False
        out.append((X, p, R, t, gt))
    return [np.stack(a) for a in zip(*out)]


def rot_err_deg(Ra, Rb):
    """Angle of Ra Rb^T in degrees, ``2 asin(|Ra - Rb|_F / sqrt(8))`` (exact for rotations and,
    unlike the arccos of the trace, accurate for tiny angles)."""
    d = np.linalg.norm(np.asarray(Ra, np.float64) - Rb, axis=(-2, -1))
    return np.degrees(2.0 * np.arcsin(np.clip(d / np.sqrt(8.0), 0.0, 1.0)))


def cv_pnp(X, p, rvec0=None, tvec0=None):
    """cv2.solvePnPRansac as VINS calls it (K = I, no distortion, ITERATIVE)."""
    guess = rvec0 is not None
    if not guess:
        rvec0, tvec0 = np.zeros((3, 1)), np.zeros((3, 1))
    return cv2.solvePnPRansac(X, p, np.eye(3), None, rvec0.copy(), tvec0.copy(), useExtrinsicGuess=guess,
                              iterationsCount=100, reprojectionError=THR, confidence=0.99,
                              flags=cv2.SOLVEPNP_ITERATIVE)


def test_p3p_recovers_exact_pose():
    g = torch.Generator().manual_seed(3)
    B = 300
    R = rodrigues(torch.randn(B, 3, generator=g, dtype=torch.float64))
    t = torch.randn(B, 3, generator=g, dtype=torch.float64)
    uv = (torch.rand(B, 3, 2, generator=g, dtype=torch.float64) - 0.5) * 1.6
    z = 2 + 8 * torch.rand(B, 3, 1, generator=g, dtype=torch.float64)
    X = (torch.cat([uv * z, z], -1) - t[:, None]) @ R
    rays = torch.cat([uv, torch.ones_like(z)], -1)
    Rs, ts, ok = p3p(X, rays)
    assert Rs.shape == (B, 4, 3, 3) and ts.shape == (B, 4, 3) and ok.shape == (B, 4)
    err = (Rs - R[:, None]).abs().amax((-1, -2)) + (ts - t[:, None]).abs().amax(-1)
    err = torch.where(ok, err, torch.full_like(err, 1e9)).amin(-1)
    assert float(err.max()) < 1e-9
    # every returned solution is a real P3P solution: the three points reproject onto their rays
    Xc = torch.einsum("bsij,bpj->bspi", Rs, X) + ts[:, :, None]
    proj_err = (Xc[..., :2] / Xc[..., 2:] - uv[:, None]).abs().amax((-1, -2))
    assert float(proj_err[ok].max()) < 1e-9
    assert bool((Xc[..., 2][ok] > 0).all())
    assert torch.isfinite(Rs).all() and torch.isfinite(ts).all()


def test_matches_opencv_64_problems_in_one_call():
    """Seeds 0..63 in ONE call (B = 64): inlier-flag agreement with cv2 >= 98 % (mean over all
    points of all problems) and the median rotation error <= 1.5 x OpenCV's median."""
    B = 64
    X, p, R, t, gt = make_problems(range(B))
    res = pnp_ransac(torch.from_numpy(X), torch.from_numpy(p))
    assert isinstance(res, PnPResult)
    assert res.R.shape == (B, 3, 3) and res.t.shape == (B, 3) and res.inliers.shape == (B, 100) and res.ok.shape == (B,)
    cv_inl = np.zeros((B, 100), bool)
    cv_R = np.zeros((B, 3, 3))
    for b in range(B):
        ok, rvec, tvec, idx = cv_pnp(X[b], p[b])
        assert ok
        cv_inl[b, idx.ravel()] = True
        cv_R[b] = cv2.Rodrigues(rvec)[0]
    assert bool(res.ok.all())
    agree = (res.inliers.numpy() == cv_inl).mean()
    assert agree >= 0.98, agree
    e_ours = rot_err_deg(res.R.numpy(), R)
    e_cv = rot_err_deg(cv_R, R)
    assert np.median(e_ours) <= 1.5 * np.median(e_cv), (np.median(e_ours), np.median(e_cv))
    assert e_ours.max() < 0.5  # no problem is lost (cv2's worst here is ~0.09 deg)
    assert np.linalg.norm(res.t.numpy() - t, axis=-1).max() < 0.05


@pytest.mark.parametrize("rate", [0.3, 0.6])
def test_exact_data(device, dtype, rate):
    B = 6
    X, p, R, t, gt = make_problems(range(100, 100 + B), rate=rate, noise_px=0.0)
    Xt = torch.from_numpy(X).to(device, dtype)
    pt = torch.from_numpy(p).to(device, dtype)
    res = pnp_ransac(Xt, pt, generator=torch.Generator(device=device).manual_seed(1))
    assert bool(res.ok.all())
    assert res.R.dtype == dtype and res.R.device.type == device.type
    tol = 1e-9 if dtype == torch.float64 else 2e-4
    assert float((res.R.cpu().double() - torch.from_numpy(R)).abs().max()) < tol
    assert float((res.t.cpu().double() - torch.from_numpy(t)).abs().max()) < tol
    assert bool((res.inliers.cpu().numpy() == gt).all())


def test_padding_and_valid_mask(device):
    """Different point counts per problem via ``valid``; masked-out slots hold NaN."""
    X, p, R, t, gt = make_problems([7, 8, 9])
    valid = np.ones((3, 100), bool)
    valid[0, 60:] = False
    valid[2, ::3] = False
    Xn, pn = X.copy(), p.copy()
    Xn[~valid] = np.nan
    pn[~valid] = np.nan
    res = pnp_ransac(torch.from_numpy(Xn).to(device), torch.from_numpy(pn).to(device), torch.from_numpy(valid).to(device))
    assert bool(res.ok.all())
    inl = res.inliers.cpu().numpy()
    assert not inl[~valid].any()
    assert (inl[valid] == gt[valid]).mean() > 0.99
    assert rot_err_deg(res.R.cpu().numpy(), R).max() < 0.5


def test_points_behind_camera_are_outliers():
    """A world point mirrored through the camera centre projects to the same normalized point; it
    must not count as an inlier (OpenCV's projectPoints would accept it)."""
    X, p, R, t, gt = make_problems([11], rate=0.0, noise_px=0.0)
    Xc = X[0] @ R[0].T + t[0]
    flip = np.zeros(100, bool)
    flip[::5] = True
    Xc[flip] *= -1.0
    X[0] = (Xc - t[0]) @ R[0]
    res = pnp_ransac(torch.from_numpy(X), torch.from_numpy(p))
    assert bool(res.ok.all())
    assert not res.inliers[0, torch.from_numpy(flip)].any()
    assert bool(res.inliers[0, torch.from_numpy(~flip)].all())
    assert np.abs(res.R.numpy() - R).max() < 1e-9


def test_degenerate_inputs_stay_finite(device, dtype):
    X, p, R, t, gt = make_problems(range(8))
    X, p = X.copy(), p.copy()
    valid = np.ones((8, 100), bool)
    X[0] = X[0, :1]  # all world points identical
    rng = np.random.default_rng(0)
    X[1] = np.array([0.0, 0.0, 5.0]) + rng.uniform(-1, 1, (100, 1)) * np.array([1.0, 0.5, 0.2])  # collinear
    p[2] = p[2, :1]  # all image points identical
    valid[3, 3:] = False  # 3 valid points
    valid[4] = False  # none
    X[5] = 0.0  # everything zero
    p[5] = 0.0
    X[6, :, 2] = 1e30  # absurd but finite depths
    # problem 7 is a normal one
    X[~valid] = np.nan
    p[~valid] = np.nan
    res = pnp_ransac(torch.from_numpy(X).to(device, dtype), torch.from_numpy(p).to(device, dtype),
                     torch.from_numpy(valid).to(device))
    for name in ("R", "t"):
        assert bool(torch.isfinite(getattr(res, name)).all()), name
    ok = res.ok.cpu().numpy()
    assert not ok[[0, 1, 3, 4, 5]].any()
    assert ok[7]
    assert not res.inliers.cpu().numpy()[~ok].any()
    eye = torch.eye(3, dtype=dtype, device=device)
    assert bool((res.R[~res.ok] == eye).all()) and bool((res.t[~res.ok] == 0).all())


def test_gradcheck_refine():
    g = torch.Generator().manual_seed(0)
    X, p, R, t, gt = make_problems([21, 22], n=6, rate=0.0)
    Xt = torch.from_numpy(X).requires_grad_()
    pt = torch.from_numpy(p).requires_grad_()
    w = torch.ones(2, 6, dtype=torch.float64)
    w[1, 0] = 0.0  # a fixed inlier set with one point left out
    R0 = rodrigues(torch.randn(2, 3, generator=g, dtype=torch.float64) * 0.02) @ torch.from_numpy(R)
    t0 = torch.from_numpy(t) + 0.02 * torch.randn(2, 3, generator=g, dtype=torch.float64)

    def f(Xa, pa):
        Rr, tr = refine_pnp(Xa, pa, w, R0, t0, iterations=5)
        return Rr, tr

    assert torch.autograd.gradcheck(f, (Xt, pt), eps=1e-6, atol=1e-6, rtol=1e-4)
    Rr, tr = f(Xt, pt)
    assert rot_err_deg(Rr.detach().numpy(), R).max() < 0.5


def test_pnp_ransac_is_differentiable():
    """Gradients of the refined pose reach points_3d and points_norm (inlier set constant)."""
    X, p, R, t, gt = make_problems([31, 32], n=12, rate=0.0)
    Xt = torch.from_numpy(X).requires_grad_()
    pt = torch.from_numpy(p).requires_grad_()

    def f(Xa, pa):
        res = pnp_ransac(Xa, pa, generator=torch.Generator().manual_seed(0), refine_iters=8)
        return res.R, res.t

    # fast mode (random projections of the Jacobian): every evaluation runs the whole RANSAC
    assert torch.autograd.gradcheck(f, (Xt, pt), eps=1e-6, atol=1e-5, rtol=1e-3, fast_mode=True)
    Rr, tr = f(Xt, pt)
    (Rr.sum() + tr.sum()).backward()
    assert Xt.grad.abs().sum() > 0 and pt.grad.abs().sum() > 0


def test_deterministic():
    X, p, *_ = make_problems(range(4), rate=0.5)
    Xt, pt = torch.from_numpy(X), torch.from_numpy(p)
    a = pnp_ransac(Xt, pt, generator=torch.Generator().manual_seed(5))
    b = pnp_ransac(Xt, pt, generator=torch.Generator().manual_seed(5))
    c = pnp_ransac(Xt, pt)
    d = pnp_ransac(Xt, pt)
    for u, v in ((a, b), (c, d)):
        assert torch.equal(u.R, v.R) and torch.equal(u.t, v.t) and torch.equal(u.inliers, v.inliers)
        assert torch.equal(u.ok, v.ok)


def test_init_guess():
    X, p, R, t, gt = make_problems(range(3))
    Xt, pt = torch.from_numpy(X), torch.from_numpy(p)
    Rg = rodrigues(torch.tensor([[0.5, 0.3, -1.0]] * 3, dtype=torch.float64)) @ torch.from_numpy(R)
    tg = torch.from_numpy(t) + 1.0
    # no model can be found (collinear world points): the guess comes back, no inliers
    X_bad = X.copy()
    X_bad[1] = np.array([0.0, 0.0, 5.0]) + np.linspace(-1, 1, 100)[:, None] * np.array([1.0, 0.3, 0.1])
    res = pnp_ransac(torch.from_numpy(X_bad), pt, init_R=Rg, init_t=tg)
    assert res.ok.tolist() == [True, False, True]
    assert torch.equal(res.R[1], Rg[1]) and torch.equal(res.t[1], tg[1]) and not res.inliers[1].any()
    # a bad guess does not hurt, a good one gives the same pose
    bad = pnp_ransac(Xt, pt, init_R=Rg, init_t=tg)
    good = pnp_ransac(Xt, pt, init_R=torch.from_numpy(R), init_t=torch.from_numpy(t))
    none = pnp_ransac(Xt, pt)
    assert rot_err_deg(bad.R.numpy(), R).max() < 0.5
    assert float((good.R - none.R).abs().max()) < 1e-8 and float((good.t - none.t).abs().max()) < 1e-8
    # fewer than 4 valid points: the guess
    v = torch.zeros(3, 100, dtype=torch.bool)
    v[:, :3] = True
    few = pnp_ransac(Xt, pt, v, init_R=Rg, init_t=tg)
    assert not few.ok.any() and torch.equal(few.R, Rg) and torch.equal(few.t, tg) and not few.inliers.any()


def test_opencv_backend():
    X, p, R, t, gt = make_problems(range(3))
    valid = np.ones((3, 100), bool)
    valid[1, 3:] = False  # 3 points: cv2 raises, reported as ok = False
    Rg = torch.from_numpy(R)
    tg = torch.from_numpy(t)
    res = pnp_ransac(torch.from_numpy(X), torch.from_numpy(p), torch.from_numpy(valid), Rg, tg, backend="opencv")
    assert res.ok.tolist() == [True, False, True]
    assert torch.equal(res.R[1], Rg[1]) and not res.inliers[1].any()
    for b in (0, 2):
        ok, rvec, tvec, idx = cv_pnp(X[b], p[b], cv2.Rodrigues(R[b])[0], t[b].reshape(3, 1))
        assert np.allclose(res.R[b].numpy(), cv2.Rodrigues(rvec)[0]) and np.allclose(res.t[b].numpy(), tvec.ravel())
        assert sorted(np.flatnonzero(res.inliers[b].numpy())) == sorted(idx.ravel().tolist())


def test_input_checks():
    X = torch.zeros(2, 10, 3)
    p = torch.zeros(2, 10, 2)
    with pytest.raises(ValueError, match="points_3d"):
        pnp_ransac(torch.zeros(2, 10, 2), p)
    with pytest.raises(ValueError, match="points_norm"):
        pnp_ransac(X, torch.zeros(2, 9, 2))
    with pytest.raises(ValueError, match="valid"):
        pnp_ransac(X, p, torch.ones(2, 9, dtype=torch.bool))
    with pytest.raises(ValueError, match="init_R"):
        pnp_ransac(X, p, init_R=torch.eye(3).expand(2, 3, 3))
    with pytest.raises(ValueError, match="init_t"):
        pnp_ransac(X, p, init_R=torch.eye(3).expand(2, 3, 3), init_t=torch.zeros(3))
    with pytest.raises(ValueError, match="backend"):
        pnp_ransac(X, p, backend="cuda")
    with pytest.raises(ValueError, match="threshold"):
        pnp_ransac(X, p, threshold=0.0)
    with pytest.raises(TypeError, match="points_norm"):
        pnp_ransac(X, p.double())
    Xn = X.clone()
    Xn[1, 4, 2] = float("nan")
    with pytest.raises(DataError, match=r"points_3d.*problem 1, point 4"):
        pnp_ransac(Xn, p)
    v = torch.ones(2, 10, dtype=torch.bool)
    v[1, 4] = False
    assert pnp_ransac(Xn, p, v).R.shape == (2, 3, 3)  # NaN in a masked-out slot is fine
    with pytest.raises(ValueError, match="weights"):
        refine_pnp(X, p, torch.ones(2, 9), torch.eye(3).expand(2, 3, 3), torch.zeros(2, 3))
