"""The packed 8-bit pyramid on the CPU: a numba kernel (``fused/layout.py`` says where each level lies).

Convention:
    ``img``: ``(B, H, W)`` uint8; ``out``: ``(B, total)`` uint8 of a :class:`~.layout.PyramidLayout`
    ``(H, W, max_level, pad)``, ``pad >= 2``. Level 0 is the image; level ``l`` is ``cv2.pyrDown`` of
    level ``l - 1`` for 8-bit images, ``(S + 128) >> 8`` with ``S`` the ``[1 4 6 4 1]^T [1 4 6 4 1]``
    sum at source pixel ``(2x, 2y)``, BORDER_REFLECT_101. Every level's ``pad`` border holds the
    level's BORDER_REFLECT_101 values.

Every value is an integer sum: any order of the taps gives the same bits (the CUDA kernel sums in
another order). The down-sampling reads the previous level's stored border for its out-of-level taps
(reflect-101 there too, ``pad >= 2``), so no index is reflected in the inner loops: the vertical
5-tap sum runs over whole padded rows (one contiguous int32 row), then the horizontal taps at every
second column.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ._simd import i8_add, i8_load, i8_mul, i8_splat, i8_sra, i8_store, u8_load_even8, u8_store8

__all__ = ["pyramid_streams"]


@njit(cache=True, nogil=True)
def _reflect101(p, n):
    """``cv2.borderInterpolate(p, n, BORDER_REFLECT_101)``, repeated reflection for any ``p``."""
    if n == 1:
        return 0
    period = 2 * (n - 1)
    p = abs(p) % period
    return period - p if p >= n else p


@njit(cache=True, nogil=True)
def _copy(src, s0, dst, d0, n):
    """``dst[d0:d0 + n] = src[s0:s0 + n]`` (distinct ranges) as a plain loop: numba's slice assignment
    checks for overlap per call (10x slower on the 480 rows of a frame)."""
    a, b = src[s0:s0 + n], dst[d0:d0 + n]
    for i in range(n):
        b[i] = a[i]


@njit(cache=True, nogil=True)
def _fill_border(row, off, h, w, pad):
    """Write level ``(h, w)``'s ``pad`` border (stored at ``row[off:]``) from its interior."""
    wp = w + 2 * pad
    for y in range(h):  # left and right columns of every interior row
        r = off + (y + pad) * wp + pad
        if pad < w:  # one reflection: column -x is x, column w - 1 + x is w - 1 - x
            for x in range(1, pad + 1):
                row[r - x] = row[r + x]
                row[r + w - 1 + x] = row[r + w - 1 - x]
        else:
            for x in range(1, pad + 1):
                row[r - x] = row[r + _reflect101(-x, w)]
                row[r + w - 1 + x] = row[r + _reflect101(w - 1 + x, w)]
    for y in range(1, pad + 1):  # whole padded rows above and below
        _copy(row, off + (_reflect101(-y, h) + pad) * wp, row, off + (pad - y) * wp, wp)
        _copy(row, off + (_reflect101(h - 1 + y, h) + pad) * wp, row, off + (pad + h - 1 + y) * wp, wp)


@njit(cache=True, nogil=True)
def _hsum(row, base, dw, out):
    """The horizontal taps of one source row at every second column: ``out[x] = r[2x - 2] + 4 r[2x - 1] +
    6 r[2x] + 4 r[2x + 1] + r[2x + 2]`` for ``x < dw`` (``r = row[base:]``, column 0 at ``base``; reads
    columns ``-2 .. 2 dw + 1``, and up to ``2 dw + 2`` in the 16-byte loads: ``pad >= 3``)."""
    if dw >= 8:
        four, six = i8_splat(4), i8_splat(6)
        last = dw - 8
        for bi in range((dw + 7) // 8):
            x0 = min(bi * 8, last)  # the last block may overlap its neighbour: the same values
            q = base + 2 * x0 - 2
            h = i8_add(i8_add(u8_load_even8(row, q), u8_load_even8(row, q + 4)),
                       i8_add(i8_mul(i8_add(u8_load_even8(row, q + 1), u8_load_even8(row, q + 3)), four),
                              i8_mul(u8_load_even8(row, q + 2), six)))
            i8_store(out, x0, h)
    else:
        for x in range(dw):
            q = base + 2 * x - 2
            out[x] = (np.int32(row[q]) + np.int32(row[q + 4])
                      + np.int32(4) * (np.int32(row[q + 1]) + np.int32(row[q + 3]))
                      + np.int32(6) * np.int32(row[q + 2]))


@njit(cache=True, nogil=True)
def _pyr_down(row, src_off, sh, sw, dst_off, dh, dw, pad, hb):
    """Level ``(dh, dw)`` at ``row[dst_off:]`` from the padded level ``(sh, sw)`` at ``row[src_off:]``:
    the horizontal taps of each source row once (a ring of 5 rows in ``hb``), then the vertical taps,
    ``(sum + 128) >> 8``."""
    swp = sw + 2 * pad
    dwp = dw + 2 * pad
    s00 = src_off + pad * swp + pad  # source pixel (0, 0)
    n = hb.shape[1]
    done = -3  # source rows -2 .. done have their horizontal taps in the ring (slot (s + 2) % 5)
    four, six, half = i8_splat(4), i8_splat(6), i8_splat(128)
    for y in range(dh):
        for s in range(max(done + 1, 2 * y - 2), 2 * y + 3):
            _hsum(row, s00 + s * swp, dw, hb[(s + 2) % 5])
        done = 2 * y + 2
        h0, h1, h2 = hb[(2 * y) % 5], hb[(2 * y + 1) % 5], hb[(2 * y + 2) % 5]
        h3, h4 = hb[(2 * y + 3) % 5], hb[(2 * y + 4) % 5]
        d = dst_off + (y + pad) * dwp + pad
        if dw >= 8:
            last = dw - 8
            for bi in range((dw + 7) // 8):
                x0 = min(bi * 8, last)
                v = i8_add(i8_add(i8_load(h0, x0), i8_load(h4, x0)),
                           i8_add(i8_mul(i8_add(i8_load(h1, x0), i8_load(h3, x0)), four),
                                  i8_mul(i8_load(h2, x0), six)))
                u8_store8(row, d + x0, i8_sra(i8_add(v, half), 8))
        else:
            for x in range(dw):
                v = h0[x] + h4[x] + np.int32(4) * (h1[x] + h3[x]) + np.int32(6) * h2[x] + np.int32(128)
                row[d + x] = np.uint8(v >> 8)
    return n


@njit(cache=True, nogil=True)
def pyramid_streams(img, out, sizes, offs, pad, s0, s1):
    """Packed pyramids of streams ``s0 .. s1 - 1``: ``img (B, H, W)`` uint8 -> ``out (B, total)``
    uint8; ``sizes (L + 1, 2)`` int64 ``(H_l, W_l)``, ``offs (L + 1,)`` int64 level offsets;
    ``pad >= 3``."""
    H, W = sizes[0, 0], sizes[0, 1]
    hb = np.empty((5, (W + 1) // 2 + 8), dtype=np.int32)
    wp = W + 2 * pad
    for b in range(s0, s1):
        row = out[b]
        for y in range(H):
            _copy(img[b, y], 0, row, offs[0] + (y + pad) * wp + pad, W)
        _fill_border(row, offs[0], H, W, pad)
        for l in range(1, sizes.shape[0]):
            _pyr_down(row, offs[l - 1], sizes[l - 1, 0], sizes[l - 1, 1], offs[l], sizes[l, 0], sizes[l, 1], pad, hb)
            _fill_border(row, offs[l], sizes[l, 0], sizes[l, 1], pad)
