"""``FeatureTracker(..., differentiable=True)``: the 8-bit path's values bit for bit, with gradients
from ``uv`` / ``xy`` / ``velocity`` to the images (this step's and, through the state, earlier
ones) and to the camera parameters; BPTT, truncation and checkpointing over ``step``."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.utils._pytree as pytree
from torch.utils.checkpoint import checkpoint

import torch_frontend as tf
from torch_frontend.cli import default_config_path
from torch_frontend.equalize import _clahe_impl, _clahe_slope, _clahe_straight_through
from torch_frontend.learn import tracking_loss

from .conftest import DEVICES, REPO, load_gray, sample_frames

CFG = default_config_path()  # EuRoC cam0, equalize: 1 (CLAHE on)
STEREO = REPO / "configs" / "euroc_stereo_mei.yaml"
FLOAT_FIELDS = ("uv", "xy", "velocity")


def _frames(n, camera="cam0"):
    return [(int(f.stem) * 1e-9, torch.from_numpy(load_gray(f))[None, None]) for f in sample_frames(camera)[:n]]


def _tensors(tree):
    return [x for x in pytree.tree_leaves(tree) if isinstance(x, torch.Tensor)]


def _identical(a, b) -> bool:
    ta, tb = _tensors(a), _tensors(b)
    return len(ta) == len(tb) and all(x.dtype == y.dtype and x.shape == y.shape and torch.equal(x.detach(), y.detach())
                                      for x, y in zip(ta, tb))


def _batch(frames, k, shift):
    """Two streams: the sequence, and the same sequence ``shift`` frames later (different images)."""
    t0, a = frames[k]
    _, b = frames[min(k + shift, len(frames) - 1)]
    return torch.tensor([t0, t0], dtype=torch.float64), torch.cat((a, b))


# ---------------------------------------------------------------------------------------------
# the same outputs as the 8-bit path


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("capturable", [False, True], ids=["eager", "capturable"])
def test_outputs_equal_the_uint8_path_on_integer_images(device, capturable):
    """Mono with CLAHE, two streams, 8 frames (5 on the capturable path, ~10x slower on the CPU; the
    golden battery runs it longer): every field of every frame and the final state are identical
    (values, dtypes), with float images that require a gradient."""
    frames = _frames(5 if capturable else 8)
    ref = tf.FeatureTracker(CFG, 2, device=device, capturable=capturable)
    dif = tf.FeatureTracker(CFG, 2, device=device, capturable=capturable, differentiable=True)
    s_ref, s_dif = ref.initial_state(), dif.initial_state()
    published = 0
    for k in range(len(frames)):
        t, u8 = _batch(frames, k, 2)
        x = u8.to(device, torch.float32).requires_grad_()
        s_ref, f_ref = ref.step(s_ref, u8, t)
        s_dif, f_dif = dif.step(s_dif, x, t)
        assert _identical(f_ref, f_dif), f"frame {k} differs"
        published += int(f_ref.valid.sum())
        if f_ref.valid.any():
            assert f_dif.uv.requires_grad and f_dif.xy.requires_grad
    assert published > 200  # the comparison covered tracked features
    assert _identical(s_ref.features, s_dif.features)


def test_fusion_stereo_outputs_equal_the_uint8_path():
    left, right = _frames(5, "cam0"), _frames(5, "cam1")
    ref = tf.FeatureTracker(STEREO, 1, mode="fusion")
    dif = tf.FeatureTracker(STEREO, 1, mode="fusion", differentiable=True)
    s_ref, s_dif = ref.initial_state(), dif.initial_state()
    for (t, a), (_, b) in zip(left, right):
        s_ref, f_ref = ref.step(s_ref, a, [t], right=b)
        s_dif, f_dif = dif.step(s_dif, a.float().requires_grad_(), [t], right=b.float().requires_grad_())
        assert _identical(f_ref, f_dif)
    assert f_dif.right_uv.requires_grad and int(f_dif.right_valid.sum()) > 20


def test_non_integer_images_are_the_rounded_images_with_gradients():
    """Float images are rounded half to even and clamped as the 8-bit door does (the values are
    those of the rounded uint8 images); the gradient passes straight through the rounding."""
    frames = _frames(6)
    g = torch.Generator().manual_seed(0)
    ref = tf.FeatureTracker(CFG, 1)
    dif = tf.FeatureTracker(CFG, 1, differentiable=True)
    s_ref, s_dif = ref.initial_state(), dif.initial_state()
    for t, u8 in frames:
        x = (u8.double() + torch.rand(u8.shape, generator=g, dtype=torch.float64) - 0.5) * 1.02 - 1.0  # some < 0, > 255
        s_ref, f_ref = ref.step(s_ref, x.round().clamp(0, 255).to(torch.uint8), [t])
        s_dif, f_dif = dif.step(s_dif, x.requires_grad_(), [t])
        assert _identical(f_ref, f_dif)
    gx, = torch.autograd.grad((f_dif.uv * f_dif.present.unsqueeze(-1)).sum(), x)
    assert gx.dtype == torch.float64 and torch.isfinite(gx).all() and gx.abs().sum() > 0


def test_a_float_image_with_a_gradient_warns_on_the_8bit_path():
    t, u8 = _frames(1)[0]
    tr = tf.FeatureTracker(CFG, 1)
    with pytest.warns(UserWarning, match="differentiable=True"):
        tr.track(u8.float().requires_grad_(), [t])


# ---------------------------------------------------------------------------------------------
# gradients


def _run(tracker, frames, images, state=None, detach_at=()):
    state = tracker.initial_state() if state is None else state
    out = []
    for k, ((t, _), x) in enumerate(zip(frames, images)):
        if k in detach_at:
            state = state.detach()
        state, fr = tracker.step(state, x, [t])
        out.append(fr)
    return state, out


def test_bptt_over_three_frames_through_step():
    """A loss on the third tracked frame's pixels reaches all three images through the state (BPTT);
    ``state.detach()`` before the last step truncates it to the last image, whose gradient is the
    same either way (it enters only in the last step)."""
    frames = _frames(6)[2:5]  # three frames with tracked features (the first two start the clock)
    tr = tf.FeatureTracker(CFG, 1, differentiable=True)
    warm, _ = _run(tr, _frames(2), [f for _, f in _frames(2)])
    images = [f.float().requires_grad_() for _, f in frames]
    state, out = _run(tr, frames, images, state=warm.detach())
    last = out[-1]
    assert int(last.present.sum()) > 50
    loss = tracking_loss(last.uv, last.present, target=last.uv.detach() + 0.25)
    grads = torch.autograd.grad(loss, images)
    norms = [float(g.abs().sum()) for g in grads]
    assert all(torch.isfinite(g).all() for g in grads)
    assert all(n > 0 for n in norms), norms
    assert state.requires_grad and not state.detach().requires_grad

    images2 = [f.float().requires_grad_() for _, f in frames]
    _, out2 = _run(tr, frames, images2, state=warm.detach(), detach_at=(2,))
    last2 = out2[-1]
    loss2 = tracking_loss(last2.uv, last2.present, target=last2.uv.detach() + 0.25)
    g2 = torch.autograd.grad(loss2, images2, allow_unused=True)
    assert g2[0] is None and g2[1] is None  # cut by the detach
    torch.testing.assert_close(g2[2], grads[2], rtol=0, atol=0)


def test_checkpointed_steps_give_the_same_gradients():
    """``torch.utils.checkpoint`` (non-reentrant) around each step recomputes it in the backward pass:
    the step is deterministic (seeded RANSAC), so the gradients are those without checkpointing."""
    frames = _frames(5)
    tr = tf.FeatureTracker(CFG, 1, differentiable=True)

    def run(ckpt):
        images = [f.float().requires_grad_() for _, f in frames]
        state = tr.initial_state()
        for (t, _), x in zip(frames, images):
            if ckpt:
                state, fr = checkpoint(tr.step, state, x, [t], use_reentrant=False)
            else:
                state, fr = tr.step(state, x, [t])
        loss = (fr.uv * fr.present.unsqueeze(-1)).sum() + fr.velocity.square().sum()
        return torch.autograd.grad(loss, images, allow_unused=True)

    plain, ckpt = run(False), run(True)
    used = [g is not None for g in plain]
    assert used == [g is not None for g in ckpt] and sum(used) >= 3
    for a, b in zip(plain, ckpt):
        if a is not None:
            torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_empty_slots_carry_no_gradient_and_masked_sums_are_finite():
    frames = _frames(5)
    tr = tf.FeatureTracker(CFG, 1, differentiable=True)
    images = [f.float().requires_grad_() for _, f in frames]
    _, out = _run(tr, frames, images)
    fr = out[-1]
    full = torch.autograd.grad(fr.uv.sum(), images[-1], retain_graph=True)[0]
    masked = torch.autograd.grad((fr.uv * fr.present.unsqueeze(-1)).sum(), images[-1], retain_graph=True)[0]
    torch.testing.assert_close(full, masked, rtol=0, atol=0)
    loss = (fr.uv * fr.valid.unsqueeze(-1)).sum() + (fr.xy * fr.valid.unsqueeze(-1)).sum()
    assert torch.isfinite(loss)
    g = torch.autograd.grad(loss, images)
    assert all(torch.isfinite(x).all() for x in g)


def test_xy_and_velocity_reach_the_camera_parameters():
    """The gradient of the lifted points w.r.t. the intrinsics is the camera's own (the tracker lifts
    its pixels with ``lift`` then divides by z, VINS's undistortedPoints)."""
    frames = _frames(5)
    tr = tf.FeatureTracker(CFG, 1, differentiable=True)
    cam = tr.camera
    cam.requires_grad_()
    try:
        _, out = _run(tr, frames, [f.float() for _, f in frames])
        fr = out[-1]
        m = fr.present.unsqueeze(-1)
        g_fx, g_k1 = torch.autograd.grad((fr.xy * m).sum(), (cam.fx, cam.k1), retain_graph=True)
        uv = fr.uv.detach().double()
        P = cam.lift(uv)
        ref = torch.autograd.grad(((P[..., :2] / P[..., 2:]).to(fr.xy.dtype) * m).sum(), (cam.fx, cam.k1))
        torch.testing.assert_close(g_fx, ref[0], rtol=1e-6, atol=0)
        torch.testing.assert_close(g_k1, ref[1], rtol=1e-6, atol=0)
        assert g_fx != 0 and g_k1 != 0
        gv, = torch.autograd.grad(fr.velocity.sum(), cam.fx)
        assert torch.isfinite(gv) and gv != 0
    finally:
        cam.requires_grad_(False)


@pytest.mark.parametrize("grad_mode", ["implicit", "unrolled"])
def test_lk_gradient_mode_is_chosen_by_the_tracker(grad_mode):
    """``grad_mode`` reaches the LK: the tracked pixels' image gradient is finite in both modes, and
    the two modes agree where the LK converged (implicit: the converged solution's gradient)."""
    frames = _frames(4)
    tr = tf.FeatureTracker(CFG, 1, differentiable=True, grad_mode=grad_mode)
    assert tr.params.lk_options.grad_mode == grad_mode
    images = [f.float().requires_grad_() for _, f in frames]
    _, out = _run(tr, frames, images)
    fr = out[-1]
    g = torch.autograd.grad((fr.uv * fr.present.unsqueeze(-1)).sum(), images[-1])[0]
    assert torch.isfinite(g).all() and g.abs().sum() > 0


def test_a_bad_grad_mode_is_refused():
    with pytest.raises(ValueError, match="grad_mode"):
        tf.FeatureTracker(CFG, 1, differentiable=True, grad_mode="magic")


# ---------------------------------------------------------------------------------------------
# CLAHE's straight-through gradient


def test_clahe_straight_through_value_and_slope():
    """The value is CLAHE's 8-bit output; the gradient is the local slope of the blended LUTs: on a
    tile-uniform histogram (every grey level equally often in every tile, no clipping) each LUT is
    the line ``(v + 1) 255 / 256``, so the slope is ``255 / 256`` everywhere."""
    v = torch.arange(256, dtype=torch.uint8)
    tile = v.view(16, 16).repeat(2, 2)  # 32 x 32 tile: every level 4 times
    img = tile.repeat(8, 8)[None]  # (1, 256, 256), 8 x 8 tiles of 32 x 32
    x = img.float().requires_grad_()
    y = _clahe_straight_through(x, 3.0, 8, 8)
    assert torch.equal(y.detach(), _clahe_impl(img, 3.0, 8, 8).image.float())
    g, = torch.autograd.grad(y.sum(), x)
    torch.testing.assert_close(g, torch.full_like(g, 255 / 256), rtol=1e-6, atol=0)


def test_clahe_slope_is_bounded_by_the_clip_limit_on_real_frames():
    frames = _frames(2)
    img = torch.cat([f for _, f in frames])[:, 0]
    s = _clahe_slope(img, 3.0, 8, 8)
    assert s.min() >= 0
    # a bin holds at most clip + its share of the excess: the slope stays near clip_limit * 255 / 256
    assert s.max() <= 3.0 * 2 and float(s.mean()) > 0.3
    x = img.float().requires_grad_()
    g, = torch.autograd.grad((_clahe_straight_through(x, 3.0, 8, 8) * 2.0).sum(), x)
    torch.testing.assert_close(g, 2.0 * s, rtol=0, atol=0)


def test_clahe_slope_matches_finite_differences_of_sparse_changes():
    """Central differences of the 8-bit CLAHE where a sparse 4 % of the pixels change by +-1 grey level
    (the LUTs barely move: each such pixel moves one histogram count): averaged over those pixels
    (the output's rounding averages out) they match the straight-through slope."""
    _, f = _frames(1)[0]
    img = f[:, 0]
    mask = torch.zeros_like(img, dtype=torch.bool)
    mask[:, ::5, ::5] = True
    mask &= (img > 0) & (img < 255)
    up = _clahe_impl(torch.where(mask, img + 1, img), 3.0, 8, 8).image.double()
    dn = _clahe_impl(torch.where(mask, img - 1, img), 3.0, 8, 8).image.double()
    fd = ((up - dn) / 2)[mask]
    s = _clahe_slope(img, 3.0, 8, 8).double()[mask]
    assert abs(float(fd.mean()) - float(s.mean())) < 0.05 * float(s.mean())
    assert np.corrcoef(fd.numpy(), s.numpy())[0, 1] > 0.8


# ---------------------------------------------------------------------------------------------
# torch.func


def test_torch_func_grad_of_a_step_equals_autograd():
    """``torch.func.grad`` composes with the step (data-dependent Python control flow is fine under
    ``grad``; ``vmap`` of a whole step is not supported: see docs/differentiability.md)."""
    frames = _frames(5)
    tr = tf.FeatureTracker(CFG, 1, differentiable=True)
    state, _ = _run(tr, frames[:4], [f.float() for _, f in frames[:4]])
    t, x = frames[4][0], frames[4][1].float()

    def loss(img):
        _, fr = tr.step(state, img, [t])
        return (fr.uv * fr.present.unsqueeze(-1)).sum()

    xx = x.clone().requires_grad_()
    ref, = torch.autograd.grad(loss(xx), xx)
    got = torch.func.grad(loss)(x)
    assert ref.abs().sum() > 0
    torch.testing.assert_close(got, ref, rtol=0, atol=0)


def test_functional_call_over_the_camera_parameters():
    """``torch.func.functional_call`` of a ``TrackerModule`` with other intrinsics, differentiated by
    ``torch.func.grad``: the same gradient as ``requires_grad_`` on the module's own parameters."""
    from torch_frontend.learn import TrackerModule

    frames = _frames(4)
    m = TrackerModule(CFG, 1)
    state = m.initial_state()
    for t, x in frames[:3]:
        state, _ = m(state, x.float(), [t])
    t, x = frames[3]

    def loss(fx):
        _, fr = torch.func.functional_call(m, {"camera.fx": fx}, (state, x.float(), [t]))
        return (fr.xy * fr.present.unsqueeze(-1)).sum()

    g = torch.func.grad(loss)(m.camera.fx.detach().clone())
    m.camera.fx.requires_grad_()
    try:
        ref, = torch.autograd.grad(loss(m.camera.fx), m.camera.fx)
    finally:
        m.camera.fx.requires_grad_(False)
    assert ref != 0
    torch.testing.assert_close(g, ref)


def test_vmap_of_a_step_is_refused_with_a_clear_error():
    t, x = _frames(1)[0]
    tr = tf.FeatureTracker(CFG, 1, differentiable=True)
    state = tr.initial_state()
    with pytest.raises(ValueError, match="num_streams=V \\* B"):
        torch.func.vmap(lambda img: tr.step(state, img, [t])[1].uv)(torch.stack((x.float(), x.float())))


def test_forward_mode_jvp_of_a_step_equals_reverse_mode():
    """``torch.func.jvp`` through a whole step (forward-mode AD; every kernel in its reference form)
    gives the reverse-mode ``<grad, v>`` to float32 rounding, and the primal is the plain value."""
    frames = _frames(5)
    tr = tf.FeatureTracker(CFG, 1, differentiable=True)
    state, _ = _run(tr, frames[:4], [f.float() for _, f in frames[:4]])
    state = state.detach()
    t, x = frames[4][0], frames[4][1].float()

    def loss(img):
        _, fr = tr.step(state, img, [t])
        return (fr.uv * fr.present.unsqueeze(-1)).sum() + fr.xy.sum() + fr.velocity.sum()

    v = torch.randn(x.shape, generator=torch.Generator().manual_seed(0))
    primal, jv = torch.func.jvp(loss, (x,), (v,))
    xx = x.clone().requires_grad_()
    value = loss(xx)
    g, = torch.autograd.grad(value, xx)
    ref = (g.double() * v.double()).sum()
    assert primal == value.detach() and abs(float(ref)) > 1e-3
    assert abs(float(jv) - float(ref)) <= 1e-4 * abs(float(ref))
