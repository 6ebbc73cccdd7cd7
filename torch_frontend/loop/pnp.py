"""Batched PnP-RANSAC for loop verification (VINS ``PnPRANSAC`` in ``findConnection``, spec §7.6).

VINS checks a loop candidate by solving the pose of the **old** keyframe's camera from the current
keyframe's 3D points (raw VIO world) and the old keyframe's matched corners (normalized
coordinates), with ``cv2.solvePnPRansac(K = I, no distortion, useExtrinsicGuess = true,
iterationsCount = 100, reprojectionError = 10/460, confidence = 0.99, flags = ITERATIVE)``. This
module solves B such problems in one call:

* ``backend="torch"``: a batched RANSAC. Minimal solver: Lambda Twist P3P (Persson & Nordberg,
  ECCV 2018) on 3 points, the 4th point of the sample picks one of the up to 4 real solutions.
  Every hypothesis is scored on every point; rounds of samples (32, then 64, ...) are replayed with
  OpenCV's sequential bookkeeping (strictly-better rule, ``RANSACUpdateNumIters`` after every
  sample) so each problem stops where OpenCV's loop would; finished problems are masked. The best
  model is refined on its inliers by Levenberg-Marquardt on the reprojection error (unrolled,
  differentiable w.r.t. ``points_3d`` and ``points_norm``), and the inliers are recomputed with the
  refined pose.
* ``backend="opencv"``: a loop of ``cv2.solvePnPRansac`` calls exactly as VINS makes them (the
  oracle and a fallback).

Convention:
    * ``points_3d: (B, N, 3)`` float, world points (VINS: the current keyframe's ``point_3d``, raw
      VIO world, metres). ``points_norm: (B, N, 2)`` float, normalized image coordinates ``(x/z,
      y/z)`` of the matched points in the camera being solved (camera matrix = identity, no
      distortion). ``valid: (B, N)`` bool, which slots hold a correspondence (masked-out slots may
      hold anything, NaN included).
    * Pose ``R: (B, 3, 3)``, ``t: (B, 3)`` map world points into the camera: ``x_cam = R X + t``
      (OpenCV's ``rvec``/``tvec``: ``R = Rodrigues(rvec)``, ``t = tvec``).
    * ``threshold`` is the inlier bound on the **Euclidean** reprojection error in normalized units
      (VINS: 10 px / 460 px focal = 10/460). OpenCV >= 3.2 (4.x included) compares
      ``|proj - p| <= reprojectionError`` (it squares both sides); OpenCV 3.0/3.1 squared the
      threshold by mistake (opencv/opencv#7827), which is why VINS passes ``sqrt(10/460)`` there.
      Here, additionally, points at or behind the camera (``z <= 0``) are outliers (OpenCV's
      ``projectPoints`` does not check).
"""

from __future__ import annotations

import math
from typing import NamedTuple, Optional, Tuple

import torch

from .._checks import check_shape, valid_first_order
from ..errors import DataError
from ..geometry import R_to_quat, quat_to_R, rodrigues
from ..polynomial import solve_cubic
from ..ransac import ransac_update_num_iters

__all__ = ["PnPResult", "p3p", "pnp_ransac", "refine_pnp"]

_SAMPLE = 4  # P3P on 3 points + 1 point to pick among its up to 4 solutions
_MIN_INLIERS = _SAMPLE + 1  # a model must explain at least one point beyond its own sample
_FIRST_ROUND = 32  # 30 % outliers: the bound is 17 (all 70 inliers found) to ~35 samples; mostly one round


class PnPResult(NamedTuple):
    """Result of :func:`pnp_ransac`.

    Attributes:
        R: ``(B, 3, 3)`` world-to-camera rotation (``x_cam = R X + t``), dtype of ``points_3d``.
        t: ``(B, 3)`` world-to-camera translation.
        inliers: ``(B, N)`` bool, never True on a masked-out slot; all False where ``ok`` is False.
        ok: ``(B,)`` bool, a model was found (``cv2.solvePnPRansac`` returned True).
    """

    R: torch.Tensor
    t: torch.Tensor
    inliers: torch.Tensor
    ok: torch.Tensor


# ----------------------------------------------------------------------------------------------
# component-wise 3-vector algebra: vectors are tuples of 3 tensors (one per coordinate), so every
# operation is one elementwise kernel over the whole batch (torch's reductions/stacks over a
# trailing dimension of size 3 cost far more than the arithmetic on CPU)
# ----------------------------------------------------------------------------------------------
def _v(t: torch.Tensor):
    return tuple(t.unbind(-1))


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _sub(a, b):
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def _scale(a, s):
    return (a[0] * s, a[1] * s, a[2] * s)


def _where(c, a, b):
    return tuple(torch.where(c, x, y) for x, y in zip(a, b))


def _safe(x: torch.Tensor, ok: torch.Tensor, fill: float = 1.0) -> torch.Tensor:
    """``x`` where ``ok`` else ``fill``: keep lanes that are masked out anyway finite (``torch.where``
    evaluates and differentiates both branches; a NaN or inf there poisons everything downstream)."""
    return torch.where(ok, x, torch.full_like(x, fill))


def _unit(a):
    n = torch.sqrt(_dot(a, a))
    ok = n > 1e-300
    return _scale(a, 1.0 / _safe(n, ok)), ok


def _sym_rows(m):
    """Rows of the symmetric matrix ``(m00, m01, m02, m11, m12, m22)``."""
    m00, m01, m02, m11, m12, m22 = m
    return (m00, m01, m02), (m01, m11, m12), (m02, m12, m22)


def _sym_mv(m, v):
    return tuple(_dot(r, v) for r in _sym_rows(m))


def _null_of_rows(rows):
    """Unit null vector of a rank-2 3x3 matrix: the longest cross product of two of its rows (the
    best-conditioned of the three), and its squared length (0: rank < 2)."""
    r0, r1, r2 = rows
    c = [_cross(r0, r1), _cross(r0, r2), _cross(r1, r2)]
    n = [_dot(x, x) for x in c]
    best, nb = c[0], n[0]
    for x, nx in zip(c[1:], n[1:]):
        take = nx > nb
        best, nb = _where(take, x, best), torch.where(take, nx, nb)
    e, _ = _unit(best)
    return e, nb


# ----------------------------------------------------------------------------------------------
# P3P (Lambda Twist)
# ----------------------------------------------------------------------------------------------
def p3p(points_3d: torch.Tensor, bearings: torch.Tensor):
    """All real P3P solutions for 3 world points and their bearing vectors (Lambda Twist).

    Args:
        points_3d: ``(..., 3, 3)`` float, three world points (rows).
        bearings: ``(..., 3, 3)`` float, the three viewing rays in the camera (rows; any positive
            scale, e.g. ``(x, y, 1)`` from normalized coordinates).

    Returns:
        ``R (..., 4, 3, 3)``, ``t (..., 4, 3)`` world-to-camera poses (``x_cam = R X + t``) and
        ``ok (..., 4)`` bool: which of the 4 slots hold a real solution with all three points in
        front of the camera. Slots that are not ok hold the identity / zero (finite).

    Convention:
        Persson & Nordberg, "Lambda Twist: An Accurate Fast Robust Perspective Three Point (P3P)
        Solver", ECCV 2018: the depths ``Λ = (λ1, λ2, λ3)`` satisfy
        ``|λi yi - λj yj|^2 = |Xi - Xj|^2``; two homogeneous combinations D1, D2 of these
        quadrics span a pencil whose degenerate member ``D0 = D1 + γ D2`` (a real root of a cubic)
        is a pair of planes through the origin of Λ-space; each plane meets the pencil in two rays,
        scaled by the distance equations -> up to 4 solutions, polished by Gauss-Newton on the
        three equations; the pose follows from the three camera points in closed form.
        Computed in float64 (returned in the input dtype); not differentiable (discrete choices).
        Degenerate input (collinear or coincident points, coincident rays, NaN) gives ok = False.
    """
    check_shape(points_3d, ("*", 3, 3), "points_3d")
    check_shape(bearings, tuple(points_3d.shape), "bearings")
    X = points_3d.detach().double()
    y = bearings.detach().double()
    R, t, ok = _p3p_impl(*(_v(X[..., i, :]) for i in range(3)), *(_v(y[..., i, :]) for i in range(3)))
    R = torch.stack([torch.stack(row, -1) for row in R], -2)
    t = torch.stack(t, -1)
    return R.to(points_3d.dtype), t.to(points_3d.dtype), ok


def _p3p_impl(X1, X2, X3, v1, v2, v3):
    """float64 Lambda Twist on component tuples (each component ``(L,)``-shaped, any shape).

    Returns ``R`` (3 rows of 3 components), ``t`` (3 components) and ``ok``, each ``(L, 4)``.
    """
    comps = X1 + X2 + X3 + v1 + v2 + v3
    fin = torch.stack([torch.isfinite(c) for c in comps], 0).all(0)
    zero = torch.zeros_like(comps[0])
    one = torch.ones_like(zero)
    # non-finite lanes: a harmless stand-in problem (masked out below)
    X1, X2, X3, v1, v2, v3 = (_where(fin, a, b) for a, b in zip(
        (X1, X2, X3, v1, v2, v3),
        ((one, zero, zero), (zero, one, zero), (zero, zero, one), (one, zero, one), (zero, one, one), (zero, zero, one))))
    y1, ok1 = _unit(v1)
    y2, ok2 = _unit(v2)
    y3, ok3 = _unit(v3)
    d12, d13, d23 = _sub(X1, X2), _sub(X1, X3), _sub(X2, X3)
    a12, a13, a23 = _dot(d12, d12), _dot(d13, d13), _dot(d23, d23)
    cr = _cross(d12, d13)
    cr2 = _dot(cr, cr)
    g12, g13, g23 = _dot(y1, y2), _dot(y1, y3), _dot(y2, y3)
    # non-collinear world triangle (relative test) and distinct rays
    good = (fin & ok1 & ok2 & ok3 & (cr2 > 1e-20 * a12 * a13)
            & (g12 < 1.0 - 1e-14) & (g13 < 1.0 - 1e-14) & (g23 < 1.0 - 1e-14))
    # world scale normalised to ~1: the algebra below mixes squared distances and cosines
    sc = _safe((a12 + a13 + a23) / 3.0, good)
    a12, a13, a23 = a12 / sc, a13 / sc, a23 / sc
    b12, b13, b23 = -2.0 * g12, -2.0 * g13, -2.0 * g23

    # Λᵀ M_ij Λ = a_ij; the pencil D1 = a23 M12 - a12 M23, D2 = a23 M13 - a13 M23 (symmetric,
    # stored as (m00, m01, m02, m11, m12, m22))
    D1 = (a23, a23 * b12 / 2, zero, a23 - a12, -a12 * b23 / 2, -a12)
    D2 = (a23, zero, a23 * b13 / 2, -a13, -a13 * b23 / 2, a23 - a13)
    A0, A1, A2 = _sym_rows(D1)  # symmetric: rows = columns
    B0, B1, B2 = _sym_rows(D2)

    def det(c0, c1, c2):
        return _dot(c0, _cross(c1, c2))

    # det(D1 + g D2) = c3 g^3 + c2 g^2 + c1 g + c0 (multilinearity in the columns)
    c3 = det(B0, B1, B2)
    c2 = det(A0, B1, B2) + det(B0, A1, B2) + det(B0, B1, A2)
    c1 = det(B0, A1, A2) + det(A0, B1, A2) + det(A0, A1, B2)
    c0 = det(A0, A1, A2)
    # a root at infinity (c3 ~ 0) means D2 itself is degenerate: solve the reversed cubic
    # det(D2 + g' D1) then, so the root used is always finite
    rev = c0.abs() > c3.abs()
    coeffs = torch.where(rev[..., None], torch.stack([c0, c1, c2, c3], -1), torch.stack([c3, c2, c1, c0], -1))
    roots, r_ok = solve_cubic(coeffs)  # (L, 3)
    Dp = tuple(torch.where(rev, q, p) for p, q in zip(D1, D2))  # D0 = Dp + g Dq
    Dq = tuple(torch.where(rev, p, q) for p, q in zip(D1, D2))
    D0 = tuple(p[..., None] + roots * q[..., None] for p, q in zip(Dp, Dq))  # 6 x (L, 3 roots)

    # closed-form eigen-structure of the rank-2 symmetric D0: sigma1, sigma2 (|sigma1| >= |sigma2|), 0
    m00, m01, m02, m11, m12, m22 = D0
    tr = m00 + m11 + m22
    m2 = m00 * m11 - m01 * m01 + m00 * m22 - m02 * m02 + m11 * m22 - m12 * m12
    disc = torch.sqrt((tr * tr - 4.0 * m2).clamp_min(0.0))
    sa, sb = (tr + disc) / 2.0, (tr - disc) / 2.0
    big_a = sa.abs() >= sb.abs()
    s1 = torch.where(big_a, sa, sb)
    s2 = torch.where(big_a, sb, sa)
    # D0 must be an indefinite pair of real planes (sigma1 sigma2 < 0); then the two planes are
    # e1 . Λ = +-s e2 . Λ with s = sqrt(-sigma2 / sigma1) in (0, 1]; prefer the root with the
    # widest plane pair (s near 0: nearly coincident planes, ill-conditioned)
    indef = r_ok & (m2 < 0) & (s1 != 0)
    s_ratio = torch.where(indef, (-s2 / _safe(s1, indef)).clamp(0.0, 1.0), torch.full_like(s1, -1.0))
    k = s_ratio.argmax(-1, keepdim=True)

    def pick(x):
        return x.gather(-1, k).squeeze(-1)

    good = good & pick(indef)
    D0k = tuple(pick(x) for x in D0)
    s1k = pick(s1)
    s = torch.sqrt(pick(s_ratio).clamp_min(0.0))
    e3, n3 = _null_of_rows(_sym_rows(D0k))
    shifted = (D0k[0] - s1k, D0k[1], D0k[2], D0k[3] - s1k, D0k[4], D0k[5] - s1k)
    e1, n1 = _null_of_rows(_sym_rows(shifted))
    e2, n2_ok = _unit(_cross(e3, e1))
    good = good & (n3 > 0) & (n1 > 0) & n2_ok

    # each plane contains e3 and m = s e1 +- e2; on it Λ = α e3 + β m, and the other pencil member
    # Dq restricted to the plane is a 2x2 quadratic form whose two null directions are the
    # solutions (closed-form 2x2 eigen-decomposition: no division by a pivot). Lanes: (L, 2 planes)
    sg = torch.tensor([1.0, -1.0], dtype=zero.dtype, device=zero.device)
    m = tuple(s[..., None] * a[..., None] + sg * b[..., None] for a, b in zip(e1, e2))
    e3p = tuple(c[..., None] for c in e3)
    Dq2 = tuple(c[..., None] for c in Dq)
    Dqe3 = _sym_mv(Dq2, e3p)
    qA = _dot(e3p, Dqe3)
    qB = _dot(m, Dqe3)
    qC = _dot(m, _sym_mv(Dq2, m))
    half = torch.sqrt(((qA - qC) / 2.0) ** 2 + qB * qB)
    mu1, mu2 = (qA + qC) / 2.0 + half, (qA + qC) / 2.0 - half
    th = 0.5 * torch.atan2(2.0 * qB, qA - qC)
    cth, sth = torch.cos(th), torch.sin(th)
    plane_ok = (mu1 > 0) & (mu2 < 0)
    ra, rb = torch.sqrt((-mu2).clamp_min(0.0)), torch.sqrt(mu1.clamp_min(0.0))
    # null directions w = ra v1 +- rb v2, v1 = (c, s), v2 = (-s, c); lanes (L, 2 planes, 2 signs)
    wa = ra[..., None] * cth[..., None] - sg * (rb * sth)[..., None]
    wb = ra[..., None] * sth[..., None] + sg * (rb * cth)[..., None]
    d = tuple((wa * a[..., None, None] + wb * b[..., None]).flatten(-2) for a, b in zip(e3, m))  # (L, 4)
    sol_ok = good[..., None] & plane_ok.repeat_interleave(2, -1)
    # scale from the sum of the three distance equations: Λᵀ (3I - Gram(y)) Λ = a12 + a13 + a23
    # (positive definite unless the rays coincide)
    g12e, g13e, g23e, asum = g12[..., None], g13[..., None], g23[..., None], (a12 + a13 + a23)[..., None]
    dSd = 2.0 * (_dot(d, d) - g12e * d[0] * d[1] - g13e * d[0] * d[2] - g23e * d[1] * d[2])
    sol_ok = sol_ok & (dSd > 1e-300)
    kk = torch.sqrt(asum / _safe(dSd, sol_ok))
    kk = torch.where(d[0] + d[1] + d[2] < 0, -kk, kk)
    lam = tuple(torch.where(sol_ok, c * kk, torch.ones_like(c)) for c in d)

    # Gauss-Newton on the three distance equations (the paper's polish), kept only where it helps
    b12e, b13e, b23e = b12[..., None], b13[..., None], b23[..., None]
    a12e, a13e, a23e = a12[..., None], a13[..., None], a23[..., None]

    def resid(L):
        l1, l2, l3 = L
        return (l1 * l1 + l2 * l2 + b12e * l1 * l2 - a12e, l1 * l1 + l3 * l3 + b13e * l1 * l3 - a13e,
                l2 * l2 + l3 * l3 + b23e * l2 * l3 - a23e)

    f = resid(lam)
    for _ in range(2):  # the closed form is already accurate; two steps reach rounding level
        l1, l2, l3 = lam
        z = torch.zeros_like(l1)
        r0 = (2 * l1 + b12e * l2, 2 * l2 + b12e * l1, z)
        r1 = (2 * l1 + b13e * l3, z, 2 * l3 + b13e * l1)
        r2 = (z, 2 * l2 + b23e * l3, 2 * l3 + b23e * l2)
        dj = _dot(r0, _cross(r1, r2))
        dj_ok = dj.abs() > 1e-14
        inv = 1.0 / _safe(dj, dj_ok)
        # J^-1 f = (f0 (r1 x r2) + f1 (r2 x r0) + f2 (r0 x r1)) / det J
        c12, c20, c01 = _cross(r1, r2), _cross(r2, r0), _cross(r0, r1)
        step = tuple((f[0] * c12[i] + f[1] * c20[i] + f[2] * c01[i]) * inv for i in range(3))
        new = _sub(lam, step)
        fn = resid(new)
        better = dj_ok & torch.isfinite(_dot(fn, fn)) & (_dot(fn, fn) < _dot(f, f))
        lam = _where(better, new, lam)
        f = _where(better, fn, f)
    sol_ok = (sol_ok & (lam[0] > 0) & (lam[1] > 0) & (lam[2] > 0) & (f[0].abs() <= 1e-6 * a12e)
              & (f[1].abs() <= 1e-6 * a13e) & (f[2].abs() <= 1e-6 * a23e))

    # pose from the three camera points: R maps the world triangle frame (d12, d13, d12 x d13)
    # onto the camera one (exact when the distances match; Gauss-Newton above makes them match)
    rs = torch.sqrt(sc)[..., None]
    Y1, Y2, Y3 = (_scale(tuple(c[..., None] for c in y), lc * rs) for y, lc in zip((y1, y2, y3), lam))
    Yd12, Yd13 = _sub(Y1, Y2), _sub(Y1, Y3)
    Yc = _cross(Yd12, Yd13)
    # rows of the inverse of [d12 | d13 | cr]: (d13 x cr, cr x d12, d12 x d13) / |cr|^2
    icr = 1.0 / _safe(cr2, good)
    xr = [tuple((c * icr)[..., None] for c in r) for r in (_cross(d13, cr), _cross(cr, d12), cr)]
    R = tuple(tuple(Yd12[i] * xr[0][j] + Yd13[i] * xr[1][j] + Yc[i] * xr[2][j] for j in range(3)) for i in range(3))
    Xm = tuple(((a + b + c) / 3.0)[..., None] for a, b, c in zip(X1, X2, X3))
    Ym = tuple((a + b + c) / 3.0 for a, b, c in zip(Y1, Y2, Y3))
    t = tuple(Ym[i] - _dot(R[i], Xm) for i in range(3))
    fin_out = torch.stack([torch.isfinite(c) for c in sum(R, ()) + t], 0).all(0)
    sol_ok = sol_ok & fin_out
    eye = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    R = tuple(tuple(torch.where(sol_ok, R[i][j], torch.full_like(R[i][j], eye[i][j])) for j in range(3))
              for i in range(3))
    t = tuple(torch.where(sol_ok, c, torch.zeros_like(c)) for c in t)
    return R, t, sol_ok


# ----------------------------------------------------------------------------------------------
# Levenberg-Marquardt refinement (differentiable)
# ----------------------------------------------------------------------------------------------
def _residual(X, p, w, R, t):
    """Camera points, residuals ``proj(R X + t) - p`` ``(B, N, 2)`` and the weighted cost ``(B,)``
    (inf where a weighted point is not in front of the camera). Depths are replaced away from 0 so
    lanes behind the camera stay finite (their weight or the inf cost decides)."""
    Xc = (X @ R.transpose(-1, -2)) + t[:, None, :]
    z = Xc[..., 2]
    front = z > 1e-9
    zs = torch.where(front, z, torch.ones_like(z))
    r = Xc[..., :2] / zs[..., None] - p
    c = (w * (r * r).sum(-1)).sum(-1)
    behind = ((w > 0) & ~front).any(-1)
    return Xc, zs, r, torch.where(behind, torch.full_like(c, float("inf")), c)


def refine_pnp(points_3d: torch.Tensor, points_norm: torch.Tensor, weights: torch.Tensor,
               R: torch.Tensor, t: torch.Tensor, iterations: int = 10):
    """Levenberg-Marquardt on the weighted reprojection error, unrolled (differentiable).

    Args:
        points_3d: ``(B, N, 3)`` float, world points.
        points_norm: ``(B, N, 2)`` float (same dtype), normalized image coordinates.
        weights: ``(B, N)`` bool or float >= 0 (e.g. the inlier mask; 0 = ignored, and such slots
            may hold NaN).
        R, t: ``(B, 3, 3)``, ``(B, 3)`` the starting pose, world to camera (``x_cam = R X + t``).
        iterations: LM iterations (a fixed count; a converged problem just stops moving).

    Returns:
        ``R (B, 3, 3)``, ``t (B, 3)``, the refined pose in the dtype of ``points_3d``.

    Convention:
        Cost ``sum_i w_i |proj(R X_i + t) - p_i|^2`` (normalized units). Update in the camera
        frame: ``R <- exp(ω) R``, ``t <- exp(ω) t + δt``, from ``(H + μ diag(H)) δ = -g`` with the
        Gauss-Newton ``H = Σ w JᵀJ``, ``g = Σ w Jᵀ r``. A step is kept when it does not raise the
        cost (ties are kept, so near convergence the accept decisions do not flip under tiny input
        changes); μ starts at 1e-3, /10 after a kept step, x10 otherwise, and carries no gradient.
        Gradients flow through every kept step to ``points_3d``, ``points_norm``, ``weights``,
        ``R`` and ``t`` (``torch.autograd.gradcheck`` in float64, tests/test_loop_pnp.py). A step
        that puts a weighted point at or behind the camera is rejected.
    """
    B, N = _check_points(points_3d, points_norm)
    check_shape(weights, (B, N), "weights")
    check_shape(R, (B, 3, 3), "R")
    check_shape(t, (B, 3), "t")
    dt = points_3d.dtype
    if int(iterations) < 0:
        raise ValueError(f"iterations: expected >= 0, got {iterations}")
    return _refine_impl(points_3d, points_norm, weights.to(dt), R.to(dt), t.to(dt), int(iterations))


def _refine_impl(X, p, w, R, t, iterations: int):
    # weight-0 slots may hold NaN/inf: replace them so 0 * NaN never enters a sum
    keep = w > 0
    X = torch.where(keep[..., None], X, torch.tensor([0.0, 0.0, 1.0], dtype=X.dtype, device=X.device))
    p = torch.where(keep[..., None], p, torch.zeros_like(p))
    B, N = w.shape
    mu = torch.full((B,), 1e-3, dtype=X.dtype, device=X.device)
    tiny = math.sqrt(torch.finfo(X.dtype).tiny)  # a damping floor that survives float32
    Xc, zs, r, cost = _residual(X, p, w, R, t)
    for _ in range(iterations):
        # Jacobian of (u, v) = proj(Xc) for Xc <- exp(ω) Xc + δt: the classic
        # [[-uv, 1+u², -v, 1/z, 0, -u/z], [-(1+v²), uv, u, 0, 1/z, -v/z]]
        iz = 1.0 / zs
        u, v = Xc[..., 0] * iz, Xc[..., 1] * iz
        zero = torch.zeros_like(u)
        J = torch.stack([-u * v, 1 + u * u, -v, iz, zero, -u * iz,
                         -(1 + v * v), u * v, u, zero, iz, -v * iz], -1).reshape(B, 2 * N, 6)
        Jw = J * w.repeat_interleave(2, -1)[..., None]
        JwT = Jw.transpose(1, 2)
        H = JwT @ J
        g = (JwT @ r.reshape(B, 2 * N, 1)).squeeze(-1)
        dH = torch.diagonal(H, dim1=-2, dim2=-1)
        # Marquardt scaling; the floor keeps the system invertible when a direction is unobserved
        # (e.g. a problem without weights: H = 0, the step is then 0)
        damp = mu[:, None] * dH + dH.amax(-1, keepdim=True) * 1e-12 + tiny
        delta = -torch.linalg.solve(H + torch.diag_embed(damp), g[..., None]).squeeze(-1)
        dR = rodrigues(delta[:, :3])
        R_new = dR @ R
        t_new = (dR @ t[..., None]).squeeze(-1) + delta[:, 3:]
        Xc_n, zs_n, r_n, cost_n = _residual(X, p, w, R_new, t_new)
        acc = torch.isfinite(cost_n) & (cost_n <= cost * (1.0 + 1e-10) + 1e-300)
        R = torch.where(acc[:, None, None], R_new, R)
        t = torch.where(acc[:, None], t_new, t)
        Xc = torch.where(acc[:, None, None], Xc_n, Xc)
        zs = torch.where(acc[:, None], zs_n, zs)
        r = torch.where(acc[:, None, None], r_n, r)
        cost = torch.where(acc, cost_n, cost)
        mu = torch.where(acc, (mu * 0.1).clamp_min(1e-10), (mu * 10.0).clamp_max(1e10)).detach()
    return R, t


# ----------------------------------------------------------------------------------------------
# RANSAC
# ----------------------------------------------------------------------------------------------
def _score(X, p, valid, R, t, thr2):
    """Inlier masks of hypotheses ``R (B, S, 3, 3), t (B, S, 3)`` on all points: ``(B, S, N)``.
    Tested without a division: ``|xy - p z|^2 <= thr^2 z^2`` with ``z > 0``."""
    B, S = R.shape[:2]
    Xc = (R.reshape(B, S * 3, 3) @ X.transpose(1, 2)).reshape(B, S, 3, -1) + t[..., None]
    x, y, z = Xc.unbind(-2)
    u, v = p[:, None, :, 0], p[:, None, :, 1]
    dx, dy = x - u * z, y - v * z
    return (dx * dx + dy * dy <= thr2 * z * z) & (z > 0) & valid[:, None, :]


def _hypotheses(X, p, valid, idx):
    """P3P on the first 3 points of each sample ``idx (B, S, 4)``, the 4th picks the solution with
    the smallest reprojection error. Returns ``R (B, S, 3, 3), t (B, S, 3), ok (B, S)``."""
    B, S, _ = idx.shape
    gi = idx.reshape(B, S * _SAMPLE)
    Xs = torch.gather(X, 1, gi[..., None].expand(B, S * _SAMPLE, 3)).reshape(B, S, _SAMPLE, 3)
    ps = torch.gather(p, 1, gi[..., None].expand(B, S * _SAMPLE, 2)).reshape(B, S, _SAMPLE, 2)
    vs = torch.gather(valid, 1, gi).reshape(B, S, _SAMPLE).all(-1)
    pts = [_v(Xs[:, :, i]) for i in range(_SAMPLE)]
    one = torch.ones_like(ps[..., 0, 0])
    rays = [(ps[:, :, i, 0], ps[:, :, i, 1], one) for i in range(3)]
    R, t, ok = _p3p_impl(*pts[:3], *rays)  # components (B, S, 4)
    X4 = tuple(c[..., None] for c in pts[3])
    c4 = tuple(_dot(R[i], X4) + t[i] for i in range(3))
    front = c4[2] > 0
    iz = 1.0 / torch.where(front, c4[2], torch.ones_like(c4[2]))
    err = (c4[0] * iz - ps[:, :, 3, 0, None]) ** 2 + (c4[1] * iz - ps[:, :, 3, 1, None]) ** 2
    err = torch.where(ok & front & torch.isfinite(err), err, torch.full_like(err, float("inf")))
    best = err.argmin(-1, keepdim=True)
    Rm = torch.stack([c for row in R for c in row], -1)  # (B, S, 4, 9)
    hR = Rm.gather(2, best[..., None].expand(B, S, 1, 9)).reshape(B, S, 3, 3)
    ht = torch.stack(t, -1).gather(2, best[..., None].expand(B, S, 1, 3)).squeeze(2)
    hok = vs & torch.isfinite(err.gather(2, best).squeeze(2))
    return hR, ht, hok


def _sample(n: torch.Tensor, order: torch.Tensor, S: int, gen: torch.Generator) -> torch.Tensor:
    """``S`` uniform random 4-subsets of each problem's ``n_b`` valid slots: ``(B, S, 4)`` slot
    indices, in random order. Draw k picks a rank in ``[0, n - k)`` and skips the ranks already
    taken (ascending), which yields distinct ranks without rejection; ``order`` (valid slots first,
    :func:`valid_first_order`) maps ranks to slots."""
    B, N = order.shape
    u = torch.rand((B, S, _SAMPLE), generator=gen, device=gen.device, dtype=torch.float64).to(order.device)
    nn = n[:, None]
    chosen = []
    for k in range(_SAMPLE):
        r = torch.minimum((u[..., k] * (nn - k).to(torch.float64)).to(torch.int64), nn - k - 1).clamp_min(0)
        if chosen:
            prev = torch.sort(torch.stack(chosen, -1), -1).values
            for j in range(k):
                r = r + (r >= prev[..., j]).to(r.dtype)
        chosen.append(r)
    ranks = torch.stack(chosen, -1).clamp_max(N - 1)  # the clamp only matters for n < 4 (never run)
    return torch.gather(order, 1, ranks.reshape(B, S * _SAMPLE)).reshape(B, S, _SAMPLE)


def _ransac(X, p, valid, thr: float, iterations: int, confidence: float, gen: torch.Generator):
    """Batched RANSAC in float64 on sanitised inputs. Returns best ``R, t``, ``count (B,)`` int64
    and the best model's inlier mask ``(B, N)``."""
    B, N = valid.shape
    dev, dt = X.device, X.dtype
    thr2 = thr * thr
    n = valid.sum(-1)
    order = valid_first_order(valid)

    def bound_of(best, n_):  # (b, S) -> (b, S): OpenCV's RANSACUpdateNumIters once a model exists
        mi = torch.full_like(best, iterations)
        nf = n_.to(torch.float64).clamp_min(1.0)[:, None]
        it = ransac_update_num_iters(confidence, (nf - best.to(torch.float64)) / nf, _SAMPLE, mi)
        return torch.where(best >= _MIN_INLIERS, it, mi)

    best_n = torch.zeros(B, dtype=torch.int64, device=dev)
    best_R = torch.eye(3, dtype=dt, device=dev).expand(B, 3, 3).clone()
    best_t = torch.zeros(B, 3, dtype=dt, device=dev)
    best_mask = torch.zeros(B, N, dtype=torch.bool, device=dev)
    bound = torch.where(n >= _SAMPLE, torch.full_like(n, iterations), torch.zeros_like(n))  # < 4 points: none
    start, size = 0, _FIRST_ROUND
    while start < iterations:
        active = bound > start
        n_act = int(active.sum())  # one host sync per round: loop control and row compaction
        if n_act == 0:
            break
        # later rounds run only the problems still below their bound
        rows = None if n_act == B else active.nonzero().squeeze(1)

        def sub(x, rows=rows):
            return x if rows is None else x.index_select(0, rows)

        Xa, pa, va, na, bn, bd = sub(X), sub(p), sub(valid), sub(n), sub(best_n), sub(bound)
        Ba = Xa.shape[0]
        S = min(size, iterations - start)
        idx = _sample(na, sub(order), S, gen)
        hR, ht, hok = _hypotheses(Xa, pa, va, idx)
        inl = _score(Xa, pa, va, hR, ht, thr2) & hok[..., None]
        cnt = inl.sum(-1)
        acc = torch.where(cnt >= _MIN_INLIERS, cnt, torch.zeros_like(cnt))
        # replay OpenCV's sequential loop over the round: sample i runs iff its index is below the
        # bound computed from the best count of the samples before it
        run_best = torch.maximum(acc.cummax(1).values, bn[:, None])
        before = torch.cat([bn[:, None], run_best[:, :-1]], 1)
        lim = torch.minimum(bound_of(before, na), bd[:, None])
        pos = torch.arange(start, start + S, device=dev)
        ran = (pos[None, :] < lim).to(torch.int8).cummin(1).values.bool()
        score = torch.where(ran, acc, torch.full_like(acc, -1))
        top, arg = score.max(1)  # the first maximum: OpenCV keeps the first of equal counts
        better = top > bn
        ar = torch.arange(Ba, device=dev)
        new_n = torch.where(better, top, bn)
        new_R = torch.where(better[:, None, None], hR[ar, arg], sub(best_R))
        new_t = torch.where(better[:, None], ht[ar, arg], sub(best_t))
        new_mask = torch.where(better[:, None], inl[ar, arg], sub(best_mask))
        new_bound = torch.minimum(bd, bound_of(new_n[:, None], na)[:, 0])
        if rows is None:
            best_n, best_R, best_t, best_mask, bound = new_n, new_R, new_t, new_mask, new_bound
        else:
            best_n = best_n.index_copy(0, rows, new_n)
            best_R = best_R.index_copy(0, rows, new_R)
            best_t = best_t.index_copy(0, rows, new_t)
            best_mask = best_mask.index_copy(0, rows, new_mask)
            bound = bound.index_copy(0, rows, new_bound)
        start += S
        size *= 2
    return best_R, best_t, best_n, best_mask


# ----------------------------------------------------------------------------------------------
# public entry point
# ----------------------------------------------------------------------------------------------
def _check_points(points_3d, points_norm) -> Tuple[int, int]:
    check_shape(points_3d, ("B", "N", 3), "points_3d")
    check_shape(points_norm, (points_3d.shape[0], points_3d.shape[1], 2), "points_norm")
    for name, x in (("points_3d", points_3d), ("points_norm", points_norm)):
        if not x.is_floating_point():
            raise TypeError(f"{name}: expected a floating point tensor, got {x.dtype}")
    if points_norm.dtype != points_3d.dtype:
        raise TypeError(f"points_norm: expected dtype {points_3d.dtype} (as points_3d), got {points_norm.dtype}")
    return points_3d.shape[0], points_3d.shape[1]


def pnp_ransac(
    points_3d: torch.Tensor,
    points_norm: torch.Tensor,
    valid: Optional[torch.Tensor] = None,
    init_R: Optional[torch.Tensor] = None,
    init_t: Optional[torch.Tensor] = None,
    threshold: float = 10.0 / 460.0,
    iterations: int = 100,
    confidence: float = 0.99,
    generator: Optional[torch.Generator] = None,
    backend: str = "torch",
    refine_iters: int = 5,
) -> PnPResult:
    """Robust camera poses of B 3D-2D correspondence sets at once (``cv2.solvePnPRansac``, batched).

    Args:
        points_3d: ``(B, N, 3)`` float, world points.
        points_norm: ``(B, N, 2)`` float (same dtype), normalized image coordinates.
        valid: ``(B, N)`` bool, default all True. Valid points must be finite (else ``DataError``).
        init_R, init_t: ``(B, 3, 3)``, ``(B, 3)`` the initial guess, world to camera (VINS: the
            current keyframe's camera pose, ``useExtrinsicGuess = true``). Both or neither.
        threshold: inlier bound on the Euclidean reprojection error, normalized units (> 0).
        iterations: most minimal samples per problem (VINS ``iterationsCount = 100``).
        confidence: RANSAC confidence for the adaptive iteration bound, in (0, 1).
        generator: ``torch.Generator`` for the samples (torch backend). None: a fresh generator
            seeded with 0 on every call, so the result is deterministic (as OpenCV, which re-seeds
            its RNG on every call).
        backend: ``"torch"`` (batched) or ``"opencv"`` (a loop of ``cv2.solvePnPRansac``).
        refine_iters: Levenberg-Marquardt iterations of the final refinement (torch backend; from
            a P3P model on its inliers the cost is at rounding level after 3).

    Returns:
        :class:`PnPResult` ``(R, t, inliers, ok)``.

    Convention:
        torch backend, per problem with n valid points:
        * Samples of 4 distinct valid points (uniform; ``torch.rand`` keys from ``generator``);
          Lambda Twist P3P on the first 3, the 4th picks one of the up to 4 solutions (OpenCV's
          own P3P rule). Degenerate samples give no model.
        * Every model is scored on all n points (``|proj - p| <= threshold``, in front of the
          camera). A model replaces the best one only with strictly more inliers and at least 5
          (its sample + 1; OpenCV: > 4 with its 5-point EPnP kernel). The bound on the number of
          samples follows OpenCV's ``RANSACUpdateNumIters(confidence, 1 - inliers/n, 4, bound)``,
          capped by ``iterations``; a problem stops at exactly the sample where OpenCV's loop would.
        * Refinement: ``refine_iters`` LM steps (:func:`refine_pnp`) on the best model's inliers,
          then the inliers are recomputed with the refined pose (OpenCV returns the RANSAC-stage
          mask). Differentiable w.r.t. ``points_3d`` and ``points_norm`` (the inlier set and the
          starting pose are constants).
        * Initial guess: OpenCV 4.x (5-point EPnP kernel) ignores it in the RANSAC stage and
          starts its final Levenberg-Marquardt on the inliers from it (measured with cv2 4.14: a
          guess ~1 rad / 1.7 m off gives a wrong pose in 1 of 50 synthetic problems that a good
          guess or none solves). Here the refinement starts from whichever of the guess and the
          best RANSAC model has the lower reprojection cost on the inliers, so a good guess is
          used and a bad one cannot hurt. Where no model is found, the guess is returned.
        * ``ok`` False (fewer than 4 valid points, or no model with >= 5 inliers): ``R, t`` =
          the guess (identity / zero without one), no inliers.
        The RANSAC stage runs in float64 (as OpenCV's double arithmetic), the refinement in the
        input dtype. One host sync per round of samples (32, then 64, ...) and one for the input
        check.

        opencv backend: per problem ``cv2.solvePnPRansac(X, p, K = I, None, rvec0, tvec0,
        useExtrinsicGuess = (guess given), iterationsCount, reprojectionError = threshold,
        confidence, flags = SOLVEPNP_ITERATIVE)`` on the valid points in slot order (float64);
        exceptions (e.g. fewer than 4 points) and failures give ``ok`` False with the guess.
        ``generator`` and ``refine_iters`` are not used. Not differentiable.
    """
    B, N = _check_points(points_3d, points_norm)
    dev, dt = points_3d.device, points_3d.dtype
    if valid is None:
        valid = torch.ones(B, N, dtype=torch.bool, device=dev)
    check_shape(valid, (B, N), "valid")
    valid = valid.to(device=dev, dtype=torch.bool)
    if (init_R is None) != (init_t is None):
        raise ValueError("init_R, init_t: give both or neither")
    if init_R is not None:
        check_shape(init_R, (B, 3, 3), "init_R")
        check_shape(init_t, (B, 3), "init_t")
        if not (torch.isfinite(init_R).all() and torch.isfinite(init_t).all()):
            raise DataError("init_R/init_t: non-finite initial guess")
    if not (threshold > 0 and math.isfinite(threshold)):
        raise ValueError(f"threshold: expected a finite value > 0, got {threshold}")
    if int(iterations) < 1:
        raise ValueError(f"iterations: expected >= 1, got {iterations}")
    if not (0.0 < confidence < 1.0):
        raise ValueError(f"confidence: expected a value in (0, 1), got {confidence}")
    if int(refine_iters) < 0:
        raise ValueError(f"refine_iters: expected >= 0, got {refine_iters}")
    if backend not in ("torch", "opencv"):
        raise ValueError(f"backend: expected 'torch' or 'opencv', got {backend!r}")
    for name, x in (("points_3d", points_3d), ("points_norm", points_norm)):
        bad = valid & ~torch.isfinite(x.detach()).all(-1)
        if bool(bad.any()):
            b, i = (int(v) for v in bad.nonzero()[0])
            raise DataError(f"{name}: non-finite value at problem {b}, point {i} (a valid slot)")
    if init_R is None:
        g_R = torch.eye(3, dtype=dt, device=dev).expand(B, 3, 3)
        g_t = torch.zeros(B, 3, dtype=dt, device=dev)
    else:
        g_R, g_t = init_R.to(device=dev, dtype=dt), init_t.to(device=dev, dtype=dt)
    if backend == "opencv":
        return _opencv_impl(points_3d, points_norm, valid, init_R is not None, g_R, g_t, float(threshold),
                            int(iterations), float(confidence))
    if generator is None:
        generator = torch.Generator(device=dev).manual_seed(0)
    return _torch_impl(points_3d, points_norm, valid, init_R is not None, g_R, g_t, float(threshold),
                       int(iterations), float(confidence), generator, int(refine_iters))


def _torch_impl(X, p, valid, has_guess, g_R, g_t, thr, iterations, confidence, gen, refine_iters):
    dt = X.dtype
    # the hypothesis stage: float64, no autograd; masked-out slots replaced by finite values
    X64 = torch.where(valid[..., None], X.detach().double(), torch.zeros((), dtype=torch.float64, device=X.device))
    p64 = torch.where(valid[..., None], p.detach().double(), torch.zeros((), dtype=torch.float64, device=X.device))
    hR, ht, cnt, mask = _ransac(X64, p64, valid, thr, iterations, confidence, gen)
    ok = cnt >= _MIN_INLIERS
    # P3P's R is orthonormal to rounding; project it onto SO(3) anyway (the LM keeps R on it)
    hR = quat_to_R(R_to_quat(hR))
    w = mask.to(torch.float64)
    if has_guess:
        # start from the guess where it explains the RANSAC inliers better (see the docstring)
        c_h = _residual(X64, p64, w, hR, ht)[3]
        c_g = _residual(X64, p64, w, g_R.detach().double(), g_t.detach().double())[3]
        use_g = c_g < c_h
        hR = torch.where(use_g[:, None, None], g_R.detach().double(), hR)
        ht = torch.where(use_g[:, None], g_t.detach().double(), ht)
    # differentiable refinement in the input dtype on the constant inlier set
    Xs = torch.where(valid[..., None], X, torch.zeros_like(X))
    ps = torch.where(valid[..., None], p, torch.zeros_like(p))
    R, t = _refine_impl(Xs, ps, mask.to(dt), hR.to(dt), ht.to(dt), refine_iters)
    fin = torch.isfinite(R).all(-1).all(-1) & torch.isfinite(t).all(-1)
    ok = ok & fin
    R = torch.where(ok[:, None, None], R, g_R)
    t = torch.where(ok[:, None], t, g_t)
    with torch.no_grad():
        inl = _score(X64, p64, valid, R.detach().double()[:, None], t.detach().double()[:, None], thr * thr)[:, 0]
    inl = inl & ok[:, None]
    return PnPResult(R, t, inl, ok)


def _opencv_impl(X, p, valid, has_guess, g_R, g_t, thr, iterations, confidence):
    import cv2
    import numpy as np

    B, N = valid.shape
    dev, dt = X.device, X.dtype
    Xn = X.detach().double().cpu().numpy()
    pn = p.detach().double().cpu().numpy()
    vn = valid.cpu().numpy()
    gR = g_R.detach().double().cpu().numpy()
    gt = g_t.detach().double().cpu().numpy()
    R_out, t_out = gR.copy(), gt.copy()
    inl = np.zeros((B, N), dtype=bool)
    ok = np.zeros(B, dtype=bool)
    K = np.eye(3)
    for b in range(B):
        sl = np.flatnonzero(vn[b])
        rvec0 = cv2.Rodrigues(gR[b])[0]
        tvec0 = gt[b].reshape(3, 1).copy()
        try:
            res, rvec, tvec, idx = cv2.solvePnPRansac(
                np.ascontiguousarray(Xn[b, sl]), np.ascontiguousarray(pn[b, sl]), K, None, rvec0, tvec0,
                useExtrinsicGuess=has_guess, iterationsCount=iterations, reprojectionError=thr,
                confidence=confidence, flags=cv2.SOLVEPNP_ITERATIVE)
        except cv2.error:
            continue
        if not res or idx is None or len(idx) == 0:
            continue
        Rb = cv2.Rodrigues(rvec)[0]
        if not (np.isfinite(Rb).all() and np.isfinite(tvec).all()):
            continue
        ok[b] = True
        R_out[b], t_out[b] = Rb, tvec.ravel()
        inl[b, sl[idx.ravel()]] = True
    return PnPResult(torch.from_numpy(R_out).to(device=dev, dtype=dt), torch.from_numpy(t_out).to(device=dev, dtype=dt),
                     torch.from_numpy(inl).to(dev), torch.from_numpy(ok).to(dev))
