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

The blend runs per band of rows (same ``ty1``) and run of columns (same ``tx1``): the four LUTs of
that cell interleaved as ``(l11, l12, l21, l22)`` per value, so a pixel is one 16-byte load, one
``<4 x float>`` product with ``(xa1, xa, xa1, xa)``, a pairwise sum and a product with
``(ya1, ya1, ya, ya)``: the same IEEE operations on the same values as the scalar expression
(``_f4_blend``), ~40 % less time than the scalar loop.

Every float here is a numpy ``float32`` (numba would widen ``float32 * int`` to float64).
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

from ._simd import _F4, F32x4, _i32, _ptr

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


@intrinsic
def _f4_load(typingctx, arr, idx):
    """Four float32 from ``arr[idx:idx + 4]`` (1-D C-contiguous, no bounds check)."""
    def cg(context, builder, sig, args):
        return builder.load(_ptr(context, builder, sig.args[0], args[0], args[1], _F4), align=4)
    return F32x4(arr, idx), cg


@intrinsic
def _f4_blend(typingctx, q, w, yw):
    """OpenCV's blend of ``q = (l11, l12, l21, l22)`` with ``w = (xa1, xa, xa1, xa)`` and
    ``yw = (ya1, ya1, ya, ya)``: ``p = q w``, ``s = p + (p1, p0, p3, p2)``, ``t = s yw``, ``t0 + t2``
    = ``(l11 xa1 + l12 xa) ya1 + (l21 xa1 + l22 xa) ya``, every product and sum one IEEE float32
    instruction (no fast-math flags: no contraction). A float32."""
    def cg(context, builder, sig, args):
        q, w, yw = args
        p = builder.fmul(q, w)
        s = builder.fadd(p, builder.shuffle_vector(p, p, ir.Constant(ir.VectorType(_i32, 4), [1, 0, 3, 2])))
        t = builder.fmul(s, yw)
        return builder.fadd(builder.extract_element(t, ir.Constant(_i32, 0)),
                            builder.extract_element(t, ir.Constant(_i32, 2)))
    return types.float32(q, w, yw), cg


@njit(cache=True, nogil=True)
def _fill_cell(t, a, b, c, d):
    """``t (1024,)`` float32: ``(a[v], b[v], c[v], d[v])`` at ``4 v``: a cell's four tile LUTs, interleaved."""
    for v in range(256):
        t[4 * v] = a[v]
        t[4 * v + 1] = b[v]
        t[4 * v + 2] = c[v]
        t[4 * v + 3] = d[v]


@njit(cache=True, nogil=True)
def _blend_run(row, o, wx, t, yw):
    """``o[x]`` = the blend of pixel ``row[x]`` of a run of columns within one cell (``t``: its
    interleaved LUTs, ``wx (4 n,)``: the columns' ``(xa1, xa, xa1, xa)``, ``yw``: the row's weights)."""
    yv = _f4_load(yw, 0)
    lo, hi = _F32(0.0), _F32(255.0)
    for x in range(row.shape[0]):
        i = np.uint32(row[x]) * np.uint32(4)
        r = np.rint(_f4_blend(_f4_load(t, i), _f4_load(wx, 4 * x), yv))  # cvRound: half to even
        o[x] = np.uint8(np.int32(min(max(r, lo), hi)))


@njit(cache=True, nogil=True)
def _blend(img, out, H, W, gx, gy, tw, th, lut, wx, seg, tab, yw):
    """``out (H, W)`` uint8: the bilinear blend of the tile LUTs ``lut (T, 256)`` float32 (step 5).

    Scratch (filled here): ``wx (4 W,)`` float32, each column's ``(xa1, xa, xa1, xa)``; ``seg (gx + 2,)``
    int64, where each run of columns with the same ``tx1`` starts; ``tab (gx + 1, 1024)`` float32, the
    interleaved LUTs of the cells of the current band of rows (same ``ty1``); ``yw (4,)`` float32.
    """
    inv_tw = _F32(1.0) / _F32(tw)
    inv_th = _F32(1.0) / _F32(th)
    half = _F32(0.5)
    one = _F32(1.0)
    for k in range(gx + 2):
        seg[k] = W
    for x in range(W - 1, -1, -1):  # tx1 in -1..gx - 1, non-decreasing in x
        txf = _F32(x) * inv_tw - half
        tx1 = int(np.floor(txf))
        a = txf - _F32(tx1)
        wx[4 * x] = one - a
        wx[4 * x + 1] = a
        wx[4 * x + 2] = one - a
        wx[4 * x + 3] = a
        seg[tx1 + 1] = x
    for k in range(gx, -1, -1):  # a run no column has: empty, where the next one starts
        if seg[k] > seg[k + 1]:
            seg[k] = seg[k + 1]
    band = -2
    for y in range(H):
        tyf = _F32(y) * inv_th - half
        ty1 = int(np.floor(tyf))
        ya = tyf - _F32(ty1)
        ya1 = one - ya
        if ty1 != band:
            band = ty1
            r1 = max(ty1, 0) * gx
            r2 = min(ty1 + 1, gy - 1) * gx
            for k in range(gx + 1):
                t1 = max(k - 1, 0)
                t2 = min(k, gx - 1)
                _fill_cell(tab[k], lut[r1 + t1], lut[r1 + t2], lut[r2 + t1], lut[r2 + t2])
        yw[0] = ya1
        yw[1] = ya1
        yw[2] = ya
        yw[3] = ya
        row = img[y]
        o = out[y]
        for k in range(gx + 1):
            x0, x1 = seg[k], seg[k + 1]
            if x1 > x0:
                _blend_run(row[x0:x1], o[x0:x1], wx[4 * x0:4 * x1], tab[k], yw)


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
    wx = np.empty(4 * W, dtype=np.float32)
    seg = np.empty(gx + 2, dtype=np.int64)
    tab = np.empty((gx + 1, 1024), dtype=np.float32)
    yw = np.empty(4, dtype=np.float32)
    for b in range(s0, s1):
        _histograms(src[b], H, W, gx, gy, tw, th, hist)
        _luts(hist, clip_limit, tw * th, lut)
        _blend(src[b], dst[b], H, W, gx, gy, tw, th, lut, wx, seg, tab, yw)
