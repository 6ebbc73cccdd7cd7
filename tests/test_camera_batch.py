"""``CameraBatch``: B per-stream cameras (any mix of models) with a leading stream dimension. Stream b
gives its own single camera's values and gradients bit for bit; a batch is a tracker's camera (stream b
of the tracker = a one-stream tracker built with camera b, every field, default and capturable path);
``TrackerModule`` registers it; gradients reach each stream's own intrinsics.

A note on the references: torch's CPU ``atan2`` (Kannala-Brandt ``lift`` / ``project``, Scaramuzza's
``project``) gives different last bits in its vectorised body and its scalar tail, so even one
camera on ``uv[b]`` and on ``uv`` (row b) can differ where the point count is not a multiple of
the SIMD block. The exact comparisons therefore use either the same layout (camera b on the whole
``uv``, row b) or a point count that is a multiple of 64 (every element in the vector body).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

import torch_frontend as tf
from torch_frontend.camera import (
    CameraBatch,
    KannalaBrandtCamera,
    MeiCamera,
    PinholeCamera,
    PinholeFullCamera,
    ScaramuzzaCamera,
)
from torch_frontend.testing.dispatch_count import OpCounter
from torch_frontend.tracker import FeatureTracker

from ._helpers import crop, small_config
from .conftest import DEVICES, DTYPES, REPO, load_gray, sample_frames

pytestmark = pytest.mark.usefixtures("single_thread")


# ---------------------------------------------------------------------------------------------
# calibrations (values of the shipped configs; Scaramuzza made up, no shipped config has one)

def _pinhole(s=1.0):
    return PinholeCamera(-2.917e-01 * s, 8.228e-02, 5.333e-05, -1.578e-04, 4.616e02 * s, 4.603e02, 3.630e02,
                         2.481e02, width=752, height=480)


def _pinhole_full(s=1.0):
    return PinholeFullCamera(-0.28 * s, 0.07, -0.002, 0.01, -0.003, 0.001, 2e-4, -1e-4, 460.0 * s, 459.0, 370.0,
                             250.0, width=752, height=480)


def _mei(s=1.0):
    return MeiCamera(2.057 * s, 0.07145, 0.5059, 4.727e-05, -0.0005492, 1115.0 * s, 1114.0, 367.2, 238.5,
                     width=752, height=480)


def _kb(s=1.0):
    return KannalaBrandtCamera(0.0034823894022493434 * s, 0.0007150348452162257, -0.0020532361418706202,
                               0.00020293673591811182, 190.97847715128717 * s, 190.9733070521226,
                               254.93170605935475, 256.8974428996504, width=512, height=512)


def _scaramuzza(s=1.0):
    poly = [-230.0 * s, 0.0, 1.2e-3, -5e-7, 1e-9]
    inv_poly = [300.0 * s, 150.0, -20.0, 8.0, 1.0] + [0.0] * 15
    return ScaramuzzaCamera(poly, inv_poly, 1.0, 0.001 * s, -0.002, 400.5, 300.25, width=800, height=600)


MAKERS = {"pinhole": _pinhole, "pinhole_full": _pinhole_full, "mei": _mei, "kannala_brandt": _kb,
          "scaramuzza": _scaramuzza}
SCALES = (1.0, 1.1, 0.9)


def _pixels(B, N, dtype, device, seed=0):
    g = torch.Generator().manual_seed(seed)
    uv = torch.rand(B, N, 2, generator=g, dtype=torch.float64) * torch.tensor([500.0, 470.0], dtype=torch.float64)
    return uv.to(device=device, dtype=dtype)


def _check_stream_equal(batch_out, cams, fn, x, exact_single):
    """Row b of ``batch_out`` is camera b's ``fn`` on the same layout (camera b on all of ``x``) and,
    where ``exact_single``, on ``x[b]`` alone."""
    for b, cam in enumerate(cams):
        ref = fn(cam, x)[b]
        assert torch.equal(batch_out[b], ref), f"stream {b}: batch differs from its camera on the same layout"
        if exact_single:
            assert torch.equal(batch_out[b], fn(cam, x[b])), f"stream {b}: batch differs from its camera on uv[b]"


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES, ids=["f32", "f64"])
@pytest.mark.parametrize("model", sorted(MAKERS))
def test_one_model_batch_is_each_streams_camera_bit_for_bit(model, dtype, device):
    """lift / project / undistort (and lift(jacobian="implicit") where the model has it) of a batch
    of three different calibrations of one model: row b = camera b, bit for bit."""
    cams = [MAKERS[model](s).to(device) for s in SCALES]
    batch = CameraBatch.from_cameras(cams)
    assert batch.model is type(cams[0]) and len(batch) == 3
    for N in (64, 9):  # 64: every element in the vector body; 9: a scalar tail (atan2, module docstring)
        exact = N % 64 == 0 or device == "cpu" and model not in ("kannala_brandt", "scaramuzza")
        exact = exact or device != "cpu"
        uv = _pixels(3, N, dtype, device).reshape(3, N, 1, 2)  # two point dimensions
        _check_stream_equal(batch.lift(uv), cams, lambda c, x: c.lift(x), uv, exact)
        _check_stream_equal(batch.undistort(uv), cams, lambda c, x: c.undistort(x), uv, exact)
        P = cams[0].lift(uv)
        _check_stream_equal(batch.project(P), cams, lambda c, x: c.project(x), P, exact)
        if batch.implicit_lift:
            _check_stream_equal(batch.lift(uv, jacobian="implicit"), cams,
                                lambda c, x: c.lift(x, jacobian="implicit"), uv, exact)
        else:
            with pytest.raises(ValueError, match="implicit"):
                batch.lift(uv, jacobian="implicit")


MIXED = ("pinhole", "kannala_brandt", "mei", "pinhole", "scaramuzza", "pinhole_full", "kannala_brandt")


def _mixed(device="cpu"):
    return [MAKERS[m](1.0 + 0.05 * b).to(device) for b, m in enumerate(MIXED)]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES, ids=["f32", "f64"])
def test_mixed_models_batch_is_each_streams_camera_bit_for_bit(dtype, device):
    cams = _mixed(device)
    batch = CameraBatch.from_cameras(cams)
    assert batch.model is None and batch.model_type == "mixed"
    assert batch.group_streams == {"pinhole": (0, 3), "kannala_brandt": (1, 6), "mei": (2,), "scaramuzza": (4,),
                                   "pinhole_full": (5,)}
    assert batch.model_types == tuple(c.model_type for c in cams)
    uv = _pixels(len(cams), 64, dtype, device)
    for fn in (lambda c, x: c.lift(x), lambda c, x: c.undistort(x)):
        out = fn(batch, uv)
        for b, cam in enumerate(cams):
            assert torch.equal(out[b], fn(cam, uv[b])), f"stream {b} ({cam.model_type})"
    P = _kb().to(device).lift(uv.reshape(-1, 2)).reshape(len(cams), 64, 3)  # rays all around
    out = batch.project(P)
    for b, cam in enumerate(cams):
        assert torch.equal(out[b], cam.project(P[b])), f"stream {b} ({cam.model_type})"
    # jacobian="implicit": PINHOLE_FULL and scaramuzza have none
    with pytest.raises(ValueError, match=r"implicit.*PINHOLE_FULL.*scaramuzza"):
        batch.lift(uv, jacobian="implicit")
    sub = CameraBatch.from_cameras([cams[i] for i in (0, 1, 2, 3)])
    out = sub.lift(uv[:4], jacobian="implicit")
    for i in range(4):
        assert torch.equal(out[i], cams[i].lift(uv[i], jacobian="implicit"))


def test_mixed_batch_launches_grow_with_models_not_streams():
    """The kernels of a mixed lift depend on the set of models, not on B (B = 3 vs 12, same models)."""
    def kernels(B):
        cams = [MAKERS[m](1.0 + 0.01 * b) for b, m in enumerate(("pinhole", "mei", "kannala_brandt") * (B // 3))]
        batch = CameraBatch.from_cameras(cams)
        uv = _pixels(B, 40, torch.float64, "cpu")
        batch.lift(uv)  # warm-up
        with OpCounter() as c:
            batch.lift(uv)
        return c.kernels

    k3, k12 = kernels(3), kernels(12)
    assert k3 == k12, f"kernels grow with B: B=3 {k3}, B=12 {k12}"


def test_a_different_option_is_its_own_group():
    cams = [_pinhole(), PinholeCamera(**_pinhole(1.1).params_dict(), undistort_iters=64, width=752, height=480)]
    batch = CameraBatch.from_cameras(cams)
    assert batch.group_streams == {"pinhole": (0,), "pinhole_2": (1,)}
    uv = _pixels(2, 16, torch.float64, "cpu")
    out = batch.lift(uv)
    assert torch.equal(out[1], cams[1].lift(uv[1])) and torch.equal(out[0], cams[0].lift(uv[0]))
    assert batch[1].undistort_iters == 64


# ---------------------------------------------------------------------------------------------
# the module: streams, state_dict, to(), problems, errors

def test_streams_are_copies_and_state_dict_names_every_stream():
    cams = [_pinhole(s) for s in SCALES]
    batch = CameraBatch.from_cameras(cams)
    sd = batch.state_dict()
    assert sorted(sd) == sorted(PinholeCamera.param_names)
    assert sd["fx"].shape == (3,) and torch.equal(sd["fx"], torch.stack([c.fx for c in cams]))
    one = batch[1]
    assert isinstance(one, PinholeCamera) and one.params_dict() == cams[1].params_dict()
    assert (one.width, one.height) == (752, 480) and batch[-1].params_dict() == cams[2].params_dict()
    with torch.no_grad():
        one.fx.add_(1.0)
        cams[0].fx.add_(1.0)  # neither a stream's camera nor a source camera shares storage with the batch
    assert float(batch.fx[1]) == 4.616e02 * 1.1 and float(batch.fx[0]) == 4.616e02
    with pytest.raises(IndexError, match="stream 3 out of range for 3"):
        batch[3]
    sc = CameraBatch.from_cameras([_scaramuzza(s) for s in SCALES])
    assert sc.state_dict()["poly"].shape == (3, 5) and sc.state_dict()["inv_poly"].shape == (3, 20)
    mixed = CameraBatch.from_cameras(_mixed())
    sd = mixed.state_dict()
    assert sd["groups.pinhole.fx"].shape == (2,) and sd["groups.kannala_brandt.mu"].shape == (2,)
    assert sd["groups.scaramuzza.poly"].shape == (1, 5)
    assert not any("rows" in k or "inverse" in k for k in sd)  # the index buffers are not state
    # a round trip through state_dict
    other = CameraBatch.from_cameras(_mixed())
    with torch.no_grad():
        other.groups["pinhole"].fx.mul_(2)
    other.load_state_dict(sd)
    assert torch.equal(other.groups["pinhole"].fx, mixed.groups["pinhole"].fx)
    assert [c.params_dict() for c in mixed.cameras()] == [c.params_dict() for c in _mixed()]


@pytest.mark.parametrize("device", DEVICES)
def test_to_moves_and_casts_every_stream(device):
    batch = CameraBatch.from_cameras(_mixed()).to(device=device, dtype=torch.float32)
    for p in batch.parameters():
        assert p.dtype == torch.float32 and p.device.type == torch.device(device).type
    uv = _pixels(len(MIXED), 8, torch.float32, device)
    out = batch.lift(uv)
    assert out.device.type == torch.device(device).type and out.dtype == torch.float32
    assert all(p.dtype == torch.float32 for p in batch[2].parameters())


def test_param_problems_name_the_stream_and_key():
    bad = PinholeCamera(**{**_pinhole().params_dict(), "fx": 0.0})
    batch = CameraBatch.from_cameras([_pinhole(), _kb(), bad])
    problems = type(batch).param_problems(batch.params_dict())
    assert problems and problems[0][0] == "fx (stream 2)" and "> 0" in problems[0][1]
    assert CameraBatch.from_cameras([_pinhole(), _kb()]).problems() == []
    params = tf.tracker.TrackerParams()
    with pytest.raises(ValueError, match=r"camera\.fx \(stream 2\): must be > 0"):
        dataclasses.replace(params, camera=batch)


def test_wrong_stream_count_and_construction_errors():
    batch = CameraBatch.from_cameras([_pinhole(), _pinhole(1.1)])
    with pytest.raises(ValueError, match=r"2 streams expects shape \(2, \.\.\., 2\).*\(3, 5, 2\)"):
        batch.lift(torch.zeros(3, 5, 2, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"2 streams"):
        batch.project(torch.ones(3, dtype=torch.float64))
    with pytest.raises(ValueError, match="at least one camera"):
        CameraBatch.from_cameras([])
    with pytest.raises(TypeError, match="stream 1: expected a CameraModel"):
        CameraBatch.from_cameras([_pinhole(), "cam.yaml"])


# ---------------------------------------------------------------------------------------------
# gradients

def _row_of(batch, b):
    """``(parameter-name prefix, row)`` of stream b in ``batch``'s parameters."""
    if batch.model is not None:
        return "", b
    g = next(g for g, rows in batch.group_streams.items() if b in rows)
    return f"groups.{g}.", batch.group_streams[g].index(b)


@pytest.mark.parametrize("kind", ["lift", "lift_implicit", "project"])
@pytest.mark.parametrize("cams", ["pinhole", "mixed"])
def test_each_stream_gets_its_own_cameras_gradient(cams, kind):
    """float64: stream b's rows of the batch's gradient equal camera b's gradient, bit for bit
    (each stream's parameters meet only its own points; the broadcast's backward sums exactly the
    elements the single camera sums)."""
    cams = [_pinhole(s) for s in SCALES] if cams == "pinhole" else _mixed()
    if kind == "lift_implicit":
        cams = [c for c in cams if c.implicit_lift]
    B = len(cams)
    batch = CameraBatch.from_cameras(cams).requires_grad_()
    uv = _pixels(B, 13, torch.float64, "cpu")
    x = _kb().lift(uv.reshape(-1, 2)).reshape(B, 13, 3) if kind == "project" else uv

    def run(cam, inp):
        if kind == "project":
            return cam.project(inp)
        return cam.lift(inp, jacobian="implicit" if kind == "lift_implicit" else "unrolled")

    w = torch.rand(run(batch, x).shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    named = dict(batch.named_parameters())
    grads = dict(zip(named, torch.autograd.grad((run(batch, x) * w).sum(), list(named.values()), allow_unused=True)))
    for b, cam in enumerate(cams):
        cam.requires_grad_()
        own = dict(cam.named_parameters())
        ref = torch.autograd.grad((run(cam, x[b]) * w[b]).sum(), list(own.values()), allow_unused=True)
        prefix, row = _row_of(batch, b)
        for n, g_ref in zip(own, ref):
            g = grads[prefix + n]
            if g_ref is None:  # e.g. Scaramuzza's inv_poly in lift
                assert g is None or not g[row].any()
                continue
            assert torch.equal(g[row], g_ref), f"stream {b} {cam.model_type}.{n}"
    # no loss on stream 0: its rows get no gradient (each stream's parameters meet its own points only)
    w[0] = 0
    g0 = torch.autograd.grad((run(batch, x) * w).sum(), list(named.values()), allow_unused=True)
    prefix, row = _row_of(batch, 0)
    for n, g in zip(named, g0):
        if g is not None and n.startswith(prefix):
            assert not g[row].any(), f"{n}: stream 0 has a gradient without a loss on it"


def test_gradcheck_mixed_batch():
    """gradcheck (float64) of lift and project w.r.t. every stream's parameters, a small mixed batch."""
    cams = [_pinhole(), _kb(), _mei(), _pinhole(1.1)]
    batch = CameraBatch.from_cameras(cams).requires_grad_()
    uv = _pixels(4, 2, torch.float64, "cpu") * 0.5 + 100.0
    params = tuple(batch.parameters())
    assert torch.autograd.gradcheck(lambda *_: batch.lift(uv), params, eps=1e-6, atol=1e-6, rtol=1e-5)
    P = batch.lift(uv).detach()
    assert torch.autograd.gradcheck(lambda *_: batch.project(P), params, eps=1e-6, atol=1e-6, rtol=1e-5)


# ---------------------------------------------------------------------------------------------
# the tracker: a batch as params.camera

SCALE_FX = (1.0, 1.04, 0.97)
#: per-stream frame periods (s): the streams publish at different frames, so the capturable path
#: runs its publish stages on a sub-batch of lanes (the batch's ``index_streams``)
PERIODS = (0.05, 0.075, 0.1)


def _scaled(cam, s):
    return PinholeCamera.from_params({**cam.params_dict(), "fx": cam.params_dict()["fx"] * s}, width=cam.width,
                                     height=cam.height, camera_name=cam.camera_name)


def _tracker_inputs(n):
    frames = [crop(load_gray(f)) for f in sample_frames("cam0")]
    steps = []
    for k in range(n):
        imgs = np.stack([frames[(k + 3 * b) % len(frames)] for b in range(len(SCALE_FX))])
        stamps = [1403715273.0 + k * PERIODS[b] for b in range(len(SCALE_FX))]
        steps.append((torch.from_numpy(imgs)[:, None], stamps))
    return steps


def _frame_fields(frame):
    return {f.name: getattr(frame, f.name) for f in dataclasses.fields(frame) if getattr(frame, f.name) is not None}


@pytest.mark.parametrize("capturable", [False, True], ids=["default", "capturable"])
def test_tracker_with_a_camera_batch_equals_one_stream_trackers(tmp_path, capturable):
    """FeatureTracker (one config, 3 streams) whose ``params.camera`` is a batch of three different
    fx: stream b's frames are exactly (every FeatureFrame field, torch.equal) a one-stream tracker's
    built with camera b, several steps, mono (CLAHE, rejectWithF, setMask, detection)."""
    cfg = tf.load_config(small_config(tmp_path))
    cams = [_scaled(cfg.camera, s) for s in SCALE_FX]
    tr = FeatureTracker(cfg, len(cams), capturable=capturable)
    tr.params = dataclasses.replace(tr.params, camera=CameraBatch.from_cameras(cams))
    singles = [FeatureTracker(dataclasses.replace(cfg, camera=c), 1, capturable=capturable) for c in cams]
    n_steps = 6 if capturable else 8
    partial = published = 0
    for k, (imgs, stamps) in enumerate(_tracker_inputs(n_steps)):
        fb = tr.track(imgs, stamps)
        npub = int(fb.published.sum())
        partial += 0 < npub < len(cams)
        published += int(fb.valid.sum())
        for b, single in enumerate(singles):
            fs = _frame_fields(single.track(imgs[b:b + 1], stamps[b:b + 1]))
            got = _frame_fields(fb)
            assert fs.keys() == got.keys()
            for name, ref in fs.items():
                assert torch.equal(got[name][b:b + 1], ref), f"step {k}, stream {b}: {name} differs"
    assert partial >= 2, "the streams never published at different frames (no sub-batch of lanes)"
    assert published > 50
    # the intrinsics matter: the streams' xy differ for the same pixels
    uv = torch.tensor([[[100.0, 80.0]]], dtype=torch.float64).expand(3, 1, 2)
    xy = tr.params.camera.undistort(uv)
    assert not torch.equal(xy[0], xy[1])


def _scaled_mei(cam, s):
    return MeiCamera.from_params({**cam.params_dict(), "gamma1": cam.params_dict()["gamma1"] * s},
                                 width=cam.width, height=cam.height, camera_name=cam.camera_name)


@pytest.mark.parametrize("capturable", [False, pytest.param(True, marks=pytest.mark.slow)],  # ~18 s on a CPU
                         ids=["default", "capturable"])
def test_fusion_stereo_with_camera_batches_equals_one_stream_trackers(capturable):
    """Fusion stereo (MEI cam0 + cam1), 2 streams, ``camera`` and ``camera1`` both batches with
    per-stream gamma1: stream b = a one-stream tracker with cameras b, every field (fusion tracks
    each image at its own size: 192 x 256 crops keep the test quick)."""
    cfg = tf.load_config(REPO / "configs" / "euroc_stereo_mei.yaml")
    scales = (1.0, 1.03)
    c0 = [_scaled_mei(cfg.camera, s) for s in scales]
    c1 = [_scaled_mei(cfg.camera1, 1.0 / s) for s in scales]
    # capturable: a small LK budget (the same for every tracker: equality holds whatever it is) keeps
    # the CPU run short (the stereo LK runs every lane every iteration)
    kw = dict(mode="fusion", capturable=capturable, lk_iter_budget=8 if capturable else None)
    tr = FeatureTracker(cfg, 2, **kw)
    tr.params = dataclasses.replace(tr.params, camera=CameraBatch.from_cameras(c0), camera1=CameraBatch.from_cameras(c1))
    singles = [FeatureTracker(dataclasses.replace(cfg, camera=a, camera1=b), 1, **kw) for a, b in zip(c0, c1)]
    left = [crop(load_gray(f)) for f in sample_frames("cam0")]
    right = [crop(load_gray(f)) for f in sample_frames("cam1")]
    n_right = 0
    for k in range(4):
        idx = [k, k + 2]
        li = torch.from_numpy(np.stack([left[i] for i in idx]))[:, None]
        ri = torch.from_numpy(np.stack([right[i] for i in idx]))[:, None]
        t = [1403715273.0 + 0.05 * k] * 2
        fb = _frame_fields(tr.track(li, t, right=ri))
        n_right += int(fb["right_valid"].sum())
        for b, single in enumerate(singles):
            fs = _frame_fields(single.track(li[b:b + 1], t[b:b + 1], right=ri[b:b + 1]))
            assert fs.keys() == fb.keys()
            for name, ref in fs.items():
                assert torch.equal(fb[name][b:b + 1], ref), f"step {k}, stream {b}: {name} differs"
    assert n_right > 20


# ---------------------------------------------------------------------------------------------
# TrackerModule and the differentiable tracker

def test_tracker_module_registers_and_moves_a_camera_batch(tmp_path):
    cfg = tf.load_config(small_config(tmp_path))
    cams = [_scaled(cfg.camera, s) for s in SCALE_FX]
    m = tf.TrackerModule(cfg, 3)
    m.use_camera(CameraBatch.from_cameras(cams))
    sd = m.state_dict()
    assert sd["camera.fx"].shape == (3,)
    assert torch.equal(sd["camera.fx"], torch.tensor([c.params_dict()["fx"] for c in cams], dtype=torch.float64))
    assert m.tracker.params.camera is m.camera
    m.double()  # the cameras stay float64 and the tracker follows the module
    assert m.camera.fx.dtype == torch.float64 and m.tracker.params.camera is m.camera
    with pytest.raises(ValueError, match="batch of 2 streams for a tracker of 3"):
        m.use_camera(CameraBatch.from_cameras(cams[:2]))


def test_differentiable_tracker_gives_each_stream_its_own_intrinsics_gradient(tmp_path):
    """A differentiable 3-stream tracker with a camera batch (requires_grad_): the gradient of a loss
    on stream b's xy w.r.t. the batch's fx[b] equals a one-stream tracker's gradient w.r.t. its fx,
    and the other streams' fx get none from it.

    Exact (torch.equal): the lift of stream b's points is the same float64 elementwise code on the
    same values (the values are bit-identical, test above), and the backward of the (B, 1) broadcast
    sums the same K products of row b in the same order as the 0-d camera's sum over its (1, K)."""
    cfg = tf.load_config(small_config(tmp_path))
    cams = [_scaled(cfg.camera, s) for s in SCALE_FX]
    m = tf.TrackerModule(cfg, 3)
    m.use_camera(CameraBatch.from_cameras(cams))
    m.camera.requires_grad_()
    singles = []
    for c in cams:
        s = tf.TrackerModule(dataclasses.replace(cfg, camera=c), 1)
        s.camera.requires_grad_()
        singles.append(s)
    state = m.initial_state()
    s_states = [s.initial_state() for s in singles]
    checked = 0
    for k, (imgs, stamps) in enumerate(_tracker_inputs(5)):
        x = imgs.float()
        state, fr = m(state, x, stamps)
        for b, s in enumerate(singles):
            s_states[b], fs = s(s_states[b], x[b:b + 1], stamps[b:b + 1])
            if not fs.valid.any():
                continue
            w = torch.linspace(0.5, 1.5, fs.xy.numel(), dtype=fs.xy.dtype).reshape(fs.xy.shape)
            g_single, = torch.autograd.grad((fs.xy * w * fs.valid[..., None]).sum(), s.camera.fx,
                                            retain_graph=True)
            g_batch, = torch.autograd.grad((fr.xy[b:b + 1] * w * fr.valid[b:b + 1, :, None]).sum(), m.camera.fx,
                                           retain_graph=True)
            assert g_single != 0
            assert torch.equal(g_batch[b], g_single), f"step {k}, stream {b}: {g_batch[b]} vs {g_single}"
            others = [i for i in range(3) if i != b]
            assert not g_batch[others].any()
            checked += 1
    assert checked >= 3


def test_mixed_config_tracker_module_gives_each_stream_its_own_intrinsics_gradient(tmp_path):
    """The learned-VIO check on per-stream configs: ``TrackerModule([cfg_0, cfg_1, cfg_2])`` with
    three calibrations (one with another ``max_cnt``): ``state_dict`` names every group's camera, the
    module moves with its cameras, and the gradient of a loss on stream b's xy reaches stream b's own
    intrinsics only, equal (torch.equal, see the test above) to a one-stream module's."""
    base = tf.load_config(small_config(tmp_path))
    cfgs = [dataclasses.replace(base, camera=_scaled(base.camera, s)) for s in SCALE_FX]
    cfgs[1] = dataclasses.replace(cfgs[1], max_cnt=40)
    m = tf.TrackerModule(cfgs)
    assert m.num_streams == 3 and len(m.group_streams) >= 2
    sd = m.state_dict()
    fx_keys = sorted(k for k in sd if k.endswith(".fx"))
    assert fx_keys and all(k.startswith("groups.") for k in fx_keys)
    stored = []
    for b in range(3):
        cam, row = m.stream_camera(b)
        stored.append(float(cam.fx if row is None else cam.fx[row]))
    assert stored == [c.camera.params_dict()["fx"] for c in cfgs]
    m.float()  # the cameras stay float64 with their values (not rounded to float32), every group's tracker follows
    assert all(p.dtype == torch.float64 for p in m.parameters())
    for b in range(3):
        cam, row = m.stream_camera(b)
        assert float(cam.fx if row is None else cam.fx[row]) == stored[b]
        assert float(cam.fy if row is None else cam.fy[row]) == cfgs[b].camera.params_dict()["fy"]
    m.requires_grad_()
    singles = [tf.TrackerModule(c) for c in cfgs]
    for s in singles:
        s.requires_grad_()
    state, s_states = m.initial_state(), [s.initial_state() for s in singles]
    checked = 0
    for k, (imgs, stamps) in enumerate(_tracker_inputs(5)):
        x = imgs.float()
        state, fr = m(state, x, stamps)
        for b, s in enumerate(singles):
            s_states[b], fs = s(s_states[b], x[b:b + 1], stamps[b:b + 1])
            if not fs.valid.any():
                continue
            K = fs.xy.shape[1]
            w = torch.linspace(0.5, 1.5, fs.xy.numel(), dtype=fs.xy.dtype).reshape(fs.xy.shape)
            g_single, = torch.autograd.grad((fs.xy * w * fs.valid[..., None]).sum(), s.camera.fx, retain_graph=True)
            loss = (fr.xy[b:b + 1, :K] * w * fr.valid[b:b + 1, :K, None]).sum()
            cams = [m.stream_camera(i) for i in range(3)]
            grads = torch.autograd.grad(loss, [c.fx for c, _ in cams], retain_graph=True, allow_unused=True)
            cam, row = cams[b]
            g_own = grads[b] if row is None else grads[b][row]
            assert g_single != 0 and torch.equal(g_own, g_single), f"step {k}, stream {b}: {g_own} vs {g_single}"
            for i, (g, (c, r)) in enumerate(zip(grads, cams)):
                if i != b and c is not cam and g is not None:
                    assert not (g if r is None else g[r]).any(), f"stream {i} got a gradient from stream {b}"
            checked += 1
    assert checked >= 3
