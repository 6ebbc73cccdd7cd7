"""Weighted 8-point fundamental-matrix refits: the public, differentiable
:func:`refit_fundamental`, and the host-sync-free forms LO-RANSAC refines its models with
(warm-started inverse iteration, an adjugate rank-2 projection, a refit with the epipole held
fixed).

Convention:
    * ``p1, p2: (B, N, 2)`` float, pixels ``(x, y)``; ``weights: (B, N)`` >= 0; F as
      ``find_fundamental``'s: ``[p2, 1] F [p1, 1]^T ~ 0``, unit Frobenius norm, largest entry
      positive, NaN with fewer than 8 points of positive weight.
    * Hartley normalisation per image (centroid, RMS distance sqrt(2)); the algebraic solution is
      the smallest eigenvector of the 9x9 weighted normal matrix ``sum_i w_i a_i a_i^T``.
"""

from __future__ import annotations

import math

import torch

from .._checks import check_points, check_shape
from .consts import _Consts
from .result import _MIN_POINTS, _canonical_sign

__all__ = ["refit_fundamental"]

#: inverse iteration: solves with the shifted normal matrix per eigenvector in the final refit
#: (converged to ~1e-12 from a 1e-2 start on tracker-like scenes); LO's steps use fewer (lo.py)
_EIG_POWER_FINAL = 8
#: rank 2: power iteration on the adjugate of ``F^T F`` (dominant eigenvector = smallest of F^T F),
#: raised to the ``2^k``-th power by k squarings
_RANK2_SQUARINGS = 3


def _epipolar_rows(x0, y0, x1, y1):
    """Rows of the linear system ``[x1 y1 1] F [x0 y0 1]^T = 0`` in OpenCV's (row-major F) order."""
    one = torch.ones_like(x0)
    return torch.stack([x1 * x0, x1 * y0, x1, y1 * x0, y1 * y0, y1, x0, y0, one], -1)


def refit_fundamental(p1: torch.Tensor, p2: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Weighted, normalised 8-point fundamental matrix, differentiable w.r.t. points and weights.

    Args:
        p1, p2: ``(B, N, 2)`` float, pixels ``(x, y)``.
        weights: ``(B, N)`` float >= 0 (or bool, e.g. the ``inliers`` of :func:`find_fundamental`).
            Slots with weight 0 or a non-finite coordinate are ignored (they may hold NaN).

    Returns:
        ``F: (B, 3, 3)`` in the dtype of ``p1``, ``[p2, 1] F [p1, 1]^T ~ 0``; NaN for problems with
        fewer than 8 slots of positive weight.

    Convention:
        * Hartley normalisation per image with weighted centroid and weighted RMS distance sqrt(2)
          (RMS rather than OpenCV's mean distance: it is smooth where a point hits the centroid).
        * The algebraic solution is the eigenvector of the smallest eigenvalue of the 9x9 weighted
          normal matrix ``sum_i w_i a_i a_i^T`` (``torch.linalg.eigh``); rank 2 is enforced as
          ``F (I - v v^T)`` with v the smallest eigenvector of ``F^T F`` (the same matrix as zeroing
          the smallest singular value, without the sign ambiguity of an SVD).
        * Output scaled to unit Frobenius norm with the largest-magnitude entry positive.
        Gradients are well defined when the two smallest eigenvalues of the normal matrix (and of
        ``F^T F``) are distinct, i.e. for >= 8 points in general position.
    """
    check_points(p1, "p1")
    check_points(p2, "p2")
    check_shape(p2, tuple(p1.shape), "p2")
    check_shape(weights, tuple(p1.shape[:-1]), "weights")
    return _refit_impl(p1, p2, weights)


def _refit_impl(p1: torch.Tensor, p2: torch.Tensor, weights: torch.Tensor, warm: torch.Tensor | None = None,
                k: _Consts | None = None) -> torch.Tensor:
    """:func:`refit_fundamental` without input checks. ``warm``: ``(B, 3, 3)`` a model near the
    solution (any scale; ``k`` its device constants): both eigenvectors then come from the
    host-sync-free solvers :func:`_smallest_eigvec` (inverse iteration from ``warm``) and
    :func:`_rank2` instead of ``torch.linalg.eigh`` (the same matrix up to rounding where the
    smallest eigenvalue is well separated; near a degenerate (planar) configuration the member of
    the family of solutions closest to ``warm``)."""
    dtype = p1.dtype
    w = weights.to(dtype)
    finite = torch.isfinite(p1).all(-1) & torch.isfinite(p2).all(-1) & torch.isfinite(w)
    use = finite & (w > 0)
    w = torch.where(use, w, torch.zeros_like(w))
    # masked lanes -> 0 so that no NaN reaches a product (gradients of where are where(use, g, 0))
    x1 = torch.where(use[..., None], p1, torch.zeros_like(p1))
    x2 = torch.where(use[..., None], p2, torch.zeros_like(p2))
    ok = use.sum(-1) >= _MIN_POINTS
    W = w.sum(-1, keepdim=True)
    W = torch.where(ok[:, None], W, torch.ones_like(W))

    def _normalise(x):
        c = (w[..., None] * x).sum(-2) / W  # (B, 2)
        d = x - c[:, None]
        r2 = (w * (d * d).sum(-1)).sum(-1, keepdim=True) / W  # weighted mean squared distance
        r2 = torch.where(ok[:, None] & (r2 > 0), r2, torch.ones_like(r2))
        s = torch.sqrt(2.0 / r2)  # (B, 1)
        return d * s[..., None], c, s[:, 0]

    n1, c1, s1 = _normalise(x1)
    n2, c2, s2 = _normalise(x2)
    A = _epipolar_rows(n1[..., 0], n1[..., 1], n2[..., 0], n2[..., 1])  # (B, N, 9)
    M = (A * w[..., None]).transpose(-1, -2) @ A if warm is None else _normal_matrix(A, w)  # (B, 9, 9)
    M = torch.where(ok[:, None, None], M, torch.eye(9, dtype=dtype, device=p1.device).expand_as(M) * torch.arange(1, 10, dtype=dtype, device=p1.device))
    zero = torch.zeros_like(s1)
    one = torch.ones_like(s1)
    if warm is None:
        f = torch.linalg.eigh(M).eigenvectors[..., 0]  # smallest eigenvalue
        Fh = f.view(-1, 3, 3)
        v = torch.linalg.eigh(Fh.transpose(-1, -2) @ Fh).eigenvectors[..., 0]  # (B, 3)
        Fh = Fh - (Fh @ v[..., None]) @ v[..., None, :]
    else:
        # the warm model in the normalised coordinates: Fn = T2^-T F T1^-1, T^-1 = [[1/s, 0, cx],
        # [0, 1/s, cy], [0, 0, 1]]
        def _Tinv(s, c):
            r = 1.0 / s
            return torch.stack([torch.stack([r, zero, c[:, 0]], -1), torch.stack([zero, r, c[:, 1]], -1),
                                torch.stack([zero, zero, one], -1)], -2)

        f0 = (_Tinv(s2, c2).transpose(-1, -2) @ warm.to(dtype) @ _Tinv(s1, c1)).reshape(-1, 9)
        Fh = _rank2(_smallest_eigvec(M, f0, k, _EIG_POWER_FINAL).view(-1, 3, 3), k)

    def _T(s, c):
        return torch.stack(
            [
                torch.stack([s, zero, -s * c[:, 0]], -1),
                torch.stack([zero, s, -s * c[:, 1]], -1),
                torch.stack([zero, zero, one], -1),
            ],
            -2,
        )

    F = _T(s2, c2).transpose(-1, -2) @ Fh @ _T(s1, c1)
    F = _canonical_sign(F)
    return torch.where(ok[:, None, None], F, torch.full_like(F, float("nan")))


def _smallest_eigvec(M: torch.Tensor, f0: torch.Tensor, k: _Consts, power: int) -> torch.Tensor:
    """Unit eigenvector of the smallest eigenvalue of symmetric PSD ``M (B, n, n)`` (n = 9, or 6 in
    :func:`_refit_fixed_epipole`) by inverse iteration from ``f0 (B, n)``, with no host sync: ``power`` solves with one LU factor of
    ``M / tr M + shift I`` (``lu_factor_ex``, no error check). The error shrinks by ``(mu1 + shift) /
    (mu2 + shift)`` per solve (mu the eigenvalues of ``M / tr M``); where the two smallest are
    (nearly) equal, as for a planar scene, the result stays near ``f0``'s component in that
    eigenspace. Vector solves, not an inverse: on the CPU ``inv_ex``, ``cholesky_solve`` and the
    9x9 ``bmm`` give a problem different last bits in different batches (the algorithm or the BLAS
    path depends on the batch and on memory alignment), ``lu_factor_ex`` / ``lu_solve`` of a
    vector do not. Differentiable (autograd through the factorisation and the solves)."""
    tr = M.diagonal(dim1=-2, dim2=-1).sum(-1)
    shift = k.shift if M.shape[-1] == 9 else k.shift6
    LU, piv, _ = torch.linalg.lu_factor_ex(torch.addcdiv(shift, M, tr[:, None, None]))
    f = f0[..., None]
    for _ in range(power):  # the norm grows to ~shift^-power (1e96 for 8): fine in float64
        f = torch.linalg.lu_solve(LU, piv, f)
    f = f[..., 0]
    return f / f.norm(dim=-1, keepdim=True)


def _normal_matrix(A: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """``sum_i w_i a_i a_i^T`` for rows ``A (B, N, 9)`` and weights ``w (B, N)``: ``(B, 9, 9)`` as an
    elementwise product and a sum (the same bits for a problem in any batch, unlike ``bmm``)."""
    Aw = A * w[..., None]
    return (Aw[:, :, :, None] * A[:, :, None, :]).sum(1)


def _rank2(Fh: torch.Tensor, k: _Consts) -> torch.Tensor:
    """``Fh (I - v v^T)`` for ``Fh (B, 3, 3)``, v the right singular vector of the smallest singular
    value (``refit_fundamental``'s rank-2 rule), with no host sync: v is the dominant eigenvector of
    the adjugate of ``S = Fh^T Fh`` (its eigenvalues are the products of pairs of S's, the largest
    belongs to S's smallest), by powers of the adjugate, from its row of largest norm. The result has
    rank <= 2 whatever the convergence (a projection); it is the closest rank-2 matrix when the
    ratio of the two smallest singular values is small (``(s3 / s2)^(2^(k+1))``)."""
    v = _null_vector(Fh)[:, None]  # (B, 1, 3)
    return torch.baddbmm(Fh, Fh @ v.transpose(-1, -2), v, alpha=-1.0)


def _null_vector(Fh: torch.Tensor) -> torch.Tensor:
    """:func:`_rank2`'s v, ``(B, 3)`` unit: the right singular vector of ``Fh``'s smallest singular
    value (of a rank-2 F: its right epipole, ``F v = 0``)."""
    S = Fh.transpose(-1, -2) @ Fh
    C = torch.linalg.cross(S.roll(-1, -2), S.roll(-2, -2), dim=-1)  # cofactors = adjugate (symmetric)
    for _ in range(_RANK2_SQUARINGS):
        C = C @ C
    v = C.gather(1, C.norm(dim=-1).argmax(-1)[:, None, None].expand(-1, 1, 3))[:, 0]
    return v / v.norm(dim=-1, keepdim=True)


def _refit_fixed_epipole(x1: torch.Tensor, x2: torch.Tensor, w: torch.Tensor, F: torch.Tensor,
                         k: _Consts) -> torch.Tensor:
    """A weighted 8-point refit with ``F``'s right epipole held fixed (the algebraic minimisation of
    Hartley & Zisserman, sec. 11.3, one step): the rows of ``Fn`` are confined to the plane
    orthogonal to the epipole e, ``f = N g`` with ``N = I_3 (x) [u v]`` (u, v an orthonormal basis of
    that plane), and g is the smallest eigenvector of ``N^T M N`` (6x6; inverse iteration from the
    projection of ``F``). Rank 2 by construction: no projection afterwards, which is what makes it
    more accurate than the plain 8-point fit (measured on the planted scenes of
    ``benchmarks/bench_fundamental_accuracy.py`` after the plain refit: median F error 0.068 px
    instead of 0.075 at 0 % outliers, 0.090 instead of 0.100 at 40 %).

    ``x1, x2 (B, N, 2)`` float64, finite (zero where ``w == 0``); ``w (B, N)`` >= 0; ``F (B, 3, 3)``
    pixel model, rank 2. Hartley normalisation over the points of positive weight (unit weights,
    RMS distance sqrt(2)). Returns ``(B, 3, 3)`` unit norm, largest entry positive, NaN with fewer
    than 8 points of positive weight. Differentiable w.r.t. the points, ``w`` and ``F``."""
    B = F.shape[0]
    use = w > 0
    ok = use.sum(-1) >= _MIN_POINTS
    wu = use.to(w.dtype)
    W = wu.sum(-1).clamp_min(1.0)[:, None]

    def _normalise(x):
        c = (wu[..., None] * x).sum(1) / W  # (B, 2)
        d = x - c[:, None]
        r2 = (wu * (d * d).sum(-1)).sum(-1, keepdim=True) / W
        s = torch.sqrt(2.0 / torch.where(r2 > 0, r2, torch.ones_like(r2)))  # (B, 1)
        one, zero = torch.ones_like(s), torch.zeros_like(s)
        T = torch.cat([s, zero, -s * c[:, :1], zero, s, -s * c[:, 1:], zero, zero, one], -1).view(B, 3, 3)
        r = 1.0 / s
        Ti = torch.cat([r, zero, c[:, :1], zero, r, c[:, 1:], zero, zero, one], -1).view(B, 3, 3)
        return d * s[..., None], T, Ti

    n1, T1, T1i = _normalise(x1)
    n2, T2, T2i = _normalise(x2)
    M = _normal_matrix(_epipolar_rows(n1[..., 0], n1[..., 1], n2[..., 0], n2[..., 1]), w)
    Fn = T2i.transpose(-1, -2) @ F @ T1i
    e = _null_vector(Fn)
    a = k.eye3.index_select(0, e.abs().argmin(-1))  # the axis least aligned with e
    u = torch.linalg.cross(e, a)
    u = u / u.norm(dim=-1, keepdim=True)
    Bm = torch.stack([u, torch.linalg.cross(e, u)], -1)  # (B, 3, 2)
    N = (k.eye3[None, :, None, :, None] * Bm[:, None, :, None, :]).reshape(B, 9, 6)
    MN = (M[:, :, :, None] * N[:, None, :, :]).sum(2)  # (B, 9, 6), elementwise (see _smallest_eigvec)
    Mg = (N[:, :, :, None] * MN[:, :, None, :]).sum(1)  # (B, 6, 6)
    g = _smallest_eigvec(Mg, (N * Fn.reshape(B, 9, 1)).sum(1), k, _EIG_POWER_FINAL)
    F = T2.transpose(-1, -2) @ (N * g[:, None, :]).sum(-1).view(B, 3, 3) @ T1
    return torch.where(ok[:, None, None], _canonical_sign(F), math.nan)
