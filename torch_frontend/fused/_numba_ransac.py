"""The fused F-RANSAC scoring on the CPU: a numba kernel, OpenCV's ``computeError`` / ``findInliers``
and ``RANSACPointSetRegistrator::run``'s bookkeeping for a block of 7-point models.

Convention (the contract of ``torch_frontend::ransac_score``, ``docs/kernels.md``, "F-RANSAC"):
    Problem ``b`` has ``M = 3 S`` models ``F[b, m]`` (row-major 3x3, float64; sample ``i`` gave models
    ``3 i, 3 i + 1, 3 i + 2`` in OpenCV's root order, ``fok[b, m]`` False where the sample gave fewer),
    ``N`` point slots ``x12[b, j] = (x1, y1, x2, y2)`` float64 of float32-rounded pixels and
    ``eff[b, j]`` (the slot holds a point), ``n[b]`` points in all. ``table[n, c + 1]`` (int64, row
    stride ``table.shape[1]``) is OpenCV's iteration bound with best count ``c`` (``-1``: none).

    A problem with ``n < 15`` is not scored (OpenCV runs LMedS there): its state passes through and
    ``kbest = -1``. Else, from the state ``(best, niters, done)``, for samples ``i = 0 .. live - 1``:
    every model ``m`` of the sample with ``fok`` is counted, ``count = #{j: eff_j and err_j <= t}``
    with OpenCV's error (below) and ``t = float32(thr2)``; a count ``> max(best, 6)`` makes ``m`` the
    best model (``best = count``, ``niters = table[n, count + 1]``); then ``done += 1`` and the loop
    stops when ``done >= niters``. The outputs are the state after the loop, ``kbest`` (the block's
    last accepted model, -1 if none) and ``mask[b]`` = that model's inliers (all False if none).

    The error of a slot, in double without FMA, in this order (OpenCV ``FMEstimatorCallback``)::

        a = F0 x1 + F1 y1 + F2;  b = F3 x1 + F4 y1 + F5;  c = F6 x1 + F7 y1 + F8
        s2 = 1 / (a a + b b);    d2 = x2 a + y2 b + c
        a = F0 x2 + F3 y2 + F6;  b = F1 x2 + F4 y2 + F7;  c = F2 x2 + F5 y2 + F8
        s1 = 1 / (a a + b b);    d1 = x1 a + y1 b + c
        err = float32(e1 < e2 ? e2 : e1),  e1 = d1 d1 s1,  e2 = d2 d2 s2   (std::max)

    every sum left to right. numba compiles without ``fastmath``: no contraction, IEEE division
    (``error_model="numpy"``: a zero line norm gives inf / NaN, as in C, not an exception).
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: OpenCV's RANSAC minimum: fewer points run LMedS (not scored here)
MIN_RANSAC_POINTS = 15
#: modelPoints - 1: a count must exceed it to be accepted
MIN_GOOD = 6


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _inlier(f, x12, eff, b, j, t):
    """Slot ``j`` of problem ``b`` is an inlier of the model ``f (9,)`` (the contract's error in its
    order, the float32 compare ``<= t``); :func:`_count` and :func:`_mask` share it."""
    x1 = x12[b, j, 0]
    y1 = x12[b, j, 1]
    x2 = x12[b, j, 2]
    y2 = x12[b, j, 3]
    a = f[0] * x1 + f[1] * y1 + f[2]
    bb = f[3] * x1 + f[4] * y1 + f[5]
    c = f[6] * x1 + f[7] * y1 + f[8]
    s2 = 1.0 / (a * a + bb * bb)
    d2 = x2 * a + y2 * bb + c
    a = f[0] * x2 + f[3] * y2 + f[6]
    bb = f[1] * x2 + f[4] * y2 + f[7]
    c = f[2] * x2 + f[5] * y2 + f[8]
    s1 = 1.0 / (a * a + bb * bb)
    d1 = x1 * a + y1 * bb + c
    e1 = d1 * d1 * s1
    e2 = d2 * d2 * s2
    e = e2 if e1 < e2 else e1
    return eff[b, j] and np.float32(e) <= t


@njit(cache=True, nogil=True, error_model="numpy")
def _count(F, m, x12, eff, b, N, t):
    """Inliers of model ``F[b, m]`` on problem ``b``'s slots (the contract's error, ``<= t``)."""
    f = F[b, m]
    cnt = 0
    for j in range(N):
        if _inlier(f, x12, eff, b, j, t):
            cnt += 1
    return cnt


@njit(cache=True, nogil=True, error_model="numpy")
def _mask(F, m, x12, eff, b, N, t, out):
    """``out[b, j]``: slot ``j`` is an inlier of model ``F[b, m]`` (the same test as :func:`_count`)."""
    f = F[b, m]
    for j in range(N):
        out[b, j] = _inlier(f, x12, eff, b, j, t)


@njit(cache=True, nogil=True, error_model="numpy")
def ransac_score_streams(F, fok, x12, eff, n, table, live, best_in, nit_in, done_in, has_state, thr2,
                         out_best, out_nit, out_done, out_kb, out_mask, s0, s1):
    """The contract (module docstring) for problems ``s0 <= b < s1``.

    ``F (B, M, 9)`` float64, ``fok (B, M)`` bool, ``x12 (B, N, 4)`` float64, ``eff (B, N)`` bool,
    ``n (B,)`` int64, ``table (R, C)`` int64; the state ``live, best_in, nit_in, done_in`` ``(B,)``
    int64 when ``has_state``, else (not read) every sample of the block from best -1,
    ``table[n, 0]`` and 0. Writes ``out_best, out_nit, out_done, out_kb (B,)`` int64 and
    ``out_mask (B, N)`` bool."""
    M = F.shape[1]
    N = x12.shape[1]
    t = np.float32(thr2)
    for b in range(s0, s1):
        nb = n[b]
        live_b = live[b] if has_state else M // 3
        best = best_in[b] if has_state else -1
        nit = nit_in[b] if has_state else table[nb, 0]
        done = done_in[b] if has_state else 0
        kb = -1
        if nb >= MIN_RANSAC_POINTS:
            for i in range(live_b):
                for r in range(3):
                    m = 3 * i + r
                    if fok[b, m]:
                        cnt = _count(F, m, x12, eff, b, N, t)
                        if cnt > max(best, MIN_GOOD):
                            best = cnt
                            kb = m
                            nit = table[nb, cnt + 1]
                done += 1
                if done >= nit:
                    break
        out_best[b] = best
        out_nit[b] = nit
        out_done[b] = done
        out_kb[b] = kb
        if kb >= 0:
            _mask(F, kb, x12, eff, b, N, t, out_mask)
        else:
            for j in range(N):
                out_mask[b, j] = False
