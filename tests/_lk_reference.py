"""An independent converged LK root for the implicit-gradient tests (numpy + cv2, float64).

The level-0 LK equations of a point ``p`` in ``prev`` with window ``(ww, wh)`` are
``F(q) = sum_x g(x) (J(q + x) - I(o + x)) = 0`` with ``o = p - half`` (the template origin),
``g`` the Scharr derivatives of ``I`` (``cv2.Scharr``, BORDER_REFLECT_101) and bilinear
interpolation everywhere; the tracked position is ``q + half``. This module solves them to rounding
with Newton's method (true Jacobian) — written without the library's code, so that central
differences of this root are an independent reference for the library's implicit gradients.
Only for windows well inside the image (no border handling).
"""

from __future__ import annotations

import cv2
import numpy as np


def _bilinear(img, x0, y0, a, b, ww, wh):
    """Windows ``(m, wh, ww)`` of ``img`` at integer origins ``(x0, y0)`` with fractional ``(a, b)``
    and their derivatives along x and y."""
    ys = y0[:, None, None] + np.arange(wh)[None, :, None]
    xs = x0[:, None, None] + np.arange(ww)[None, None, :]
    f00, f01 = img[ys, xs], img[ys, xs + 1]
    f10, f11 = img[ys + 1, xs], img[ys + 1, xs + 1]
    a, b = a[:, None, None], b[:, None, None]
    v = (1 - b) * ((1 - a) * f00 + a * f01) + b * ((1 - a) * f10 + a * f11)
    dx = (1 - b) * (f01 - f00) + b * (f11 - f10)
    dy = (1 - a) * (f10 - f00) + a * (f11 - f01)
    return v, dx, dy


def converged_lk(I, J, pts, q_start, win, iters=30):
    """Root of the level-0 LK equations near ``q_start + half`` for each point.

    Args:
        I, J: ``(H, W)`` float64 images; pts: ``(m, 2)`` points in ``I``; q_start: ``(m, 2)``
            starting positions in ``J``; win: ``(ww, wh)``.

    Returns:
        ``(m, 2)`` converged positions in ``J`` and ``(m,)`` the last Newton step's size.
    """
    ww, wh = win
    half = np.array([(ww - 1) / 2, (wh - 1) / 2])
    Ix = cv2.Scharr(I, cv2.CV_64F, 1, 0, borderType=cv2.BORDER_REFLECT_101)
    Iy = cv2.Scharr(I, cv2.CV_64F, 0, 1, borderType=cv2.BORDER_REFLECT_101)
    o = pts - half
    io = np.floor(o).astype(np.int64)
    a, b = (o - io).T
    t, _, _ = _bilinear(I, io[:, 0], io[:, 1], a, b, ww, wh)
    gx, _, _ = _bilinear(Ix, io[:, 0], io[:, 1], a, b, ww, wh)
    gy, _, _ = _bilinear(Iy, io[:, 0], io[:, 1], a, b, ww, wh)
    q = q_start - half
    step = np.full(len(q), np.inf)
    for _ in range(iters):
        iq = np.floor(q).astype(np.int64)
        c, d = (q - iq).T
        v, dx, dy = _bilinear(J, iq[:, 0], iq[:, 1], c, d, ww, wh)
        e = v - t
        F = np.stack(((gx * e).sum((1, 2)), (gy * e).sum((1, 2))), 1)
        A = np.stack((np.stack(((gx * dx).sum((1, 2)), (gx * dy).sum((1, 2))), 1),
                      np.stack(((gy * dx).sum((1, 2)), (gy * dy).sum((1, 2))), 1)), 1)
        s = np.linalg.solve(A, F[..., None])[..., 0]
        q = q - s
        step = np.abs(s).max(1)
    return q + half, step
