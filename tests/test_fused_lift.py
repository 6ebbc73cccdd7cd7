"""The fused PINHOLE lift (``torch_frontend::pinhole_lift``, ``fused/lift_op.py``): the tracker's
``lift_normalised`` of a ``PinholeCamera`` bit for bit (``docs/kernels.md``, "The PINHOLE lift").

Against the tensor path (``PinholeCamera._lift_impl`` in float64, the golden battery's reference):
random and real points (corners of the repo's frames, sub-pixel), EuRoC's, distortion-free and
strongly distorted (diverging: inf / NaN) parameters, float32 and float64 points, B > 1 with a
camera per stream (``CameraBatch``, its ``index_streams`` rows), invalid slots; one op and no sync
per call; the door (other models, mixed batches, gradients: the tensor path); the backend's
resolution; the tracker's use; the Triton kernel under ``TRITON_INTERPRET=1`` == the CPU kernel.
"""

from __future__ import annotations

import os
import subprocess
import sys
import warnings

import cv2
import numpy as np
import pytest
import torch

import torch_frontend as tf
from torch_frontend import fused
from torch_frontend.camera.batch import CameraBatch
from torch_frontend.camera.pinhole import PinholeCamera
from torch_frontend.errors import ConfigError
from torch_frontend.fused.lift_op import pinhole_lift_op, pinhole_of, pinhole_params
from torch_frontend.testing.dispatch_count import OpCounter
from torch_frontend.tracker.stages import lift_normalised

from .conftest import REPO, load_gray, sample_frames

EUROC = (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 458.654, 457.296, 367.215, 248.375)
PARAMS = {
    "euroc": EUROC,
    "none": (0.0, 0.0, 0.0, 0.0, 458.654, 457.296, 367.215, 248.375),  # camodocal's noDistortion shortcut
    "strong": (-1.5, 4.0, 0.05, -0.08, 180.0, 170.0, 376.0, 240.0),  # diverges at the borders: inf / NaN
    "barrel": (0.6, 0.9, -0.01, 0.02, 300.0, 320.0, 350.5, 260.25),
}


def _bits(t: torch.Tensor) -> torch.Tensor:
    return t.view(torch.int64 if t.dtype == torch.float64 else torch.int32)


def _same(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Bit for bit (NaNs included: the same payload and sign)."""
    return a.dtype == b.dtype and a.shape == b.shape and torch.equal(_bits(a), _bits(b))


def _points(B, N, seed, dtype=torch.float32, spread=1.0):
    g = torch.Generator().manual_seed(seed)
    c = torch.tensor([376.0, 240.0], dtype=torch.float64)
    uv = c + (torch.rand((B, N, 2), generator=g, dtype=torch.float64) - 0.5) * torch.tensor([752.0, 480.0],
                                                                                          dtype=torch.float64) * spread
    valid = torch.rand((B, N), generator=g) < 0.8
    return uv.to(dtype), valid


def _both(camera, uv, valid):
    return lift_normalised(camera, uv, valid, "tensor"), lift_normalised(camera, uv, valid, "fused")


@pytest.mark.parametrize("name", list(PARAMS))
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fused_equals_tensor_on_random_points(name, dtype):
    cam = PinholeCamera(*PARAMS[name])
    uv, valid = _points(3, 257, seed=len(name), dtype=dtype, spread=1.3)  # past the image: far from the centre
    ref, got = _both(cam, uv, valid)
    assert _same(ref, got), name
    assert bool((got[~valid] == 0).all()) and not bool(torch.signbit(got[~valid]).any())
    if name == "strong":
        assert not bool(torch.isfinite(ref[valid]).all())  # the case is not vacuous: the fixed point diverged


def test_fused_equals_tensor_on_real_corners():
    """Corners of the repo's frames (``cv2.goodFeaturesToTrack``, then sub-pixel offsets as LK gives),
    the EuRoC config's own camera; float32 as the tracker's table."""
    cam = tf.load_config(REPO / "configs" / "euroc.yaml").camera
    assert pinhole_of(cam) == 8
    pts = []
    for p in sample_frames("cam0")[:2]:
        c = cv2.goodFeaturesToTrack(load_gray(p), 150, 0.01, 30).reshape(-1, 2)
        pts.append(np.pad(c, ((0, 150 - len(c)), (0, 0))))
    uv = torch.from_numpy(np.stack(pts)).float()
    uv = uv + torch.rand(uv.shape, generator=torch.Generator().manual_seed(1)) - 0.5
    valid = torch.ones(uv.shape[:2], dtype=torch.bool)
    valid[1, -7:] = False
    for x in (uv, uv.double()):
        ref, got = _both(cam, x, valid)
        assert _same(ref, got)


def test_streams_with_their_own_cameras():
    """B > 1, a camera per stream (a one-model ``CameraBatch``; one stream distortion-free) and the
    capturable step's sub-batch (``index_streams``)."""
    cams = [PinholeCamera(*PARAMS[n]) for n in ("euroc", "none", "barrel", "strong")]
    batch = CameraBatch.from_cameras(cams)
    assert pinhole_of(batch) == 8 and tuple(pinhole_params(batch, torch.zeros(4, 1, 2)).shape) == (4, 8)
    uv, valid = _points(4, 300, seed=7)
    ref, got = _both(batch, uv, valid)
    assert _same(ref, got)
    for b, cam in enumerate(cams):  # and each stream's own camera's
        assert _same(lift_normalised(cam, uv[b:b + 1], valid[b:b + 1], "fused"), got[b:b + 1])
    rows = torch.tensor([2, 0])
    sub = batch.index_streams(rows)
    assert pinhole_of(sub) == 8
    ref, got = _both(sub, uv[:2], valid[:2])
    assert _same(ref, got)


def test_iterations_and_non_finite_input():
    uv = torch.tensor([[[float("inf"), 3.0], [float("nan"), 1.0], [-float("inf"), float("inf")], [700.0, 20.0]]],
                      dtype=torch.float64)
    valid = torch.ones(1, 4, dtype=torch.bool)
    for name in ("none", "euroc"):
        for iters in (1, 3, 64):
            cam = PinholeCamera(*PARAMS[name], undistort_iters=iters)
            ref, got = _both(cam, uv, valid)
            assert _same(ref, got), (name, iters)
    # the shortcut: no distortion keeps the infinite inputs' m_d (upstream), not the loop's NaN
    got = lift_normalised(PinholeCamera(*PARAMS["none"]), uv, valid, "fused")
    assert torch.isinf(got[0, 0, 0]) and torch.isinf(got[0, 2]).all()


def test_op_checks_and_one_op_no_sync():
    cam = PinholeCamera(*EUROC)
    for B in (1, 5):
        uv, valid = _points(B, 150, seed=B)
        lift_normalised(cam, uv, valid, "fused")  # warm-up
        with OpCounter() as c:
            lift_normalised(cam, uv, valid, "fused")
        # the parameters' stack and the op
        assert c.kernels == 2 and c.names["pinhole_lift"] == 1 and c.names["stack"] == 1, c.summary()
        assert c.syncs == 0, c.summary()
    uv, valid = _points(2, 33, seed=0)
    params = pinhole_params(cam, uv)
    res = torch.library.opcheck(pinhole_lift_op, (uv, valid, params, 8))
    assert all(v == "SUCCESS" for v in res.values()), res
    got = torch.compile(lambda a, m: pinhole_lift_op(a, m, params, 8), backend="eager", fullgraph=True)(uv, valid)
    assert _same(got, pinhole_lift_op(uv, valid, params, 8))
    with pytest.raises(ValueError, match="params must be"):
        pinhole_lift_op(uv, valid, params.float(), 8)
    with pytest.raises(ValueError, match="valid must be"):
        pinhole_lift_op(uv, valid[:, :5], params, 8)
    with pytest.raises(ValueError, match="iters"):
        pinhole_lift_op(uv, valid, params, 0)


def test_threads_split_streams_without_changing_a_bit():
    uv, valid = _points(7, 150, seed=3)
    params = pinhole_params(CameraBatch.from_cameras([PinholeCamera(*EUROC)] * 6 + [PinholeCamera(*PARAMS["strong"])]),
                            uv)
    one = pinhole_lift_op(uv, valid, params, 8)
    n = torch.get_num_threads()
    try:
        torch.set_num_threads(3)
        assert _same(pinhole_lift_op(uv, valid, params, 8), one)
    finally:
        torch.set_num_threads(n)


def test_the_door():
    """Other models, mixed batches and a wanted gradient lift with the tensor path."""
    mei = tf.load_config(REPO / "configs" / "euroc_mono_mei.yaml").camera
    assert pinhole_of(mei) is None
    assert pinhole_of(CameraBatch.from_cameras([PinholeCamera(*EUROC), mei])) is None

    class Mine(PinholeCamera):
        def _lift_impl(self, uv, *a, **k):
            return super()._lift_impl(uv, *a, **k)

    assert pinhole_of(Mine(*EUROC)) is None
    uv, valid = _points(1, 20, seed=2)
    ref, got = _both(mei, uv, valid)
    assert _same(ref, got)
    cam = PinholeCamera(*EUROC).requires_grad_()
    with OpCounter() as c:
        xy = lift_normalised(cam, uv, valid, "fused")
    assert c.kernels > 10 and xy.requires_grad  # the tensor path, with its graph
    x = uv.clone().requires_grad_()
    assert lift_normalised(PinholeCamera(*EUROC), x, valid, "fused").requires_grad


def test_backend_resolution(monkeypatch):
    assert fused.resolve_lift_backend(None, "cpu") == "fused" and fused.resolve_lift_backend("auto", "cpu") == "fused"
    assert fused.resolve_lift_backend("tensor", "cpu") == "tensor"
    assert fused.resolve_lift_backend(None, "meta") == "tensor"
    with pytest.raises(ConfigError, match="lift_backend"):
        fused.resolve_lift_backend("numba", "cpu")
    monkeypatch.setitem(fused._STATUS, ("lift", "cpu"), "numba cannot be loaded (ImportError: no numba)")
    monkeypatch.setattr(fused, "_WARNED", set())
    with pytest.warns(RuntimeWarning, match="fused PINHOLE lift cannot run"):
        assert fused.resolve_lift_backend(None, "cpu") == "tensor"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert fused.resolve_lift_backend(None, "cpu") == "tensor"  # said once
    with pytest.raises(ConfigError, match="numba cannot be loaded"):
        fused.resolve_lift_backend("fused", "cpu")


def test_the_tracker_runs_the_resolved_lift():
    """``FeatureTracker(lift_backend=...)``: resolved once, in the params, and the same frames
    (normalised points and velocities included) either way."""
    cfg = tf.load_config(REPO / "configs" / "euroc.yaml")
    frames = [torch.from_numpy(load_gray(p)) for p in sample_frames("cam0")[:4]]
    outs = {}
    for be in ("fused", "tensor"):
        tr = tf.FeatureTracker(cfg, num_streams=2, lift_backend=be)
        assert tr.lift_backend == be and tr.params.lift_backend == be
        outs[be] = []
        for i, f in enumerate(frames):
            img = torch.stack([f, frames[(i + 1) % 4]])[:, None]
            fr = tr.track(img, [0.05 * i] * 2)
            outs[be].append([t.clone() for t in vars(fr).values() if isinstance(t, torch.Tensor)])
    for a, b in zip(outs["fused"], outs["tensor"]):
        assert len(a) == len(b) and all(_same(p, q) if p.is_floating_point() else torch.equal(p, q)
                                        for p, q in zip(a, b))
    assert tf.FeatureTracker(cfg).lift_backend == "fused"


# --------------------------------------------------------------------------- Triton and machine code
_TRITON_SCRIPT = r"""
import torch
from torch_frontend.fused._triton_lift import pinhole_lift_cuda
from torch_frontend.fused.lift_op import pinhole_lift_op, selfcheck_case
import tests.test_fused_lift as t
uv, valid, params, iters = selfcheck_case()
for x in (uv, uv.double()):
    assert t._same(pinhole_lift_cuda(x, valid, params, iters), pinhole_lift_op(x, valid, params, iters))
    assert t._same(pinhole_lift_cuda(x, valid, params[:1], 3), pinhole_lift_op(x, valid, params[:1], 3))
for name, p in t.PARAMS.items():
    x, m = t._points(2, 130, seed=5, spread=1.3)
    P = torch.tensor([p], dtype=torch.float64)
    assert t._same(pinhole_lift_cuda(x, m, P, 8), pinhole_lift_op(x, m, P, 8)), name
x = torch.tensor([[[float("inf"), 3.0], [float("nan"), 1.0], [700.0, 20.0]]], dtype=torch.float64)
m = torch.ones(1, 3, dtype=torch.bool)
for name in ("none", "euroc"):
    P = torch.tensor([t.PARAMS[name]], dtype=torch.float64)
    assert t._same(pinhole_lift_cuda(x, m, P, 8), pinhole_lift_op(x, m, P, 8)), name
print("PASS triton")
"""


def test_triton_kernel_equals_the_cpu_kernel_interpreted():
    """The CUDA kernel (``_triton_lift``) under ``TRITON_INTERPRET=1`` on CPU tensors == the CPU kernel,
    bit for bit (float32 / float64 points, one or B parameter rows, every parameter set, non-finite
    input; in a child: ``TRITON_INTERPRET`` is read when ``@triton.jit`` decorates)."""
    if os.environ.get("TORCH_FRONTEND_REQUIRE_TRITON") != "1":
        pytest.importorskip("triton", reason="the fused CUDA kernels are Triton kernels: triton is not installed "
                                             "(make test-all installs it: pip install -e '.[triton]')")
    env = {**os.environ, "TRITON_INTERPRET": "1", "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-c", _TRITON_SCRIPT], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0 and "PASS triton" in proc.stdout, proc.stdout + proc.stderr[-4000:]


@pytest.mark.slow  # a cold numba compile in a child
def test_numba_lift_has_no_fma(tmp_path):
    """No fused multiply-add in the CPU kernel's machine code (the tensor path rounds every product
    before its sum): compiled afresh in a child; the kernel is float64 code."""
    code = ("import numpy as np, torch_frontend.fused._numba_lift as m; x = np.zeros((1, 4, 2)); "
            "v = np.ones((1, 4), bool); p = np.ones((1, 8)); m.lift_streams(x, v, p, 8, x.copy(), 0, 1); "
            "asm = ''.join(m.lift_streams.inspect_asm().values()); "
            "print(len(asm), 'vfmadd' in asm or 'vfmsub' in asm or 'vfnmadd' in asm, 'mulsd' in asm or 'mulpd' in asm)")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=REPO, timeout=600)
    assert res.returncode == 0, res.stderr
    size, has_fma, has_mul = res.stdout.split()
    assert int(size) > 1000 and has_fma == "False" and has_mul == "True", res.stdout
