"""VINS's ``setMask`` on the CPU: a numba kernel (the contract is ``docs/kernels.md``, "setMask").

Convention:
    ``pts``: ``(B, N, 2)`` float32 or float64 pixels ``(x, y)``; ``pri``: ``(B, N)`` integer track
    counts; ``valid``: ``(B, N)`` bool; ``base``: ``(Bm, H, W)`` uint8 with ``Bm`` 1 (every stream) or
    ``B``; ``keep``: ``(B, N)`` bool out (input order); ``out``: ``(B, H, W)`` uint8 out.
    ``spans``: ``(R + 1,)`` int64, the half width of the filled disc's row ``|dy|`` for
    ``dy = 0..R`` (:func:`~.mask_op.disc_spans`); ``r2``: the disc's integer squared radius (the
    disc is ``dx² + dy² <= r2``, ``cv2.circle(..., radius, 0, FILLED)`` for ``r2 = radius²``).

Per stream, the sequential VINS loop itself: ``out = base``; the features in the order of a stable
sort by track count, descending (invalid ones are never visited); a feature is kept iff its centre
``(cvRound(x), cvRound(y))`` (half to even) lies in the image and ``out`` there is exactly 255; a
kept feature then writes 0 on its disc's row spans (clipped to the image). The result is the tensor
kernel's (``masks._distance_mask_impl``) bit for bit: every decision is an integer comparison.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["set_mask_streams"]


@njit(cache=True, nogil=True)
def _centre(v, size):
    """``cvRound(v)`` (half to even) as an int64 when it lies in ``[0, size)``, else -1 (NaN and
    infinities too)."""
    if not (v > -1.0 and v < size + 1.0):  # False for NaN; a finite range before the conversion
        return -1
    c = np.int64(np.rint(v))
    return c if c >= 0 and c < size else -1


@njit(cache=True, nogil=True)
def _stable_order(pri, valid, order):
    """The valid slots of one stream by ``pri`` descending, ties by slot (a stable insertion of each
    slot after the ones that are not smaller), into ``order``; returns their count."""
    n = 0
    for i in range(pri.shape[0]):
        if not valid[i]:
            continue
        p = pri[i]
        j = n
        while j > 0 and pri[order[j - 1]] < p:
            order[j] = order[j - 1]
            j -= 1
        order[j] = i
        n += 1
    return n


@njit(cache=True, nogil=True)
def _disc(out, cx, cy, spans):
    """0 on the filled disc's row spans around ``(cx, cy)``, clipped to ``out (H, W)``."""
    H, W = out.shape
    R = spans.shape[0] - 1
    for dy in range(-R, R + 1):
        y = cy + dy
        if y < 0 or y >= H:
            continue
        hw = spans[abs(dy)]
        x0 = max(cx - hw, 0)
        seg = out[y, x0:min(cx + hw + 1, W)]  # a slice: indices from 0, no wrap-around test per pixel
        for x in range(seg.shape[0]):
            seg[x] = 0


@njit(cache=True, nogil=True)
def set_mask_streams(pts, pri, valid, base, spans, keep, out, s0, s1):
    """setMask of streams ``s0 .. s1 - 1`` (see the module docstring)."""
    B, N = valid.shape
    H, W = out.shape[1], out.shape[2]
    order = np.empty(N, dtype=np.int64)
    for b in range(s0, s1):
        src = base[b if base.shape[0] > 1 else 0].reshape(H * W)  # C-contiguous: views
        dst = out[b]
        flat = dst.reshape(H * W)
        for e in range(H * W):
            flat[e] = src[e]
        for i in range(N):
            keep[b, i] = False
        n = _stable_order(pri[b], valid[b], order)
        for k in range(n):
            i = order[k]
            cx = _centre(pts[b, i, 0], W)
            cy = _centre(pts[b, i, 1], H)
            if cx < 0 or cy < 0 or dst[cy, cx] != 255:
                continue
            keep[b, i] = True
            _disc(dst, cx, cy, spans)
