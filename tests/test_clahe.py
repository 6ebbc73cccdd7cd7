"""The tensor CLAHE vs cv2.createCLAHE(3.0, (8, 8)).apply on real EuRoC frames (batched, CPU/CUDA).
(The fused op ``torch_frontend::clahe``: ``tests/test_fused_clahe.py``.)"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from torch_frontend.equalize import clahe
from torch_frontend.errors import ConfigError

from .conftest import load_gray, sample_frames


def _frames(n=3):
    return [load_gray(p) for p in sample_frames("cam0")[:: max(1, 24 // n)][:n]]


def _compare(batch_np, device, clip=3.0, grid=(8, 8), backend="tensor"):
    out = clahe(torch.from_numpy(batch_np)[:, None].to(device), clip, grid, backend=backend)
    assert out.dtype == torch.uint8 and out.shape == (len(batch_np), 1) + batch_np.shape[1:]
    out = out[:, 0].cpu().numpy().astype(np.int32)
    ref = np.stack([cv2.createCLAHE(clip, grid).apply(np.ascontiguousarray(b)) for b in batch_np]).astype(np.int32)
    d = np.abs(out - ref)
    return int(d.max()), float((d == 0).mean())


# 752x480 native, 640x480 and 512x512 crops (multiples of 8), 749x477 (neither), 752x477 and
# 749x480 (one divisible dimension: OpenCV pads it by a whole extra tile).
@pytest.mark.parametrize("wh", [(752, 480), (640, 480), (512, 512), (749, 477), (752, 477), (749, 480)])
def test_clahe_matches_opencv(device, wh):
    w, h = wh
    batch = np.stack([f[:h, :w] for f in _frames(3)])
    dmax, same = _compare(batch, device)
    # bar: max |diff| <= 1 and >= 99.9 % identical; measured: bit-exact
    assert dmax <= 1 and same >= 0.999
    assert dmax == 0 and same == 1.0


@pytest.mark.parametrize("clip,grid", [(2.0, (4, 4)), (40.0, (8, 8)), (0.0, (8, 8)), (3.0, (6, 5))])
def test_clahe_other_parameters(clip, grid):
    batch = np.stack([f[100:300, 50:350] for f in _frames(2)])
    dmax, same = _compare(batch, "cpu", clip, grid)
    assert dmax == 0 and same == 1.0


def test_clahe_layouts_and_float():
    f = _frames(2)
    b = torch.from_numpy(np.stack([x[:64, :96] for x in f]))
    out3 = clahe(b, backend="tensor")  # (B, H, W) in -> (B, H, W) out
    assert out3.shape == (2, 64, 96)
    outf = clahe(b[:, None].double(), backend="tensor")  # float grey levels are rounded to 8-bit first
    assert torch.equal(outf[:, 0], out3)
    assert torch.equal(clahe(b[:, None].double())[:, 0], out3)  # the default (fused on the CPU) too


def test_clahe_errors():
    x = torch.zeros(1, 1, 32, 32, dtype=torch.uint8)
    with pytest.raises(ConfigError):
        clahe(x, 3.0, (0, 8))
    with pytest.raises(ValueError):
        clahe(torch.zeros(2, 3, 32, 32, dtype=torch.uint8))
    with pytest.raises(ConfigError):  # reflect-101 pad of 4 rows needs more than 4 rows
        clahe(torch.zeros(1, 1, 4, 33, dtype=torch.uint8))


def test_clahe_cpu_row_blocks_equal_one_block(monkeypatch):
    """The CPU row blocking (cache-sized pixel blocks) does not change the result."""
    import dataclasses

    from torch_frontend import _tuning

    b = torch.from_numpy(np.stack([x[:120, :200] for x in _frames(2)]))[:, None]
    ref = clahe(b, backend="tensor")
    monkeypatch.setitem(_tuning.STRATEGIES, "cpu", _tuning.ONE_PASS)  # no blocking, as on other devices
    assert torch.equal(clahe(b, backend="tensor"), ref)
    blocks = dataclasses.replace(_tuning.CPU, clahe_block_pixels=1000)  # 5 rows per block, crossing streams
    monkeypatch.setitem(_tuning.STRATEGIES, "cpu", blocks)
    assert torch.equal(clahe(b, backend="tensor"), ref)
    blocks = dataclasses.replace(_tuning.CPU, clahe_block_pixels=1)  # one row per block; padded (49x61) size
    monkeypatch.setitem(_tuning.STRATEGIES, "cpu", blocks)
    dmax, same = _compare(np.ascontiguousarray(b[:, 0, :49, :61].numpy()), "cpu")
    assert dmax == 0 and same == 1.0


def test_public_name_is_the_function_after_module_import():
    """The module is ``equalize``: importing it (as the tracker does) leaves ``torch_frontend.clahe``
    the function (a module of the same name would replace the package attribute)."""
    import importlib

    import torch_frontend as tf

    importlib.import_module("torch_frontend.equalize")
    assert callable(tf.clahe) and tf.clahe is clahe
    out = tf.clahe(torch.zeros(1, 16, 16, dtype=torch.uint8))
    assert out.shape == (1, 16, 16) and out.dtype == torch.uint8


# sizes that are multiples of the grid, and which block offset each takes: 752x480 (blocks regular
# in y, 48 / 46 / 47... pixels in x: the float32 cell boundary is off the tile centre), 64x63 with
# 8x7 tiles (regular in x only), 63x63 with 7x7 tiles (neither: a (B, H, W) offset), 16x8 with
# 8x8 tiles (1-pixel-high tiles have no second half: the per-cell form)
_BLOCK_CASES = [((752, 480), 3.0, (8, 8), (16, 30, 752)), ((640, 480), 40.0, (8, 8), (16, 30, 640)),
                ((300, 200), 2.0, (6, 5), (10, 20, 300)), ((64, 63), 3.0, (8, 7), (63, 16, 4)),
                ((63, 63), 0.0, (7, 7), (63, 63)), ((63, 63), 3.0, (7, 7), (63, 63)), ((16, 8), 3.0, (8, 8), None)]


@pytest.mark.parametrize("wh,clip,grid,shape", _BLOCK_CASES, ids=[f"{c[0][0]}x{c[0][1]}-{c[1]}-{c[2][0]}x{c[2][1]}"
                                                                  for c in _BLOCK_CASES])
def test_clahe_block_keys_equal_opencv_and_default(monkeypatch, wh, clip, grid, shape):
    """The device form of the capturable CLAHE (``Strategy.clahe_block_keys``: one key per pixel for
    histograms and LUT gather, the 2^23 rounding) == cv2 == the default path, bit for bit."""
    import dataclasses

    from torch_frontend import _tuning
    from torch_frontend.equalize import _block_geometry, _clahe_impl

    w, h = wh
    batch = np.stack([f[:h, :w] for f in _frames(3)])
    x = torch.from_numpy(batch)
    dflt = _clahe_impl(x, clip, *grid).image
    monkeypatch.setitem(_tuning.STRATEGIES, "cpu", dataclasses.replace(_tuning.CPU, clahe_block_keys=True))
    blk = _block_geometry(3, h, w, grid[0], grid[1], x.device)
    assert (blk is None) == (shape is None) and (blk is None or blk.view_shape[1:] == shape)
    got = _clahe_impl(x, clip, *grid, capturable=True).image
    assert got.dtype == torch.uint8 and got.is_contiguous() and torch.equal(got, dflt)
    ref = np.stack([cv2.createCLAHE(clip, grid).apply(np.ascontiguousarray(b)) for b in batch])
    assert np.array_equal(got.numpy(), ref)
    assert torch.equal(_clahe_impl(x[1:2], clip, *grid, capturable=True).image, got[1:2])  # B = 1: its row


def test_clahe_block_keys_extremes(monkeypatch):
    """Saturated, constant and two-level images (clipping with every residual, ties of the blend)."""
    import dataclasses

    from torch_frontend import _tuning
    from torch_frontend.equalize import _clahe_impl

    g = torch.Generator().manual_seed(3)
    noise = torch.randint(0, 256, (2, 96, 128), generator=g, dtype=torch.uint8)
    x = torch.cat([noise, noise // 128 * 255, torch.full((1, 96, 128), 7, dtype=torch.uint8),
                   torch.zeros(1, 96, 128, dtype=torch.uint8).index_fill_(2, torch.arange(0, 128, 3), 255)])
    monkeypatch.setitem(_tuning.STRATEGIES, "cpu", dataclasses.replace(_tuning.CPU, clahe_block_keys=True))
    for clip in (3.0, 1.0, 0.0):
        got = _clahe_impl(x, clip, 8, 8, capturable=True).image
        ref = np.stack([cv2.createCLAHE(clip, (8, 8)).apply(b) for b in x.numpy()])
        assert np.array_equal(got.numpy(), ref), clip


def test_clahe_block_keys_kernels_and_no_sync(monkeypatch):
    """The device form: no host sync, 23 kernels whatever B (the per-cell form takes 40)."""
    import dataclasses

    from torch_frontend import _tuning
    from torch_frontend.equalize import _clahe_impl
    from torch_frontend.testing.dispatch_count import OpCounter

    monkeypatch.setitem(_tuning.STRATEGIES, "cpu", dataclasses.replace(_tuning.CPU, clahe_block_keys=True))
    f = _frames(2)
    for B in (1, 5):
        x = torch.from_numpy(np.stack([f[b % 2][:120, :160] for b in range(B)]))
        _clahe_impl(x, 3.0, 8, 8, capturable=True)  # warm-up: cached geometry
        with OpCounter() as c:
            _clahe_impl(x, 3.0, 8, 8, capturable=True)
        assert c.syncs == 0 and c.kernels <= 23, c.summary()
