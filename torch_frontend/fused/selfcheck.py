"""The CUDA kernels' run-time self-check: a small built-in case against bits stored from the CPU kernels.

Triton's interpreter (the tests' CPU run of the CUDA kernels) executes numpy, so it cannot show a GPU's
own rounding: a compiler that contracted ``a * b + c`` into an FMA, an approximate division or square
root, a flush-to-zero would change bits only on the GPU. Before the fused CUDA kernels are used on a
device, :func:`cuda_selfcheck` runs them on :func:`case` (two synthetic 8-bit frames, a shift of a few
pixels, points inside, at the edge, outside, invalid, with an initial guess, with the forward-backward
check; CLAHE of both frames; setMask on those points) and compares every output bit with :data:`EXPECTED`, which the CPU kernels produced
(``tests/test_fused.py`` holds the two equal). Any difference: the fused backend is refused on CUDA,
with the reason, and the tensor kernels run (one warning, ``fused.resolve_backend``). It runs once per
process, at the first resolution of the backend on CUDA (tracker construction, a ``track_lk`` call),
outside any graph capture or compilation.

Convention:
    :func:`case` returns the ops' arguments as CPU tensors; :func:`digest` reduces the outputs
    ``(packed pyramids, next_pts, status, capped)`` to one sha256 hex string.
"""

from __future__ import annotations

import hashlib
from typing import Dict, Optional

import numpy as np
import torch

__all__ = ["case", "digest", "cuda_selfcheck", "EXPECTED", "run_case", "corners_selfcheck", "run_corners_case"]

#: sha256 of the CPU kernels' outputs on :func:`case` (regenerate with ``python -m torch_frontend.fused.selfcheck``
#: after a change to the kernels that is meant to move bits; tests/test_fused.py checks it)
EXPECTED = "7fb7e81dfab8bb9802fcf74398b3ba535bb3bd7ebf5041696766e2e5f39f3a96"

_H, _W = 72, 104
_MAX_LEVEL, _PAD, _WIN = 2, 22, 21


def _texture(seed: int) -> np.ndarray:
    """A textured ``(_H + 16, _W + 16)`` uint8 image from integer arithmetic only (bit-reproducible on
    any machine): a linear congruential field, box-smoothed twice, plus a ramp."""
    n = (_H + 16) * (_W + 16)
    x = np.empty(n, dtype=np.int64)
    s = seed
    for i in range(n):
        s = (1103515245 * s + 12345) % (1 << 31)
        x[i] = s >> 23
    img = x.reshape(_H + 16, _W + 16)
    for _ in range(2):
        p = np.pad(img, 1, mode="edge")
        img = sum(p[dy:dy + img.shape[0], dx:dx + img.shape[1]] for dy in range(3) for dx in range(3)) // 9
    ramp = (np.arange(_W + 16)[None, :] + 2 * np.arange(_H + 16)[:, None]) // 3
    return ((img + ramp) % 256).astype(np.uint8)


def case() -> Dict[str, torch.Tensor]:
    """The built-in case (CPU tensors): ``prev``, ``next`` ``(2, _H, _W)`` uint8 (stream 1 the same
    scene shifted differently), ``pts``, ``init`` ``(2, 12, 2)`` float32, ``valid`` ``(2, 12)`` bool."""
    big = _texture(7)
    prev = np.stack([big[4:4 + _H, 5:5 + _W], big[9:9 + _H, 2:2 + _W]])
    nxt = np.stack([big[6:6 + _H, 8:8 + _W], big[7:7 + _H, 1:1 + _W]])  # shifts (3, 2) and (-1, -2) px
    gy, gx = np.meshgrid(np.linspace(12.3, _H - 13.1, 3), np.linspace(10.7, _W - 9.9, 3), indexing="ij")
    grid = np.stack([gx.ravel(), gy.ravel()], 1)
    extra = np.array([[1.5, 2.25], [_W - 1.25, _H - 0.5], [-30.0, 20.0]])  # edge, edge, outside
    pts = np.stack([np.concatenate([grid, extra]), np.concatenate([grid[::-1], extra])]).astype(np.float32)
    valid = np.ones((2, 12), dtype=bool)
    valid[1, 4] = False
    init = pts + np.array([[[2.5, 1.75]], [[-0.5, -1.5]]], dtype=np.float32)
    init[1, 7, 0] = np.nan  # a non-finite guess: status 0, the lane holds its point
    return {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in
            dict(prev=prev, next=nxt, pts=pts, valid=valid, init=init).items()}


def digest(*outputs: torch.Tensor) -> str:
    """sha256 hex of the outputs' dtypes, shapes and bytes (on the CPU)."""
    h = hashlib.sha256()
    for t in outputs:
        t = t.detach().cpu().contiguous()
        h.update(f"{t.dtype} {tuple(t.shape)};".encode())
        h.update((t.to(torch.uint8) if t.dtype == torch.bool else t).numpy().tobytes())
    return h.hexdigest()


def run_case(device) -> str:
    """The fused ops on :func:`case` on ``device`` (both pyramids; the LK plain, with a guess, with the
    forward-backward check; CLAHE of both frames, VINS's and a padded grid, with and without
    clipping; setMask, :func:`_mask_outputs`), as one :func:`digest`."""
    from .clahe_op import clahe_op
    from .ops import lk_op, pyramid_op

    c = {k: v.to(device) for k, v in case().items()}
    P = pyramid_op(c["prev"], _MAX_LEVEL, _PAD)
    Q = pyramid_op(c["next"], _MAX_LEVEL, _PAD)
    outs = [P, Q]
    for init, fb in ((None, -1), (c["init"], -1), (None, 1)):
        outs += list(lk_op(P, Q, c["pts"], c["valid"], init, _H, _W, _PAD, _PAD, _MAX_LEVEL, _WIN, _WIN, 30, 0.01,
                           1e-4, fb, 0.5, True))
    for img, clip, gx, gy in ((c["prev"], 3.0, 8, 8), (c["next"], 2.0, 5, 3), (c["next"], 0.0, 4, 4)):
        outs.append(clahe_op(img, clip, gx, gy))  # 104 % 5 != 0: the reflect-101 padded histogram source
    outs += _mask_outputs(c)
    return digest(*outs)


def _mask_outputs(c) -> list:
    """setMask (``torch_frontend::set_mask``) on the case's points and guesses as 24 features per stream
    (the edge, outside and NaN ones among them), track counts with ties, discs that overlap and cross
    the border: one base mask for both streams (int64 counts), then one per stream (int32, float64)."""
    from .mask_op import set_mask_op

    pts = torch.cat((c["pts"], c["init"]), 1)
    B, N = pts.shape[:2]
    cnt = (torch.arange(B * N, device=pts.device).view(B, N) * 7) % 4
    valid = torch.cat((c["valid"], c["valid"]), 1)
    base = torch.full((1, _H, _W), 255, dtype=torch.uint8, device=pts.device)
    base[:, :, :6] = 254  # not exactly 255: no feature kept there
    base[:, 40:, 90:] = 0
    outs = list(set_mask_op(pts, cnt, valid, base, 17.0))
    per_stream = torch.cat((base, base.flip(-1)))
    outs += list(set_mask_op(pts.double(), cnt.int(), valid, per_stream, 11.5))
    return outs


def cuda_selfcheck(device=None) -> Optional[str]:
    """None when the fused CUDA kernels give :data:`EXPECTED` on ``device`` (default: the current CUDA
    device), else why not (a difference or an error)."""
    dev = torch.device("cuda", torch.cuda.current_device()) if device is None else torch.device(device)
    try:
        got = run_case(dev)
    except Exception as e:  # noqa: BLE001 - a kernel that fails to compile or launch: not usable
        return f"the CUDA kernels failed their self-check ({type(e).__name__}: {str(e).splitlines()[0][:200]})"
    if got != EXPECTED:
        return f"the CUDA kernels' self-check gave other bits than the CPU kernels ({got[:12]} != {EXPECTED[:12]})"
    return None


def run_corners_case(device) -> str:
    """``torch_frontend::good_features`` on :func:`case`'s two frames on ``device`` (no mask, and a mask
    with a hole and a cut-off border; minimum distances 8, 3 and 0.5), as one :func:`digest`."""
    from .corners_op import good_features_op

    img = case()["prev"].to(device)
    B, H, W = img.shape
    mask = torch.ones((B, H, W), dtype=torch.bool)
    mask[0, 20:40, 30:60] = False
    mask[1, :, :12] = False
    mask = mask.to(device)
    mc = torch.tensor([25, 9], device=device)
    outs = []
    for m in (None, mask):
        for md in (8.0, 3.0, 0.5):
            outs += list(good_features_op(img, mc, m, 25, 0.01, md))
    return digest(*outs)


def corners_selfcheck(device=None) -> Optional[str]:
    """None when the fused detection's CUDA kernels give the CPU kernel's bits on
    :func:`run_corners_case` (computed here, on the CPU: the CPU kernel is held equal to the tensor
    path and cv2 by the tests), else why not."""
    dev = torch.device("cuda", torch.cuda.current_device()) if device is None else torch.device(device)
    try:
        got = run_corners_case(dev)
        want = run_corners_case("cpu")
    except Exception as e:  # noqa: BLE001 - a kernel that fails to compile or launch: not usable
        return f"the CUDA detection kernels failed their self-check ({type(e).__name__}: {str(e).splitlines()[0][:200]})"
    if got != want:
        return f"the CUDA detection kernels' self-check gave other bits than the CPU kernel ({got[:12]} != {want[:12]})"
    return None


if __name__ == "__main__":  # print the CPU kernels' digest (to store in EXPECTED); --warm: compile them quietly
    import sys
    import time

    t0 = time.perf_counter()
    got = run_case("cpu")
    if "--warm" in sys.argv[1:]:
        from .ransac_op import cuda_selfcheck as _ransac_check

        _ransac_check("cpu")  # compiles the F-RANSAC scoring kernel too (its CPU run against itself)
        run_corners_case("cpu")
        # the CPU-only front op (CLAHE -> pyramid -> LK by stream groups): compiled too, outside the digest
        from .front_op import front_op
        from .ops import pyramid_op

        c = case()
        front_op(c["next"], pyramid_op(c["prev"], _MAX_LEVEL, _PAD), c["pts"], c["valid"], 3.0, 8, 8, _MAX_LEVEL, _PAD,
                 _MAX_LEVEL, _WIN, _WIN, 30, 0.01, 1e-4, 1)
        print(f"torch_frontend: the fused CPU kernels are compiled and cached ({time.perf_counter() - t0:.1f} s)")
    else:
        print(got)
