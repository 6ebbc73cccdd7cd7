"""OpenCV's 7-point fundamental-matrix solver (``run7Point``), batched, and the cubic it solves
(``cv::solveCubic``): the one solver of every driver (default, capturable, LO-RANSAC).

Convention:
    * ``m: (M, 7, 2, 2)`` float64 samples (sample point, image, x/y), pixels.
    * Models are row-major ``(M, 3, 9)`` (up to three per sample), unit Frobenius norm, with ``ok
      (M, 3)``; a model that is not ok holds garbage (not zero).
    * Model order = OpenCV's: which of two models with the same inlier count RANSAC keeps depends
      on it (OpenCV keeps the first). Hence OpenCV's own basis of the null space
      (``consts._opencv_null_seeds``) and ``cv::solveCubic``'s root order.

Factorisation-free (a fixed sequence of batched elementwise ops and small matmuls): no host sync
with ``full=True`` (the capturable path), no per-matrix loop on CUDA (as a batched QR or SVD has).
With ``full=False`` the CPU skips the cubic's rare branches when no lane needs them (a free host
check there); every returned ok root is the same bit for bit either way.
"""

from __future__ import annotations

import math

import torch

from .. import _tuning
from .consts import _Consts
from .result import _DBL_EPSILON, _MODEL_POINTS

_FLT_EPSILON = 1.1920928955078125e-07


def _collinear_last(m: torch.Tensor, k: _Consts) -> torch.Tensor:
    """OpenCV ``haveCollinearPoints`` for a full 7-point subset: is the last point on a line through
    two earlier ones (or too close to one)? ``m: (M, 7, 2, 2)`` -> ``(M, 2)`` bool (per image).

    Every pair ``j > k`` of the six difference vectors ``d`` to the last point: ``|d_k x d_j| <=
    FLT_EPSILON (|d_j|_1 + |d_k|_1)`` (OpenCV's expressions). The 15 pairs are gathered from one
    stacked ``(dx, dy, |d|_1)`` tensor (two index selects; broadcasting over the small pair and
    image dimensions is slower on the CPU)."""
    d = m[:, :-1] - m[:, -1:]  # (M, 6, 2, 2)
    dx, dy = d[..., 0], d[..., 1]  # (M, 6, 2)
    s = torch.stack([dx, dy, dx.abs() + dy.abs()], 1)  # (M, 3, 6, 2)
    d1 = s.index_select(2, k.pair_j)  # (M, 3, 15, 2)
    d2 = s.index_select(2, k.pair_k)
    cross = d2[:, 0] * d1[:, 1] - d2[:, 1] * d1[:, 0]
    tol = _FLT_EPSILON * (d1[:, 2] + d2[:, 2])
    return (cross.abs() <= tol).any(1)


def _solve_cubic_opencv(c: torch.Tensor, k: _Consts, *, full: bool = False):
    """Real roots of ``c[:,0] x^3 + c[:,1] x^2 + c[:,2] x + c[:,3]`` as ``cv::solveCubic`` finds them
    (its form in OpenCV 4.14: coefficients scaled by their largest magnitude, expanded
    discriminant): the same number, in the same order, by the same formulas (float64, batched, no
    gradients). ``c: (M, 4)`` -> ``roots (M, 3)``, ``ok (M, 3)`` bool, the real roots first; roots
    where not ok are garbage (not zero).

    Convention (``cv::solveCubic``; its branch decisions are taken on OpenCV's own arithmetic, the
    very operations in the same order, so for the same coefficients the number of roots is cv2's,
    also at a double root where it depends on rounding). With ``m = max |c_k|`` and ``eps`` the
    float64 epsilon:
        * ``|c0| >= eps m``: ``a_k = (c_k / m) / (c0 / m)``, ``Q = (a1^2 - 3 a2) / 9``,
          ``R = (2 a1^3 - 9 a1 a2 + 27 a3) / 54`` and ``d = Q^3 - R^2`` (expanded, as OpenCV).
          ``d > 0``: three roots ``-2 sqrt(Q) cos((theta + 2 pi k) / 3) - a1 / 3``, ``theta =
          acos(R / sqrt(Q^3))``, k = 0, 1, 2, i.e. the smallest, the largest, then the middle one.
          ``d == 0``: the simple root, then the double one (one root if they coincide).
          ``d < 0``: one root.
        * ``|c0| < eps m``: the quadratic's roots, the one from the larger ``|q|`` of ``q = (-c2 +-
          sqrt(disc)) / 2`` first (one root if ``disc == 0``, none if ``disc < 0``); ``|c1| < eps m``
          too: the linear root; ``|c2| < eps m`` too (or ``m < eps``): no root.
    No Newton polish (OpenCV's models come from these very formulas); where OpenCV's formulas give
    NaN (an ``acos`` argument past 1 by rounding) the root is not ok.

    ``full``: evaluate the rare branches (a double root, a negligible ``c0``) always; else the CPU
    skips them when no lane needs them (a free host check there; elsewhere it would be a host sync,
    so other devices evaluate them always). The ok roots are the same bits either way.
    """
    ac = c.abs()
    mc = ac.amax(-1)
    big = (ac >= (_DBL_EPSILON * mc)[:, None]) & (mc >= _DBL_EPSILON)[:, None]  # |c_k| >= eps m, m >= eps
    cubic = big[:, 0]
    # OpenCV's expressions, operation by operation (C++ evaluates left to right; its x86 builds do
    # not contract into fused multiply-adds), so the sign of d is OpenCV's bit for bit
    cs = c * mc.reciprocal()[:, None]  # x.reciprocal() == 1.0 / x: the same bits
    a1, a2, a3 = (cs[:, 1:] * cs[:, 0].reciprocal()[:, None]).unbind(-1)
    a11 = a1 * a1
    Q = (a11 - 3.0 * a2) * (1.0 / 9.0)
    a3_27 = 27.0 * a3
    R = (a1 * (2.0 * a1 * a1 - 9.0 * a2) + a3_27) * (1.0 / 54.0)
    two_a2 = 2.0 * a2
    d = (a11 * (a2 * a2 - 4.0 * a1 * a3) + two_a2 * (9.0 * a1 * a3 - two_a2 * a2) - a3_27 * a3) * (1.0 / 108.0)
    three = cubic & (d > 0)
    dbl = cubic & (d == 0)
    t2 = a1 * (1.0 / 3.0)
    # d > 0: trigonometric form
    theta = torch.acos(R / torch.sqrt(Q * Q * Q))
    x3 = (-2.0 * torch.sqrt(Q))[:, None] * torch.cos((theta * (1.0 / 3.0))[:, None] + k.phases) - t2[:, None]
    # d < 0: one root
    aR = R.abs()
    e = (torch.sqrt(-d) + aR).pow(1.0 / 3.0)
    e = torch.where(R > 0, -e, e)
    if not full and _tuning.for_device(c.device).host_checks_free and not bool((dbl | ~cubic).any()):
        roots = torch.where(three[:, None], x3, ((e + Q / e) - t2)[:, None])
        return roots, torch.stack([cubic, three, three], -1) & (roots.abs() < math.inf)
    # d == 0: the simple root -2 cbrt(R) - a1 / 3, then the double one
    cr = torch.sign(R) * aR.pow(1.0 / 3.0)  # std::cbrt(R) (torch has none), odd in R
    a13 = a1 / 3.0
    y0, y1 = -2.0 * cr - a13, cr - a13
    roots = torch.where(three[:, None], x3, torch.stack([torch.where(dbl, y0, (e + Q / e) - t2), y1, y1], -1))
    ok = torch.stack([cubic, three | (dbl & (y0 != y1)), three], -1)
    # negligible c0: the quadratic of the unscaled coefficients (as OpenCV), or the linear root
    c1, c2, c3 = c[:, 1], c[:, 2], c[:, 3]
    quad = big[:, 1] & ~cubic
    lin = big[:, 2] & ~(cubic | big[:, 1])
    qd = c2 * c2 - 4.0 * c1 * c3
    sqd = torch.sqrt(qd)
    q1 = (-c2 + sqd) * 0.5
    q2 = (c2 + sqd) * -0.5
    q = torch.where(q1.abs() > q2.abs(), q1, q2)
    qroots = torch.stack([torch.where(quad, q / c1, -c3 / c2), c3 / q, q], -1)
    qok = torch.stack([torch.where(quad, qd >= 0, lin), quad & (qd > 0), cubic], -1)
    roots = torch.where(cubic[:, None], roots, qroots)
    return roots, torch.where(cubic[:, None], ok, qok) & (roots.abs() < math.inf)


def _run_7point(m: torch.Tensor, k: _Consts, *, full: bool = False):
    """Batched OpenCV ``run7Point``: ``m (M, 7, 2, 2)`` float64 -> ``F (M, 3, 9)`` (row-major, unit
    Frobenius norm; garbage where not ok) and ``ok (M, 3)`` (a real root, a usable normalisation, a
    finite model, the sample not degenerate), in OpenCV's model order. ``full``: see
    :func:`_solve_cubic_opencv`.

    Like OpenCV: the collinearity check of the last sample point in either image
    (:func:`_collinear_last`), Hartley-style normalisation (centroid, mean distance sqrt(2)), the
    two-dimensional null space of the 7x9 system, the real roots of det(a*F1 + (1 - a)*F2) = 0,
    then de-normalisation. OpenCV's null-space basis (``f1 ~ P r7``, ``f2`` the unit vector of
    ``P r8`` orthogonal to ``f1``, P the projection onto the null space; any other basis gives the
    same models in another order) comes from modified Gram-Schmidt on the rows ``[A; r7; r8]`` (7
    fixed steps and one re-orthogonalisation; what is left of r7 and r8 is ``P r7`` and ``P r8``);
    the cubic's coefficients ``<cof F_p, F_q>`` of both basis models in one matmul. Both images
    are handled in one tensor (half the small ops).
    """
    M = m.shape[0]
    degenerate = _collinear_last(m, k).any(-1)
    c = m.mean(1, keepdim=True)  # (M, 1, 2, 2)
    dm = m - c
    s = dm.norm(dim=-1).mean(1)  # (M, 2)
    good = (s >= _FLT_EPSILON).all(-1)
    s = math.sqrt(2.0) / torch.where(good[:, None], s, k.one)
    nm = dm * s[:, None, :, None]
    h = torch.nn.functional.pad(nm, (0, 1), value=1.0)  # (M, 7, image, 3)
    # the rows of [x1 y1 1] F [x0 y0 1]^T = 0 in OpenCV's (row-major F) order: h2 (x) h1
    A = (h[:, :, 1, :, None] * h[:, :, 0, None, :]).flatten(-2)  # (M, 7, 9)
    R = torch.cat([A, k.null_rows.expand(M, 2, 9)], 1)  # (M, 9, 9)
    qs = []
    elementwise = _tuning.for_device(m.device).ransac_gs_elementwise
    for _ in range(_MODEL_POINTS):  # modified Gram-Schmidt: remove row 0 from the rows below it
        g = R @ R[:, :1].transpose(-1, -2)  # (M, rows, 1): <r_0, r_i>
        r0 = R[:, :1]
        qs.append(r0)
        # one product and one difference per entry either way, so the same bits (_tuning: the CPU
        # is faster elementwise, a device saves a launch with baddbmm)
        if elementwise:
            R = R[:, 1:] - (g[:, 1:] / g[:, :1]) * r0
        else:
            R = torch.baddbmm(R[:, 1:], g[:, 1:] / g[:, :1], r0, alpha=-1.0)
    # one more (classical) projection against the orthogonalised rows ("twice is enough"): the
    # residual |A P r| drops from ~eps cond(A) |A| |r| (1e-12 on tracker-like samples) to ~eps
    Qr = torch.cat(qs, 1)  # (M, 7, 9)
    R = torch.baddbmm(R, (R @ Qr.transpose(-1, -2)) / (Qr * Qr).sum(-1)[:, None], Qr, alpha=-1.0)
    # R = [P r7; P r8]: u ~ P r7, w the part of P r8 orthogonal to u, both unit
    G = R @ R.transpose(-1, -2)  # (M, 2, 2)
    w = torch.addcmul(R[:, 1], R[:, 0], (G[:, 1, 0] / G[:, 0, 0])[:, None], value=-1.0)
    uw = torch.stack([R[:, 0], w], 1)
    uw = uw / uw.norm(dim=-1, keepdim=True)
    Fab = k.basis @ uw  # (M, 2, 9): Fa = u - w = f1 - f2, Fb = w = f2; F(alpha) = alpha Fa + Fb
    F3 = Fab.view(M, 2, 3, 3)
    cof = torch.linalg.cross(F3.roll(-1, -2), F3.roll(-2, -2), dim=-1)  # rows r1 x r2, r2 x r0, r0 x r1
    # det(alpha Fa + Fb) = alpha^3 det Fa + alpha^2 <cof Fa, Fb> + alpha <cof Fb, Fa> + det Fb
    coeffs = (cof.view(M, 2, 9) @ Fab.transpose(-1, -2)).view(M, 4) * k.cubic_scale
    roots, rok = _solve_cubic_opencv(coeffs, k, full=full)  # (M, 3), OpenCV's order
    Fn = torch.addcmul(Fab[:, 1:], roots[..., None], Fab[:, :1])  # (M, 3, 9)
    # de-normalise: F = T2^T Fn T1, i.e. vec(F) = (T2^T (x) T1^T) vec(Fn), with T^T = [[s, 0, 0],
    # [0, s, 0], [-s cx, -s cy, 1]] per image
    top = s[..., None, None] * k.eye23  # (M, 2, 2, 3)
    bot = torch.nn.functional.pad(c[:, 0] * -s[..., None], (0, 1), value=1.0)  # (M, 2, 3)
    Tt = torch.cat([top, bot[:, :, None]], 2)  # (M, image, 3, 3)
    kron = (Tt[:, 1, :, None, :, None] * Tt[:, 0, None, :, None, :]).view(M, 9, 9)
    F = Fn @ kron.transpose(-1, -2)  # (M, 3, 9)
    nrm = F.norm(dim=-1)  # (M, 3)
    # nrm > 0 holds: alpha Fa + Fb = alpha u + (1 - alpha) w != 0 (u, w orthonormal)
    ok = rok & (good & ~degenerate)[:, None] & (nrm < math.inf)
    return F / nrm[..., None], ok
