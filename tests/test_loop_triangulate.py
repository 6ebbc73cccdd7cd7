"""Multi-view triangulation: exact recovery, noise, rejection rules, degenerate input, gradients."""

from __future__ import annotations

import math

import pytest
import torch

from torch_frontend.geometry import quat_to_R, ypr_to_R
from torch_frontend.loop.triangulate import DEFAULT_MAX_REPROJ, camera_poses, triangulate_points


def scene(P=40, F=6, seed=0, noise=0.0, baseline=2.0, depth=6.0):
    """Cameras spread along world x looking roughly along +z; points in front of all of them.

    Returns float64 ``R_wc, t_wc, obs, X_true`` (camera-to-world poses)."""
    g = torch.Generator().manual_seed(seed)
    t_wc = torch.stack([torch.linspace(-baseline / 2, baseline / 2, F, dtype=torch.float64),
                        0.1 * torch.randn(F, generator=g, dtype=torch.float64),
                        0.1 * torch.randn(F, generator=g, dtype=torch.float64)], -1) + torch.tensor(
        [10.0, -20.0, 3.0], dtype=torch.float64)  # away from the origin: conditioning matters
    R_wc = ypr_to_R(torch.randn(F, 3, generator=g, dtype=torch.float64) * 4)
    X = torch.randn(P, 3, generator=g, dtype=torch.float64) * torch.tensor([2.0, 1.5, 1.0], dtype=torch.float64)
    X = X + torch.tensor([10.0, -20.0, 3.0 + depth], dtype=torch.float64)
    obs = project(R_wc, t_wc, X)
    obs = obs + noise * torch.randn(obs.shape, generator=g, dtype=torch.float64)
    return R_wc, t_wc, obs, X


def project(R_wc, t_wc, X):
    Pc = torch.einsum("fji,pfj->pfi", R_wc, X[:, None] - t_wc)  # R_wc^T (X - t_wc)
    return Pc[..., :2] / Pc[..., 2:]


def to(dev, dt, *xs):
    return [x.to(dev, dt) if x.is_floating_point() else x.to(dev) for x in xs]


def test_exact_recovery_noiseless(device, dtype):
    R, t, obs, X = scene(P=60, F=7)
    g = torch.Generator().manual_seed(5)
    mask = torch.rand(60, 7, generator=g) < 0.6
    mask[:, 0] = mask[:, -1] = True  # at least 2 views with a full baseline
    obs = torch.where(mask[..., None], obs, torch.full_like(obs, float("nan")))  # unobserved: garbage
    R, t, obs, mask = to(device, dtype, R, t, obs, mask)
    Xe, ok = triangulate_points(R, t, obs, mask)
    assert Xe.dtype == dtype and Xe.device.type == device.type and ok.shape == (60,)
    assert ok.all()
    tol = 1e-9 if dtype == torch.float64 else 2e-4  # float32 world coords of size ~20 m
    assert (Xe.cpu().double() - X).abs().max() < tol


def test_dlt_alone_is_exact_and_refine_keeps_it():
    R, t, obs, X = scene()
    mask = torch.ones(40, 6, dtype=torch.bool)
    X0, ok0 = triangulate_points(R, t, obs, mask, refine_iters=0)
    X3, ok3 = triangulate_points(R, t, obs, mask, refine_iters=3)
    assert (X0 - X).abs().max() < 1e-8 and (X3 - X).abs().max() < 1e-9
    assert ok0.all() and ok3.all()


def test_batched_leading_dims_match_single():
    a, b = scene(seed=1), scene(seed=2, F=6)
    R = torch.stack([a[0], b[0]])
    t = torch.stack([a[1], b[1]])
    obs = torch.stack([a[2], b[2]])
    mask = torch.ones(2, 40, 6, dtype=torch.bool)
    mask[1, :5, 2:] = False
    Xb, okb = triangulate_points(R, t, obs, mask)
    assert Xb.shape == (2, 40, 3) and okb.shape == (2, 40)
    for i in range(2):
        Xi, oki = triangulate_points(R[i], t[i], obs[i], mask[i])
        assert torch.allclose(Xb[i], Xi, atol=1e-12) and torch.equal(okb[i], oki)
    # two leading dims
    X4, ok4 = triangulate_points(R[None], t[None], obs[None], mask[None])
    assert X4.shape == (1, 2, 40, 3) and torch.allclose(X4[0], Xb)


def test_noise_refinement_lowers_reprojection_error_and_scales():
    sigma = 1.0 / 460.0  # 1 px
    R, t, obs, X = scene(P=400, F=8, noise=sigma, seed=3)
    mask = torch.ones(400, 8, dtype=torch.bool)

    def rms(Xe):
        return (project(R, t, Xe) - obs).pow(2).sum(-1).mean(-1).sqrt()

    X0, _ = triangulate_points(R, t, obs, mask, refine_iters=0)
    X3, ok = triangulate_points(R, t, obs, mask, refine_iters=3)
    assert (rms(X3) <= rms(X0) + 1e-12).all()  # Gauss-Newton never makes it worse
    assert rms(X3).mean() < rms(X0).mean()
    # the residual of the optimum ~ sigma * sqrt(1 - 3 / (2F)) per coordinate
    assert rms(X3).mean() / math.sqrt(2) == pytest.approx(sigma * math.sqrt(1 - 3 / 16), rel=0.1)
    assert ok.float().mean() > 0.8  # 3 px default gate: most points pass
    # 3D error grows linearly with the noise
    e1 = (X3 - X).norm(dim=-1).median()
    R2, t2, obs2, _ = scene(P=400, F=8, noise=2 * sigma, seed=3)
    e2 = (triangulate_points(R2, t2, obs2, mask)[0] - X).norm(dim=-1).median()
    assert 1.6 < float(e2 / e1) < 2.4 and float(e1) < 0.05


def test_rejections(device, dtype):
    R, t, obs, X = scene(P=6, F=4)
    mask = torch.ones(6, 4, dtype=torch.bool)
    mask[0, 1:] = False  # 1 view
    mask[1, 2:] = False  # 2 views: fine with min_views=2, rejected with 3
    obs = obs.clone()
    obs[2, 3] += 10 * DEFAULT_MAX_REPROJ  # a gross outlier in one view
    R, t, obs, mask = to(device, dtype, R, t, obs, mask)
    _, ok = triangulate_points(R, t, obs, mask)
    assert ok.tolist() == [False, True, False, True, True, True]
    _, ok = triangulate_points(R, t, obs, mask, min_views=3)
    assert ok.tolist() == [False, False, False, True, True, True]
    _, ok = triangulate_points(R, t, obs, mask, max_reproj=1.0)  # loose gate: the outlier passes
    assert ok.tolist() == [False, True, True, True, True, True]
    _, ok = triangulate_points(R, t, obs, mask, min_parallax_deg=60.0)  # ~20 degrees here
    assert not ok.any()


def test_zero_baseline_and_behind_camera_rejected():
    # zero baseline: pure rotation, same centre; observations of real points
    R, t, obs, X = scene(P=10, F=4)
    t0 = t[:1].expand(4, 3).clone()
    obs0 = project(R, t0, X)
    mask = torch.ones(10, 4, dtype=torch.bool)
    X0, ok = triangulate_points(R, t0, obs0, mask)
    assert not ok.any() and torch.isfinite(X0).all()
    # behind: points mirrored behind every camera project to valid-looking observations
    Rb, tb = torch.eye(3, dtype=torch.float64).expand(3, 3, 3).clone(), torch.zeros(3, 3, dtype=torch.float64)
    tb[:, 0] = torch.tensor([-1.0, 0.0, 1.0])
    Xb = torch.tensor([[0.3, 0.2, -5.0], [0.0, -0.5, -3.0], [0.2, 0.1, 4.0]], dtype=torch.float64)
    ob = project(Rb, tb, Xb)
    Xe, ok = triangulate_points(Rb, tb, ob, torch.ones(3, 3, dtype=torch.bool))
    assert ok.tolist() == [False, False, True]
    assert torch.allclose(Xe, Xb, atol=1e-9)  # the geometry is recovered, just rejected


def test_degenerate_inputs_stay_finite_with_finite_gradients():
    R, t, obs, X = scene(P=6, F=4)
    R, t = R.clone(), t.clone()
    t[1] = t[0]
    R[1] = R[0]  # two identical cameras
    obs = project(R, t, X)
    obs[4, 1] = obs[4, 0]  # point 4: identical rays from the two identical cameras
    mask = torch.ones(6, 4, dtype=torch.bool)
    mask[0] = False  # no view at all
    mask[1, 1:] = False  # one view
    mask[4, 2:] = False
    obs[0] = float("nan")  # unobserved entries are never read
    obs[1, 1:] = float("inf")
    obs.requires_grad_(True)
    Rg = R.clone().requires_grad_(True)
    tg = t.clone().requires_grad_(True)
    Xe, ok = triangulate_points(Rg, tg, obs, mask)
    assert torch.isfinite(Xe).all()
    assert ok.tolist() == [False, False, True, True, False, True]
    (Xe * ok[:, None]).sum().backward()  # the usual loss: rejected lanes get zero gradient
    for g in (obs.grad, Rg.grad, tg.grad):
        assert torch.isfinite(g).all()
    assert (obs.grad[[0, 1, 4]] == 0).all()
    # every camera identical, every point: finite, all rejected
    Xs, oks = triangulate_points(R[:1].expand(4, 3, 3), t[:1].expand(4, 3), obs.detach().nan_to_num(0, 0, 0),
                                 torch.ones(6, 4, dtype=torch.bool))
    assert torch.isfinite(Xs).all() and not oks.any()
    # nothing observed at all
    Xn, okn = triangulate_points(R, t, obs.detach(), torch.zeros(6, 4, dtype=torch.bool))
    assert torch.isfinite(Xn).all() and not okn.any()


def test_gradcheck_obs_and_poses():
    R, t, obs, X = scene(P=2, F=3, noise=1e-3, seed=7)
    mask = torch.ones(2, 3, dtype=torch.bool)

    def f(R_, t_, o_):
        return triangulate_points(R_, t_, o_, mask, refine_iters=2)[0]

    assert torch.autograd.gradcheck(f, (R.clone().requires_grad_(), t.clone().requires_grad_(),
                                        obs.clone().requires_grad_()), eps=1e-7, atol=1e-5, rtol=1e-4)


def test_camera_poses_composition():
    R_w_i = ypr_to_R(torch.tensor([[30.0, 5.0, -3.0], [100.0, 0.0, 2.0]], dtype=torch.float64))
    T_w_i = torch.tensor([[1.0, 2.0, 3.0], [-1.0, 0.0, 0.5]], dtype=torch.float64)
    R_ic = quat_to_R(torch.tensor([0.5, -0.5, 0.5, -0.5], dtype=torch.float64))
    t_ic = torch.tensor([0.05, -0.02, 0.01], dtype=torch.float64)
    R_wc, t_wc = camera_poses(R_w_i, T_w_i, R_ic, t_ic)
    Xc = torch.tensor([0.1, 0.2, 3.0], dtype=torch.float64)
    for k in range(2):  # camera -> body -> world equals camera -> world
        Xw = R_w_i[k] @ (R_ic @ Xc + t_ic) + T_w_i[k]
        assert torch.allclose(R_wc[k] @ Xc + t_wc[k], Xw, atol=1e-12)
    with pytest.raises(ValueError, match=r"t_ic: expected shape \(\.\.\., 3\), got \(4,\)"):
        camera_poses(R_w_i, T_w_i, R_ic, torch.zeros(4))


def test_shape_errors_name_the_argument():
    R, t, obs, _ = scene(P=3, F=4)
    mask = torch.ones(3, 4, dtype=torch.bool)
    with pytest.raises(ValueError, match=r"t_wc: expected shape \(4, 3\)"):
        triangulate_points(R, t[:3], obs, mask)
    with pytest.raises(ValueError, match=r"obs_norm: expected shape \('P', 4, 2\)"):
        triangulate_points(R, t, obs[:, :3], mask)
    with pytest.raises(ValueError, match=r"mask: expected shape \(3, 4\)"):
        triangulate_points(R, t, obs, mask[:2])
    with pytest.raises(TypeError, match="mask: expected torch.bool"):
        triangulate_points(R, t, obs, mask.float())
    with pytest.raises(ValueError, match="min_views"):
        triangulate_points(R, t, obs, mask, min_views=1)
    with pytest.raises(ValueError, match=r"R_wc: expected shape"):
        triangulate_points(R[..., :2], t, obs, mask)
