"""Batched fundamental-matrix RANSAC (OpenCV ``findFundamentalMat(FM_RANSAC)`` semantics), LO-RANSAC
and a differentiable weighted 8-point refit.

VINS-Mono's ``rejectWithF`` (spec §3.8, §5.4) lifts every track into a 460-px virtual pinhole and
calls ``cv2.findFundamentalMat(un_cur, un_forw, FM_RANSAC, F_threshold, 0.99)``. This package solves
B such problems together, with OpenCV's own samples, models (in OpenCV's order) and sequential
bookkeeping, so the inlier masks are OpenCV's.

Convention:
    * ``p1, p2: (B, N, 2)`` float, pixels ``(x, y)`` of the virtual pinhole; ``valid: (B, N)`` bool.
      Masked-out slots may hold anything (NaN included); valid slots with a non-finite coordinate are
      treated as masked out (and reported as outliers).
    * ``F: (B, 3, 3)`` maps image-1 points to image-2 epipolar lines: ``[p2, 1] F [p1, 1]^T = 0``
      (OpenCV's convention). Returned F are scaled to unit Frobenius norm, with the entry of largest
      magnitude positive (OpenCV instead scales to ``F[2, 2] = 1``, which is ill-conditioned for
      rectified-stereo-like geometry where ``F[2, 2] ~ 0``).
    * Inlier test (OpenCV ``FMEstimatorCallback::computeError``): ``max(d1^2, d2^2) <= threshold^2``
      with ``dk`` the distance of the point in image k to its epipolar line (points are rounded to
      float32 first, as OpenCV does; arithmetic in float64).

Seeding rule (determinism; see :func:`find_fundamental`): problem b's minimal samples are exactly
the ones OpenCV's ``getSubset`` draws with ``cv::RNG(seed_b)`` for its n_b valid points taken in slot
order (``next() % n_b``, repeated indices redrawn). The default seed is OpenCV's own
(``(uint64)-1``, re-seeded on every call), which is why the masks equal cv2's. The sample stream
depends only on (seed_b, n_b): nothing depends on b, B, N, the padding layout, the round size or the
other problems, so a problem gets the same result in any batch as in a single call with the same
seed. The sample tables are generated on the host lazily and cached process-wide (``samples.py``;
thread-safe: calls from several threads give the single-threaded results).

The rooms: ``result`` (the result types and OpenCV's per-call rules), ``samples`` (OpenCV's random
stream), ``seven_point`` (the one 7-point solver and its cubic, shared by every driver),
``scoring`` (the inlier test), ``bounds`` (the adaptive iteration bound), ``eager`` (the default
path: OpenCV's loop replayed in rounds), ``capturable`` (one static block per problem, no host
sync), ``lo`` (LO-RANSAC, both paths), ``refit`` (weighted 8-point refits), ``consts`` (device
constants). :func:`_find_fundamental_impl` picks the driver.
"""

from __future__ import annotations

from typing import Optional, Sequence, Union

import torch

from .._checks import check_points, check_shape, default_valid
from .._compiler import constant_result
from .bounds import ransac_update_num_iters
from .capturable import _find_fundamental_capturable
from .eager import _find_fundamental_eager
from .lo import _find_fundamental_lo, _find_fundamental_lo_capturable
from .refit import refit_fundamental
from .result import (
    METHOD_LMEDS,
    METHOD_NONE,
    METHOD_RANSAC,
    METHODS,
    FundamentalFit,
    FundamentalResult,
    opencv_threshold_confidence,
)
from .samples import OPENCV_SEED, _state_of

__all__ = ["FundamentalFit", "FundamentalResult", "METHODS", "METHOD_LMEDS", "METHOD_NONE", "METHOD_RANSAC",
           "OPENCV_SEED", "find_fundamental", "opencv_threshold_confidence", "ransac_update_num_iters",
           "refit_fundamental"]


def _seeds(B: int, generator: torch.Generator | None = None,
           seed: Union[None, int, Sequence[int], torch.Tensor] = None) -> list:
    """Per-problem ``cv::RNG`` states as B Python ints, from ``seed`` / ``generator`` as
    :func:`find_fundamental` takes them (see its seeding rule; the default is OpenCV's own state).
    A caller that runs many calls with the same seeds computes them once and passes them to
    :func:`_find_fundamental_impl`."""
    if seed is not None:
        s = torch.as_tensor(seed, dtype=torch.int64).cpu()
        if s.dim() == 0:
            s = s.expand(B)
        check_shape(s, (B,), "seed")
        return [_state_of(v) for v in s.tolist()]
    if generator is not None:
        v = torch.randint(-(2**63), 2**63 - 1, (1,), dtype=torch.int64, generator=generator, device=generator.device)
        return [_state_of(int(v.item()))] * B
    return [_state_of(OPENCV_SEED)] * B


def find_fundamental(
    p1: torch.Tensor,
    p2: torch.Tensor,
    valid: torch.Tensor | None = None,
    threshold: float = 1.0,
    confidence: float = 0.99,
    max_iters: int = 1000,
    generator: torch.Generator | None = None,
    batch_hypotheses: int | None = None,
    seed: Union[None, int, Sequence[int], torch.Tensor] = None,
    capturable: bool = False,
    method: str = "opencv",
    backend: Optional[str] = None,
) -> FundamentalResult:
    """Robust fundamental matrices for B point-set pairs at once (``cv2.findFundamentalMat`` with
    ``FM_RANSAC``, batched).

    Args:
        p1, p2: ``(B, N, 2)`` float, pixels ``(x, y)`` (VINS: the 460-px virtual pinhole), matched
            slot by slot.
        valid: ``(B, N)`` bool, which slots hold a correspondence (default all). Masked-out slots may
            contain NaN.
        threshold: inlier distance in pixels (VINS ``F_threshold``); ``<= 0`` means 3 (OpenCV).
        confidence: RANSAC confidence for the adaptive iteration bound (outside (0, 1): 0.99).
        max_iters: cap on minimal samples per problem (OpenCV default 1000).
        generator: optional ``torch.Generator``; one int64 is drawn from it (``torch.randint`` on the
            generator's device) and used as the ``cv::RNG`` state of every problem of the call.
        batch_hypotheses: the largest number of minimal samples evaluated per problem per round
            (rounds grow 32, 64, 128, ... up to it and never exceed the current iteration bound).
            None (default): from a memory budget (about 2^20 problem x sample x point lanes per
            round). Memory/speed knob only: results do not depend on it.
        seed: optional int or ``(B,)`` ints, per-problem ``cv::RNG`` states (two's complement, so
            ``-1`` is ``(uint64)-1``; 0 is mapped to it as well; takes precedence over
            ``generator``). Default (neither given), 0 or -1: OpenCV's own seed for every problem,
            so the masks reproduce cv2's.
        capturable: shape-static and free of host syncs after a first call with the same seeds,
            N, ``max_iters`` and ``confidence`` (CUDA graphs, ``torch.compile``): every problem
            evaluates a fixed block of ``batch_hypotheses`` samples (default and at most
            ``max_iters``: exact); the result is the default path's (``F`` up to rounding)
            wherever ``overflow`` is False. Memory ~30 MB per problem of 150 points at the
            default block.
        method: ``"opencv"`` (default): OpenCV's FM_RANSAC exactly, the convention below.
            ``"lo"``: LO-RANSAC on the same hypotheses, see "LO-RANSAC" below.
        backend: how the OpenCV method scores and counts its 7-point models: None / ``"auto"``
            (default: ``_tuning.Strategy.ransac_backend``, ``"fused"`` on the CPU and CUDA),
            ``"fused"`` (one ``torch_frontend::ransac_score`` op per round: numba / Triton,
            OpenCV's ``computeError`` in its double order and its float32 comparison, stopping at
            OpenCV's last sample) or ``"tensor"`` (``scoring.py``: ``d^2 <= thr^2 min(s1, s2)`` in
            float64 matmuls). The masks are the same but for an error within float32 rounding of
            the threshold, where the fused test is OpenCV's. ``docs/kernels.md``, "F-RANSAC".

    Returns:
        :class:`FundamentalResult` ``(F, inliers)`` with extra attributes ``ok``, ``num_iters``,
        ``method``, ``overflow``.

    Convention:
        Per problem with n valid, finite correspondences:
        * n < 8: no estimation (VINS skips it): F NaN, every valid point an inlier, ``ok`` False.
        * 8 <= n <= 14: OpenCV's silent LMedS fallback: ``max(3, RANSACUpdateNumIters(conf, 0.45,
          7, max_iters))`` (300 for 0.99) 7-point samples, the model of least median error (upper
          median, ``err[n // 2]`` of the sorted errors), inliers ``err <= sigma^2`` with
          ``sigma = max(0.001, 2.5 * 1.4826 * (1 + 5 / (n - 7)) * sqrt(median))``; ``ok`` iff at
          least 7 inliers. ``threshold`` is ignored, as in OpenCV. Deviation: medians below
          (1e-6 px)^2 count as equal (first in draw order wins). For n <= 13 OpenCV's median rank
          n // 2 <= 6 lies among the sample's own 7 exact-fit points, so its choice between models
          is floating-point noise and cannot be reproduced; from n = 14 on the masks are OpenCV's.
        * n >= 15: RANSAC with the 7-point solver (up to three models per sample, each scored, in
          OpenCV's order); a model replaces the best one only with strictly more inliers (and at
          least 7: of two models with the same count the first drawn is kept, as in OpenCV); the
          iteration bound follows OpenCV's ``RANSACUpdateNumIters(confidence, outlier ratio, 7,
          bound)``, capped by ``max_iters``. Rounds run while some problem is below its bound;
          within a round the bound is replayed after every sample, so each problem stops at exactly
          OpenCV's last sample (``num_iters``) and later samples of the round are discarded.
        * All outliers (unrelated points): as OpenCV, some 7-point model that fits its own sample
          (>= 7 inliers, ``ok`` True) after ``max_iters`` samples.
        * No model found (all samples degenerate, e.g. all points identical): F NaN, every valid
          point an inlier, ``ok`` False.
        The returned F is the best minimal-sample model (as OpenCV; no re-fit), unit Frobenius norm,
        largest entry positive; re-fit with :func:`refit_fundamental` on ``inliers`` if wanted.
        Points are rounded to float32 (as OpenCV), all arithmetic is float64; F is returned in the
        dtype of ``p1``. Not differentiable (the mask is discrete; see :func:`refit_fundamental`).
        One host sync per round (loop control and sample tables; a second one in large rounds,
        which score real roots only) plus one at the start (per-problem counts).

    LO-RANSAC (``method="lo"``, n >= 15; 8..14 points get the LMedS result above):
        * Hypotheses, their order and the inlier test are OpenCV's (the same samples, 7-point
          models and ``max(d1^2, d2^2) <= threshold^2``). OpenCV's loop is replayed, but every
          model it accepts (more inliers than the current best, at least 7) is locally optimised:
          3 iteratively reweighted 8-point refits on its inliers (unit weights, then Sampson
          weights; Hartley-normalised over all valid points; the last one rank 2, kept if it has
          at least as many inliers as the hypothesis), each re-scored for the next refit's inliers.
        * The optimised inlier count is the new best: later hypotheses must beat it, and the
          iteration bound is OpenCV's ``RANSACUpdateNumIters(confidence, (n - count) / n, 7,
          bound)`` with it (LO counts are higher, so the loop stops earlier than OpenCV's).
        * Final refit, on the points as given and the best model's inliers, Sampson-weighted: an
          8-point refit (``refit_fundamental``'s normalisation and rank-2 rule), then one with its
          epipole held fixed (rank 2 without a projection: Hartley & Zisserman's algebraic
          minimisation); ``F`` is it and ``inliers`` its inliers (OpenCV's test) unless it has
          fewer inliers than the best optimised model (degenerate data), which is then kept. ``F``
          is differentiable w.r.t. ``p1, p2`` through the final refit (mask and the weights' model
          held fixed).
        * ``capturable``: a fixed budget of 4 optimised models per problem in OpenCV's order plus
          one more (the best remaining hypothesis); ``overflow`` where OpenCV's loop would have
          accepted another model or drawn past the block. Elsewhere the result is the default
          path's (masks, ``ok``, ``num_iters``, ``method`` exactly, ``F`` up to rounding).
        * Memory and speed: as the OpenCV path (the loop stops earlier, and each accepted model
          costs a local optimisation; ``benchmarks/bench_fundamental_accuracy.py``).

    Seeding rule:
        Sample g of problem b is the g-th 7-subset OpenCV's ``getSubset`` would draw with
        ``cv::RNG(seed_b)`` from the n_b valid points in slot order. It depends only on (seed_b,
        n_b), so a problem in a batch gives exactly the same result as a single call on its valid
        points with the same seed. (Deviation: OpenCV redraws a subset whose last point is
        collinear with two others within FLT_EPSILON; here that sample just yields no model, so on
        such degenerate data the later samples differ from OpenCV's.)
    """
    check_points(p1, "p1")
    check_points(p2, "p2")
    check_shape(p2, tuple(p1.shape), "p2")
    valid = default_valid(p1, valid)
    threshold, confidence = opencv_threshold_confidence(threshold, confidence)
    H = None if batch_hypotheses is None else int(batch_hypotheses)
    if H is not None and H < 1:
        raise ValueError(f"batch_hypotheses: expected >= 1, got {batch_hypotheses}")
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    states = _seeds(valid.shape[0], generator, seed)
    return FundamentalResult.from_fit(_find_fundamental_impl(p1, p2, valid, float(threshold), float(confidence),
                                                             max_iters, states, H, capturable=capturable,
                                                             method=method, backend=backend))


def _find_fundamental_impl(
    p1: torch.Tensor,
    p2: torch.Tensor,
    valid: torch.Tensor,
    threshold: float,
    confidence: float,
    max_iters: int,
    states: Sequence[int],
    batch_hypotheses: int | None,
    *,
    capturable: bool = False,
    method: str = "opencv",
    backend: Optional[str] = None,
) -> FundamentalFit:
    """:func:`find_fundamental` without input checks: the kernel the tracker's stage calls.

    Args:
        p1, p2: ``(B, N, 2)`` float, pixels ``(x, y)``, matched slot by slot.
        valid: ``(B, N)`` bool.
        threshold: inlier distance in pixels, > 0 (the public function maps ``<= 0`` to 3).
        confidence: in ``(0, 1)`` (the public function maps other values to 0.99).
        max_iters: cap on minimal samples per problem.
        states: B ``cv::RNG`` states as Python ints (:func:`_seeds`).
        batch_hypotheses: largest round (>= 1), or None for the memory budget. With
            ``capturable``: the block of minimal samples per problem (None: ``max_iters``, exact).
        capturable: the shape-static, host-sync-free path (``capturable.py``, ``lo.py``): the same
            ``F`` (up to rounding), ``inliers``, ``ok``, ``num_iters`` and ``method`` wherever its
            ``overflow`` is False.
        method: ``"opencv"`` (OpenCV's FM_RANSAC, exactly: ``eager.py`` / ``capturable.py``) or
            ``"lo"`` (LO-RANSAC, see :func:`find_fundamental`; ``lo.py``).
        backend: the OpenCV method's scoring: None / ``"auto"`` (``Strategy.ransac_backend``),
            ``"fused"`` (``torch_frontend::ransac_score``, OpenCV's ``computeError`` bits) or
            ``"tensor"`` (``scoring.py``); see :func:`find_fundamental`.

    Returns:
        :class:`FundamentalFit` ``(F, inliers, ok, num_iters, method, overflow)``: ``overflow`` a
        ``(B,)`` bool tensor with ``capturable``, None on the default path (which is exact).
    """
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    if method == "lo":
        solve = _find_fundamental_lo_capturable if capturable else _find_fundamental_lo
        return solve(p1, p2, valid, threshold, confidence, max_iters, states, batch_hypotheses)
    solve = _find_fundamental_capturable if capturable else _find_fundamental_eager
    fused = _scoring_backend(backend, p1.device.type) == "fused"
    return solve(p1, p2, valid, threshold, confidence, max_iters, states, batch_hypotheses, fused=fused)


@constant_result
def _scoring_backend(requested: Optional[str], device_type: str) -> str:
    """``fused.resolve_ransac_backend`` (a constant for ``torch.compile``: resolved once, outside the
    graph; on CUDA the first resolution runs the kernel's self-check, so make a first call outside
    any capture, as the capturable path's tables need anyway)."""
    from ..fused import resolve_ransac_backend

    return resolve_ransac_backend(requested, device_type)
