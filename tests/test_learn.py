"""``torch_frontend.learn``: tracking losses (masked, NaN-safe), the soft / straight-through status,
and the ``nn.Module`` wrappers (``LucasKanade``, ``TrackerModule``)."""

from __future__ import annotations

import math

import pytest
import torch
from torch.autograd import gradcheck, gradgradcheck

import torch_frontend as tf
from torch_frontend.cli import default_config_path
from torch_frontend.learn import (
    LucasKanade,
    TrackerModule,
    homography_targets,
    sample_flow,
    soft_status,
    tracking_loss,
)

from .conftest import DEVICES, load_gray, sample_frames

CFG = default_config_path()
F64 = torch.float64


def _pts(B=2, N=7, seed=0, dtype=F64):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(B, N, 2, generator=g, dtype=dtype) * 40 + 5)


# ---------------------------------------------------------------------------------------------
# tracking_loss


@pytest.mark.parametrize("loss", ["epe", "l1", "l2", "huber", "charbonnier"])
def test_loss_values_against_the_formulas(loss):
    tracked = torch.tensor([[[3.0, 4.0], [0.5, 0.0], [9.0, 9.0]]], dtype=F64)
    target = torch.zeros_like(tracked)
    valid = torch.tensor([[True, True, False]])
    e = torch.tensor([5.0, 0.5], dtype=F64)
    d = torch.tensor([[3.0, 4.0], [0.5, 0.0]], dtype=F64)
    want = {"epe": e, "l1": d.abs().sum(-1), "l2": e**2,
            "huber": torch.where(e <= 1, 0.5 * e**2, e - 0.5),
            "charbonnier": torch.sqrt(e**2 + 1) - 1}[loss]
    got = tracking_loss(tracked, valid, target, loss=loss, reduction="none")
    torch.testing.assert_close(got[0, :2], want)
    assert got[0, 2] == 0
    torch.testing.assert_close(tracking_loss(tracked, valid, target, loss=loss), want.mean())
    torch.testing.assert_close(tracking_loss(tracked, valid, target, loss=loss, reduction="sum"), want.sum())


def test_loss_is_nan_safe_and_masked_points_get_no_gradient():
    """NaN / inf in masked slots (tracked, target or weights) reach neither the value nor the
    gradient; with no point left the mean is 0 with a zero gradient."""
    tracked = _pts(1, 4).requires_grad_()
    target = tracked.detach() + 1.0
    with torch.no_grad():
        bad = tracked.clone()
        bad[0, 1] = float("nan")
    bad.requires_grad_()
    target[0, 2] = float("inf")
    valid = torch.tensor([[True, False, True, True]])
    out = tracking_loss(bad, valid, target)
    assert torch.isfinite(out)
    g, = torch.autograd.grad(out, bad)
    assert torch.isfinite(g).all() and (g[0, 1] == 0).all() and (g[0, 2] == 0).all() and (g[0, 0] != 0).all()
    none = tracking_loss(bad, torch.zeros_like(valid), target)
    g0, = torch.autograd.grad(none, bad)
    assert none == 0 and (g0 == 0).all()


def test_epe_gradient_is_zero_not_nan_at_zero_error():
    x = _pts(1, 3).requires_grad_()
    out = tracking_loss(x, torch.ones(1, 3, dtype=torch.bool), x.detach().clone())
    g, = torch.autograd.grad(out, x)
    assert out == 0 and (g == 0).all()


def test_soft_weights_weight_the_mean():
    tracked = torch.tensor([[[1.0, 0.0], [3.0, 0.0]]], dtype=F64)
    w = torch.tensor([[1.0, 0.25]], dtype=F64)
    out = tracking_loss(tracked, w, torch.zeros_like(tracked))
    torch.testing.assert_close(out, torch.tensor((1.0 * 1 + 0.25 * 3) / 1.25, dtype=F64))


def test_homography_and_flow_targets():
    start = _pts(2, 5)
    H = torch.eye(3, dtype=F64).repeat(2, 1, 1)
    H[0, :2, 2] = torch.tensor([2.0, -1.0], dtype=F64)
    H[1] = torch.tensor([[1.01, 0.02, 1.0], [-0.01, 0.99, 0.5], [1e-4, -2e-4, 1.0]], dtype=F64)
    tgt, ok = homography_targets(start, H)
    h = torch.cat((start, torch.ones_like(start[..., :1])), -1) @ H.transpose(1, 2)
    torch.testing.assert_close(tgt, h[..., :2] / h[..., 2:])
    assert ok.all()
    # the same loss from the homography, from per-point flow and from a dense field
    tracked = tgt + 0.3
    valid = torch.ones(2, 5, dtype=torch.bool)
    a = tracking_loss(tracked, valid, start=start, homography=H)
    b = tracking_loss(tracked, valid, start=start, flow=tgt - start)
    torch.testing.assert_close(a, b)
    torch.testing.assert_close(a, torch.tensor(0.3 * math.sqrt(2), dtype=F64))
    # a constant dense field sampled anywhere inside gives that flow; outside the image: masked
    field = torch.zeros(2, 2, 60, 70, dtype=F64)
    field[:, 0], field[:, 1] = 1.5, -0.5
    f, ok = sample_flow(field, torch.tensor([[[10.2, 20.7], [80.0, 5.0]]] * 2, dtype=F64))
    torch.testing.assert_close(f[:, 0], torch.tensor([[1.5, -0.5]] * 2, dtype=F64))
    assert ok[:, 0].all() and not ok[:, 1].any() and (f[:, 1] == 0).all()


def test_loss_argument_errors_name_the_argument():
    x = _pts(1, 3)
    v = torch.ones(1, 3, dtype=torch.bool)
    with pytest.raises(ValueError, match="exactly one of"):
        tracking_loss(x, v)
    with pytest.raises(ValueError, match="needs start"):
        tracking_loss(x, v, homography=torch.eye(3, dtype=F64)[None])
    with pytest.raises(ValueError, match="valid: expected shape"):
        tracking_loss(x, v[:, :2], x)
    with pytest.raises(ValueError, match="loss: expected one of"):
        tracking_loss(x, v, x, loss="l3")


@pytest.mark.parametrize("loss", ["epe", "huber", "charbonnier", "l2"])
def test_loss_gradcheck_and_gradgradcheck(loss):
    start = _pts(1, 4)
    H = torch.eye(3, dtype=F64)[None].clone()
    H[0, :2, 2] = torch.tensor([1.0, 2.0], dtype=F64)
    tracked = (start + torch.tensor([1.5, 1.0], dtype=F64)).requires_grad_()
    w = torch.tensor([[1.0, 0.5, 0.3, 0.2]], dtype=F64, requires_grad=True)  # > 0: w = 0 is the mask's edge
    Hp = H.requires_grad_()
    fn = lambda t, w, Hm: tracking_loss(t, w, start=start, homography=Hm, loss=loss)  # noqa: E731
    assert gradcheck(fn, (tracked, w, Hp))
    assert gradgradcheck(fn, (tracked, w, Hp))


# ---------------------------------------------------------------------------------------------
# soft status


def _blob_images(B=1, H=48, W=56, shift=(1.3, -0.7), dtype=F64):
    ys, xs = torch.meshgrid(torch.arange(H, dtype=dtype), torch.arange(W, dtype=dtype), indexing="ij")

    def img(dx, dy):
        return 128 + 60 * torch.sin((xs - dx) / 4.0) * torch.cos((ys - dy) / 5.0)

    return img(0, 0).expand(B, 1, H, W).clone(), img(*shift).expand(B, 1, H, W).clone()


def test_soft_status_values_and_straight_through():
    I, J = _blob_images()
    pts = torch.tensor([[[20.0, 20.0], [30.0, 24.0], [0.2, 24.0], [30.0, 24.0]]], dtype=F64)
    good = pts + torch.tensor([1.3, -0.7], dtype=F64)
    tracked = good.clone()
    tracked[0, 1] += 6.0  # a wrong match
    tracked[0, 2, 0] = -0.4  # left the inBorder region
    status = torch.tensor([[True, True, True, False]])
    s = soft_status(I, J, pts, tracked, status)
    assert s[0, 0] > 0.95 and s[0, 1] < s[0, 0] and s[0, 2] < 0.2 and s[0, 3] == 0
    st = soft_status(I, J, pts, tracked, status, mode="straight_through")
    torch.testing.assert_close(st, status.to(F64))
    t = tracked.clone().requires_grad_()
    g_soft, = torch.autograd.grad(soft_status(I, J, pts, t, status).sum(), t)
    g_st, = torch.autograd.grad(soft_status(I, J, pts, t, status, mode="straight_through").sum(), t)
    torch.testing.assert_close(g_soft, g_st)
    assert (g_soft[0, 3] == 0).all() and g_soft[0, 1].abs().sum() > 0


def test_soft_status_gradcheck_wrt_points_and_images():
    I, J = _blob_images(H=32, W=36)
    pts = torch.tensor([[[15.3, 14.6], [18.2, 12.1]]], dtype=F64)
    tracked = (pts + torch.tensor([1.1, -0.4], dtype=F64)).requires_grad_()
    Ig, Jg = I.requires_grad_(), J.requires_grad_()
    fn = lambda t, a, b: soft_status(a, b, pts, t, win_size=5, sigma=8.0)  # noqa: E731
    assert gradcheck(fn, (tracked, Ig, Jg), atol=1e-6)
    # second order w.r.t. the tracked points (bilinear sampling is piecewise linear in the images)
    assert gradgradcheck(lambda t: soft_status(I.detach(), J.detach(), pts, t, win_size=5, sigma=8.0), (tracked,),
                         atol=1e-6)


def test_soft_status_refuses_bad_settings():
    I, J = _blob_images()
    p = _pts(1, 2)
    with pytest.raises(ValueError, match="mode"):
        soft_status(I, J, p, p, mode="fuzzy")
    with pytest.raises(ValueError, match="sigma"):
        soft_status(I, J, p, p, sigma=0)
    with pytest.raises(ValueError, match="tracked: expected shape"):
        soft_status(I, J, p, p[:, :1])


# ---------------------------------------------------------------------------------------------
# modules


def _two_frames():
    a, b = (torch.from_numpy(load_gray(f))[None, None] for f in sample_frames("cam0")[:2])
    pts, valid = tf.good_features_to_track(a, 60, 0.01, 30)
    return a, b, pts, valid


@pytest.mark.parametrize("status", ["hard", "soft", "straight_through"])
def test_lucas_kanade_module_is_track_lk(status):
    a, b, pts, valid = _two_frames()
    lk = LucasKanade(status=status)
    out, st = lk(a, b, pts, valid)
    ref, ref_st = tf.track_lk(a, b, pts, valid)
    assert torch.equal(out, ref)
    if status == "hard":
        assert torch.equal(st, ref_st)
    else:
        assert st.dtype == out.dtype and ((st > 0) <= ref_st).all()
        if status == "straight_through":
            assert torch.equal(st, ref_st.to(st.dtype))
    assert "grad_mode='implicit'" in repr(lk)


def test_lucas_kanade_module_trains_an_image_without_clipping():
    """Gradients through the module (implicit mode) to a float image are finite and reduce the loss."""
    a, b, pts, valid = _two_frames()
    lk = LucasKanade(max_level=2)
    x = a.float().requires_grad_()
    out, st = lk(x, b.float(), pts, valid)
    loss = tracking_loss(out, st & valid, target=pts)
    g, = torch.autograd.grad(loss, x)
    assert torch.isfinite(g).all() and g.abs().max() > 0


def test_lucas_kanade_module_refuses_unknown_modes():
    with pytest.raises(ValueError, match="grad_mode"):
        LucasKanade(grad_mode="approx")
    with pytest.raises(ValueError, match="status"):
        LucasKanade(status="fuzzy")


@pytest.mark.parametrize("device", DEVICES)
def test_tracker_module_state_dict_to_and_forward(device):
    m = TrackerModule(CFG, 2).to(device)
    assert m.tracker.device.type == torch.device(device).type and m.tracker.params.differentiable
    keys = set(m.state_dict())
    assert {"camera.fx", "camera.fy", "camera.cx", "camera.cy", "camera.k1"} <= keys
    assert all(p.device.type == torch.device(device).type and p.dtype == F64 for p in m.parameters())
    m2 = TrackerModule(CFG, 2)
    sd = {k: v.clone() for k, v in m.state_dict().items()}
    sd["camera.fx"] += 1.0
    m2.load_state_dict(sd)
    assert float(m2.camera.fx) == float(m.camera.fx) + 1.0
    ref = tf.FeatureTracker(CFG, 2, device=device)
    s, s_ref = m.initial_state(), ref.initial_state()
    for f in sample_frames("cam0")[:4]:
        img = torch.from_numpy(load_gray(f))[None, None].expand(2, 1, -1, -1).to(device)
        t = [int(f.stem) * 1e-9] * 2
        s, fr = m(s, img.float(), t)
        s_ref, fr_ref = ref.step(s_ref, img, t)
        assert torch.equal(fr.uv.detach(), fr_ref.uv) and torch.equal(fr.ids, fr_ref.ids)


@pytest.mark.parametrize("cast", ["float", "half", "to_float32"])
def test_tracker_module_dtype_casts_keep_the_cameras_float64_values(cast):
    """``.float()`` / ``.half()`` / ``.to(torch.float32)`` leave the camera parameters float64 with
    their exact values (a cast to float32 and back would round fx = 458.654 to 458.6539916...)."""
    m = TrackerModule(CFG, 1)
    before = {k: v.clone() for k, v in m.state_dict().items()}
    {"float": m.float, "half": m.half, "to_float32": lambda: m.to(torch.float32)}[cast]()
    after = m.state_dict()
    assert all(after[k].dtype == F64 and torch.equal(after[k], v) for k, v in before.items())
    assert torch.equal(m.tracker.params.camera.fx, before["camera.fx"])


def test_tracker_module_camera_parameters_train():
    m = TrackerModule(CFG, 1)
    m.camera.requires_grad_()
    params = [p for p in m.parameters() if p.requires_grad]
    assert len(params) == 8
    s = m.initial_state()
    for f in sample_frames("cam0")[:5]:
        s, fr = m(s, torch.from_numpy(load_gray(f))[None, None].float(), [int(f.stem) * 1e-9])
    loss = (fr.xy * fr.present.unsqueeze(-1)).square().sum()
    grads = torch.autograd.grad(loss, params)
    assert all(torch.isfinite(g) for g in grads) and sum(float(g.abs()) > 0 for g in grads) >= 6
