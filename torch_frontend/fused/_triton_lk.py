"""The fused pyramidal LK on a CUDA device: a Triton kernel, bit-identical to ``cv2.calcOpticalFlowPyrLK``.

Convention:
    A *lane* is one point of one stream: lane ``k = b N + i`` of ``B`` streams of ``N`` points.
    ``prev``, ``next``: packed pyramids (``fused/layout.py``), ``(B, Tp)`` / ``(B, Tn)`` uint8 of
    ``PyramidLayout(height, width, >= top, pad_prev / pad_next)``, ``pad >= max(ww, wh) + 1``.
    ``pts``, ``init``, the result's positions: ``(B, N, 2)`` float32 pixel coordinates ``(x, y)`` of
    level 0 (pixel centres at integers); ``valid``, ``status``, ``capped``: ``(B, N)`` bool. The
    window is ``(ww, wh)`` pixels (VINS: 21 x 21). The arithmetic of every lane is "Op 2" of the LK
    contract (``opencv_lk_arithmetic.md`` of the shared docs says why each step is what it is): the
    CPU kernel (``_numba_lk.py``) and this one give identical bits on every lane, tracked or not.

How the contract's sequential float sums are kept on a GPU:
    A program runs ``_BLOCK`` lanes; each lane runs all its levels and iterations itself (lanes that
    stop early wait, masked, for the block's last one: the iteration loop ends when no lane of the
    block still runs). The window is walked row by row: a row is a ``(BLOCK, WP)`` integer tile
    (``WP`` = ``ww`` rounded up to a power of two, columns ``>= ww`` masked to 0), or ``(BLOCK, WP, 2)``
    for two quantities at once (``diff Ix, diff Iy``). Every float accumulator of the contract is
    its own register chain, updated row after row in the contract's order: the 4 SIMD-lane
    accumulators of ``K`` quantities are a ``(BLOCK, 4, K)`` float tile (element ``(k, l, q)`` is lane
    ``k``'s accumulator ``l`` of quantity ``q``), the scalar tails a ``(BLOCK, K)`` tile. The values
    added to them are *integers* (exact products below 2^24, int32 pair sums) picked out of a row
    tile by a masked integer ``tl.sum``: one value and zeros, exact in any order. No float value is
    ever reduced across elements; the final ``t + ((c0 + c2) + (c1 + c3))`` picks the accumulators
    out of the tile bit-wise (their int32 patterns, again one value and zeros) and adds them in that
    order.

Template storage: the template of a lane at a level is written once per level to a global scratch
buffer ``(B N, 3, wh ww)`` int16 that the launcher allocates (``|I| <= 8160``, ``|Ix|, |Iy| <= 4080``):
plane 0 holds ``I[y, x]`` at ``y ww + x``, planes 1-2 ``(Ix, Iy)`` interleaved at ``2 (y ww + x)``, so
that an iteration reads a row's gradients as one ``(BLOCK, WP, 2)`` tile (2.6 KB per lane for 21 x 21,
L1/L2 resident). Each lane's scratch is written and read by its own program only.

Forward-backward: a second launch of the same kernel (``BACKWARD``) tracks the result back on the
lanes the first kept. One tracker per compiled kernel: with both inlined in one kernel ptxas took
~80 s (one: ~5 s).

Floating point: every kernel is compiled with ``enable_fp_fusion=False`` (no FMA contraction: every
product is rounded before its sum, as SSE2 does) and ``enable_reflect_ftz=False`` (Triton's default
makes libdevice flush subnormals: ``tl.floor`` was ``cvt.rmi.ftz.f32``); ``tl.div_rn`` /
``tl.sqrt_rn`` (Triton's ``/`` and ``tl.sqrt`` are approximate on sm_90 for float32); ``rint`` as
``(x + 2^23) - 2^23`` (exact round-half-even for ``0 <= x <= 2^22``); the double-precision tests on
``fp64`` values (the thresholds are ``fp64`` kernel arguments, the literal 0.01 an fp64 constant).
:func:`ptx_sm90` compiles every kernel of this module and of ``_triton_pyramid.py`` for sm_90
without a GPU, for a test that their PTX has no ``fma``, ``.approx``, ``div.full`` or ``.ftz`` and
rounds every float add / sub / mul ``.rn`` (ptxas may contract a mul and an add without it).
"""

from typing import Dict, Optional, Tuple

import torch
import triton
import triton.language as tl

from . import _triton_pyramid
from ._triton_pyramid import _COMPILE_OPTIONS

__all__ = ["lk_cuda", "ptx_sm90"]

#: lanes per program and warps: (32, 32) int32 row tiles, (32, 32, 2) for two quantities (8 elements per
#: thread at 8 warps). ptxas for sm_90: 255 registers and 28 bytes of spill at 8 warps (4 warps:
#: 1.6 KB of spill per thread; 16 lanes at 8 warps: 176 registers, no spill, half the lanes per CTA)
_BLOCK = 32
_NUM_WARPS = 8

#: OpenCV's fixed-point constants: bilinear weights in 2^14, the template in 2^5 grey levels
_W_ONE = tl.constexpr(16384)  # 1 << W_BITS
_W_ONE_F = tl.constexpr(16384.0)
_ROUND_I = tl.constexpr(256)  # 1 << (W_BITS - 5 - 1): (.. + 2^8) >> 9 = grey x 32 rounded
_SHIFT_I = tl.constexpr(9)  # W_BITS - 5
_ROUND_D = tl.constexpr(8192)  # 1 << (W_BITS - 1): derivatives keep their scale, >> 14
_SHIFT_D = tl.constexpr(14)  # W_BITS
#: 2^23: float32 ``(x + 2^23) - 2^23`` is x rounded half-to-even for 0 <= x <= 2^22 (one ulp = 1 there)
_RINT_MAGIC = tl.constexpr(8388608.0)
#: OpenCV's FLT_SCALE = 1 / 2^20 (exact): the sums are in (2^5 grey)^2 and (2^5 grey)(derivative)
_FLT_SCALE = tl.constexpr(2.0 ** -20)
#: float32 FLT_EPSILON: the determinant threshold (a float32 comparison)
_FLT_EPSILON = tl.constexpr(1.1920928955078125e-07)
#: OpenCV's oscillation threshold, compared in double with a float32 |dx + pdx|
_OSC = tl.constexpr(0.01)


# ----------------------------------------------------------------------------------------- helpers
@triton.jit
def _level_geom(height, width, pad, L):
    """Level ``L``'s ``rows, cols`` (``ceil`` halvings), its padded block's offset in a stream's
    row and ``1 / 2^L`` (float32, exact)."""
    h = height
    w = width
    off = height * 0
    scale = (height * 0).to(tl.float32) + 1.0
    for _k in range(L):
        off += (h + 2 * pad) * (w + 2 * pad)
        h = (h + 1) >> 1
        w = (w + 1) >> 1
        scale = scale * 0.5
    return h, w, off, scale


@triton.jit
def _inside(fx, fy, rows, cols, WW: tl.constexpr, WH: tl.constexpr):
    """``fx in [-ww, cols) and fy in [-wh, rows)`` of float32 floors; False for NaN (outside)."""
    return (fx >= -WW) & (fx < cols) & (fy >= -WH) & (fy < rows)


@triton.jit
def _weights(a, b):
    """OpenCV's bilinear weights (int32, sum 2^14) of fractions ``a, b`` in ``[0, 1]`` (finite).

    ``cvRound(p * 2^14)`` of the float32 products ``p`` (rounded before the scaling, exact), rounded
    half to even by ``(x + 2^23) - 2^23`` (two float32 adds, no FMA: x <= 2^14).
    """
    wa = 1.0 - a
    wb = 1.0 - b
    w00 = (((wa * wb) * _W_ONE_F + _RINT_MAGIC) - _RINT_MAGIC).to(tl.int32)
    w01 = (((a * wb) * _W_ONE_F + _RINT_MAGIC) - _RINT_MAGIC).to(tl.int32)
    w10 = (((wa * b) * _W_ONE_F + _RINT_MAGIC) - _RINT_MAGIC).to(tl.int32)
    w11 = _W_ONE - w00 - w01 - w10
    return w00, w01, w10, w11


@triton.jit
def _template_row(base, pitch, m, u, v, rows, cols, w00, w01, w10, w11):
    """Row ``v`` of a lane's template: ``I, Ix, Iy`` (int32 ``(BLOCK, WP)``) at level pixels ``u``.

    ``base`` points at level pixel ``(u, v)`` of each element (``(BLOCK, WP)`` pointers, rows of
    ``pitch``), ``m`` masks the loads. Reads level pixels ``u - 1 .. u + 2``, ``v - 1 .. v + 2``
    (inside the padded block: ``pad >= win + 1``). The derivatives are 0 outside the level
    (OpenCV pads them with zeros), the grey levels are the stored reflect-101 values.
    """
    # p<R><C>: level pixel (u - 1 + C, v - 1 + R)
    p00 = tl.load(base - pitch - 1, mask=m, other=0).to(tl.int32)
    p01 = tl.load(base - pitch, mask=m, other=0).to(tl.int32)
    p02 = tl.load(base - pitch + 1, mask=m, other=0).to(tl.int32)
    p03 = tl.load(base - pitch + 2, mask=m, other=0).to(tl.int32)
    p10 = tl.load(base - 1, mask=m, other=0).to(tl.int32)
    p11 = tl.load(base, mask=m, other=0).to(tl.int32)
    p12 = tl.load(base + 1, mask=m, other=0).to(tl.int32)
    p13 = tl.load(base + 2, mask=m, other=0).to(tl.int32)
    p20 = tl.load(base + pitch - 1, mask=m, other=0).to(tl.int32)
    p21 = tl.load(base + pitch, mask=m, other=0).to(tl.int32)
    p22 = tl.load(base + pitch + 1, mask=m, other=0).to(tl.int32)
    p23 = tl.load(base + pitch + 2, mask=m, other=0).to(tl.int32)
    p30 = tl.load(base + 2 * pitch - 1, mask=m, other=0).to(tl.int32)
    p31 = tl.load(base + 2 * pitch, mask=m, other=0).to(tl.int32)
    p32 = tl.load(base + 2 * pitch + 1, mask=m, other=0).to(tl.int32)
    p33 = tl.load(base + 2 * pitch + 2, mask=m, other=0).to(tl.int32)
    # in-level masks of columns u, u + 1 and rows v, v + 1 (derivatives are 0 outside)
    cu0 = (u >= 0) & (u < cols)
    cu1 = (u + 1 >= 0) & (u + 1 < cols)
    rv0 = (v >= 0) & (v < rows)
    rv1 = (v + 1 >= 0) & (v + 1 < rows)
    # Scharr at (u + c, v + r) (calcSharrDeriv): Dx = 3 (right - left) of the rows above and below
    # + 10 (right - left) of its own row; Dy transposed
    dx00 = tl.where(cu0 & rv0, 3 * (p02 - p00) + 10 * (p12 - p10) + 3 * (p22 - p20), 0)
    dx01 = tl.where(cu1 & rv0, 3 * (p03 - p01) + 10 * (p13 - p11) + 3 * (p23 - p21), 0)
    dx10 = tl.where(cu0 & rv1, 3 * (p12 - p10) + 10 * (p22 - p20) + 3 * (p32 - p30), 0)
    dx11 = tl.where(cu1 & rv1, 3 * (p13 - p11) + 10 * (p23 - p21) + 3 * (p33 - p31), 0)
    dy00 = tl.where(cu0 & rv0, 3 * (p20 - p00) + 10 * (p21 - p01) + 3 * (p22 - p02), 0)
    dy01 = tl.where(cu1 & rv0, 3 * (p21 - p01) + 10 * (p22 - p02) + 3 * (p23 - p03), 0)
    dy10 = tl.where(cu0 & rv1, 3 * (p30 - p10) + 10 * (p31 - p11) + 3 * (p32 - p12), 0)
    dy11 = tl.where(cu1 & rv1, 3 * (p31 - p11) + 10 * (p32 - p12) + 3 * (p33 - p13), 0)
    # (>> on int32 is arithmetic: floor, as OpenCV's CV_DESCALE)
    ti = (p11 * w00 + p12 * w01 + p21 * w10 + p22 * w11 + _ROUND_I) >> _SHIFT_I
    tx = (dx00 * w00 + dx01 * w01 + dx10 * w10 + dx11 * w11 + _ROUND_D) >> _SHIFT_D
    ty = (dy00 * w00 + dy01 * w01 + dy10 * w10 + dy11 * w11 + _ROUND_D) >> _SHIFT_D
    return ti, tx, ty


@triton.jit
def _add_singles(q, t, p, BLOCK: tl.constexpr, WP: tl.constexpr, WW: tl.constexpr, K: tl.constexpr):
    """The gradient sums' per-row update, for ``K`` quantities at once: ``q[l] += float(p[x])`` for the
    SIMD columns ``x = x0 + l, x0 + l + 4`` (``x0 = 0, 8, ..``, in this order), then
    ``t += float(p[x])`` for the tail columns ``ws .. ww - 1`` in order.

    ``p``: exact int32 products ``(BLOCK, WP, K)`` (< 2^24 in magnitude, so ``float(p)`` is the
    rounded float product); ``q``: ``(BLOCK, 4, K)`` float32; ``t``: ``(BLOCK, K)`` float32.
    """
    WS: tl.constexpr = 8 * (WW // 8)
    # column x = 4 m + l: m = 2 (x0 / 8) + (0 for x0 + l, 1 for x0 + l + 4)
    p4 = tl.reshape(p, (BLOCK, WP // 4, 4, K))
    m_idx = tl.arange(0, WP // 4)[None, :, None, None]
    for m in tl.static_range(WS // 4):
        q = q + tl.sum(tl.where(m_idx == m, p4, 0), axis=1).to(tl.float32)
    cols = tl.arange(0, WP)[None, :, None]
    for x in tl.static_range(WS, WW):
        t = t + tl.sum(tl.where(cols == x, p, 0), axis=1).to(tl.float32)
    return q, t


@triton.jit
def _add_pairs(c, t, p, BLOCK: tl.constexpr, WP: tl.constexpr, WW: tl.constexpr, K: tl.constexpr):
    """The mismatch sums' per-row update, for ``K`` quantities at once: ``c[l] += float(p[x0 + l]
    + p[x0 + l + 4])`` (the pair summed in int32 first) for ``x0 = 0, 8, ..`` in order, then
    ``t += float(p[x])`` for the tail columns in order.

    ``p``: int32 ``(BLOCK, WP, K)``; ``c``: ``(BLOCK, 4, K)`` float32; ``t``: ``(BLOCK, K)`` float32.
    """
    WS: tl.constexpr = 8 * (WW // 8)
    # column x = 8 g + 4 h + l; the pair of lane l at x0 = 8 g is h = 0, 1 (an exact int32 sum)
    s = tl.sum(tl.reshape(p, (BLOCK, WP // 8, 2, 4, K)), axis=2)
    g_idx = tl.arange(0, WP // 8)[None, :, None, None]
    for g in tl.static_range(WS // 8):
        c = c + tl.sum(tl.where(g_idx == g, s, 0), axis=1).to(tl.float32)
    cols = tl.arange(0, WP)[None, :, None]
    for x in tl.static_range(WS, WW):
        t = t + tl.sum(tl.where(cols == x, p, 0), axis=1).to(tl.float32)
    return c, t


@triton.jit
def _pick(v, k):
    """Element ``k`` of the last axis of a float32 tile, bit-exact: the int32 bit patterns of one
    value and zeros summed (an integer reduction), never a float reduction."""
    LAST: tl.constexpr = len(v.shape) - 1
    idx = tl.arange(0, v.shape[LAST])
    bits = tl.where(idx == k, v.to(tl.int32, bitcast=True), 0)
    return tl.sum(bits, axis=LAST).to(tl.float32, bitcast=True)


@triton.jit
def _lane_total(c, t):
    """``t + ((c0 + c2) + (c1 + c3))`` (OpenCV's x86 horizontal sum, float32) of ``(BLOCK, 4, K)``
    lane accumulators and their ``(BLOCK, K)`` tail: ``(BLOCK, K)``."""
    ct = tl.permute(c, (0, 2, 1))  # (BLOCK, K, 4): the lane axis last for _pick
    return t + ((_pick(ct, 0) + _pick(ct, 2)) + (_pick(ct, 1) + _pick(ct, 3)))


# ------------------------------------------------------------------------------------ the tracker
@triton.jit
def _track(P, Q, pad_p, pad_q, px, py, sx, sy, ok, top, height, width, max_iters, eps2, min_eig, tpl,
           WW: tl.constexpr, WH: tl.constexpr, WP: tl.constexpr, BLOCK: tl.constexpr):
    """The contract's ``LK(P, Q, p, start, top)`` for a block of lanes.

    ``P``, ``Q``: ``(BLOCK,)`` pointers to each lane's stream row of the template's / the target's
    packed pyramid (pads ``pad_p``, ``pad_q``); ``(px, py)``: the point in ``P`` (level 0);
    ``(sx, sy)``: the start in ``Q`` (level 0; the point itself when there is none); ``ok``: lanes
    to track (the others compute nothing and return ``status`` False). ``tpl``: ``(BLOCK,)``
    pointers to each lane's ``(3, wh ww)`` int16 scratch. Returns ``nx, ny`` (float32), ``status``,
    ``capped``.
    """
    HW: tl.constexpr = (WW - 1) * 0.5
    HH: tl.constexpr = (WH - 1) * 0.5
    WIN: tl.constexpr = WW * WH
    cidx = tl.arange(0, WP)
    cmask = (cidx < WW)[None, :]
    k2 = tl.arange(0, 2)[None, None, :]
    status = ok
    lane_zero = tl.zeros((BLOCK,), tl.int32)
    capped = lane_zero != 0
    nx = sx
    ny = sy
    for k in range(0, top + 1):
        L = top - k
        rows, cols, off_p, scale = _level_geom(height, width, pad_p, L)
        _r, _c, off_q, _s = _level_geom(height, width, pad_q, L)
        pitch_p = cols + 2 * pad_p
        pitch_q = cols + 2 * pad_q
        # per-lane vectors, not scalars: the interpreter turns (bool vector & bool scalar) into int32
        lvl0 = (lane_zero + L) == 0
        # the start at the top level, else the finer level's doubling (exact)
        nx = tl.where(k == 0, sx * scale, nx * 2.0)
        ny = tl.where(k == 0, sy * scale, ny * 2.0)

        # ---- the template window at (px, py) / 2^L - half window
        qx = px * scale - HW
        qy = py * scale - HH
        fx = tl.floor(qx)
        fy = tl.floor(qy)
        act = ok & _inside(fx, fy, rows, cols, WW, WH)
        status = status & ~(ok & ~act & lvl0)
        # inactive lanes (possibly NaN / inf) get harmless in-range values before any int conversion
        ix = tl.where(act, fx, 0.0).to(tl.int32)
        iy = tl.where(act, fy, 0.0).to(tl.int32)
        iw00, iw01, iw10, iw11 = _weights(tl.where(act, qx - fx, 0.0), tl.where(act, qy - fy, 0.0))
        m = act[:, None] & cmask
        u = ix[:, None] + cidx[None, :]
        pbase = P[:, None] + off_p + pad_p * pitch_p + pad_p + u
        # the gradient sums: [A11, A12] from Ix (Ix, Iy), [A21, A22] from Iy (Ix, Iy)
        qa = tl.zeros((BLOCK, 4, 2), tl.float32)
        qb = tl.zeros((BLOCK, 4, 2), tl.float32)
        ta = tl.zeros((BLOCK, 2), tl.float32)
        tb = tl.zeros((BLOCK, 2), tl.float32)
        for y in range(WH):
            v = (iy + y)[:, None]
            ti, tx, ty = _template_row(pbase + v * pitch_p, pitch_p, m, u, v, rows, cols,
                                       iw00[:, None], iw01[:, None], iw10[:, None], iw11[:, None])
            # the scratch: I at [y, x], (Ix, Iy) interleaved at WIN + 2 (y ww + x) + (0, 1)
            trow = tpl[:, None] + y * WW + cidx[None, :]
            tl.store(trow, ti.to(tl.int16), mask=m)
            grow = tpl[:, None] + WIN + 2 * (y * WW + cidx[None, :])
            tl.store(grow, tx.to(tl.int16), mask=m)
            tl.store(grow + 1, ty.to(tl.int16), mask=m)
            g = tl.join(tx, ty)
            qa, ta = _add_singles(qa, ta, tx[:, :, None] * g, BLOCK, WP, WW, 2)
            qb, tb = _add_singles(qb, tb, ty[:, :, None] * g, BLOCK, WP, WW, 2)
        sa = _lane_total(qa, ta) * _FLT_SCALE
        sb = _lane_total(qb, tb) * _FLT_SCALE
        A11 = _pick(sa, 0)
        A12 = _pick(sa, 1)
        A22 = _pick(sb, 1)
        # the template's stores before any thread of the program reads them back (another thread
        # may own an element in the iterations' layouts)
        tl.debug_barrier()

        # ---- the minimum eigenvalue test (minEig compared in double, D in float32)
        D = A11 * A22 - A12 * A12
        disc = tl.sqrt_rn((A11 - A22) * (A11 - A22) + (4.0 * A12) * A12)
        min_eig_l = tl.div_rn((A22 + A11) - disc, tl.zeros_like(D) + 2.0 * WIN)
        good = act & ~((min_eig_l.to(tl.float64) < min_eig) | (D < _FLT_EPSILON))
        status = status & ~(act & ~good & lvl0)
        d_inv = tl.div_rn(tl.zeros_like(D) + 1.0, tl.where(good, D, 1.0))

        # ---- the iterations
        cx = nx - HW
        cy = ny - HH
        pdx = tl.zeros((BLOCK,), tl.float32)
        pdy = tl.zeros((BLOCK,), tl.float32)
        run = good
        j = 0
        while (j < max_iters) & (tl.max(run.to(tl.int32), axis=0) > 0):
            gx = tl.floor(cx)
            gy = tl.floor(cy)
            inb = _inside(gx, gy, rows, cols, WW, WH)
            status = status & ~(run & ~inb & lvl0)
            run = run & inb
            jx = tl.where(run, gx, 0.0).to(tl.int32)
            jy = tl.where(run, gy, 0.0).to(tl.int32)
            w00, w01, w10, w11 = _weights(tl.where(run, cx - gx, 0.0), tl.where(run, cy - gy, 0.0))
            w00 = w00[:, None]
            w01 = w01[:, None]
            w10 = w10[:, None]
            w11 = w11[:, None]
            mj = run[:, None] & cmask
            qbase = Q[:, None] + off_q + (jy[:, None] + pad_q) * pitch_q + pad_q + jx[:, None] + cidx[None, :]
            mg = mj[:, :, None] & (k2 < 2)
            c = tl.zeros((BLOCK, 4, 2), tl.float32)
            t = tl.zeros((BLOCK, 2), tl.float32)
            for y in range(WH):
                r = qbase + y * pitch_q
                j00 = tl.load(r, mask=mj, other=0).to(tl.int32)
                j01 = tl.load(r + 1, mask=mj, other=0).to(tl.int32)
                j10 = tl.load(r + pitch_q, mask=mj, other=0).to(tl.int32)
                j11 = tl.load(r + pitch_q + 1, mask=mj, other=0).to(tl.int32)
                ti = tl.load(tpl[:, None] + y * WW + cidx[None, :], mask=mj, other=0).to(tl.int32)
                g = tl.load(tpl[:, None, None] + WIN + 2 * (y * WW + cidx[None, :, None]) + k2, mask=mg,
                            other=0).to(tl.int32)
                diff = ((j00 * w00 + j01 * w01 + j10 * w10 + j11 * w11 + _ROUND_I) >> _SHIFT_I) - ti
                # (diff Ix, diff Iy): |.| <= 8160 * 4080 < 2^25, pair sums < 2^26: int32
                c, t = _add_pairs(c, t, diff[:, :, None] * g, BLOCK, WP, WW, 2)
            bb = _lane_total(c, t) * _FLT_SCALE
            b1 = _pick(bb, 0)
            b2 = _pick(bb, 1)
            dx = (A12 * b2 - A22 * b1) * d_inv
            dy = (A12 * b1 - A11 * b2) * d_inv
            cx = tl.where(run, cx + dx, cx)
            cy = tl.where(run, cy + dy, cy)
            nx = tl.where(run, cx + HW, nx)
            ny = tl.where(run, cy + HH, ny)
            dx64 = dx.to(tl.float64)
            dy64 = dy.to(tl.float64)
            conv = run & (dx64 * dx64 + dy64 * dy64 <= eps2)
            osc = (run & ~conv & ((lane_zero + j) > 0) & (tl.abs(dx + pdx).to(tl.float64) < _OSC)
                   & (tl.abs(dy + pdy).to(tl.float64) < _OSC))
            nx = tl.where(osc, nx - dx * 0.5, nx)
            ny = tl.where(osc, ny - dy * 0.5, ny)
            run = run & ~conv & ~osc
            pdx = dx
            pdy = dy
            j += 1
        # lanes still running after max_iters iterations at level 0 hit the cap
        capped = capped | (run & lvl0)
        # every read of this level's template before the next level overwrites it
        tl.debug_barrier()

    # the final bounds check of level 0
    status = status & _inside(tl.floor(nx - HW), tl.floor(ny - HH), height, width, WW, WH)
    return nx, ny, status, capped


@triton.jit
def _lk_kernel(prev_ptr, next_ptr, pts_ptr, valid_ptr, init_ptr, origin_ptr, out_pts_ptr, status_ptr,
               capped_ptr, tpl_ptr, n_lanes, n_per_stream, total_prev, total_next, height, width, pad_prev,
               pad_next, top, max_iters, eps2: tl.float64, min_eig: tl.float64, fb_threshold: tl.float64,
               WW: tl.constexpr, WH: tl.constexpr, WP: tl.constexpr, HAS_INIT: tl.constexpr,
               BACKWARD: tl.constexpr, BLOCK: tl.constexpr):
    """One pass of "Op 2" for lanes ``pid * BLOCK ..``: grid ``(cdiv(B N, BLOCK),)``.

    Forward (``BACKWARD`` False): tracks ``pts`` from ``prev`` into ``next`` (starting at ``init``
    when ``HAS_INIT``), writes ``out_pts``, ``status``, ``capped``. Backward (the forward-backward
    check, a second launch): ``prev`` / ``next`` are the forward pass's ``next`` / ``prev``, ``pts``
    its result, ``valid`` its status, ``init`` the points (``fb_from_pts``) or absent, ``origin`` the
    points; writes only ``status`` = valid and tracked back and ``|back - origin| <= fb_threshold``.
    ``eps2`` = eps^2 (double: OpenCV squares the criteria's epsilon), ``min_eig`` and
    ``fb_threshold`` are doubles.
    """
    pid = tl.program_id(0)
    lane = pid * BLOCK + tl.arange(0, BLOCK)
    live = lane < n_lanes
    lane = tl.where(live, lane, 0)
    px = tl.load(pts_ptr + 2 * lane, mask=live, other=0.0)
    py = tl.load(pts_ptr + 2 * lane + 1, mask=live, other=0.0)
    ok = live & (tl.load(valid_ptr + lane, mask=live, other=0) != 0)
    if HAS_INIT:
        gx = tl.load(init_ptr + 2 * lane, mask=live, other=0.0)
        gy = tl.load(init_ptr + 2 * lane + 1, mask=live, other=0.0)
        # isfinite: False for NaN and +-inf
        finite = (tl.abs(gx) < float("inf")) & (tl.abs(gy) < float("inf"))
        ok = ok & finite
        gx = tl.where(finite, gx, px)
        gy = tl.where(finite, gy, py)
    else:
        gx = px
        gy = py
    stream = (lane // n_per_stream).to(tl.int64)
    P = prev_ptr + stream * total_prev
    Q = next_ptr + stream * total_next
    tpl = tpl_ptr + lane.to(tl.int64) * (3 * WW * WH)
    nx, ny, status, capped = _track(P, Q, pad_prev, pad_next, px, py, gx, gy, ok, top, height, width,
                                    max_iters, eps2, min_eig, tpl, WW, WH, WP, BLOCK)
    if BACKWARD:
        ox = tl.load(origin_ptr + 2 * lane, mask=live, other=0.0)
        oy = tl.load(origin_ptr + 2 * lane + 1, mask=live, other=0.0)
        # the float32 differences, then double: the distance and its comparison in double (tl.sqrt_rn
        # takes fp32 only; tl.sqrt of fp64 is sqrt.rn.f64, correctly rounded: PTX has no approximate
        # f64 square root)
        ex = (nx - ox).to(tl.float64)
        ey = (ny - oy).to(tl.float64)
        tl.store(status_ptr + lane, ok & status & (tl.sqrt(ex * ex + ey * ey) <= fb_threshold), mask=live)
    else:
        nx = tl.where(ok, nx, gx)
        ny = tl.where(ok, ny, gy)
        tl.store(out_pts_ptr + 2 * lane, nx, mask=live)
        tl.store(out_pts_ptr + 2 * lane + 1, ny, mask=live)
        tl.store(status_ptr + lane, ok & status, mask=live)
        tl.store(capped_ptr + lane, ok & capped, mask=live)


# -------------------------------------------------------------------------------------- launchers
def _row_tile(ww: int) -> int:
    """``WP``: the row tile's width, ``ww`` rounded up to a power of two, at least 8 (the SIMD
    grouping reshapes a row into ``(WP / 8, 2, 4)``)."""
    return max(8, triton.next_power_of_2(int(ww)))


def lk_cuda(prev: torch.Tensor, next: torch.Tensor, pts: torch.Tensor, valid: torch.Tensor,
            init: Optional[torch.Tensor], height: int, width: int, pad_prev: int, pad_next: int, top: int,
            win_w: int, win_h: int, max_iters: int, eps: float, min_eig: float, fb_top: int,
            fb_threshold: float, fb_from_pts: bool) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Track ``pts`` from ``prev`` into ``next`` ("Op 2" of the LK contract) on their device.

    Args:
        prev, next: ``(B, Tp)`` / ``(B, Tn)`` uint8 packed pyramids of ``height x width`` images with
            at least ``max(top, fb_top) + 1`` levels and pads ``pad_prev`` / ``pad_next``
            (``>= max(win_w, win_h) + 1``).
        pts: ``(B, N, 2)`` float32 points in ``prev`` (level-0 pixels).
        valid: ``(B, N)`` bool: lanes to track (the others keep their start, status False).
        init: ``(B, N, 2)`` float32 starting positions in ``next`` (OPTFLOW_USE_INITIAL_FLOW), or None.
        height, width: level 0's size; top: the coarsest level (already capped by the caller).
        win_w, win_h: the window (pixels); max_iters, eps: the termination criteria (COUNT | EPS).
        min_eig: the minimum-eigenvalue threshold (OpenCV's default 1e-4).
        fb_top: the backward pass's coarsest level, -1 for no forward-backward check.
        fb_threshold: the largest forward-backward distance (pixels) kept.
        fb_from_pts: the backward pass starts at ``pts`` (else at the forward result).

    Returns:
        ``next_pts`` ``(B, N, 2)`` float32, ``status`` ``(B, N)`` bool, ``capped`` ``(B, N)`` bool
        (the forward pass hit ``max_iters`` at level 0).
    """
    B, N = int(pts.shape[0]), int(pts.shape[1])
    dev = pts.device
    out_pts = torch.empty((B, N, 2), dtype=torch.float32, device=dev)
    status = torch.empty((B, N), dtype=torch.bool, device=dev)
    capped = torch.empty((B, N), dtype=torch.bool, device=dev)
    n_lanes = B * N
    if n_lanes == 0:
        return out_pts, status, capped
    prev = prev.contiguous()
    next = next.contiguous()
    pts = pts.contiguous().to(torch.float32)
    valid = valid.contiguous().to(torch.bool)
    init = None if init is None else init.contiguous().to(torch.float32)
    ww, wh = int(win_w), int(win_h)
    # the per-lane template scratch: (I | (Ix, Iy) interleaved), int16
    tpl = torch.empty((n_lanes, 3, wh * ww), dtype=torch.int16, device=dev)
    grid = (triton.cdiv(n_lanes, _BLOCK),)
    common = dict(WW=ww, WH=wh, WP=_row_tile(ww), BLOCK=_BLOCK, num_warps=_NUM_WARPS, **_COMPILE_OPTIONS)
    eps = float(eps)
    # the forward pass (unused pointer arguments get a tensor of the right type: never read)
    torch.library.wrap_triton(_lk_kernel)[grid](
        prev, next, pts, valid, pts if init is None else init, pts, out_pts, status, capped, tpl,
        n_lanes, N, int(prev.shape[1]), int(next.shape[1]), int(height), int(width), int(pad_prev),
        int(pad_next), int(top), int(max_iters), eps * eps, float(min_eig), float(fb_threshold),
        HAS_INIT=init is not None, BACKWARD=False, **common)
    if int(fb_top) < 0:
        return out_pts, status, capped
    # the backward pass: a second launch (one tracker per compiled kernel: ptxas's time grows much
    # faster than the code), next -> prev from the result, on the lanes the forward pass kept
    fb_status = torch.empty_like(status)
    torch.library.wrap_triton(_lk_kernel)[grid](
        next, prev, out_pts, status, pts, pts, out_pts, fb_status, capped, tpl,
        n_lanes, N, int(next.shape[1]), int(prev.shape[1]), int(height), int(width), int(pad_next),
        int(pad_prev), int(fb_top), int(max_iters), eps * eps, float(min_eig), float(fb_threshold),
        HAS_INIT=bool(fb_from_pts), BACKWARD=True, **common)
    return out_pts, fb_status, capped


# ----------------------------------------------------------------------------------- PTX (no GPU)
#: VINS's setting: a 21 x 21 window
_VINS_WIN = 21

_LK_SIGNATURE = {
    "prev_ptr": "*u8", "next_ptr": "*u8", "pts_ptr": "*fp32", "valid_ptr": "*i1", "init_ptr": "*fp32",
    "origin_ptr": "*fp32", "out_pts_ptr": "*fp32", "status_ptr": "*i1", "capped_ptr": "*i1",
    "tpl_ptr": "*i16",
    "n_lanes": "i32", "n_per_stream": "i32", "total_prev": "i32", "total_next": "i32", "height": "i32",
    "width": "i32", "pad_prev": "i32", "pad_next": "i32", "top": "i32", "max_iters": "i32",
    "eps2": "fp64", "min_eig": "fp64", "fb_threshold": "fp64",
    "WW": "constexpr", "WH": "constexpr", "WP": "constexpr", "HAS_INIT": "constexpr", "BACKWARD": "constexpr",
    "BLOCK": "constexpr",
}
_PYR_SIGNATURES = {
    "pyramid_level0": {"img_ptr": "*u8", "out_ptr": "*u8", "height": "i32", "width": "i32", "total": "i32",
                       "pad": "i32", "BLOCK": "constexpr"},
    "pyramid_down": {"out_ptr": "*u8", "total": "i32", "src_off": "i32", "s_h": "i32", "s_w": "i32",
                     "dst_off": "i32", "d_h": "i32", "d_w": "i32", "pad": "i32", "BLOCK": "constexpr"},
}
#: the LK variants compiled by :func:`ptx_sm90`: (HAS_INIT, BACKWARD)
_LK_VARIANTS = {
    "lk": (False, False),  # VINS-Mono: no initial flow (the forward pass of every forward-backward too)
    "lk_init": (True, False),  # OPTFLOW_USE_INITIAL_FLOW
    "lk_back": (True, True),  # the backward pass from the points (the only one with fp64 sqrt)
}


def _ptx_only_hook(*args):
    """A ``knobs.runtime.add_stages_inspection_hook`` that stops the pipeline at PTX: the ``cubin``
    stage (ptxas: a third of the LK kernel's compile time, nothing the PTX check reads) returns no
    binary. Called with no argument it names itself for the cache key, so these binary-less kernels
    never shadow a launchable one in Triton's cache."""
    if not args:
        return "torch_frontend-ptx-only", "torch_frontend-ptx-only"
    stages = args[1]
    stages["cubin"] = lambda src, metadata: b""


def ptx_sm90() -> Dict[str, str]:
    """The PTX of every Triton kernel of the fused LK, pyramid and CLAHE, compiled for sm_90 without a GPU.

    Compiled with the launchers' options (``enable_fp_fusion=False``, their ``num_warps``) and
    constexprs (a 21 x 21 window), one entry per LK variant (see ``_LK_VARIANTS``), per pyramid
    kernel and per setMask kernel (``_triton_mask.KERNELS``). Must run in a process without ``TRITON_INTERPRET`` (it replaces ``@triton.jit``).
    """
    from triton.backends.compiler import GPUTarget

    target = GPUTarget("cuda", 90, 32)
    out: Dict[str, str] = {}
    runtime = getattr(getattr(triton, "knobs", None), "runtime", None)
    if runtime is None or not hasattr(runtime, "add_stages_inspection_hook"):  # older Triton: with ptxas
        _compile_all(target, out)
        return out
    saved = runtime.add_stages_inspection_hook
    runtime.add_stages_inspection_hook = _ptx_only_hook
    try:
        _compile_all(target, out)
    finally:
        runtime.add_stages_inspection_hook = saved
    return out


def _compile_all(target, out: Dict[str, str]) -> None:
    """Fill ``out`` with the PTX of every kernel variant (see :func:`ptx_sm90`)."""
    from triton.compiler import ASTSource

    for name, (has_init, backward) in _LK_VARIANTS.items():
        consts = {"WW": _VINS_WIN, "WH": _VINS_WIN, "WP": _row_tile(_VINS_WIN), "HAS_INIT": has_init,
                  "BACKWARD": backward, "BLOCK": _BLOCK}
        src = ASTSource(fn=_lk_kernel, signature=_LK_SIGNATURE, constexprs=consts)
        out[name] = triton.compile(src, target=target, options={**_COMPILE_OPTIONS,
                                                                 "num_warps": _NUM_WARPS}).asm["ptx"]
    for name, kern in _triton_pyramid.KERNELS.items():
        src = ASTSource(fn=kern, signature=_PYR_SIGNATURES[name],
                        constexprs={"BLOCK": _triton_pyramid._BLOCK})
        out[name] = triton.compile(src, target=target, options={
            **_COMPILE_OPTIONS, "num_warps": _triton_pyramid._NUM_WARPS}).asm["ptx"]
    from . import _triton_clahe

    for name, kern in _triton_clahe.KERNELS.items():
        src = ASTSource(fn=kern, signature=_triton_clahe.SIGNATURES[name], constexprs={"BLOCK": _triton_clahe._BLOCK})
        out[name] = triton.compile(src, target=target, options={
            **_COMPILE_OPTIONS, "num_warps": _triton_clahe._NUM_WARPS}).asm["ptx"]
    from . import _triton_mask

    for name, (kern, sig, consts, warps) in _triton_mask.KERNELS.items():
        src = ASTSource(fn=kern, signature=sig, constexprs=consts)
        out[name] = triton.compile(src, target=target, options={**_COMPILE_OPTIONS, "num_warps": warps}).asm["ptx"]

    from . import _triton_ransac  # the F-RANSAC scoring (fused/ransac_op.py)

    for name, (kern, has_state) in _triton_ransac.KERNELS.items():
        src = ASTSource(fn=kern, signature=_triton_ransac.SIGNATURES, constexprs=_triton_ransac.constexprs(has_state))
        out[name] = triton.compile(src, target=target, options={
            **_COMPILE_OPTIONS, "num_warps": _triton_ransac.NUM_WARPS}).asm["ptx"]
    from . import _triton_corners  # detection: the response and the candidates' keys

    for name, kern in _triton_corners.KERNELS.items():
        src = ASTSource(fn=kern, signature=_triton_corners.SIGNATURES[name], constexprs=_triton_corners.CONSTEXPRS[name])
        out[name] = triton.compile(src, target=target, options={
            **_COMPILE_OPTIONS, "num_warps": _triton_corners.NUM_WARPS}).asm["ptx"]
    from . import _triton_lift  # the PINHOLE lift (fused/lift_op.py)

    for name, (kern, sig, consts, warps) in _triton_lift.KERNELS.items():
        src = ASTSource(fn=kern, signature=sig, constexprs=consts)
        out[name] = triton.compile(src, target=target, options={**_COMPILE_OPTIONS, "num_warps": warps}).asm["ptx"]
