"""CLAHE vs cv2.createCLAHE(3.0, (8, 8)).apply on real EuRoC frames (batched, CPU/CUDA)."""

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


def _compare(batch_np, device, clip=3.0, grid=(8, 8)):
    out = clahe(torch.from_numpy(batch_np)[:, None].to(device), clip, grid)
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
    out3 = clahe(b)  # (B, H, W) in -> (B, H, W) out
    assert out3.shape == (2, 64, 96)
    outf = clahe(b[:, None].double())  # float grey levels are rounded to 8-bit first
    assert torch.equal(outf[:, 0], out3)


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
    ref = clahe(b)
    monkeypatch.setitem(_tuning.STRATEGIES, "cpu", _tuning.ONE_PASS)  # no blocking, as on other devices
    assert torch.equal(clahe(b), ref)
    blocks = dataclasses.replace(_tuning.CPU, clahe_block_pixels=1000)  # 5 rows per block, crossing streams
    monkeypatch.setitem(_tuning.STRATEGIES, "cpu", blocks)
    assert torch.equal(clahe(b), ref)
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
