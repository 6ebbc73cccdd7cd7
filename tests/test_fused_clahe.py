"""The fused CLAHE (``torch_frontend::clahe``, ``fused/clahe_op.py``) against OpenCV and the tensor CLAHE.

Bars (issue 41): the fused op equals ``cv2.createCLAHE(clip, grid).apply`` and the tensor CLAHE on every
pixel of the repo's real frames and ``../shared``'s, odd sizes (OpenCV's reflect-101 padded histogram
source), other clip limits and grids, saturated / constant images; each stream of a batch equals its
own single-stream call; threads change no bit; one op per call, no host sync; the Triton kernels equal
the CPU kernel under ``TRITON_INTERPRET=1``.
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
from torch_frontend.equalize import _clahe_impl, _clahe_straight_through, clahe
from torch_frontend.errors import ConfigError
from torch_frontend.fused.clahe_op import clahe_op
from torch_frontend.testing.dispatch_count import OpCounter

from .conftest import REPO, load_gray, sample_frames, shared_data_or_skip

pytestmark = pytest.mark.usefixtures("single_thread")


def _cv2(batch: np.ndarray, clip=3.0, grid=(8, 8)) -> np.ndarray:
    c = cv2.createCLAHE(clip, grid)
    return np.stack([c.apply(np.ascontiguousarray(b)) for b in batch])


def _fused(batch: np.ndarray, clip=3.0, grid=(8, 8)) -> np.ndarray:
    return clahe_op(torch.from_numpy(np.ascontiguousarray(batch)), float(clip), grid[0], grid[1]).numpy()


def _tensor(batch: np.ndarray, clip=3.0, grid=(8, 8)) -> np.ndarray:
    return _clahe_impl(torch.from_numpy(np.ascontiguousarray(batch)), float(clip), grid[0], grid[1]).image.numpy()


def _assert_same(name, got, ref):
    bad = np.argwhere(got != ref)
    assert bad.size == 0, f"{name}: {len(bad)} pixels differ, first at {tuple(bad[0])}: {got[tuple(bad[0])]} " \
                          f"vs {ref[tuple(bad[0])]}"


def _extremes(h=96, w=128):
    g = np.random.default_rng(3)
    noise = g.integers(0, 256, (h, w), dtype=np.uint8)
    stripes = np.zeros((h, w), np.uint8)
    stripes[:, ::3] = 255
    return np.stack([noise, noise // 128 * 255, np.full((h, w), 7, np.uint8), stripes])


# ------------------------------------------------------------------------------------ against cv2
def test_fused_equals_cv2_and_tensor_on_the_repos_frames():
    """Every pixel of every sample frame (cam0 and cam1, one batch of different images): fused == cv2
    == tensor; and each stream equals its own B = 1 call (streams are independent)."""
    batch = np.stack([load_gray(p) for cam in ("cam0", "cam1") for p in sample_frames(cam)])
    assert len(batch) >= 20 and batch.shape[1:] == (480, 752)
    got = _fused(batch)
    _assert_same("fused vs cv2", got, _cv2(batch))
    _assert_same("fused vs tensor", got, _tensor(batch))
    for b in (0, len(batch) // 2, len(batch) - 1):
        _assert_same(f"stream {b} alone", _fused(batch[b:b + 1])[0], got[b])


def test_fused_equals_cv2_on_shared_frames():
    """Every frame of ``../shared``'s EuRoC V1_01 excerpt (cam0 and cam1) against cv2; every 8th also
    against the tensor CLAHE."""
    root = shared_data_or_skip("sequences", "euroc_v1_01_easy_micro", "mav0")
    files = sorted((root / "cam0" / "data").glob("*.png")) + sorted((root / "cam1" / "data").glob("*.png"))
    if not files:
        pytest.skip(f"no frames under {root} (cam0/data, cam1/data)")
    batch = np.stack([load_gray(f) for f in files])
    got = _fused(batch)
    _assert_same("shared: fused vs cv2", got, _cv2(batch))
    _assert_same("shared: fused vs tensor", got[::8], _tensor(batch[::8]))


# sizes: multiples of the grid; neither dimension; one dimension divisible (OpenCV pads it by a whole
# extra tile); small and thin images; one tile
_SIZES = [((752, 480), 3.0, (8, 8)), ((749, 477), 3.0, (8, 8)), ((752, 477), 3.0, (8, 8)), ((749, 480), 3.0, (8, 8)),
          ((53, 37), 3.0, (8, 8)), ((9, 17), 40.0, (2, 3)), ((64, 33), 2.0, (3, 5)), ((57, 100), 1.0, (1, 1)),
          ((300, 200), 0.0, (8, 8)), ((301, 199), 0.5, (6, 5))]


@pytest.mark.parametrize("wh,clip,grid", _SIZES, ids=[f"{c[0][0]}x{c[0][1]}-{c[1]}-{c[2][0]}x{c[2][1]}"
                                                      for c in _SIZES])
def test_fused_odd_sizes_clips_and_grids(wh, clip, grid):
    w, h = wh
    frames = [load_gray(p) for p in sample_frames("cam0")[:2]]
    batch = np.stack([frames[0][:h, :w], frames[1][480 - h:, 752 - w:]])
    got = _fused(batch, clip, grid)
    _assert_same("fused vs cv2", got, _cv2(batch, clip, grid))
    _assert_same("fused vs tensor", got, _tensor(batch, clip, grid))


def test_fused_extremes():
    """Noise, two levels, a constant image, stripes: clipping with large residuals, ties of the blend."""
    x = _extremes()
    for clip in (3.0, 1.0, 0.0, 100.0):
        _assert_same(f"clip {clip}", _fused(x, clip), _cv2(x, clip))


def test_the_door():
    """``clahe(backend=...)`` and ``_clahe_impl(backend=...)``: both paths (capturable too), layouts,
    float input, the same bits as the tensor CLAHE."""
    frames = [load_gray(p)[:120, :200] for p in sample_frames("cam0")[:3]]
    x = torch.from_numpy(np.stack(frames))
    ref = clahe(x, backend="tensor")
    for be in (None, "auto", "fused"):
        assert torch.equal(clahe(x, backend=be), ref)
        assert torch.equal(clahe(x[:, None].double(), backend=be)[:, 0], ref)
    for cap in (False, True):
        assert torch.equal(_clahe_impl(x, 3.0, 8, 8, capturable=cap, backend="fused").image, ref)
    with pytest.raises(ConfigError, match="clahe_backend"):
        clahe(x, backend="numba")
    with pytest.raises(ValueError, match="uint8"):
        clahe_op(x.float(), 3.0, 8, 8)
    with pytest.raises(ValueError, match="too small"):
        clahe_op(torch.zeros(1, 4, 33, dtype=torch.uint8), 3.0, 8, 8)
    assert clahe_op(torch.zeros(0, 16, 16, dtype=torch.uint8), 3.0, 8, 8).shape == (0, 16, 16)


def test_straight_through_values_from_the_fused_op():
    """The differentiable CLAHE: values from the fused op, the gradient (the LUT's slope) from the
    tensor CLAHE: both equal the tensor-only path's."""
    x = torch.from_numpy(np.stack([load_gray(p)[:64, :96] for p in sample_frames("cam0")[:2]])).float()
    outs = []
    for be in ("tensor", "fused"):
        xi = x.clone().requires_grad_(True)
        y = _clahe_straight_through(xi, 3.0, 8, 8, backend=be)
        (y * torch.linspace(0, 1, y.numel()).view_as(y)).sum().backward()
        outs.append((y.detach(), xi.grad))
    assert torch.equal(outs[0][0], outs[1][0]) and torch.equal(outs[0][1], outs[1][1])


# ------------------------------------------------------------------------------ op, threads, counts
def test_one_op_no_sync_and_tools():
    """One op per call (B = 1 and 5, both paths of ``_clahe_impl``), no host sync; ``opcheck``;
    ``torch.compile(fullgraph=True)`` without a graph break."""
    f = [load_gray(p)[:120, :160] for p in sample_frames("cam0")[:2]]
    for B in (1, 5):
        x = torch.from_numpy(np.stack([f[b % 2] for b in range(B)]))
        _clahe_impl(x, 3.0, 8, 8, backend="fused")  # warm-up
        for cap in (False, True):
            with OpCounter() as c:
                _clahe_impl(x, 3.0, 8, 8, capturable=cap, backend="fused")
            assert c.kernels == 1 and c.syncs == 0, (B, cap, c.summary())
    x = torch.from_numpy(np.stack(f))
    res = torch.library.opcheck(clahe_op, (x, 3.0, 8, 8))
    assert all(v == "SUCCESS" for v in res.values()), res
    got = torch.compile(lambda a: clahe_op(a, 3.0, 8, 8), backend="eager", fullgraph=True)(x)
    assert torch.equal(got, clahe_op(x, 3.0, 8, 8))


def test_threads_split_streams_without_changing_a_bit():
    frames = [load_gray(p) for p in sample_frames("cam0")[:5]]
    x = torch.from_numpy(np.stack(frames))
    one = clahe_op(x, 3.0, 8, 8)
    n = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        assert torch.equal(clahe_op(x, 3.0, 8, 8), one)
        torch.set_num_threads(3)
        assert torch.equal(clahe_op(x[:4], 3.0, 8, 8), one[:4])
    finally:
        torch.set_num_threads(n)


# ------------------------------------------------------------------------------------------ backend
def test_backend_resolution_and_fallback(monkeypatch):
    assert fused.resolve_clahe_backend(None, "cpu") == "fused" and fused.resolve_clahe_backend("auto", "cpu") == "fused"
    assert fused.resolve_clahe_backend("tensor", "cpu") == "tensor"
    assert fused.resolve_clahe_backend(None, "meta") == "tensor"  # no fused kernel there
    with pytest.raises(ConfigError, match="clahe_backend"):
        fused.resolve_clahe_backend("numba", "cpu")
    monkeypatch.setitem(fused._STATUS, ("clahe", "cpu"), "numba cannot be loaded (ImportError: no module named numba)")
    monkeypatch.setattr(fused, "_WARNED", set())
    with pytest.warns(RuntimeWarning, match="fused CLAHE cannot run"):
        assert fused.resolve_clahe_backend(None, "cpu") == "tensor"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert fused.resolve_clahe_backend(None, "cpu") == "tensor"  # said once
    with pytest.raises(ConfigError, match="numba cannot be loaded"):
        fused.resolve_clahe_backend("fused", "cpu")


def test_the_tracker_runs_the_resolved_clahe():
    """``FeatureTracker(clahe_backend=...)``: resolved once, in the params, and the same features
    either way (EuRoC's config equalises)."""
    cfg = tf.load_config(REPO / "configs" / "euroc.yaml")
    assert cfg.equalize
    frames = [torch.from_numpy(load_gray(p)) for p in sample_frames("cam0")[:3]]
    outs = {}
    for be in ("fused", "tensor"):
        tr = tf.FeatureTracker(cfg, num_streams=2, clahe_backend=be)
        assert tr.clahe_backend == be and tr.params.clahe_backend == be
        outs[be] = []
        for i, f in enumerate(frames):
            img = torch.stack([f, frames[(i + 1) % 3]])[:, None]
            fr = tr.track(img, [0.05 * i] * 2)
            outs[be].append((fr.ids.clone(), fr.uv.clone(), fr.valid.clone()))
    for a, b in zip(outs["fused"], outs["tensor"]):
        assert all(torch.equal(p, q) for p, q in zip(a, b))
    assert tf.FeatureTracker(cfg).clahe_backend == "fused"


# --------------------------------------------------------------------------- Triton and machine code
_TRITON_SCRIPT = r"""
import numpy as np, torch
from torch_frontend.fused._triton_clahe import clahe_cuda
from torch_frontend.fused.clahe_op import clahe_op
import tests.test_fused_clahe as t
from tests.conftest import load_gray, sample_frames
f = [load_gray(p) for p in sample_frames("cam0")[:2]]
cases = [((37, 53), 3.0, (8, 8)), ((48, 64), 3.0, (8, 8)), ((33, 64), 2.0, (3, 5)), ((17, 9), 40.0, (2, 3)),
         ((40, 40), 0.0, (4, 4))]
for (h, w), clip, grid in cases:
    x = np.stack([f[0][100:100 + h, 200:200 + w], f[1][:h, :w], t._extremes(h, w)[0]])
    x = torch.from_numpy(np.ascontiguousarray(x))
    got = clahe_cuda(x, clip, *grid)
    assert torch.equal(got, clahe_op(x, clip, *grid)), (h, w, clip, grid)
x = torch.from_numpy(t._extremes(24, 32))
for clip in (1.0, 100.0):
    assert torch.equal(clahe_cuda(x, clip, 4, 4), clahe_op(x, clip, 4, 4)), clip
print("PASS triton")
"""


def test_triton_kernels_equal_the_cpu_kernel_interpreted():
    """The CUDA kernels (``_triton_clahe``) under ``TRITON_INTERPRET=1`` on CPU tensors == the CPU
    kernel, bit for bit: small crops, padded sizes, grids 1..8, no clipping, large residuals
    (~5 s; in a child: ``TRITON_INTERPRET`` is read when ``@triton.jit`` decorates)."""
    if os.environ.get("TORCH_FRONTEND_REQUIRE_TRITON") != "1":
        pytest.importorskip("triton", reason="the fused CUDA kernels are Triton kernels: triton is not installed "
                                             "(make test-all installs it: pip install -e '.[triton]')")
    env = {**os.environ, "TRITON_INTERPRET": "1", "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-c", _TRITON_SCRIPT], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0 and "PASS triton" in proc.stdout, proc.stdout + proc.stderr[-4000:]


@pytest.mark.slow  # a cold numba compile in a child
def test_numba_clahe_has_no_fma(tmp_path):
    """No fused multiply-add in the CPU kernel's machine code (OpenCV rounds every product before its
    sum): compiled afresh in a child (a cache hit cannot be inspected); the blend is float code."""
    code = ("import numpy as np, torch_frontend.fused._numba_clahe as m; x = np.zeros((1, 16, 16), np.uint8); "
            "m.clahe_streams(x, x.copy(), 3.0, 2, 2, 0, 1); asm = ''.join(m.clahe_streams.inspect_asm().values()); "
            "print(len(asm), 'vfmadd' in asm or 'vfmsub' in asm or 'vfnmadd' in asm, 'mulss' in asm or 'mulps' in asm)")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=REPO, timeout=600)
    assert res.returncode == 0, res.stderr
    size, has_fma, has_mul = res.stdout.split()
    assert int(size) > 1000 and has_fma == "False" and has_mul == "True", res.stdout
