"""OpenCV's inlier test of fundamental matrices (``FMEstimatorCallback::computeError``), for K
models on N points at once.

Convention:
    * ``h1, h2: (B, N, 3)`` homogeneous points (:func:`_homogeneous`), ``(0, 0, 0)`` at masked-out
      slots; models ``F: (B, K, 3, 3)`` or row-major ``(B, K, 9)``.
    * The error of a point pair is ``max(d1^2, d2^2)``, ``dk`` the distance of the point in image k
      to its epipolar line (px^2); an inlier has ``error <= threshold^2``. Arithmetic in float64.
"""

from __future__ import annotations

import torch

from .consts import _Consts


def _homogeneous(x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """``(B, N, 2)`` points (zero at masked-out slots) -> ``(B, N, 3)`` homogeneous points, with
    ``(0, 0, 0)`` at masked-out slots: their epipolar lines are degenerate (``s = 0``), so they never
    count as inliers and have infinite error, without a mask op on the ``(B, N, K)`` score tensors."""
    return torch.cat([x, valid[..., None].to(x.dtype)], -1)


def _epipolar_terms(F: torch.Tensor, h1: torch.Tensor, h2: torch.Tensor):
    """Algebraic residual and line norms for K models on N points, as three batched matmuls.

    ``F: (B, K, 3, 3)``, ``h1, h2: (B, N, 3)`` (see ``_homogeneous``) -> ``d2 = (x2^T F x1)^2``,
    ``s2 = |(F x1)_xy|^2`` and ``s1 = |(F^T x2)_xy|^2``, each ``(B, N, K)``."""
    B, K = F.shape[:2]
    outer = (h2[..., :, None] * h1[..., None, :]).flatten(-2)  # (B, N, 9)
    d = outer @ F.flatten(-2).transpose(-1, -2)  # (B, N, K)
    # F x1, rows 0 and 1 of every model: columns [row0 of model 0..K-1, row1 of model 0..K-1]
    l2 = h1 @ F[:, :, :2, :].transpose(1, 2).reshape(B, 2 * K, 3).transpose(-1, -2)  # (B, N, 2K)
    l1 = h2 @ F[:, :, :, :2].permute(0, 3, 1, 2).reshape(B, 2 * K, 3).transpose(-1, -2)
    l2 = l2 * l2  # x*x: much cheaper than pow/square on CPU
    l1 = l1 * l1
    return d * d, l1[..., :K] + l1[..., K:], l2[..., :K] + l2[..., K:]


def _epipolar_errors(F: torch.Tensor, h1: torch.Tensor, h2: torch.Tensor) -> torch.Tensor:
    """OpenCV ``computeError``: ``max(d1^2, d2^2)`` squared point-to-epipolar-line distances,
    ``(B, N, K)`` for ``F: (B, K, 3, 3)``; inf where a line is degenerate (and at masked-out slots)."""
    d2, s1, s2 = _epipolar_terms(F, h1, h2)
    smin = torch.minimum(s1, s2)
    pos = smin > 0
    return torch.where(pos, d2 / torch.where(pos, smin, torch.ones_like(smin)), torch.full_like(d2, float("inf")))


def _inlier_mask(F: torch.Tensor, h1: torch.Tensor, h2: torch.Tensor, thr2: float) -> torch.Tensor:
    """``max(d1^2, d2^2) <= thr^2`` for K models on N points -> ``(B, N, K)`` bool, without divisions:
    ``d^2 <= thr^2 * min(s1, s2)`` (and a non-degenerate line; never at a masked-out slot).

    OpenCV compares ``(float)err <= (float)thr^2``; this differs only for errors within float32
    rounding of the threshold."""
    d2, s1, s2 = _epipolar_terms(F, h1, h2)
    smin = torch.minimum(s1, s2)
    bound = smin if thr2 == 1.0 else smin * thr2  # x * 1.0 == x: skip a full pass (VINS: 1 px)
    return (d2 <= bound) & (smin > 0)


def _score_rows(F: torch.Tensor, k: _Consts) -> torch.Tensor:
    """``F (B, K, 9)`` row-major models -> ``(B, K, 5, 9)`` rows mapping a point pair's outer product
    ``h2 (x) h1`` to ``x2^T F x1, (F x1)_0, (F x1)_1, (F^T x2)_0, (F^T x2)_1`` (a 0/1 selection: exact),
    so that one batched matmul scores every model on every point. Model-major: the matmul's own
    output layout (no copy), and any range of models is contiguous per problem."""
    B, K = F.shape[:2]
    return (F.reshape(B * K, 9) @ k.select).view(B, K, 5, 9)


def _score_terms(rows: torch.Tensor, outer: torch.Tensor):
    """``rows (B, K, 5, 9)`` (:func:`_score_rows`, or a range of its models) on ``outer (B, N, 9)`` ->
    ``d2 = (x2^T F x1)^2`` and ``smin = min(|(F x1)_xy|^2, |(F^T x2)_xy|^2)`` (``_epipolar_terms``'),
    each ``(B, K, N)``; both 0 at masked-out slots (their outer product is 0).

    Both are strided views of the one ``(B, K, 5, N)`` float64 buffer the matmul writes (40 bytes a
    model-point pair; nothing else of that size is allocated): the squares, the two sums and their
    minimum are written into its planes in place. Float64 throughout, as OpenCV's
    ``computeError`` (only its final error is rounded to float)."""
    B, K = rows.shape[:2]
    N = outer.shape[1]
    o = torch.bmm(rows.reshape(B, K * 5, 9), outer.transpose(1, 2)).view(B, K, 5, N)
    o.mul_(o)
    o[:, :, 1::2].add_(o[:, :, 2::2])  # planes 1, 3 <- |F x1|_xy^2, |F^T x2|_xy^2 (one launch for both)
    # the minimum in place in plane 1 (``clamp_max_``: the same values for finite squares; an
    # ``out=`` strided plane would break dynamo's graph)
    return o[:, :, 0], o[:, :, 1].clamp_max_(o[:, :, 3])


def _line_rows(F: torch.Tensor) -> torch.Tensor:
    """``F (B, M, 9)`` row-major models -> ``(B, 2, M, 9)`` float64: the quadratic forms of the
    squared line norms, ``|(F x1)_xy|^2 = h1^T G h1`` with ``G = P^T P`` (``P``: rows 0, 1 of F) and
    ``|(F^T x2)_xy|^2 = h2^T H h2`` with ``H = Q Q^T`` (``Q``: columns 0, 1), row-major ``G, H``
    (one batched matmul of 3x2 factors)."""
    B, M = F.shape[:2]
    A = F.view(B, M, 3, 3)
    S = torch.stack([A[:, :, :2, :].transpose(-1, -2), A[:, :, :, :2]], 1)  # (B, 2, M, 3, 2): P^T, Q
    return (S @ S.transpose(-1, -2)).view(B, 2, M, 9)


def _line_features(outer: torch.Tensor) -> torch.Tensor:
    """``outer (B, N, 9)`` (:func:`_outer_products`) -> ``(B, 2, N, 9)``: ``h1 (x) h1`` and ``h2 (x)
    h2`` of every point (exact: products of float32-rounded coordinates), 0 at masked-out slots."""
    B, N = outer.shape[:2]
    W = torch.stack([outer[..., 6:9], outer[..., 2::3]], 1)  # h1 = h2_2 h1, h2 = h2 h1_2 (h_2 = 1 or 0)
    return (W[..., :, None] * W[..., None, :]).view(B, 2, N, 9)


def _count_terms(F: torch.Tensor, lines: torch.Tensor, outer: torch.Tensor, feats: torch.Tensor):
    """:func:`_score_terms`' ``d2, smin`` (each ``(B, M, N)``; both 0 at masked-out slots) of the models
    ``F (B, M, 9)`` from three planes instead of five: ``d = x2^T F x1`` (one matmul on ``outer``, as
    there) and the squared line norms as quadratic forms (``lines = _line_rows(F)`` on ``feats =
    _line_features(outer)``, one matmul): 24 bytes a model-point pair written instead of 40, and
    no squaring pass over the line planes.

    Float64 throughout, as OpenCV's ``computeError``. The quadratic forms round differently from
    the squares of rounded lines (as ``_score_terms`` rounds differently from the default path's
    matmuls): ~1e-15 relative, ~1e-11 within a pixel of the epipole, against OpenCV's own float32
    rounding of the error (~6e-8)."""
    B, M = F.shape[:2]
    N = outer.shape[1]
    d = torch.bmm(F, outer.transpose(1, 2))  # (B, M, N)
    d2 = d.mul_(d)
    L = torch.bmm(lines.reshape(B * 2, M, 9), feats.reshape(B * 2, N, 9).transpose(1, 2)).view(B, 2, M, N)
    return d2, L[:, 0].clamp_max_(L[:, 1])  # in place, as _score_terms' minimum


def _outer_products(x12: torch.Tensor, eff: torch.Tensor) -> torch.Tensor:
    """``h2 (x) h1`` of every point pair, ``(B, N, 9)`` (entry ``3 i + j = h2_i h1_j``), from
    ``x12 (B, N, 4)`` float64 and ``eff (B, N)``; 0 at masked-out slots (:func:`_homogeneous`)."""
    B, N = eff.shape
    h = torch.cat([x12.view(B, N, 2, 2), eff[:, :, None, None].expand(B, N, 2, 1).to(x12.dtype)], -1)
    return (h[:, :, 1, :, None] * h[:, :, 0, None, :]).flatten(-2)
