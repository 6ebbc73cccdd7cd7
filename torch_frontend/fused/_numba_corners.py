"""``goodFeaturesToTrack`` as VINS calls it, on the CPU: a numba kernel (``docs/kernels.md``, "Detection").

Convention:
    ``img`` ``(B, H, W)`` uint8; ``mask`` ``(B, H, W)`` uint8 (non-zero = allowed) or ignored when
    ``has_mask`` is False; ``mc`` ``(B,)`` int64 corners per stream (clipped to ``K``; ``<= 0``: none);
    ``out_pts`` ``(B, K, 2)`` float32 pixel positions ``(x, y)``, ``out_valid`` ``(B, K)`` bool, both
    zero-filled by the caller. Block size 3, Sobel aperture 3, the min-eigenvalue response.

The contract (the tensor reference: ``corners.responses._min_eigen_impl`` and
``corners.selection._select_corners``, bit for bit):

1. ``dx``, ``dy``: the Sobel-3 derivatives of the grey levels, BORDER_REFLECT_101, integers;
   ``Sxx``, ``Sxy``, ``Syy``: their products summed over the 3x3 block, BORDER_REFLECT_101 on the
   product planes, integers below 2**24 (9 x 1020²), so int32 here and exact as float32;
2. the response, in float32 without FMA: ``d = Sxx - Syy``; ``disc = d * d + (4 Sxy) * Sxy``;
   ``r = ((Sxx + Syy) - sqrt(disc)) * c`` with ``c = float32(0.5 / 3060²)``;
3. ``maxVal`` = the largest response over the mask (the image without one; 0 for an empty mask),
   ``thr = float32(double(maxVal) * quality)``, ``t = r if r > thr else 0``;
4. candidates: ``1 <= x <= W - 2``, ``1 <= y <= H - 2``, mask set, ``t != 0`` and ``t`` equal to
   the 3x3 maximum of ``t``;
5. order: response descending, ties later raster position first (OpenCV's ``greaterThanPtr``);
6. greedy: a candidate is taken unless an accepted corner lies at ``d² < min_distance²`` in one of
   the 3x3 grid cells (cell ``cvRound(min_distance)``) around it; none is tested when
   ``min_distance < 1``; at most ``mc`` corners.

**Only where the mask matters.** The response at a pixel depends on the image only: its own 3x3
block of products, each of which depends on a 3x3 block of grey levels; every value is computed
from its own inputs by the same operations, whatever else is computed (no running sums across a
row, unlike OpenCV's box filter). The selection reads the response at (a) every mask pixel (the
maximum, step 3) and (b) the 3x3 neighbours of a candidate, which is a mask pixel (step 4). So the
response is computed on ``need = dilate3x3(mask)`` (clipped to the image) and nowhere else, and its
products on ``dilate3x3(need)`` (a reflected index is at most one pixel from its source, so the
reflection stays inside that dilation). Every value read is computed exactly as on the whole image,
so the corners keep every bit; the pixels skipped (masked discs around tracked features, and
outside a fisheye mask) are never read. OpenCV computes ``cornerMinEigenVal`` over the whole image
and ``dilate`` over it too, then scans the whole image for candidates.

The passes run on a row's *runs* of ``need`` (``pneed``), with runs less than ``_GAP`` columns apart
merged (computing more is always safe: it only adds values nobody reads). Measured (thread time,
752x480): a run costs ~0.1 µs of calls and loop set-up per pass, so setMask's discs (gaps of at most
one disc diameter, ~10 runs a row) cost more than they save unless bridged; with ``_GAP = 64`` a
steady-state mask costs what an unmasked frame does (1.99 against 1.75 ms), and a fisheye-style
mask (43 % of the frame in wide margins) 0.72x of it (1.25 ms).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["gftt_streams", "RESP_SCALE", "scratch"]

#: runs of ``need`` / ``pneed`` closer than this many columns are merged (:func:`_runs`): a run costs a
#: few calls and loop set-ups (~0.3 µs), a bridged pixel a few ns
_GAP = 64

#: ``0.5 * scale²`` of the response, ``scale = 1 / (4 * 3 * 255)`` (aperture 3, block 3, 8-bit), as the
#: tensor path's ``mul_`` rounds it (to float32)
RESP_SCALE = np.float32(0.5 * (1.0 / (4.0 * 3 * 255.0)) ** 2)


@njit(cache=True, nogil=True)
def _refl(i, n):
    """BORDER_REFLECT_101 of an index at most one out of ``[0, n)`` (``n >= 2``)."""
    if i < 0:
        return -i
    if i >= n:
        return 2 * n - 2 - i
    return i


@njit(cache=True, nogil=True)
def _dilate_rows(src, dst, H, W, tmp):
    """``dst = dilate3x3(src != 0)`` clipped to the image, uint8 (non-zero = set; ``dst`` distinct from
    ``src``; ``tmp`` a row of scratch). Slices indexed from 0, so the loops vectorise."""
    for y in range(H):
        a, b, c = src[max(y - 1, 0)], src[y], src[min(y + 1, H - 1)]
        for x in range(W):
            tmp[x] = a[x] | b[x] | c[x]
        r = dst[y]
        r[0] = tmp[0] | tmp[1]
        r[W - 1] = tmp[W - 2] | tmp[W - 1]
        t0, t1, t2, o = tmp[0:W - 2], tmp[1:W - 1], tmp[2:W], r[1:W - 1]
        for i in range(W - 2):
            o[i] = t0[i] | t1[i] | t2[i]


@njit(cache=True, nogil=True)
def _products(a, b, c, x0, x1, W, pxx, pxy, pyy):
    """Sobel-3 products of the row between ``a`` (above) and ``c`` (below) at columns ``[x0, x1)``,
    reflect-101 at the left and right edges. Every value is an integer below 2**24 (float32 exact;
    float32 lanes vectorise where numba's int32 arithmetic widens to int64), and the loops index
    slices from 0 (no negative index: numba's wrap-around check would block the vectoriser)."""
    lo = max(x0, 1)
    hi = min(x1, W - 1)
    if x0 == 0:  # column 0: x - 1 reflects to 1
        dy = (np.float32(c[1]) + np.float32(2.0) * np.float32(c[0]) + np.float32(c[1])) - (
            np.float32(a[1]) + np.float32(2.0) * np.float32(a[0]) + np.float32(a[1]))
        pxx[0], pxy[0], pyy[0] = np.float32(0.0), np.float32(0.0), dy * dy
    n = hi - lo
    if n > 0:
        al, am, ar = a[lo - 1:hi - 1], a[lo:hi], a[lo + 1:hi + 1]
        bl, br = b[lo - 1:hi - 1], b[lo + 1:hi + 1]
        cl, cm, cr = c[lo - 1:hi - 1], c[lo:hi], c[lo + 1:hi + 1]
        oxx, oxy, oyy = pxx[lo:hi], pxy[lo:hi], pyy[lo:hi]
        two = np.float32(2.0)
        for i in range(n):
            dx = (np.float32(ar[i]) - np.float32(al[i])) + two * (np.float32(br[i]) - np.float32(bl[i])) + (
                np.float32(cr[i]) - np.float32(cl[i]))
            dy = (np.float32(cl[i]) + two * np.float32(cm[i]) + np.float32(cr[i])) - (
                np.float32(al[i]) + two * np.float32(am[i]) + np.float32(ar[i]))
            oxx[i] = dx * dx
            oxy[i] = dx * dy
            oyy[i] = dy * dy
    if x1 == W:  # column W - 1: x + 1 reflects to W - 2
        x = W - 1
        dy = (np.float32(c[x - 1]) + np.float32(2.0) * np.float32(c[x]) + np.float32(c[x - 1])) - (
            np.float32(a[x - 1]) + np.float32(2.0) * np.float32(a[x]) + np.float32(a[x - 1]))
        pxx[x], pxy[x], pyy[x] = np.float32(0.0), np.float32(0.0), dy * dy


@njit(cache=True, nogil=True)
def _response_row(P, r0, r1, r2, x0, x1, W, out, V):
    """Responses of one row at columns ``[x0, x1)`` from the product rows ``r0, r1, r2`` of ``P (3, 3, W)``
    (block 3, reflect-101 across columns); ``V (3, W)`` scratch (the vertical sums). Integer sums
    below 2**24 in float32: exact, so any order gives the same values."""
    a = max(x0 - 1, 0)
    b = min(x1 + 1, W)
    n = b - a
    p0, p1, p2 = P[r0], P[r1], P[r2]
    for k in range(3):
        u0, u1, u2, v = p0[k, a:b], p1[k, a:b], p2[k, a:b], V[k, a:b]
        for i in range(n):
            v[i] = u0[i] + u1[i] + u2[i]
    vxx, vxy, vyy = V[0], V[1], V[2]
    if x0 == 0:
        _response_px(vxx[1] + vxx[0] + vxx[1], vxy[1] + vxy[0] + vxy[1], vyy[1] + vyy[0] + vyy[1], out, 0)
    lo = max(x0, 1)
    hi = min(x1, W - 1)
    n = hi - lo
    if n > 0:
        o = out[lo:hi]
        xl, xm, xr = vxx[lo - 1:hi - 1], vxx[lo:hi], vxx[lo + 1:hi + 1]
        yl, ym, yr = vxy[lo - 1:hi - 1], vxy[lo:hi], vxy[lo + 1:hi + 1]
        zl, zm, zr = vyy[lo - 1:hi - 1], vyy[lo:hi], vyy[lo + 1:hi + 1]
        for i in range(n):
            _response_px(xl[i] + xm[i] + xr[i], yl[i] + ym[i] + yr[i], zl[i] + zm[i] + zr[i], o, i)
    if x1 == W:
        x = W - 1
        _response_px(vxx[x - 1] + vxx[x] + vxx[x - 1], vxy[x - 1] + vxy[x] + vxy[x - 1],
                     vyy[x - 1] + vyy[x] + vyy[x - 1], out, x)


@njit(cache=True, nogil=True, inline="always")
def _response_px(sxx, sxy, syy, out, x):
    """The float32 response of one pixel's integer sums (module docstring, step 2; no FMA)."""
    fxx = np.float32(sxx)
    fxy = np.float32(sxy)
    fyy = np.float32(syy)
    d = fxx - fyy
    disc = d * d
    disc = disc + (np.float32(4.0) * fxy) * fxy
    out[x] = ((fxx + fyy) - np.sqrt(disc)) * RESP_SCALE


@njit(cache=True, nogil=True, fastmath={"nnan", "nsz"})
def _masked_max(v, m, x0, x1, mx):
    """``max(mx, max(v[x] for x in [x0, x1) if m[x]))``: a maximum is exact in any order, and the
    responses of a uint8 image are finite (``nnan`` lets LLVM vectorise the reduction)."""
    ninf = np.float32(-np.inf)
    for x in range(x0, x1):
        u = v[x] if m[x] != 0 else ninf
        mx = u if u > mx else mx
    return mx


@njit(cache=True, nogil=True, fastmath={"nnan", "nsz"})
def _row_max(v, W, mx):
    for x in range(W):
        u = v[x]
        mx = u if u > mx else mx
    return mx


@njit(cache=True, nogil=True)
def _t_row(r, thr, x0, x1, W, t, hm):
    """On columns ``[x0, x1)``: ``t = r if r > thr else 0``, and its horizontal 3-maximum ``hm`` on the
    interior columns of the segment (at its ends ``hm`` reads ``t`` one column out, which may be stale:
    such a column is one no candidate reads, see :func:`_stream`)."""
    zero = np.float32(0.0)
    n = x1 - x0
    rs, ts = r[x0:x1], t[x0:x1]
    for i in range(n):
        u = rs[i]
        ts[i] = u if u > thr else zero
    lo = max(x0, 1)
    hi = min(x1, W - 1)
    if hi > lo:
        tl, tm, tr, h = t[lo - 1:hi - 1], t[lo:hi], t[lo + 1:hi + 1], hm[lo:hi]
        for i in range(hi - lo):
            a = tl[i]
            b = tm[i]
            c = tr[i]
            u = a if a > b else b
            h[i] = u if u > c else c


@njit(cache=True, nogil=True)
def _cand_row(t1, h0, h1, h2, x0, x1, flag):
    """``flag[x] = t1[x] != 0 and t1[x] == max(h0, h1, h2)[x]`` on ``[x0, x1)`` (h1[x] >= t1[x])."""
    zero = np.float32(0.0)
    n = x1 - x0
    a, b, c, d, f = t1[x0:x1], h0[x0:x1], h1[x0:x1], h2[x0:x1], flag[x0:x1]
    for i in range(n):
        v = a[i]
        f[i] = (v != zero) & (v >= b[i]) & (v >= c[i]) & (v >= d[i])


@njit(cache=True, nogil=True)
def _runs(flag, W, starts, stops, tr):
    """The runs of ``flag[:W]`` (values 0 / 1): ``[starts[i], stops[i])``, runs less than ``_GAP``
    columns apart merged into one; returns their number. (A merged run also covers columns outside
    ``flag``: the passes compute there from values that may be stale, and no candidate reads them,
    see :func:`_stream`.)
    ``tr``: uint8 scratch of ``8 * ceil((W + 1) / 8)`` bytes whose tail past ``W`` is 0. The
    transitions ``flag[x] ^ flag[x - 1]`` are written in one vectorised pass, then read 8 at a time
    (a run edge is rare: most words are 0)."""
    tr[0] = flag[0]
    a, b, o = flag[0:W - 1], flag[1:W], tr[1:W]
    for i in range(W - 1):
        o[i] = a[i] ^ b[i]
    tr[W] = flag[W - 1]  # a run open at the last column closes at W
    words = tr.view(np.uint64)
    n = 0
    k = 0
    for w in range(words.shape[0]):
        if words[w] == 0:
            continue
        for x in range(8 * w, 8 * w + 8):
            if tr[x] != 0:
                if k == 0:
                    if n > 0 and x - stops[n - 1] < _GAP:
                        n -= 1  # bridge the gap: reopen the previous run
                    else:
                        starts[n] = x
                    k = 1
                else:
                    stops[n] = x
                    n += 1
                    k = 0
    return n


@njit(cache=True, nogil=True)
def _stream(img, m, has_mask, mc, quality, min_dist, cell, r2i, out_pts, out_valid, resp, need, pneed, P, keys,
            head, nxt, ax, ay, starts, stops, ones, V, T, HM, flag, rs, re, roff, tmp, tr):
    """One stream (module docstring); scratch passed in. With a mask, every pass runs on the runs of
    ``need`` (responses, their maximum over the mask, the thresholded rows and the candidate test) or
    of ``pneed`` (products); without one, on whole rows."""
    H, W = img.shape
    K = out_pts.shape[0]
    n_max = min(mc, K)
    if n_max <= 0:
        return
    if has_mask:
        _dilate_rows(m, need, H, W, tmp)
        _dilate_rows(need, pneed, H, W, tmp)
    # responses: product rows j ring-buffered in P[j % 3], computed on pneed's runs of row j; the runs
    # of need kept per row (rs, re from roff[y]) for the candidate pass
    mx = np.float32(-np.inf)
    done = -1  # product rows < done + 1 are computed
    nrun = 0
    for y in range(H):
        last = min(y + 1, H - 1)
        while done < last:
            j = done + 1
            a, b, c = img[_refl(j - 1, H)], img[j], img[_refl(j + 1, H)]
            q = j % 3
            if has_mask:
                nr = _runs(pneed[j], W, starts, stops, tr)
                for i in range(nr):
                    _products(a, b, c, starts[i], stops[i], W, P[q, 0], P[q, 1], P[q, 2])
            else:
                _products(a, b, c, 0, W, W, P[q, 0], P[q, 1], P[q, 2])
            done = j
        r0, r1, r2 = _refl(y - 1, H) % 3, y % 3, _refl(y + 1, H) % 3
        roff[y] = nrun
        if has_mask:
            nr = _runs(need[y], W, starts, stops, tr)
            for i in range(nr):
                _response_row(P, r0, r1, r2, starts[i], stops[i], W, resp[y], V)
                mx = _masked_max(resp[y], m[y], starts[i], stops[i], mx)
                rs[nrun] = starts[i]
                re[nrun] = stops[i]
                nrun += 1
        else:
            _response_row(P, r0, r1, r2, 0, W, W, resp[y], V)
            mx = _row_max(resp[y], W, mx)
            rs[nrun] = 0
            re[nrun] = W
            nrun += 1
    roff[H] = nrun
    if not np.isfinite(mx):
        mx = np.float32(0.0)
    thr = np.float32(np.float64(mx) * quality)
    # candidates (3x3 maximum of the thresholded response, interior, mask) -> keys that sort ascending
    # in OpenCV's order: response descending (float bits made order-preserving), raster descending.
    # Only need's runs are visited: a candidate (y, x) is a mask pixel, so its 3x3 neighbours and
    # theirs in the row (the horizontal maximum) are need pixels of their rows; values outside need
    # are stale and reach no candidate's test.
    bits = resp.view(np.int32)
    ib = 1
    while (1 << ib) < H * W:
        ib += 1
    top = (1 << ib) - 1
    n = 0
    for j in range(0, min(2, H)):
        for k in range(roff[j], roff[j + 1]):
            _t_row(resp[j], thr, rs[k], re[k], W, T[j % 3], HM[j % 3])
    for y in range(1, H - 1):
        j = y + 1
        for k in range(roff[j], roff[j + 1]):
            _t_row(resp[j], thr, rs[k], re[k], W, T[j % 3], HM[j % 3])
        mrow = m[y] if has_mask else ones
        ba = bits[y]
        for k in range(roff[y], roff[y + 1]):
            x0, x1 = max(rs[k], 1), min(re[k], W - 1)
            if x1 <= x0:
                continue
            _cand_row(T[y % 3], HM[(y - 1) % 3], HM[y % 3], HM[(y + 1) % 3], x0, x1, flag)
            for x in range(x0, x1):
                if not flag[x] or mrow[x] == 0:
                    continue
                bv = np.int64(ba[x])
                if bv < 0:
                    bv ^= 0x7FFFFFFF
                keys[n] = ((np.int64(0x7FFFFFFF) - bv) << ib) + (top - (y * W + x))
                n += 1
    if n == 0:
        return
    srt = np.sort(keys[:n])
    got = 0
    if min_dist < 1:
        for i in range(min(n, n_max)):
            pix = top - (srt[i] & top)
            out_pts[i, 0] = np.float32(pix % W)
            out_pts[i, 1] = np.float32(pix // W)
            out_valid[i] = True
        return
    gw = (W + cell - 1) // cell
    gh = (H + cell - 1) // cell
    for i in range(gw * gh):
        head[i] = -1
    for i in range(n):
        pix = top - (srt[i] & top)
        x = pix % W
        y = pix // W
        cx = x // cell
        cy = y // cell
        good = True
        for yy in range(max(cy - 1, 0), min(cy + 2, gh)):
            for xx in range(max(cx - 1, 0), min(cx + 2, gw)):
                k = head[yy * gw + xx]
                while k >= 0:
                    ddx = x - ax[k]
                    ddy = y - ay[k]
                    if ddx * ddx + ddy * ddy < r2i:
                        good = False
                        break
                    k = nxt[k]
                if not good:
                    break
            if not good:
                break
        if not good:
            continue
        ax[got] = x
        ay[got] = y
        c = cy * gw + cx
        nxt[got] = head[c]
        head[c] = got
        out_pts[got, 0] = np.float32(x)
        out_pts[got, 1] = np.float32(y)
        out_valid[got] = True
        got += 1
        if got >= n_max:
            return


def scratch(B_unused: int, H: int, W: int):
    """The image-sized scratch of :func:`gftt_streams` for ``H x W`` frames: ``(resp, need, pneed, keys,
    rs, re)``. The caller keeps it per thread and size (no page faults of fresh buffers on every
    call); its contents never matter (every value read is written first, or is stale where no
    candidate reads it)."""
    n = H * (W // 2 + 1)
    return (np.empty((H, W), dtype=np.float32), np.empty((H, W), dtype=np.uint8), np.empty((H, W), dtype=np.uint8),
            np.empty(H * W, dtype=np.int64), np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64))


@njit(cache=True, nogil=True)
def gftt_streams(img, mask, has_mask, mc, quality, min_dist, cell, r2i, out_pts, out_valid, s0, s1, resp, need,
                 pneed, keys, rs, re):
    """Streams ``s0 .. s1 - 1`` (module docstring). ``cell = cvRound(min_dist)``, ``r2i =
    ceil(min_dist²)`` (a conflict is an integer ``d² < r2i``), from the caller; ``resp .. re``:
    :func:`scratch`."""
    _, H, W = img.shape
    K = out_pts.shape[1]
    P = np.zeros((3, 3, W), dtype=np.float32)
    c = max(cell, 1)
    head = np.empty(((W + c - 1) // c) * ((H + c - 1) // c), dtype=np.int32)
    nxt = np.empty(max(K, 1), dtype=np.int32)
    ax = np.empty(max(K, 1), dtype=np.int64)
    ay = np.empty(max(K, 1), dtype=np.int64)
    starts = np.empty(W, dtype=np.int64)
    stops = np.empty(W, dtype=np.int64)
    ones = np.ones(W, dtype=np.uint8)
    V = np.zeros((3, W), dtype=np.float32)
    T = np.zeros((3, W), dtype=np.float32)
    HM = np.zeros((3, W), dtype=np.float32)
    flag = np.zeros(W, dtype=np.bool_)
    roff = np.empty(H + 1, dtype=np.int64)
    tmp = np.empty(W, dtype=np.uint8)
    tr = np.zeros(8 * ((W + 8) // 8), dtype=np.uint8)  # W + 1 transitions, a zero tail
    for s in range(s0, s1):
        ms = mask[s] if has_mask else mask[0]
        _stream(img[s], ms, has_mask, mc[s], quality, min_dist, c, r2i, out_pts[s], out_valid[s], resp, need,
                pneed, P, keys, head, nxt, ax, ay, starts, stops, ones, V, T, HM, flag, rs, re, roff, tmp, tr)
