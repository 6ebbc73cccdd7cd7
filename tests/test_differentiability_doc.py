"""``docs/differentiability.md``: every public name is in it, the README links to it, and its most
important claims hold (small float64 probes: what carries a gradient, what is cut, where the
gradient is exactly zero)."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch
from torch.autograd import gradcheck, gradgradcheck

import torch_frontend as tf
import torch_frontend.learn as learn
from tests.conftest import REPO, load_gray, sample_frames
from torch_frontend.camera import (
    KannalaBrandtCamera,
    MeiCamera,
    PinholeCamera,
    PinholeFullCamera,
    ScaramuzzaCamera,
)

DOC = REPO / "docs" / "differentiability.md"
D = torch.float64


def _code_spans(text: str) -> list:
    return re.findall(r"`([^`\n]+)`", text)


@pytest.mark.parametrize("names", [tf.__all__, learn.__all__], ids=["torch_frontend", "torch_frontend.learn"])
def test_every_public_name_is_in_the_doc(names):
    spans = _code_spans(DOC.read_text(encoding="utf-8"))
    missing = [n for n in names if not any(re.search(rf"(?<![\w]){re.escape(n)}(?![\w])", s) for s in spans)]
    assert not missing, f"docs/differentiability.md: no backticked row for {missing}"


def test_readme_links_the_doc():
    assert "docs/differentiability.md" in (REPO / "README.md").read_text(encoding="utf-8")


def _smooth_pair(H=40, W=40, shift=(0.7, -0.4)):
    yy, xx = torch.meshgrid(torch.arange(H, dtype=D), torch.arange(W, dtype=D), indexing="ij")

    def img(dx, dy):
        x, y = xx - dx, yy - dy
        return (100 + 60 * torch.sin(x / 4.0) * torch.cos(y / 5.0)
                + 40 * torch.exp(-((x - 20) ** 2 + (y - 18) ** 2) / 60))[None, None]

    return img(0.0, 0.0), img(*shift)


def test_clahe_output_is_8bit_without_graph():
    img = _smooth_pair(32, 32)[0].clone().requires_grad_()
    out = tf.clahe(img)
    assert out.dtype == torch.uint8 and out.grad_fn is None and not out.requires_grad


def test_track_lk_lost_lanes_implicit_zero_unrolled_identity():
    I, J = _smooth_pair()
    pts0 = torch.tensor([[[15.3, 16.6], [22.2, 14.1], [-80.0, 10.0]]], dtype=D)  # the last: outside
    grads = {}
    for mode in ("implicit", "unrolled"):
        Ig, Jg, p = I.clone().requires_grad_(), J.clone().requires_grad_(), pts0.clone().requires_grad_()
        out, st = tf.track_lk(Ig, Jg, p, win_size=9, max_level=1, grad_mode=mode)
        assert st.tolist() == [[True, True, False]]
        gp, gI, gJ = torch.autograd.grad(out.sum(), (p, Ig, Jg))
        assert torch.isfinite(gp).all() and torch.isfinite(gI).all() and torch.isfinite(gJ).all()
        assert (gp[0, :2].abs().sum(-1) > 0.5).all() and gI.abs().sum() > 0 and gJ.abs().sum() > 0
        grads[mode] = gp[0, 2]
    assert (grads["implicit"] == 0).all()  # status False: exactly zero
    assert (grads["unrolled"] == 1).all()  # the lost lane returns its input: identity


class _Lift(torch.nn.Module):
    """``forward = cam.lift`` so that ``torch.func.functional_call`` can swap the parameters."""

    def __init__(self, cam, jacobian):
        super().__init__()
        self.cam, self.jacobian = cam, jacobian

    def forward(self, uv):
        return self.cam.lift(uv, jacobian=self.jacobian)


def _cameras():
    poly = np.array([-230.0, 0.0, 1.2e-3, -5e-7, 1e-9])  # a plausible OCAM calibration (tests/test_camera.py)
    phi = np.linspace(0.0, 420.0, 4000)
    theta = np.arctan2(np.polynomial.polynomial.polyval(phi, poly), phi)
    inv_poly = np.zeros(20)
    inv_poly[:17] = np.polynomial.polynomial.polyfit(theta, phi, 16)
    return {
        "pinhole": PinholeCamera(-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 458.654, 457.296, 367.215, 248.375),
        "pinhole_full": PinholeFullCamera(-0.28, 0.07, 0.001, 0.01, 0.002, 0.0005, 0.0002, 1e-5, 458.0, 457.0, 367.0, 248.0),
        "mei": MeiCamera(1.9, -0.27, 0.06, 0.0003, -0.0002, 780.0, 780.0, 370.0, 250.0),
        "kb": KannalaBrandtCamera(-0.01, 0.05, -0.08, 0.04, 190.0, 190.0, 254.0, 256.0),
        "scaramuzza": ScaramuzzaCamera(poly, inv_poly, 1.0, 0.001, -0.002, 400.5, 300.25),
    }


@pytest.mark.parametrize("model, jacobian", [("pinhole", "unrolled"), ("pinhole", "implicit"), ("pinhole_full", "unrolled"),
                                             ("mei", "implicit"), ("kb", "unrolled"), ("scaramuzza", "unrolled")])
def test_camera_lift_gradcheck_float64(model, jacobian):
    cam = _cameras()[model]
    uv = torch.tensor([[100.3, 80.7], [300.1, 200.2], [500.5, 400.25]], dtype=D)
    assert not any(p.requires_grad for p in cam.parameters())  # frozen until cam.requires_grad_()
    assert gradcheck(lambda x: cam.lift(x, jacobian=jacobian), (uv.clone().requires_grad_(),))
    assert gradgradcheck(lambda x: cam.lift(x, jacobian=jacobian), (uv.clone().requires_grad_(),))
    mod = _Lift(cam, jacobian)
    names = [n for n, _ in mod.named_parameters()]
    vals = tuple(p.detach().clone().requires_grad_() for _, p in mod.named_parameters())
    # Scaramuzza's inv_poly is used by project only: no gradient from lift
    unused = [n for n in names if n.endswith("inv_poly")]
    used = tuple(v for n, v in zip(names, vals) if n not in unused)
    fixed = {n: v.detach() for n, v in zip(names, vals) if n in unused}

    def f(*pv):
        return torch.func.functional_call(mod, {**dict(zip([n for n in names if n not in unused], pv)), **fixed}, (uv,))

    assert gradcheck(f, used)


def test_camera_axis_jacobians_are_zero_documented_limit():
    """Known limit (docs/differentiability.md): exactly on the axis Kannala-Brandt ``lift`` /
    ``project`` and Scaramuzza ``project`` return a zero Jacobian. If this fails, the limit was
    fixed: update the doc."""
    cams = _cameras()
    kb, sc = cams["kb"], cams["scaramuzza"]

    def jac(f, x):
        return torch.autograd.functional.jacobian(lambda z: f(z)[0], torch.tensor([x], dtype=D))[:, 0]

    assert (jac(kb.lift, [254.0, 256.0]) == 0).all()
    near = jac(kb.lift, [254.0 + 1e-6, 256.0])
    torch.testing.assert_close(near[:2], torch.eye(2, dtype=D) / 190.0)  # 1e-6 px away: 1 / mu
    assert (jac(kb.project, [0.0, 0.0, 1.0]) == 0).all()
    assert (jac(sc.project, [0.0, 0.0, 1.0]) == 0).all()
    assert (jac(sc.project, [1e-6, 0.0, 1.0])[:, :2].diagonal() > 200).all()


@pytest.mark.filterwarnings("ignore:images. the images require a gradient")  # the door says so
def test_default_tracker_cuts_images_keeps_camera_gradients():
    """The default path rounds float images to uint8 (``uv`` has no graph, the images get no
    gradient), while ``xy`` and ``velocity`` carry gradients to a camera that requires them."""
    tr = tf.FeatureTracker(tf.load_config(REPO / "configs" / "euroc.yaml"))
    tr.camera.requires_grad_()
    images = [torch.from_numpy(load_gray(p))[None, None].float().requires_grad_() for p in sample_frames("cam0")[:5]]
    for k, img in enumerate(images):
        fr = tr.track(img, torch.tensor([0.05 * k], dtype=torch.float64))
    assert fr.valid.any()
    assert fr.uv.grad_fn is None and fr.xy.grad_fn is not None and fr.velocity.grad_fn is not None
    m = fr.valid.unsqueeze(-1)
    loss = torch.where(m, fr.xy, 0.0).sum() + torch.where(m, fr.velocity, 0.0).sum()
    params = list(tr.camera.parameters())
    g = torch.autograd.grad(loss, params + images, allow_unused=True)
    assert all(x is not None and torch.isfinite(x).all() for x in g[:len(params)])
    assert sum(float(x.abs().sum()) for x in g[:len(params)]) > 0
    assert all(x is None for x in g[len(params):])


def test_tracking_loss_nan_safe_and_zero_gradient_when_masked():
    tracked = torch.tensor([[[10.0, 12.0], [float("nan"), float("nan")], [5.0, 6.0]]], dtype=D, requires_grad=True)
    target = torch.tensor([[[10.5, 11.0], [1.0, 1.0], [5.0, 6.0]]], dtype=D)  # the last: d = 0
    valid = torch.tensor([[True, False, True]])
    loss = learn.tracking_loss(tracked, valid, target)
    (g,) = torch.autograd.grad(loss, tracked)
    assert torch.isfinite(loss) and torch.isfinite(g).all()
    assert (g[0, 1:] == 0).all() and (g[0, 0] != 0).all()  # masked NaN slot, and epe at d = 0
    assert torch.isnan((tracked * valid.unsqueeze(-1)).sum())  # why: 0 * NaN is NaN
