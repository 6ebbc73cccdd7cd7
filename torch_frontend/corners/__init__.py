"""Corner responses and Shi-Tomasi detection, as OpenCV's ``cornerMinEigenVal`` / ``cornerHarris`` /
``goodFeaturesToTrack`` (spec §5.2), batched over streams.

Modules:

* :mod:`.responses`: the min-eigenvalue and Harris responses (Sobel-3 derivatives, box sums, and
  OpenCV's derivative scale), :func:`check_block`;
* :mod:`.selection`: the default selection (NMS, OpenCV's order, the exact greedy minimum-distance
  pass in data-sized chunks and rounds, driven by the host);
* :mod:`.selection_capturable`: the capturable selection (one top-k, a fixed
  :class:`GreedyBudget`, an ``overflow`` flag; no host sync);
* here, the doors: :func:`min_eigen_response`, :func:`harris_response`,
  :func:`good_features_to_track` (checked, normalised arguments) and :func:`_good_features_impl`,
  which the tracker's stages call with ``capturable=...`` and which returns a
  :class:`CornersResult` on both paths.

Measured agreement: responses within ~2.4e-7 of the image maximum of cv2 4.14's; on the 24 repo
frames (CLAHE, quality 0.01) identical corners in identical order to ``cv2.goodFeaturesToTrack``
(``tests/test_corners.py``). The capturable path gives the default path's corners bit for bit
wherever its ``overflow`` is False (``tests/test_detect_capturable.py``).
"""

from __future__ import annotations

import math
from typing import NamedTuple, Optional, Tuple, Union

import torch

from .._checks import as_image_batch

# every name of the package, private ones included, is importable from here
from .responses import (  # noqa: F401
    _as_float,
    _covariance_sums,
    _covariance_sums_stacked,
    _harris_impl,
    _min_eigen_impl,
    _response_impl,
    _safe_sqrt,
    check_block,
)
from .selection import _greedy_accept, _nms_candidates, _resolve_rounds, _select_corners  # noqa: F401
from .selection_capturable import (  # noqa: F401
    _I64_MIN,
    GFTT_BUDGET,
    GreedyBudget,
    _disc_spans,
    _distance_threshold,
    _greedy_capturable,
    _iota,
    _lower,
    _pair_conflicts,
    _pixel_table,
    _resolve_dense,
    _select_corners_capturable,
    _select_from_keys,
    _stream_offsets,
)

__all__ = ["min_eigen_response", "harris_response", "good_features_to_track"]


def _select_keys_gftt(keys, mc, min_distance, H, W, K):
    """The fused op's CUDA selection: :func:`_select_from_keys` with :data:`GFTT_BUDGET`, float32 points."""
    return _select_from_keys(keys, mc, min_distance, H, W, K, GFTT_BUDGET, torch.float32)


def _register_selection() -> None:
    from ..fused.corners_op import set_selection

    set_selection(_select_keys_gftt)


_register_selection()


def min_eigen_response(img: torch.Tensor, block_size: int = 3) -> torch.Tensor:
    """Smaller eigenvalue of the gradient covariance, as ``cv2.cornerMinEigenVal(img, block_size, 3)``.

    Convention:
        Sobel aperture 3, BORDER_REFLECT_101 for the derivatives and the un-normalised
        ``block_size`` box sum; derivatives scaled by OpenCV's ``1 / (4 * block_size * 255)``
        (grey levels are taken as 8-bit for float input too). Differentiable (float input).

    Args:
        img: ``(B, 1, H, W)`` or ``(B, H, W)``, uint8 or float 0..255.
        block_size: neighbourhood size (3 in goodFeaturesToTrack).

    Returns:
        ``(B, 1, H, W)`` response in the image's float dtype (float32 for uint8).
    """
    x = as_image_batch(img, "img")
    check_block(x.shape[-2], x.shape[-1], int(block_size))
    return _response_impl(x, False, int(block_size), 0.0)  # k: Harris only


def harris_response(img: torch.Tensor, block_size: int = 3, k: float = 0.04) -> torch.Tensor:
    """Harris response ``det - k * trace²``, as ``cv2.cornerHarris(img, block_size, 3, k)``.

    Convention: as :func:`min_eigen_response` (same derivative scale). Differentiable.

    Returns:
        ``(B, 1, H, W)`` in the image's float dtype (float32 for uint8).
    """
    x = as_image_batch(img, "img")
    check_block(x.shape[-2], x.shape[-1], int(block_size))
    return _response_impl(x, True, int(block_size), float(k))


def _mask_batch(mask: torch.Tensor | None, B: int, H: int, W: int, device) -> torch.Tensor | None:
    """``mask``: None, (H, W), (B, H, W) or (B, 1, H, W); non-zero = allowed -> (B, H, W) bool
    (None stays None: no mask)."""
    if mask is None:
        return None
    if not isinstance(mask, torch.Tensor):
        raise TypeError(f"mask: expected a torch.Tensor, got {type(mask).__name__}")
    m = mask
    if m.dim() == 4 and m.shape[1] == 1:
        m = m[:, 0]
    # the shape is checked before a 2-D mask is expanded to B streams (expand's own error names no mask)
    if not (tuple(m.shape) == (H, W) or tuple(m.shape) == (B, H, W)):
        raise ValueError(f"mask: expected shape (H, W), (B, H, W) or (B, 1, H, W) with B={B}, H={H}, W={W}, "
                         f"got {tuple(mask.shape)}")
    if m.dim() == 2:
        m = m.unsqueeze(0).expand(B, H, W)
    return (m != 0).to(device)


def good_features_to_track(
    img: torch.Tensor,
    max_corners: Union[int, torch.Tensor],
    quality_level: float = 0.01,
    min_distance: float = 30,
    mask: torch.Tensor | None = None,
    use_harris: bool = False,
    block_size: int = 3,
    k: float = 0.04,
    capacity: int | None = None,
) -> Tuple[torch.Tensor, torch.Tensor]:
    """Shi-Tomasi / Harris corners, as ``cv2.goodFeaturesToTrack`` (spec §5.2), batched.

    Convention:
        Per stream: ``maxVal`` = max response over the mask's non-zero pixels; responses
        ``<= quality_level * maxVal`` are zeroed; candidates are non-zero pixels equal to their
        3x3 dilation, with ``x in [1, W-2]``, ``y in [1, H-2]`` and ``mask != 0``; sorted by
        response descending, ties later raster position first; greedily accepted when no accepted
        corner is closer than ``min_distance`` (``d² < min_distance²``, OpenCV's grid of cell
        ``cvRound(min_distance)``; no distance test when ``min_distance < 1``); at most
        ``max_corners`` per stream. ``max_corners <= 0`` gives no corners (unlike OpenCV, where it
        means unlimited: VINS only calls with ``n_max > 0``). All candidates are considered (no
        cap), so the result is exactly OpenCV's up to response ties (see :mod:`.selection`).

    Args:
        img: ``(B, 1, H, W)`` or ``(B, H, W)``, uint8 or float 0..255.
        max_corners: int, or ``(B,)`` integer tensor (each stream its own count).
        quality_level: relative threshold (0.01 in VINS).
        min_distance: minimum corner distance in pixels (``MIN_DIST``).
        mask: optional ``(H, W)``, ``(B, H, W)`` or ``(B, 1, H, W)``; non-zero = allowed.
        use_harris, block_size, k: as OpenCV.
        capacity: output size K; default ``max(max_corners)`` (a host sync when a tensor).

    Returns:
        pts: ``(B, K, 2)`` float (response dtype), integer pixel positions ``(x, y)``, descending
        response. valid: ``(B, K)`` bool; invalid lanes hold 0.
    """
    x = as_image_batch(img, "img")
    B, _, H, W = x.shape
    check_block(H, W, int(block_size))
    res = _good_features_impl(x, _max_corners(max_corners, B, x.device), float(quality_level),
                              float(min_distance), _mask_batch(mask, B, H, W, x.device), bool(use_harris),
                              int(block_size), float(k), None if capacity is None else int(capacity))
    return res.pts, res.valid


def _max_corners(max_corners: Union[int, torch.Tensor], B: int, device) -> torch.Tensor:
    """An int or a ``(B,)`` integer tensor -> ``(B,)`` int64 >= 0."""
    mc = torch.as_tensor(max_corners, device=device)
    if mc.dim() == 0:
        mc = mc.expand(B)
    elif tuple(mc.shape) != (B,):
        raise ValueError(f"max_corners: expected an int or shape ({B},), got {tuple(mc.shape)}")
    return mc.long().clamp_min(0)


class CornersResult(NamedTuple):
    """What :func:`_good_features_impl` returns, on both paths.

    Attributes:
        pts: ``(B, K, 2)`` float (the response's dtype), integer pixel positions ``(x, y)`` in
            descending response order; invalid lanes hold 0.
        valid: ``(B, K)`` bool.
        overflow: ``(B,)`` bool on the capturable path (True where the fixed budget was too small
            for OpenCV's exact answer), None on the default path.
    """

    pts: torch.Tensor
    valid: torch.Tensor
    overflow: Optional[torch.Tensor]


def _good_features_impl(
    img: torch.Tensor,
    max_corners: torch.Tensor,
    quality_level: float,
    min_distance: float,
    mask: torch.Tensor | None,
    use_harris: bool,
    block_size: int,
    k: float,
    capacity: int | None,
    *,
    capturable: bool = False,
    budget: Optional[GreedyBudget] = None,
    backend: str = "tensor",
) -> CornersResult:
    """:func:`good_features_to_track` without input checks (the kernel's ``_impl``).

    Args:
        img: ``(B, 1, H, W)`` uint8 or float grey levels 0..255 (sizes: :func:`check_block`).
        max_corners: ``(B,)`` int64 >= 0, corners per stream.
        quality_level, min_distance: as OpenCV (``min_distance`` in pixels).
        mask: ``(B, H, W)`` bool (True = allowed) or None (everywhere).
        use_harris, block_size, k: the response (Harris with ``k``, else the min eigenvalue).
        capacity: output size K, or None for ``max(max_corners)`` (a host sync; not with
            ``capturable``).
        capturable: False: the exact, host-driven selection (all candidates, rounds until
            resolved, CPU stream groups). True: shape-static and free of host syncs, with a kernel
            count independent of B and of the data: the ``budget.block`` best candidates per
            stream and a fixed number of greedy rounds (:func:`_select_corners_capturable`).
        budget: the fixed work of the capturable path (default :data:`GFTT_BUDGET`).
        backend: ``"fused"``: the ``torch_frontend::good_features`` op where it applies
            (``fused.corners_op.fused_corners_applies``: uint8, min eigenvalue, block 3; the
            budget the default one), the same corners; ``"tensor"`` (default): the tensor kernels.
            Resolved by the caller (``fused.resolve_corner_backend``).

    Returns:
        A :class:`CornersResult`: ``pts (B, K, 2)`` float and ``valid (B, K)`` bool as
        :func:`good_features_to_track`; ``overflow`` ``(B,)`` bool with ``capturable`` (True where
        the budget was too small for OpenCV's exact answer; elsewhere the result equals the default
        path's), None on the default path (exact).
    """
    if backend == "fused" and budget is None:
        res = _fused_gftt(img, max_corners, quality_level, min_distance, mask, use_harris, block_size, capacity,
                          capturable)
        if res is not None:
            return res
    if not capturable:
        resp = _response_impl(img, use_harris, block_size, k)[:, 0].detach()
        return CornersResult(*_select_corners(resp, max_corners, quality_level, min_distance, mask, capacity), None)
    if capacity is None:
        raise ValueError("_good_features_impl: capturable=True needs an int capacity (the output size)")
    # one pass over the batch (the CPU stream groups are host-side strategy); a uint8 image as it is:
    # the stacked sums take it in exact integer passes (responses._covariance_sums_integral)
    resp = _harris_impl(img, block_size, k, True) if use_harris else _min_eigen_impl(img, block_size, True)
    resp = resp[:, 0].detach()
    # a uint8 image's response is finite (integer sums below 2**24; no NaN; Harris: a finite k)
    return CornersResult(*_select_corners_capturable(resp, max_corners, quality_level, min_distance, mask,
                                                     int(capacity), GFTT_BUDGET if budget is None else budget,
                                                     finite=img.dtype == torch.uint8 and math.isfinite(k)))


def _fused_gftt(img: torch.Tensor, max_corners: torch.Tensor, quality_level: float, min_distance: float,
                mask: torch.Tensor | None, use_harris: bool, block_size: int, capacity: int | None,
                capturable: bool) -> Optional[CornersResult]:
    """The fused op's result for :func:`_good_features_impl`'s arguments, or None where it does not apply
    (or, on the default path on CUDA, where its fixed selection budget overflowed: the exact tensor
    path then runs)."""
    from ..fused.corners_op import fused_corners_applies, good_features_op

    if not fused_corners_applies(img, use_harris, block_size, quality_level):
        return None
    if capacity is None:
        if capturable:
            raise ValueError("_good_features_impl: capturable=True needs an int capacity (the output size)")
        capacity = int(max_corners.max()) if max_corners.numel() else 0  # host sync, as the tensor path
    x = img[:, 0] if img.dim() == 4 else img
    pts, valid, overflow = good_features_op(x, max_corners, mask, int(capacity), float(quality_level),
                                            float(min_distance))
    if capturable:
        return CornersResult(pts, valid, overflow)
    if img.device.type != "cpu" and bool(overflow.any()):  # the CPU kernel is exact (never overflows)
        return None
    return CornersResult(pts, valid, None)


def _gftt_from_response(
    resp: torch.Tensor,
    max_corners: Union[int, torch.Tensor],
    quality_level: float,
    min_distance: float,
    mask: torch.Tensor | None,
    capacity: int | None,
    *,
    capturable: bool = False,
    budget: Optional[GreedyBudget] = None,
) -> CornersResult:
    """GFTT selection on a response map ``resp`` (B, H, W) float, inputs as
    :func:`good_features_to_track` (checked and normalised here); ``capturable``, ``budget`` and
    the result as :func:`_good_features_impl` (``capacity`` required with ``capturable``)."""
    B, H, W = resp.shape
    mc = _max_corners(max_corners, B, resp.device)
    m = _mask_batch(mask, B, H, W, resp.device)
    if capturable:
        if capacity is None:
            raise ValueError("_gftt_from_response: capturable=True needs an int capacity")
        return CornersResult(*_select_corners_capturable(resp, mc, float(quality_level), float(min_distance), m,
                                                         int(capacity), GFTT_BUDGET if budget is None else budget))
    return CornersResult(*_select_corners(resp, mc, float(quality_level), float(min_distance), m,
                                          None if capacity is None else int(capacity)), None)


