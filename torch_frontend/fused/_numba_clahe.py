"""CLAHE on the CPU: a numba kernel, ``cv2.createCLAHE(clip_limit, (gx, gy)).apply`` of 8-bit images bit for bit.

Convention:
    ``src``, ``dst``: ``(B, H, W)`` uint8 (``dst`` written); ``gx, gy``: tiles along x / y; ``clip_limit``
    as OpenCV's (``<= 0``: no clipping); streams ``s0 <= b < s1``. The image must be large enough for
    the reflect-101 padding (``equalize.check_grid``: one reflection suffices).

The contract, operation by operation (``docs/kernels.md``, "CLAHE"), in OpenCV's order:

1. **Tiles.** ``W % gx == 0 and H % gy == 0``: tiles of ``(W // gx) x (H // gy)`` pixels of the image;
   otherwise of the image padded bottom / right by ``gx - W % gx`` columns and ``gy - H % gy`` rows
   with BORDER_REFLECT_101 (a dimension that was divisible then gets a whole extra tile: OpenCV's
   quirk). ``area = tw * th``.
2. **Histograms** (int32, exact in any order) of every tile.
3. **Clip** (``clip_limit > 0``): ``clip = max(int(clip_limit * area / 256), 1)`` (double, truncated);
   bins above it are cut, ``excess`` the sum cut; every bin gets ``excess // 256``, and the remainder
   ``r = excess % 256`` one count each on bins ``0, s, 2s, ...`` (the first ``r`` of them,
   ``s = max(256 // r, 1)``).
4. **LUTs.** ``lut[v] = cvRound(float(cumsum[v]) * (255.f / float(area)))`` in float32, saturated.
5. **Blend**, per pixel ``(x, y)`` of value ``v``: ``txf = float(x) * (1.f / tw) - 0.5f``,
   ``tx1 = floor(txf)``, ``xa = txf - tx1``, ``xa1 = 1.f - xa`` (likewise ``y``), tile columns
   ``max(tx1, 0)`` and ``min(tx1 + 1, gx - 1)`` (rows likewise), then
   ``cvRound((l11 xa1 + l12 xa) ya1 + (l21 xa1 + l22 xa) ya)``, every product and sum rounded to
   float32 in that order (no FMA: numba contracts nothing without ``fastmath``).

Every float here is a numpy ``float32`` (numba would widen ``float32 * int`` to float64).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["clahe_streams"]

_F32 = np.float32


@njit(cache=True, nogil=True)
def _histograms(img, H, W, gx, gy, tw, th, hist):
    """The ``(gy * gx, 256)`` int32 tile histograms of ``img (H, W)``, padded bottom / right to
    ``(gy th, gx tw)`` with BORDER_REFLECT_101 (row ``H + k`` is row ``H - 2 - k``)."""
    hist[:] = 0
    Hs, Ws = gy * th, gx * tw
    wx = min(W, Ws)
    for yy in range(Hs):
        sr = yy if yy < H else 2 * H - 2 - yy
        row = img[sr]
        t0 = (yy // th) * gx
        for tx in range(gx):
            h = hist[t0 + tx]
            x1 = min((tx + 1) * tw, wx)
            for x in range(tx * tw, x1):
                h[row[x]] += 1
        h = hist[t0 + gx - 1]
        for x in range(W, Ws):  # the padded columns all lie in the last tile column
            h[row[2 * W - 2 - x]] += 1


@njit(cache=True, nogil=True)
def _luts(hist, clip_limit, area, lut):
    """Clip and redistribute every tile histogram of ``hist (T, 256)`` in place, then ``lut (T, 256)``
    float32 = the rounded, saturated LUT values (integers 0..255)."""
    T = hist.shape[0]
    clip = 0
    if clip_limit > 0.0:
        clip = max(int(clip_limit * area / 256), 1)  # double, as OpenCV
    scale = _F32(255.0) / _F32(area)
    for t in range(T):
        h = hist[t]
        if clip_limit > 0.0:
            excess = 0
            for i in range(256):
                if h[i] > clip:
                    excess += h[i] - clip
                    h[i] = clip
            batch = excess // 256
            residual = excess - batch * 256
            for i in range(256):
                h[i] += batch
            if residual != 0:
                step = max(256 // residual, 1)
                i = 0
                while i < 256 and residual > 0:
                    h[i] += 1
                    i += step
                    residual -= 1
        s = 0
        lt = lut[t]
        for i in range(256):
            s += h[i]
            r = np.rint(_F32(s) * scale)
            lt[i] = min(max(r, _F32(0.0)), _F32(255.0))


@njit(cache=True, nogil=True)
def _blend(img, out, H, W, gx, gy, tw, th, lut, xa, xa1, c1, c2):
    """``out (H, W)`` uint8: the bilinear blend of the tile LUTs ``lut (T * 256,)`` float32 (step 5);
    ``xa, xa1 (W,)`` float32 and ``c1, c2 (W,)`` int64 (the left / right tile's LUT offsets) are
    scratch, filled here."""
    inv_tw = _F32(1.0) / _F32(tw)
    inv_th = _F32(1.0) / _F32(th)
    half = _F32(0.5)
    one = _F32(1.0)
    for x in range(W):
        txf = _F32(x) * inv_tw - half
        tx1 = int(np.floor(txf))
        a = txf - _F32(tx1)
        xa[x] = a
        xa1[x] = one - a
        c1[x] = max(tx1, 0) * 256
        c2[x] = min(tx1 + 1, gx - 1) * 256
    for y in range(H):
        tyf = _F32(y) * inv_th - half
        ty1 = int(np.floor(tyf))
        ya = tyf - _F32(ty1)
        ya1 = one - ya
        l1 = lut[max(ty1, 0) * gx * 256:]
        l2 = lut[min(ty1 + 1, gy - 1) * gx * 256:]
        row = img[y]
        o = out[y]
        for x in range(W):
            v = np.int64(row[x])
            i1 = c1[x] + v
            i2 = c2[x] + v
            res = (l1[i1] * xa1[x] + l1[i2] * xa[x]) * ya1 + (l2[i1] * xa1[x] + l2[i2] * xa[x]) * ya
            r = np.rint(res)  # cvRound: half to even; res lies in [0, 255] up to rounding
            o[x] = np.uint8(min(max(r, _F32(0.0)), _F32(255.0)))


@njit(cache=True, nogil=True)
def clahe_streams(src, dst, clip_limit, gx, gy, s0, s1):
    """CLAHE of streams ``s0 <= b < s1`` of ``src (B, H, W)`` uint8 into ``dst`` (module docstring)."""
    H, W = src.shape[1], src.shape[2]
    if W % gx == 0 and H % gy == 0:
        tw, th = W // gx, H // gy
    else:
        tw, th = (W + gx - W % gx) // gx, (H + gy - H % gy) // gy
    T = gx * gy
    hist = np.empty((T, 256), dtype=np.int32)
    lut = np.empty((T, 256), dtype=np.float32)
    lut1 = lut.reshape(T * 256)
    xa = np.empty(W, dtype=np.float32)
    xa1 = np.empty(W, dtype=np.float32)
    c1 = np.empty(W, dtype=np.int64)
    c2 = np.empty(W, dtype=np.int64)
    for b in range(s0, s1):
        _histograms(src[b], H, W, gx, gy, tw, th, hist)
        _luts(hist, clip_limit, tw * th, lut)
        _blend(src[b], dst[b], H, W, gx, gy, tw, th, lut1, xa, xa1, c1, c2)
