"""The fused pyramidal LK on the CPU: one numba kernel runs every level and iteration of every point.

It follows ``cv2.calcOpticalFlowPyrLK``'s x86 arithmetic line by line (``docs/kernels.md``; the
operation-by-operation account is ``opencv_lk_arithmetic.md`` of the shared docs), so that status and
float32 positions are OpenCV's bit for bit:

* integer stages in int32 (bilinear weights ``cvRound(. 2^14)``, grey-level and Scharr templates
  ``CV_DESCALE``, window differences): exact, any order;
* the gradient sums ``A11, A12, A22`` in OpenCV's SIMD partition: per window row, the columns
  ``x < ws = 8 (ww // 8)`` go to 4 float32 lane accumulators (lane ``l`` takes ``x = l (mod 4)``, in
  ascending ``x``), the columns ``ws <= x < ww`` to a scalar accumulator, combined as
  ``t + ((q0 + q2) + (q1 + q3))`` (x86's horizontal sum);
* the mismatch vector ``b``: the products of pixels ``x0 + l`` and ``x0 + l + 4`` summed in int32
  before one conversion to float32 (``_mm_madd_epi16``), the same lanes and combination;
* no FMA (numba does not contract ``a * b + c`` without ``fastmath``; ``tests/test_fused.py``
  checks the kernel's bits against cv2), correctly rounded division and square root, the
  comparisons OpenCV makes in double made in double.

Convention:
    Packed pyramids as :mod:`.layout` (``(B, total)`` uint8 rows); points ``(B, N, 2)`` float32
    pixels ``(x, y)``, pixel centres at integer coordinates; ``valid``, ``status``, ``capped``
    ``(B, N)`` bool. A lane's computation is the contract of ``docs/kernels.md`` ("The LK kernel,
    lane by lane"), shared with the CUDA kernel (``_triton_lk.py``), which gives the same bits.

Speed (``benchmarks/bench_lk.py``): the window loops run on contiguous int32 rows (the compiler
vectorises them); the lane accumulators are four named scalars (a small array would live in memory);
every integer intermediate is cast back to int32 so that the compiler keeps 8 lanes per vector.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ._simd import (
    f4_add,
    f4_hsum,
    f4_mul,
    f4_zero,
    i4_load,
    i4_to_f4,
    i8_add,
    i8_load,
    i8_mul,
    i8_pairsum,
    i8_splat,
    i8_sra,
    i8_store,
    i8_sub,
    u8_load8,
)

__all__ = ["lk_streams"]

_I32 = np.int32
_F32 = np.float32
_FLT_SCALE = _F32(2.0 ** -20)
_FLT_EPSILON = _F32(1.1920928955078125e-07)
_W_ONE = _F32(16384.0)


@njit(cache=True, nogil=True, inline="always")
def _weights(a, b):
    """OpenCV's fixed-point bilinear weights from float32 fractions ``a``, ``b`` (``cvRound``: half to even)."""
    one = _F32(1.0)
    w00 = _I32(np.rint(((one - a) * (one - b)) * _W_ONE))
    w01 = _I32(np.rint((a * (one - b)) * _W_ONE))
    w10 = _I32(np.rint(((one - a) * b) * _W_ONE))
    w11 = _I32(16384) - w00 - w01 - w10
    return w00, w01, w10, w11


@njit(cache=True, nogil=True)
def _blocks(n):
    """Starts of the 8-wide blocks that cover ``[0, n)`` (``n >= 8``): ``0, 8, ...`` and, when 8 does not
    divide ``n``, one last block ending at ``n`` (overlapping its neighbour: positionwise values, so a
    pixel computed twice is written twice with the same value)."""
    nb = (n + 7) // 8
    return nb, n - 8


@njit(cache=True, nogil=True)
def _scharr(P, o, wp, ix, iy, cols, rows, ww, wh, DX, DY):
    """Scharr derivatives ``DX``, ``DY`` ``((wh + 1) x (ww + 1))`` int32 of the level pixels
    ``[ix, ix + ww] x [iy, iy + wh]`` of the padded level at ``P[o:]`` (``o``: pixel (0, 0), row pitch
    ``wp``), 0 outside the level (``calcSharrDeriv``'s result padded with zeros); inside, the
    reflect-101 grey levels of the stored border give OpenCV's values at the level's edge."""
    dw = ww + 1
    three, ten = i8_splat(3), i8_splat(10)
    nb, last = _blocks(dw)
    for y in range(wh + 1):
        r = o + (iy + y) * wp + ix - 1  # column -1 of the row: a window reads [ix - 1, ix + ww + 1]
        k = y * dw
        for bi in range(nb):
            x0 = min(bi * 8, last)
            q = r + x0
            um, up = u8_load8(P, q - wp), u8_load8(P, q - wp + 2)
            mm, mp = u8_load8(P, q), u8_load8(P, q + 2)
            dm, dp = u8_load8(P, q + wp), u8_load8(P, q + wp + 2)
            dx = i8_add(i8_mul(i8_add(i8_sub(up, um), i8_sub(dp, dm)), three), i8_mul(i8_sub(mp, mm), ten))
            dy = i8_add(i8_mul(i8_add(i8_sub(dm, um), i8_sub(dp, up)), three),
                        i8_mul(i8_sub(u8_load8(P, q + wp + 1), u8_load8(P, q - wp + 1)), ten))
            i8_store(DX, k + x0, dx)
            i8_store(DY, k + x0, dy)
    if not (ix >= 0 and iy >= 0 and ix + ww < cols and iy + wh < rows):
        for y in range(wh + 1):
            row_in = iy + y >= 0 and iy + y < rows
            for x in range(dw):
                if not row_in or ix + x < 0 or ix + x >= cols:
                    DX[y * dw + x] = 0
                    DY[y * dw + x] = 0


@njit(cache=True, nogil=True)
def _interp_window(P, o, wp, ix, iy, ww, wh, w00, w01, w10, w11, I, DX, DY, GX, GY):
    """The window's grey levels ``I`` (x32, ``CV_DESCALE(sum P iw, 9)``) and derivatives ``GX``, ``GY``
    (``CV_DESCALE(sum D iw, 14)``), ``(wh, ww)`` int32, from the padded level and ``DX``, ``DY``."""
    dw = ww + 1
    v00, v01, v10, v11 = i8_splat(w00), i8_splat(w01), i8_splat(w10), i8_splat(w11)
    h9, h14 = i8_splat(1 << 8), i8_splat(1 << 13)
    nb, last = _blocks(ww)
    for y in range(wh):
        r = o + (iy + y) * wp + ix
        k, kd = y * ww, y * dw
        for bi in range(nb):
            x0 = min(bi * 8, last)
            q = r + x0
            s = i8_add(i8_add(i8_mul(u8_load8(P, q), v00), i8_mul(u8_load8(P, q + 1), v01)),
                       i8_add(i8_mul(u8_load8(P, q + wp), v10), i8_mul(u8_load8(P, q + wp + 1), v11)))
            i8_store(I, k + x0, i8_sra(i8_add(s, h9), 9))
            q = kd + x0
            s = i8_add(i8_add(i8_mul(i8_load(DX, q), v00), i8_mul(i8_load(DX, q + 1), v01)),
                       i8_add(i8_mul(i8_load(DX, q + dw), v10), i8_mul(i8_load(DX, q + dw + 1), v11)))
            i8_store(GX, k + x0, i8_sra(i8_add(s, h14), 14))
            s = i8_add(i8_add(i8_mul(i8_load(DY, q), v00), i8_mul(i8_load(DY, q + 1), v01)),
                       i8_add(i8_mul(i8_load(DY, q + dw), v10), i8_mul(i8_load(DY, q + dw + 1), v11)))
            i8_store(GY, k + x0, i8_sra(i8_add(s, h14), 14))


@njit(cache=True, nogil=True)
def _gradient_sums(GX, GY, ww, wh):
    """``(A11, A12, A22)`` float32 of the derivative windows, in OpenCV's lane order (module docstring)."""
    q11, q12, q22 = f4_zero(), f4_zero(), f4_zero()
    t11 = t12 = t22 = _F32(0.0)
    ws = (ww // 8) * 8
    for y in range(wh):
        k = y * ww
        for x0 in range(0, ws, 4):  # pixels x0 + l: lane l takes x = l (mod 4), in ascending x
            fx = i4_to_f4(i4_load(GX, k + x0))
            fy = i4_to_f4(i4_load(GY, k + x0))
            q11 = f4_add(q11, f4_mul(fx, fx))
            q12 = f4_add(q12, f4_mul(fx, fy))
            q22 = f4_add(q22, f4_mul(fy, fy))
        for x in range(ws, ww):
            gx, gy = GX[k + x], GY[k + x]
            t11 += _F32(gx * gx)
            t12 += _F32(gx * gy)
            t22 += _F32(gy * gy)
    A11 = (t11 + f4_hsum(q11)) * _FLT_SCALE
    A12 = (t12 + f4_hsum(q12)) * _FLT_SCALE
    A22 = (t22 + f4_hsum(q22)) * _FLT_SCALE
    return A11, A12, A22


@njit(cache=True, nogil=True)
def _template(P, o, wp, ix, iy, cols, rows, ww, wh, a, b, I, GX, GY, DX, DY):
    """The level's template of one point: grey levels ``I`` and Scharr derivatives ``GX``, ``GY``
    ``(wh, ww)`` int32 of the window at origin ``(ix, iy)`` (fractions ``a``, ``b``) of the padded
    level at ``P[o:]`` (row pitch ``wp``, ``o`` = the element of level pixel (0, 0)); the float32
    gradient sums ``(A11, A12, A22)`` in OpenCV's order."""
    w00, w01, w10, w11 = _weights(a, b)
    _scharr(P, o, wp, ix, iy, cols, rows, ww, wh, DX, DY)
    _interp_window(P, o, wp, ix, iy, ww, wh, w00, w01, w10, w11, I, DX, DY, GX, GY)
    return _gradient_sums(GX, GY, ww, wh)


@njit(cache=True, nogil=True)
def _mismatch(Q, o, wp, jx, jy, ww, wh, a, b, I, GX, GY, tail):
    """``(b1, b2)`` float32 of one iteration: the window at origin ``(jx, jy)`` (fractions ``a``, ``b``)
    of the padded level at ``Q[o:]`` against the template, in OpenCV's order (scaled by 2^-20)."""
    w00, w01, w10, w11 = _weights(a, b)
    v00, v01, v10, v11 = i8_splat(w00), i8_splat(w01), i8_splat(w10), i8_splat(w11)
    half = i8_splat(256)
    c1, c2 = f4_zero(), f4_zero()
    t1 = t2 = _F32(0.0)
    ws = (ww // 8) * 8
    for y in range(wh):
        r = o + (jy + y) * wp + jx
        k = y * ww
        for x0 in range(0, ws, 8):
            # 8 pixels: interpolated x32 (CV_DESCALE(., 9)) minus the template, then the products with
            # the derivatives, pixels x0 + l and x0 + 4 + l summed in int32 per lane, one conversion
            q = r + x0
            s = i8_add(i8_add(i8_mul(u8_load8(Q, q), v00), i8_mul(u8_load8(Q, q + 1), v01)),
                       i8_add(i8_mul(u8_load8(Q, q + wp), v10), i8_mul(u8_load8(Q, q + wp + 1), v11)))
            d = i8_sub(i8_sra(i8_add(s, half), 9), i8_load(I, k + x0))
            c1 = f4_add(c1, i4_to_f4(i8_pairsum(i8_mul(d, i8_load(GX, k + x0)))))
            c2 = f4_add(c2, i4_to_f4(i8_pairsum(i8_mul(d, i8_load(GY, k + x0)))))
        if ws < ww:
            # the tail's window differences from one block ending at ww (into ``tail``), then OpenCV's
            # scalar sums over x = ws .. ww - 1
            x0 = ww - 8
            q = r + x0
            s = i8_add(i8_add(i8_mul(u8_load8(Q, q), v00), i8_mul(u8_load8(Q, q + 1), v01)),
                       i8_add(i8_mul(u8_load8(Q, q + wp), v10), i8_mul(u8_load8(Q, q + wp + 1), v11)))
            i8_store(tail, 0, i8_sub(i8_sra(i8_add(s, half), 9), i8_load(I, k + x0)))
            for x in range(ws, ww):
                d = tail[x - x0]
                t1 += _F32(_I32(d * GX[k + x]))
                t2 += _F32(_I32(d * GY[k + x]))
    b1 = (t1 + f4_hsum(c1)) * _FLT_SCALE
    b2 = (t2 + f4_hsum(c2)) * _FLT_SCALE
    return b1, b2


@njit(cache=True, nogil=True)
def _inside(f, lo, hi):
    """``lo <= f < hi`` for a float32 ``floor`` (False for NaN: OpenCV's ``cvFloor(NaN)`` is INT_MIN)."""
    return f >= lo and f < hi


@njit(cache=True, nogil=True)
def _track(P, offs_p, wp_p, Q, offs_q, wp_q, sizes, px, py, has_start, sx, sy, top, ww, wh, max_iters, eps2,
           min_eig, I, GX, GY, DX, DY, tail):
    """One lane: OpenCV's pyramidal LK of point ``(px, py)`` from the packed pyramid ``P`` into ``Q``
    (``offs_*``: the element of pixel (0, 0) of each level; ``wp_*``: row pitches), starting at
    ``(sx, sy)`` when ``has_start`` (OPTFLOW_USE_INITIAL_FLOW). Returns ``(x, y, status, capped)``."""
    hw = _F32((ww - 1) * 0.5)
    hh = _F32((wh - 1) * 0.5)
    status = True
    capped = False
    nx = ny = _F32(0.0)
    for L in range(top, -1, -1):
        s = _F32(1.0 / (1 << L))
        if L == top:
            if has_start:
                nx, ny = sx * s, sy * s
            else:
                nx, ny = px * s, py * s
        else:
            nx, ny = nx * _F32(2.0), ny * _F32(2.0)
        rows, cols = sizes[L, 0], sizes[L, 1]
        qx = px * s - hw
        qy = py * s - hh
        fx, fy = np.floor(qx), np.floor(qy)
        if not (_inside(fx, -ww, cols) and _inside(fy, -wh, rows)):
            if L == 0:
                status = False
            continue
        ix, iy = int(fx), int(fy)
        A11, A12, A22 = _template(P, offs_p[L], wp_p[L], ix, iy, cols, rows, ww, wh, qx - fx, qy - fy,
                                  I, GX, GY, DX, DY)
        D = A11 * A22 - A12 * A12
        dd = A11 - A22
        min_e = ((A22 + A11) - np.sqrt(dd * dd + (_F32(4.0) * A12) * A12)) / _F32(2 * ww * wh)
        if np.float64(min_e) < min_eig or D < _FLT_EPSILON:
            if L == 0:
                status = False
            continue
        Dinv = _F32(1.0) / D
        cx, cy = nx - hw, ny - hh
        pdx = pdy = _F32(0.0)
        stopped = False
        for j in range(max_iters):
            fx, fy = np.floor(cx), np.floor(cy)
            if not (_inside(fx, -ww, cols) and _inside(fy, -wh, rows)):
                if L == 0:
                    status = False
                stopped = True
                break
            b1, b2 = _mismatch(Q, offs_q[L], wp_q[L], int(fx), int(fy), ww, wh, cx - fx, cy - fy, I, GX, GY,
                               tail)
            dx = (A12 * b2 - A22 * b1) * Dinv
            dy = (A12 * b1 - A11 * b2) * Dinv
            cx = cx + dx
            cy = cy + dy
            nx = cx + hw
            ny = cy + hh
            ddx, ddy = np.float64(dx), np.float64(dy)
            if ddx * ddx + ddy * ddy <= eps2:
                stopped = True
                break
            if j > 0 and abs(np.float64(dx + pdx)) < 0.01 and abs(np.float64(dy + pdy)) < 0.01:
                nx = nx - dx * _F32(0.5)
                ny = ny - dy * _F32(0.5)
                stopped = True
                break
            pdx, pdy = dx, dy
        if not stopped and L == 0:
            capped = True
    if status:
        fx, fy = np.floor(nx - hw), np.floor(ny - hh)
        if not (_inside(fx, -ww, sizes[0, 1]) and _inside(fy, -wh, sizes[0, 0])):
            status = False
    return nx, ny, status, capped


@njit(cache=True, nogil=True)
def lk_streams(prev, nxt, offs_p, wp_p, offs_n, wp_n, sizes, pts, valid, init, has_init, top, ww, wh, max_iters,
               eps, min_eig, fb_top, fb_threshold, fb_from_pts, out, status, capped, s0, s1):
    """The fused LK of streams ``s0 .. s1 - 1`` (see the module docstring and ``docs/kernels.md``).

    ``prev``, ``nxt``: ``(B, total)`` uint8 packed pyramids; ``offs_*`` ``(L + 1,)`` int64: the element of
    level pixel (0, 0) in a row; ``wp_*`` ``(L + 1,)`` int64 row pitches; ``sizes`` ``(L + 1, 2)`` int64
    ``(H_l, W_l)``; ``pts``, ``init`` ``(B, N, 2)`` float32 (``init`` read when ``has_init``);
    ``valid`` ``(B, N)`` bool; ``eps``: the criteria's epsilon (compared squared, in double);
    ``fb_top >= 0``: track back from the result with ``fb_top`` levels (from ``pts`` when
    ``fb_from_pts``) and keep lanes that return within ``fb_threshold`` px. Writes ``out``,
    ``status``, ``capped``."""
    N = pts.shape[1]
    I = np.empty(wh * ww, dtype=np.int32)
    GX = np.empty(wh * ww, dtype=np.int32)
    GY = np.empty(wh * ww, dtype=np.int32)
    DX = np.empty((wh + 1) * (ww + 1), dtype=np.int32)
    DY = np.empty((wh + 1) * (ww + 1), dtype=np.int32)
    tail = np.empty(8, dtype=np.int32)
    eps2 = np.float64(eps) * np.float64(eps)
    for b in range(s0, s1):
        P = prev[b]
        Q = nxt[b]
        for i in range(N):
            px, py = pts[b, i, 0], pts[b, i, 1]
            ok = valid[b, i]
            sx, sy = px, py
            if has_init:
                gx, gy = init[b, i, 0], init[b, i, 1]
                if math.isfinite(gx) and math.isfinite(gy):
                    sx, sy = gx, gy
                else:
                    ok = False
            if not ok:
                out[b, i, 0], out[b, i, 1] = sx, sy
                status[b, i] = False
                capped[b, i] = False
                continue
            nx, ny, st, cp = _track(P, offs_p, wp_p, Q, offs_n, wp_n, sizes, px, py, has_init, sx, sy, top, ww, wh,
                                    max_iters, eps2, min_eig, I, GX, GY, DX, DY, tail)
            if fb_top >= 0 and st:
                bx, by, bst, _ = _track(Q, offs_n, wp_n, P, offs_p, wp_p, sizes, nx, ny, fb_from_pts, px, py, fb_top,
                                        ww, wh, max_iters, eps2, min_eig, I, GX, GY, DX, DY, tail)
                ex, ey = np.float64(bx - px), np.float64(by - py)
                st = bst and math.sqrt(ex * ex + ey * ey) <= fb_threshold
            out[b, i, 0], out[b, i, 1] = nx, ny
            status[b, i] = st
            capped[b, i] = cp
