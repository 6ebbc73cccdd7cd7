"""What a fundamental-matrix call returns, and OpenCV's rules that shape it: which method a problem
gets from its point count, the argument defaults, the points as OpenCV sees them, the F normal form.

Convention:
    * ``F: (B, 3, 3)`` maps image-1 points to image-2 epipolar lines, ``[p2, 1] F [p1, 1]^T = 0``;
      returned with unit Frobenius norm and the entry of largest magnitude positive
      (:func:`_canonical_sign`), NaN where no model was found.
    * ``method`` codes per problem with n valid, finite points: :data:`METHOD_NONE` (n < 8, no
      estimation), :data:`METHOD_LMEDS` (8..14: OpenCV's silent LMedS fallback),
      :data:`METHOD_RANSAC` (n >= 15), as :func:`_method_codes`.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Optional, Tuple

import torch

__all__ = ["FundamentalFit", "FundamentalResult", "METHODS", "METHOD_LMEDS", "METHOD_NONE", "METHOD_RANSAC",
           "opencv_threshold_confidence"]

_MODEL_POINTS = 7  # a minimal sample: the 7-point solver
_MIN_POINTS = 8  # VINS rejectWithF skips F estimation below 8 tracks
_MIN_RANSAC_POINTS = 15  # OpenCV: 8..14 points => LMedS even when FM_RANSAC is asked for
_DEFAULT_THRESHOLD = 3.0  # px: findFundamentalMat's threshold when given one <= 0
_DEFAULT_CONFIDENCE = 0.99  # findFundamentalMat's confidence when given one outside (0, 1)
_DBL_EPSILON = 2.220446049250313e-16

METHOD_NONE, METHOD_LMEDS, METHOD_RANSAC = 0, 1, 2
#: ``find_fundamental``'s estimators: OpenCV's FM_RANSAC exactly, or LO-RANSAC on its hypotheses
METHODS = ("opencv", "lo")


class FundamentalFit(NamedTuple):
    """What ``_find_fundamental_impl`` returns (the kernel contract's result: the same fields on
    both paths).

    Attributes:
        F: ``(B, 3, 3)`` in the dtype of ``p1``: unit Frobenius norm, largest entry positive; NaN
            where ``ok`` is False.
        inliers: ``(B, N)`` bool (never True on a masked-out slot; every valid, finite point where
            ``ok`` is False).
        ok: ``(B,)`` bool, a model was found.
        num_iters: ``(B,)`` int64 minimal samples drawn.
        method: ``(B,)`` int8 :data:`METHOD_NONE` / :data:`METHOD_LMEDS` / :data:`METHOD_RANSAC`.
        overflow: ``(B,)`` bool on the capturable path (the hypothesis block or the budget of
            optimised models was too small for the default path's answer), None on the default path.
    """

    F: torch.Tensor
    inliers: torch.Tensor
    ok: torch.Tensor
    num_iters: torch.Tensor
    method: torch.Tensor
    overflow: Optional[torch.Tensor]


class _FundamentalPair(NamedTuple):
    F: torch.Tensor
    inliers: torch.Tensor


class FundamentalResult(_FundamentalPair):
    """Result of :func:`~torch_frontend.ransac.find_fundamental`; unpacks as
    ``F, inliers = find_fundamental(...)``.

    Attributes:
        F: ``(B, 3, 3)`` best RANSAC (or LMedS) 7-point hypothesis, unit Frobenius norm, largest
            entry positive; NaN where ``ok`` is False.
        inliers: ``(B, N)`` bool inlier mask from the RANSAC scoring (never True on a masked-out
            slot). Where ``ok`` is False every valid (finite) point is reported as an inlier, so that
            a tracker keeps its tracks (spec §3.8).
        ok: ``(B,)`` bool, a model was found (OpenCV would return a non-empty F).
        num_iters: ``(B,)`` int64 number of minimal samples drawn for the problem.
        method: ``(B,)`` int8, 0 = none (< 8 valid points), 1 = LMedS (8..14), 2 = RANSAC (>= 15).
        overflow: ``(B,)`` bool, the capturable path's hypothesis block was too small for OpenCV's
            exact answer (it would have drawn more samples); the problem's other fields are then
            not OpenCV's. Always False on the default path and with the default block.
    """

    ok: torch.Tensor
    num_iters: torch.Tensor
    method: torch.Tensor

    def __new__(cls, F, inliers, ok, num_iters, method, overflow=None):
        self = super().__new__(cls, F, inliers)
        self.ok = ok
        self.num_iters = num_iters
        self.method = method
        self._overflow = overflow
        return self

    @classmethod
    def from_fit(cls, fit: FundamentalFit) -> FundamentalResult:
        """The public result of a :class:`FundamentalFit` (``overflow`` None: zeros when read)."""
        return cls(fit.F, fit.inliers, fit.ok, fit.num_iters, fit.method, fit.overflow)

    @property
    def overflow(self) -> torch.Tensor:
        # made on first use: the default path (never overflows) does not pay a kernel for it
        if self._overflow is None:
            self._overflow = torch.zeros_like(self.ok)
        return self._overflow

    def __reduce__(self):
        return (FundamentalResult, (self.F, self.inliers, self.ok, self.num_iters, self.method, self._overflow))


def opencv_threshold_confidence(threshold: float, confidence: float) -> Tuple[float, float]:
    """``findFundamentalMat``'s own argument rules: a threshold ``<= 0`` means 3 px, a confidence
    outside ``[DBL_EPSILON, 1 - DBL_EPSILON]`` means 0.99."""
    if threshold <= 0:
        threshold = _DEFAULT_THRESHOLD
    if not (_DBL_EPSILON <= confidence <= 1 - _DBL_EPSILON):
        confidence = _DEFAULT_CONFIDENCE
    return float(threshold), float(confidence)


def _method_codes(n: torch.Tensor) -> torch.Tensor:
    """The method OpenCV runs for ``n`` valid points (any shape, int) as int8 codes: 0 below 8
    points, 1 (LMedS) for 8..14, 2 (RANSAC) from 15. The one definition: the drivers apply it to
    their problems' counts, the capturable path tabulates it for every count."""
    return (n >= _MIN_POINTS).to(torch.int8) + (n >= _MIN_RANSAC_POINTS).to(torch.int8)


class _Points(NamedTuple):
    """The points of B problems as OpenCV sees them (:func:`_opencv_points`)."""

    x12: torch.Tensor  # (B, N, 4) float64 (x1, y1, x2, y2), float32-rounded, zero at masked-out slots
    eff: torch.Tensor  # (B, N) bool: valid and finite
    n: torch.Tensor  # (B,) int64: valid, finite points per problem


def _opencv_points(p1: torch.Tensor, p2: torch.Tensor, valid: torch.Tensor,
                   zero: Optional[torch.Tensor] = None) -> _Points:
    """OpenCV converts the points to float32 before anything else; the solvers then run in float64.
    A valid slot with a non-finite coordinate is masked out. Masked-out slots become 0: every later
    ``torch.where`` evaluates both branches, so they must stay finite. ``zero``: a cached 0-dim
    float64 zero on the points' device (the capturable path: no scalar-tensor launch per call)."""
    x12 = torch.cat([p1.detach(), p2.detach()], -1).to(torch.float32).to(torch.float64)  # (B, N, 4)
    # a sum of float32-range values is finite iff all are (no overflow in float64)
    eff = valid & (x12.sum(-1).abs() < math.inf)
    x12 = torch.where(eff[..., None], x12, 0.0 if zero is None else zero)
    return _Points(x12, eff, eff.sum(-1))


def _unsolved(pts: _Points, dtype: torch.dtype) -> FundamentalFit:
    """The fit before any problem is solved: F NaN, every valid point an inlier, ``ok`` False, no
    samples, the problems' methods; the drivers fill in the rows they solve."""
    B = pts.eff.shape[0]
    dev = pts.eff.device
    return FundamentalFit(torch.full((B, 3, 3), math.nan, dtype=dtype, device=dev), pts.eff.clone(),
                          torch.zeros(B, dtype=torch.bool, device=dev), torch.zeros(B, dtype=torch.int64, device=dev),
                          _method_codes(pts.n), None)


def _canonical_sign(F: torch.Tensor) -> torch.Tensor:
    """Unit Frobenius norm with the largest-magnitude entry positive (``(..., 3, 3)``)."""
    flat = F.flatten(-2)
    nrm = flat.norm(dim=-1, keepdim=True)
    flat = flat / torch.where(nrm > 0, nrm, torch.ones_like(nrm))
    idx = flat.abs().argmax(-1, keepdim=True)
    sgn = torch.where(flat.gather(-1, idx) < 0, -1.0, 1.0).to(flat.dtype)
    return (flat * sgn).view_as(F)


def _canonical_sign_unit(F: torch.Tensor) -> torch.Tensor:
    """:func:`_canonical_sign` of unit-norm ``F (B, 9)``: the sign only (3 kernels fewer)."""
    return F * F.gather(-1, F.abs().argmax(-1, keepdim=True)).sign()
