"""Camera derivatives: exact second derivatives of Kannala-Brandt ``lift``, the
``jacobian="implicit"`` (converged) ``lift`` of Pinhole / MEI, and a damped-Newton undistortion
that stays finite where camodocal's fixed point diverges."""

from __future__ import annotations

import pytest
import torch

from torch_frontend.camera import KannalaBrandtCamera, MeiCamera, PinholeCamera
from torch_frontend.camera.base import radtan_undistort_converged

EUROC = dict(k1=-0.28340811, k2=0.07395907, p1=0.00019359, p2=1.76187114e-05, fx=458.654, fy=457.296,
             cx=367.215, cy=248.375)
D = torch.float64


def _grid(W=752, H=480, n=(24, 16)):
    u, v = torch.meshgrid(torch.linspace(0, W, n[0], dtype=D), torch.linspace(0, H, n[1], dtype=D), indexing="ij")
    return torch.stack((u, v), -1).reshape(-1, 2)


def _hessian_error(f, x, w):
    """max |analytic - central-difference| / max |.| of the Hessian of sum(w * f(x)) w.r.t. x."""
    def grad(z):
        z = z.clone().requires_grad_()
        return torch.autograd.grad((f(z) * w).sum(), z, create_graph=True)[0]

    xg = x.clone().requires_grad_()
    g = grad(xg).flatten()
    H = torch.stack([torch.autograd.grad(g[i], xg, retain_graph=True)[0].flatten() for i in range(g.numel())])
    h = 1e-5
    E = torch.eye(x.numel(), dtype=D)
    Hfd = torch.stack([(grad(x + h * E[i].view(x.shape)) - grad(x - h * E[i].view(x.shape))).flatten() / (2 * h)
                       for i in range(x.numel())]).t()
    return float((H - Hfd).abs().max() / Hfd.abs().max())


def test_kannala_brandt_second_derivatives():
    cam = KannalaBrandtCamera(-0.01, 0.05, -0.08, 0.04, 190.0, 190.0, 254.0, 256.0)
    uv = torch.tensor([[100.3, 120.7], [400.1, 30.2], [260.0, 250.0]], dtype=D)
    w = torch.tensor([0.3, -0.7, 0.5], dtype=D)
    # measured: 0.39 with one Newton step on the graph (exact to first order only), 4e-9 with two
    assert _hessian_error(cam.lift, uv, w) < 1e-6
    assert _hessian_error(lambda z: cam.undistort(z), uv, w[:2]) < 1e-6
    # w.r.t. the distortion coefficients too (the root θ of r(θ) = ρ)
    kk = torch.tensor([-0.01, 0.05, -0.08, 0.04], dtype=D, requires_grad=True)
    assert torch.autograd.gradgradcheck(lambda k: _kb_theta(k, uv), (kk,))
    assert torch.equal(cam.lift(uv, jacobian="implicit"), cam.lift(uv))


def _kb_theta(k, uv):
    from torch_frontend.camera.kannala_brandt import effective_coefficients, solve_theta

    px, py = (uv[..., 0] - 254.0) / 190.0, (uv[..., 1] - 256.0) / 190.0
    return solve_theta(torch.sqrt(px * px + py * py), *effective_coefficients(*k.unbind()))


def test_fixed_point_nan_reproduced_and_damped_newton_finite():
    """EuRoC cam0 with k2 = 0 (a plausible perturbation): camodocal's fixed point with 64
    evaluations gives inf/NaN at ~22 % of the pixels; the damped Newton inverse is finite
    everywhere and exact where an inverse exists."""
    p = dict(EUROC, k2=0.0)
    uv = _grid()
    bad = PinholeCamera(*p.values(), undistort_iters=64).undistort(uv)
    assert (~torch.isfinite(bad)).any(-1).double().mean() > 0.1  # the bug, reproduced
    cam = PinholeCamera(*p.values())
    m = cam.undistort(uv, jacobian="implicit")
    assert torch.isfinite(m).all()
    mxd, myd = (uv[:, 0] - p["cx"]) / p["fx"], (uv[:, 1] - p["cy"]) / p["fy"]
    _, _, conv = radtan_undistort_converged(mxd, myd, *(torch.tensor(p[k], dtype=D) for k in ("k1", "k2", "p1", "p2")))
    rt = (cam.project(torch.cat((m, torch.ones_like(m[:, :1])), -1)) - uv).norm(dim=-1)
    assert conv.double().mean() > 0.5 and rt[conv].max() < 1e-6
    # no inverse (beyond the polynomial's turning point): finite value, zero gradient, no NaN
    uvg = uv.clone().requires_grad_()
    (g,) = torch.autograd.grad(cam.undistort(uvg, jacobian="implicit").sum(), uvg)
    assert torch.isfinite(g).all() and (g[~conv] == 0).all() and (g[conv] != 0).any()


@pytest.mark.parametrize("fast", [True, pytest.param(False, marks=pytest.mark.slow)], ids=["fast_mode", "full"])
@pytest.mark.parametrize("model", ["pinhole", "mei"])
def test_implicit_lift_is_converged_inverse(model, fast):
    if model == "pinhole":
        cam = PinholeCamera(*EUROC.values())
    else:
        cam = MeiCamera(1.9, -0.27, 0.06, 0.0003, -0.0002, 780.0, 780.0, 370.0, 250.0)
    uv = _grid(n=(6, 4))
    if model == "mei":  # the central part: these MEI parameters have no ray (z NaN) at the corners
        uv = 0.5 * uv + torch.tensor([188.0, 120.0], dtype=D)
    # default: camodocal's values, unchanged
    P8 = cam.lift(uv)
    Pi = cam.lift(uv, jacobian="implicit")
    assert torch.isfinite(Pi).all()
    rt = (cam.project(Pi) - uv).norm(dim=-1)
    assert rt.max() < 1e-8  # converged (camodocal's 8 evaluations: up to ~0.1 px at EuRoC's corners)
    assert (P8 - Pi).abs().max() > 0 or model == "mei"
    # its Jacobian is that of the converged inverse: d lift / d uv inverts d project / d P on the ray
    x = uv[:5].clone().requires_grad_()
    J = torch.autograd.functional.jacobian(lambda z: cam.undistort(z, jacobian="implicit").sum(0), x).permute(1, 0, 2)
    Pn = cam.undistort(uv[:5], jacobian="implicit")
    Jp = torch.autograd.functional.jacobian(
        lambda m: cam.project(torch.cat((m, torch.ones_like(m[:, :1])), -1)).sum(0), Pn).permute(1, 0, 2)
    torch.testing.assert_close(J @ Jp, torch.eye(2, dtype=D).expand(5, 2, 2), atol=1e-9, rtol=0)
    # first and second derivatives w.r.t. pixels and the distortion coefficients
    # fast_mode (make test): random directions instead of every input, each lift being a Newton solve
    # of ~0.1 s; the full check of every entry runs under the slow marker (make test-all, CI)
    assert torch.autograd.gradcheck(lambda z: cam.lift(z, jacobian="implicit"), (x,), fast_mode=fast)
    assert torch.autograd.gradgradcheck(lambda z: cam.lift(z, jacobian="implicit"), (x,), fast_mode=fast)
    k = torch.tensor([EUROC[n] for n in ("k1", "k2", "p1", "p2")], dtype=D, requires_grad=True)
    mxd, myd = (uv[:5, 0] - 367.2) / 458.6, (uv[:5, 1] - 248.4) / 457.3

    def f(k):
        return torch.stack(radtan_undistort_converged(mxd, myd, *k.unbind())[:2])

    assert torch.autograd.gradcheck(f, (k,), fast_mode=fast) and torch.autograd.gradgradcheck(f, (k,), fast_mode=fast)


def test_jacobian_option_checked():
    cam = PinholeCamera(*EUROC.values())
    with pytest.raises(ValueError):
        cam.lift(torch.zeros(1, 2, dtype=D), jacobian="magic")
