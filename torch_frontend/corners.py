"""Corner responses and Shi-Tomasi detection, as OpenCV's ``cornerMinEigenVal`` / ``cornerHarris`` /
``goodFeaturesToTrack`` (spec §5.2), batched over streams.

Scale of the responses (OpenCV ``cornerEigenValsVecs``): the Sobel derivatives are multiplied by
``scale = 1 / (2**(aperture - 1) * block_size * 255)`` for 8-bit input, i.e. ``1 / 3060`` for
aperture 3 and block 3 (confirmed against cv2 4.14: responses agree to ~2.4e-7 of the image
maximum); the response is therefore ``scale**2`` times the eigenvalue of the raw integer Sobel
sums. We apply the same scale (to float images too: grey levels are always taken as 8-bit
0..255), so values equal OpenCV's without rescaling. The derivatives and their box sums are
computed un-scaled (integers, exact in float32 for 8-bit images) and scaled once at the end,
which keeps OpenCV's exact ties exact.

Detection (``good_features_to_track``) follows OpenCV: threshold relative to the maximum inside
the mask, 3x3 dilation NMS with equality, 1-pixel border, descending response with ties broken
by later raster position first (OpenCV's ``greaterThanPtr``), then greedy minimum-distance
acceptance including OpenCV's grid detail (a conflict needs ``d² < min_distance²`` *and* the two
corners in the same or adjacent cells of size ``cvRound(min_distance)``). The greedy pass is
tensor code: candidates are processed in rank chunks (128, 256, then 512) and, within a chunk,
the survivors of the test against earlier accepted corners in parallel rounds (see
``_resolve_rounds``), which gives exactly the sequential result. There is no candidate cap: on
EuRoC frames (CLAHE, quality 0.01) there are ~5200-6400 candidates per frame and OpenCV's 150th
corner is found at rank ~1500-1900, i.e. ~5 chunks; work stops at the chunk where every stream
has its ``max_corners``. Measured on the 24 repo frames: identical corners in identical order to
``cv2.goodFeaturesToTrack``.

Speed (CPU, 1 thread): the candidates of all streams are one flat list (NMS by 1-D shifted
maxima, one ``nonzero``, two stable sorts), and image-sized passes run on groups of streams of
about one 752x480 frame (``_tuning.Strategy.corner_streams``), so temporaries stay cache-sized;
see ``benchmarks/bench_image.py``.

Capturable path (``_good_features_impl(..., capturable=True)``, for CUDA graphs / a whole-step
compile): no host syncs and a fixed op sequence. The candidates of each stream are ranked by one
top-k of a unique integer key (OpenCV's order and tie order) and a fixed :class:`GreedyBudget`
replaces the data-dependent chunks and rounds; an ``overflow (B,)`` flag says where the budget
was too small for OpenCV's exact answer, and wherever it is False the corners are the default
path's, bit for bit. The budget is sized from measured maxima (:data:`GFTT_BUDGET`).

Layers: the public functions check and normalise their inputs and call the ``_impl`` layer
(:func:`_response_impl`, :func:`_good_features_impl`), which a pipeline that validated once calls
directly.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple, Optional, Tuple, Union

import torch
import torch.nn.functional as F

from . import _tuning
from ._checks import as_image_batch
from .errors import ConfigError

__all__ = ["min_eigen_response", "harris_response", "good_features_to_track"]


def check_block(height: int, width: int, block_size: int) -> None:
    """The size checks of the responses: ``block_size >= 1`` (``ConfigError``) and an image large
    enough for the Sobel border and the reflect-101 box sum (``ValueError``)."""
    if block_size < 1:
        raise ConfigError(f"block_size must be >= 1, got {block_size}")
    H, W = height, width
    if H < 2 or W < 2:
        raise ValueError(f"img: expected H, W >= 2 for the Sobel border, got {(H, W)}")
    lo = block_size // 2
    hi = block_size - 1 - lo
    if max(lo, hi) >= min(H, W):
        raise ValueError(f"img: block_size {block_size} too large for image {(H, W)}")


def _covariance_sums(img: torch.Tensor, block_size: int,
                     stacked: bool = False) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor, float]:
    """Un-scaled Sobel-3 products box-summed over ``block_size``, and OpenCV's derivative scale.

    ``img``: (B, 1, H, W) float (sizes checked by :func:`check_block`). Returns (Sxx, Sxy, Syy)
    each (B, H, W), and ``scale``. The in-place accumulations act on fresh tensors that autograd
    does not save, so this one form is also differentiable. ``stacked``: the three products are
    box-summed as one (B, 3, H, W) tensor (the same operations per element, so the same values,
    in a third of the launches: the capturable path; on the CPU the per-product passes keep the
    buffers cache- and mmap-friendly).
    """
    if stacked:
        return _covariance_sums_stacked(img, block_size)
    H, W = img.shape[-2:]
    lo = block_size // 2
    hi = block_size - 1 - lo
    # reflect-101 (OpenCV BORDER_DEFAULT) == torch 'reflect'. Separable Sobel by slicing: adds
    # are exact for integer grey levels and, done in place, much cheaper on CPU than a conv2d
    # with one input channel (fewer fresh full-size buffers).
    xp = F.pad(img, (1, 1, 1, 1), mode="reflect")
    hx = xp[..., :, 2:] - xp[..., :, :-2]  # [-1, 0, 1] along x, (B, 1, H+2, W)
    hs = torch.add(xp[..., :, :-2], xp[..., :, 1:-1], alpha=2.0)  # [1, 2, 1] along x
    hs += xp[..., :, 2:]
    dx = torch.add(hx[..., :-2, :], hx[..., 1:-1, :], alpha=2.0)
    dx += hx[..., 2:, :]
    dy = hs[..., 2:, :] - hs[..., :-2, :]
    del hx, hs, xp
    # one product at a time (not a 3-channel cat): buffers stay below glibc's mmap threshold,
    # so big temporaries are recycled instead of page-faulted in on every call.
    sums = []
    for u, w in ((dx, dx), (dx, dy), (dy, dy)):
        prod = (u * w)[:, 0]
        if block_size == 1:
            sums.append(prod)
            continue
        # un-normalised box sum, anchor at ksize // 2 like OpenCV (Point(-1, -1)), reflect-101
        pp = F.pad(prod[:, None], (lo, hi, lo, hi), mode="reflect")[:, 0]
        del prod
        rows = pp[:, 0:H, :].clone()
        for i in range(1, block_size):  # loop over kernel taps
            rows += pp[:, i:i + H, :]
        del pp
        S = rows[..., 0:W].clone()
        for i in range(1, block_size):
            S += rows[..., i:i + W]
        sums.append(S)
    del dx, dy
    scale = 1.0 / (4.0 * block_size * 255.0)  # 2**(aperture-1) * block * 255, aperture 3
    return sums[0], sums[1], sums[2], scale


def _covariance_sums_stacked(img: torch.Tensor, block_size: int) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor, float]:
    """:func:`_covariance_sums` with the three products in one tensor (see there)."""
    H, W = img.shape[-2:]
    lo = block_size // 2
    hi = block_size - 1 - lo
    xp = F.pad(img, (1, 1, 1, 1), mode="reflect")
    hx = xp[..., :, 2:] - xp[..., :, :-2]
    hs = torch.add(xp[..., :, :-2], xp[..., :, 1:-1], alpha=2.0)
    hs += xp[..., :, 2:]
    dx = torch.add(hx[..., :-2, :], hx[..., 1:-1, :], alpha=2.0)
    dx += hx[..., 2:, :]
    dy = hs[..., 2:, :] - hs[..., :-2, :]
    prod = torch.cat((dx, dx, dy), 1) * torch.cat((dx, dy, dy), 1)  # (B, 3, H, W): xx, xy, yy
    if block_size > 1:
        pp = F.pad(prod, (lo, hi, lo, hi), mode="reflect")
        rows = pp[:, :, 0:H, :].clone()
        for i in range(1, block_size):
            rows += pp[:, :, i:i + H, :]
        prod = rows[..., 0:W].clone()
        for i in range(1, block_size):
            prod += rows[..., i:i + W]
    scale = 1.0 / (4.0 * block_size * 255.0)
    return prod[:, 0], prod[:, 1], prod[:, 2], scale


def _safe_sqrt(x: torch.Tensor) -> torch.Tensor:
    # sqrt'(0) is infinite: flat regions ((a-c)² + b² == 0) would give inf/NaN gradients. The
    # inner where keeps the untaken branch finite, so the gradient there is exactly 0.
    pos = x > 0
    return torch.where(pos, torch.sqrt(torch.where(pos, x, torch.ones_like(x))), torch.zeros_like(x))


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


def _as_float(x: torch.Tensor) -> torch.Tensor:
    """Grey levels as float (float32 for uint8; a float image as it is)."""
    return x if x.is_floating_point() else x.to(torch.float32)


def _response_impl(img: torch.Tensor, use_harris: bool, block_size: int, k: float) -> torch.Tensor:
    """Min-eigenvalue (``use_harris=False``) or Harris response of ``img`` ``(B, 1, H, W)`` uint8 or
    float 0..255 -> ``(B, 1, H, W)`` float, no input checks (sizes: :func:`check_block`; ``k`` is
    used by Harris only).

    On the CPU without autograd the streams are processed in groups
    (``_tuning.Strategy.corner_streams``): the response needs ~10 image-sized temporaries, which
    for a whole batch fall out of cache and above glibc's mmap threshold (fresh buffers are
    page-faulted in on every call). The values are those of one pass.
    """
    def fn(x):
        return _harris_impl(x, block_size, k) if use_harris else _min_eigen_impl(x, block_size)

    B, _, H, W = img.shape
    per = _tuning.for_device(img.device).corner_streams(B, H, W)
    if per is None or img.requires_grad:
        return fn(_as_float(img))
    out = None
    for b0 in range(0, B, per):
        r = fn(_as_float(img[b0:b0 + per]))  # uint8 -> float per group, too
        if out is None:
            out = r.new_empty((B,) + tuple(r.shape[1:]))
        out[b0:b0 + per] = r
    return out


def _min_eigen_impl(x: torch.Tensor, block_size: int, stacked: bool = False) -> torch.Tensor:
    sxx, sxy, syy, s = _covariance_sums(x, block_size, stacked)
    # lambda_min = ((Sxx + Syy) - sqrt((Sxx - Syy)² + 4 Sxy²)) / 2 on the un-scaled sums, times
    # scale² once (OpenCV scales first; the difference is ~1e-7 relative, and equal sums still
    # give exactly equal responses, which keeps OpenCV's ties). The in-place steps act on fresh
    # tensors autograd does not save; only the square root has a reference form (finite gradients
    # where the discriminant is 0), which equals ``sqrt_`` wherever the input is finite.
    disc = sxx - syy
    disc = disc * disc
    disc.addcmul_(sxy, sxy, value=4.0)
    root = disc.sqrt_() if _tuning.inplace_ok(disc) else _safe_sqrt(disc)
    return (sxx + syy).sub_(root).mul_(0.5 * s * s).unsqueeze(1)


def harris_response(img: torch.Tensor, block_size: int = 3, k: float = 0.04) -> torch.Tensor:
    """Harris response ``det - k * trace²``, as ``cv2.cornerHarris(img, block_size, 3, k)``.

    Convention: as :func:`min_eigen_response` (same derivative scale). Differentiable.

    Returns:
        ``(B, 1, H, W)`` in the image's float dtype (float32 for uint8).
    """
    x = as_image_batch(img, "img")
    check_block(x.shape[-2], x.shape[-1], int(block_size))
    return _response_impl(x, True, int(block_size), float(k))


def _harris_impl(x: torch.Tensor, block_size: int, k: float, stacked: bool = False) -> torch.Tensor:
    sxx, sxy, syy, s = _covariance_sums(x, block_size, stacked)
    s2 = s * s
    a = sxx * s2
    b = sxy * s2
    c = syy * s2
    return (a * c - b * b - k * (a + c) * (a + c)).unsqueeze(1)


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
        cap), so the result is exactly OpenCV's up to response ties (see module docstring).

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
    return _good_features_impl(x, _max_corners(max_corners, B, x.device), float(quality_level),
                               float(min_distance), _mask_batch(mask, B, H, W, x.device), bool(use_harris),
                               int(block_size), float(k), None if capacity is None else int(capacity))


def _max_corners(max_corners: Union[int, torch.Tensor], B: int, device) -> torch.Tensor:
    """An int or a ``(B,)`` integer tensor -> ``(B,)`` int64 >= 0."""
    mc = torch.as_tensor(max_corners, device=device)
    if mc.dim() == 0:
        mc = mc.expand(B)
    elif tuple(mc.shape) != (B,):
        raise ValueError(f"max_corners: expected an int or shape ({B},), got {tuple(mc.shape)}")
    return mc.long().clamp_min(0)


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
) -> tuple:
    """:func:`good_features_to_track` without input checks.

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
            stream and a fixed number of greedy rounds (:func:`_select_corners_static`).
        budget: the fixed work of the capturable path (default :data:`GFTT_BUDGET`).

    Returns:
        ``pts (B, K, 2)`` float, ``valid (B, K)`` bool, as :func:`good_features_to_track`; with
        ``capturable`` also ``overflow (B,)`` bool: True where the budget was too small for
        OpenCV's exact answer (elsewhere the result equals the default path's).
    """
    if not capturable:
        resp = _response_impl(img, use_harris, block_size, k)[:, 0].detach()
        return _select_corners(resp, max_corners, quality_level, min_distance, mask, capacity)
    if capacity is None:
        raise ValueError("_good_features_impl: capturable=True needs an int capacity (the output size)")
    x = _as_float(img)  # one pass over the batch (the CPU stream groups are host-side strategy)
    resp = _harris_impl(x, block_size, k, True) if use_harris else _min_eigen_impl(x, block_size, True)
    resp = resp[:, 0].detach()
    return _select_corners_static(resp, max_corners, quality_level, min_distance, mask, int(capacity),
                                  GFTT_BUDGET if budget is None else budget)


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
) -> tuple:
    """GFTT selection on a response map ``resp`` (B, H, W) float, inputs as
    :func:`good_features_to_track` (checked and normalised here); ``capturable`` and ``budget``
    as :func:`_good_features_impl` (``capacity`` required then)."""
    B, H, W = resp.shape
    mc = _max_corners(max_corners, B, resp.device)
    m = _mask_batch(mask, B, H, W, resp.device)
    if capturable:
        if capacity is None:
            raise ValueError("_gftt_from_response: capturable=True needs an int capacity")
        return _select_corners_static(resp, mc, float(quality_level), float(min_distance), m, int(capacity),
                                      GFTT_BUDGET if budget is None else budget)
    return _select_corners(resp, mc, float(quality_level), float(min_distance), m,
                           None if capacity is None else int(capacity))


def _select_corners(
    resp: torch.Tensor,
    mc: torch.Tensor,
    quality_level: float,
    min_distance: float,
    m: torch.Tensor | None,
    capacity: int | None,
) -> Tuple[torch.Tensor, torch.Tensor]:
    """GFTT selection on ``resp`` (B, H, W) float with ``mc`` (B,) int64 >= 0 corners per stream and
    ``m`` (B, H, W) bool or None; no input checks. See :func:`good_features_to_track`."""
    B, H, W = resp.shape
    dev = resp.device
    K = capacity if capacity is not None else (int(mc.max()) if B > 0 else 0)
    out_pts = torch.zeros(B, K, 2, dtype=resp.dtype, device=dev)
    out_valid = torch.zeros(B, K, dtype=torch.bool, device=dev)
    if K <= 0 or B == 0:
        return out_pts, out_valid
    mc = mc.clamp_max(K)
    strategy = _tuning.for_device(dev)

    # max inside the mask (VINS-Fusion-gpu#25); an empty mask gives maxVal 0 like minMaxLoc.
    if m is None:
        max_val = resp.flatten(1).amax(1)
    else:
        max_val = torch.where(m, resp, float("-inf")).flatten(1).amax(1)
    max_val = torch.where(torch.isfinite(max_val), max_val, torch.zeros_like(max_val))
    # threshold() on a float32 image casts its double threshold to float
    thr = (max_val.double() * float(quality_level)).to(resp.dtype)
    # candidates: t != 0 and t == its 3x3 dilation (border excluded), t = resp thresholded to 0.
    # On CPU by groups of streams (as _response_impl: image-sized temporaries stay cache-sized).
    # The candidates of all streams form one flat list of indices into (B*H*W,), raster order
    # (nonzero: one host sync per group, for its length).
    per = strategy.corner_streams(B, H, W) or B
    flats = []
    for b0 in range(0, B, per):
        r = resp[b0:b0 + per]
        t = torch.where(r > thr[b0:b0 + per, None, None], r, 0.0)
        cand = _nms_candidates(t)
        if m is not None:
            cand &= m[b0:b0 + per]
        f = cand.view(-1).nonzero().squeeze(1)
        flats.append(f + b0 * H * W if b0 else f)
    flat = flats[0] if len(flats) == 1 else torch.cat(flats)
    if flat.numel() == 0:
        return out_pts, out_valid
    # order per stream: response descending, ties later raster index first (greaterThanPtr)
    v = resp.reshape(-1)[flat]  # == t at candidates (t != 0 there)
    ib = max(1, (H * W - 1).bit_length())  # bits of a raster index
    if resp.dtype == torch.float32 and 32 + ib + max(1, (B - 1).bit_length()) <= 62:
        # one sort of a unique int64 key (stream, value descending, raster index descending).
        # float32 bits -> int with the same order (negative values: flip the magnitude bits)
        bits = v.view(torch.int32).to(torch.int64)
        bits = bits ^ ((bits >> 31) & 0x7FFFFFFF)
        b = torch.div(flat, H * W, rounding_mode="floor")
        pix = flat - b * (H * W)
        key = (b << (32 + ib)) + ((0x7FFFFFFF - bits) << ib) + ((1 << ib) - 1 - pix)
        o = torch.sort(key).indices
        b, pix = b[o], pix[o]
    else:
        # general: flip (-> stream and raster index descending), stable sort by value
        # descending, stable sort by stream ascending
        flat = flat.flip(0)
        flat = flat[torch.sort(v.flip(0), descending=True, stable=True).indices]
        b = torch.div(flat, H * W, rounding_mode="floor")
        sb = torch.sort(b, stable=True)
        b = sb.values
        flat = flat[sb.indices]
        pix = flat - b * (H * W)
    counts = torch.bincount(b, minlength=B)
    M = int(counts.max())  # host sync: the candidate count decides the work
    rank = torch.arange(flat.numel(), device=dev) - (torch.cumsum(counts, 0) - counts)[b]
    slot = b * M + rank
    pos_flat = torch.zeros(B * M, 2, dtype=torch.long, device=dev)
    pos_flat[slot, 0] = pix % W
    pos_flat[slot, 1] = torch.div(pix, W, rounding_mode="floor")
    cvalid = torch.zeros(B * M, dtype=torch.bool, device=dev)
    cvalid[slot] = True
    pos = pos_flat.view(B, M, 2)  # (B, M, 2) long, rank order
    cvalid = cvalid.view(B, M)

    accepted = _greedy_accept(pos, cvalid, mc, min_distance, strategy.gftt_chunk, strategy.gftt_chunk_max)

    # cut at max_corners by rank and compact into (B, K)
    rank = torch.cumsum(accepted.long(), 1) - 1
    keep = accepted & (rank < mc[:, None])
    slot = torch.where(keep, rank, torch.full_like(rank, K))  # K = dump slot
    pts_buf = torch.zeros(B, K + 1, 2, dtype=resp.dtype, device=dev)
    pts_buf.scatter_(1, slot[..., None].expand(B, M, 2), pos.to(resp.dtype))
    val_buf = torch.zeros(B, K + 1, dtype=torch.bool, device=dev)
    val_buf.scatter_(1, slot, keep)
    out_valid = val_buf[:, :K]
    out_pts = torch.where(out_valid[..., None], pts_buf[:, :K], torch.zeros_like(pts_buf[:, :K]))
    return out_pts, out_valid


def _resolve_rounds(conf_t: torch.Tensor, und: torch.Tensor) -> torch.Tensor:
    """Greedy acceptance in parallel rounds.

    ``conf_t`` (B, C, C) float 0/1, *transposed* conflicts: ``conf_t[b, j, i] = 1`` iff j is
    ranked above i and accepting j excludes i. ``und`` (B, C) bool: candidates still to decide
    (others are out). Returns accepted (B, C): i accepted iff no accepted j conflicts with it -
    the sequential greedy result. Each round rejects candidates with an accepted higher conflict
    and accepts those whose higher conflicts are all decided; the highest undecided one is
    always decided, and real data needs a handful of rounds (one host check each).
    """
    acc = torch.zeros_like(und)
    if not bool(und.any()):
        return acc
    # state rows: [accepted, undecided] as 0/1 floats
    state = torch.zeros(und.shape[0], 2, und.shape[1], dtype=conf_t.dtype, device=und.device)
    state[:, 1] = und
    while True:
        # one (B, 2, C) x (B, C, C) matmul answers both questions for every i: any accepted /
        # any undecided higher conflict (this layout is ~4x faster on CPU than (B, C, C) x
        # (B, C, 2); counts are small integers, exact in float32)
        blocked, waiting = (torch.bmm(state, conf_t) > 0).unbind(1)
        und = und & ~blocked  # rejected: an accepted higher conflict
        acc |= und & ~waiting  # accepted: every higher conflict decided, none accepted
        und &= waiting
        if not bool(und.any()):
            return acc
        state[:, 0] = acc
        state[:, 1] = und


def _nms_candidates(t: torch.Tensor) -> torch.Tensor:
    """``t != 0 & t == dilate3x3(t)`` of (B, H, W), False on the 1-pixel image border.

    The 3x3 max is taken on the flat (B*H*W,) buffer with 1-D shifts (contiguous, vectorised
    maxima; ~10x faster on CPU than 2-D slices or ``max_pool2d``). A shift by one mixes the end
    of a row with the start of the next, and a shift by W mixes streams, but only in windows
    centred on border pixels, which are never candidates.
    """
    B, H, W = t.shape
    cand = torch.zeros(B, H, W, dtype=torch.bool, device=t.device)
    N = B * H * W
    if H < 3 or W < 3:
        return cand
    f = t.reshape(-1)
    r = torch.maximum(f[:-2], f[1:-1])  # r[j]: row max centred on j + 1
    r = torch.maximum(r, f[2:], out=r)
    d = torch.maximum(r[:-2 * W], r[W:-W])  # d[k]: 3x3 max centred on k + W + 1
    d = torch.maximum(d, r[2 * W:], out=d)
    centre = f[W + 1:N - W - 1]
    c = cand.view(-1)[W + 1:N - W - 1]
    torch.eq(centre, d, out=c)
    c &= centre != 0
    # fill_ on views, not ``cand[...] = False`` (a Python scalar is uploaded as a tensor first)
    cand[:, ::H - 1, :].fill_(False)  # rows 0 and H - 1
    cand[:, :, ::W - 1].fill_(False)  # columns 0 and W - 1
    return cand


def _greedy_accept(pos: torch.Tensor, cvalid: torch.Tensor, mc: torch.Tensor, min_distance: float,
                   chunk: int, chunk_max: int) -> torch.Tensor:
    """Exact sequential greedy minimum-distance acceptance, in tensor rounds.

    ``pos`` (B, M, 2) integer pixel positions in rank order, ``cvalid`` (B, M), ``mc`` (B,) the
    per-stream corner budget (acceptance stops mattering once a stream has ``mc`` corners).
    Returns ``accepted`` (B, M) bool: candidate i accepted iff no *accepted* higher-ranked
    candidate conflicts with it - exactly OpenCV's sequential loop.

    Candidates are processed in rank chunks of ``chunk``, doubling up to ``chunk_max`` (speed and
    memory only: ``_tuning.Strategy.gftt_chunk``). A
    chunk's candidates first test the corners accepted in earlier chunks (a fixed buffer of
    max(mc) slots); the survivors are compacted (rank order kept) and resolve among themselves
    in rounds: every undecided candidate with an accepted higher
    conflict is rejected; every undecided candidate whose higher conflicts are all decided (none
    accepted) is accepted. By induction on rank this is the greedy result, and each round
    decides at least the highest undecided candidate. Chunks stop once every stream has its
    ``mc`` corners or has run out of candidates (one host check per chunk and per round).
    """
    B, M, _ = pos.shape
    dev = pos.device
    accepted = torch.zeros(B, M, dtype=torch.bool, device=dev)
    if min_distance < 1:
        # OpenCV: no distance test, simply the first max_corners candidates
        return cvalid.clone()
    cell = int(round(min_distance))  # cvRound (half to even)
    r2i = int(math.ceil(min_distance * min_distance))  # integer d²: d² < r²  <=>  d² < ceil(r²)
    # chunks are small, so d² by broadcasting in int32 is cheap (and, unlike a matmul, immune to
    # TF32 on CUDA). Coordinates < 2**15 keep d² < 2**31.
    pi = pos.to(torch.int32) if int(pos.max()) < 32768 else pos
    # separate contiguous x / y: broadcasting strided slices is several times slower on CPU
    xs, ys = pi[..., 0].contiguous(), pi[..., 1].contiguous()
    # OpenCV only looks at the 3x3 neighbouring cells of size cvRound(min_distance); when that
    # rounds down, pairs in cells two apart are not conflicts. Only then test the cells.
    need_cells = cell < min_distance
    gx, gy = xs // cell, ys // cell

    def conflicts(a, b) -> torch.Tensor:
        """a, b: (x, y, cell x, cell y) tuples of (B, Ca) / (B, Cb) -> (B, Ca, Cb) bool."""
        # in place: (B, Ca, Cb) temporaries of several MB at B=8 cost page faults when fresh
        dx = a[0][:, :, None] - b[0][:, None, :]
        dx *= dx
        dy = a[1][:, :, None] - b[1][:, None, :]
        dy *= dy
        dx += dy
        c = dx < r2i
        if need_cells:
            c &= (a[2][:, :, None] - b[2][:, None, :]).abs() <= 1
            c &= (a[3][:, :, None] - b[3][:, None, :]).abs() <= 1
        return c

    # accepted corners of earlier chunks: fixed-capacity buffer of Kcap = max(mc) slots plus a
    # dump slot. A stream only collects while it has < mc <= Kcap corners, so it never needs more.
    kcap = int(mc.max()) if B > 0 else 0
    acc_buf = tuple(torch.zeros(B, kcap + 1, dtype=t.dtype, device=dev) for t in (xs, ys, gx, gy))
    acc_ok = torch.zeros(B, kcap + 1, dtype=torch.bool, device=dev)
    count = torch.zeros(B, dtype=torch.long, device=dev)
    filled = 0  # max(count), capped at kcap (host copy)
    start, size = 0, chunk
    while start < M:
        stop = min(start + size, M)
        # later chunks are mostly rejected by the accepted buffer: grow them (fewer rounds of
        # Python overhead) while the survivors alone enter the quadratic in-chunk resolution
        size = min(2 * size, chunk_max)
        live = count < mc  # streams still collecting
        v = cvalid[:, start:stop] & live[:, None]
        if not bool(v.any()):
            break
        cur = tuple(t[:, start:stop] for t in (xs, ys, gx, gy))
        und = v
        if filled > 0:  # only the filled part of the buffer (slots >= a stream's count are off)
            hit = conflicts(cur, tuple(t[:, :filled] for t in acc_buf))
            hit &= acc_ok[:, None, :filled]
            und = v & ~hit.any(-1)
        S = int(und.sum(1).max())
        if S > 0:
            # compact the survivors (rank order kept) and resolve them among themselves
            order = torch.sort(und.to(torch.uint8), dim=1, descending=True, stable=True).indices[:, :S]
            sur = tuple(torch.gather(t, 1, order) for t in cur)
            sv = torch.gather(und, 1, order)
            conf = conflicts(sur, sur)  # symmetric; transposed layout [j, i] for _resolve_rounds
            conf &= torch.ones(S, S, dtype=torch.bool, device=dev).triu(1)  # j < i: j ranked higher
            conf &= sv[:, :, None]
            acc = _resolve_rounds(conf.to(torch.float32), sv)
            accepted[:, start:stop].scatter_(1, order, acc)
            # append to the buffer in rank order (beyond kcap -> dump slot)
            slot = torch.cumsum(acc, 1) - 1 + count[:, None]
            slot = torch.where(acc & (slot < kcap), slot, kcap)
            for buf, t in zip(acc_buf, sur):
                buf.scatter_(1, slot, t)
            acc_ok.scatter_(1, slot, acc)
            acc_ok[:, kcap] = False
            count += acc.sum(1)
            filled = min(int(count.max()), kcap)
        start = stop
    return accepted


# ---------------------------------------------------------------------------------------------
# The capturable selection (``capturable=True``): shape-static, no host syncs, and a kernel count
# that depends on neither B nor the data. The same rules as :func:`_select_corners`; what the
# default path decides on the host (how many candidates, chunks and rounds) is a fixed budget
# here, and an ``overflow`` flag says where it was too small for OpenCV's exact answer.


class GreedyBudget(NamedTuple):
    """Fixed work of the capturable GFTT selection (per stream and call).

    ``block``: candidates kept per stream, the best in OpenCV's order (one top-k). The greedy
    minimum-distance pass runs in two stages: the ``first`` best candidates resolve among
    themselves in ``rounds_first`` rounds on a dense ``first x first`` conflict matrix; the rest
    of the block is tested against the corners accepted there, and its survivors (rank order
    kept, at most ``survivors`` of them) resolve among themselves in ``rounds`` rounds. Memory
    per stream ~``13 B x (first² + survivors²) + 9 B x block x max_corners``; kernels
    ~``130 + 4 x (rounds_first + rounds)`` per call (response included), whatever B and the data.
    """

    block: int
    first: int
    rounds_first: int
    survivors: int
    rounds: int


#: The tracker's budget: measured maxima with headroom. Measured through these kernels (1,800
#: calls) on what the tracker sees: max_cnt 150, quality 0.01, min_dist 30 / 25 / 20; the calls of
#: mono (CLAHE) and fusion (raw) trackers in steady state, with setMask's masks of the tracked
#: features; and every frame as a first frame (no mask, 150 new corners; CLAHE and raw). Frames:
#: EuRoC mini cam0 / cam1, V1_01 micro cam0 / cam1, the Middlebury pair, the synthetic flight.
#:
#: ==========================================================  =========  ======  ========
#: quantity (max over the calls)                               EuRoC      all     budget
#: ==========================================================  =========  ======  ========
#: candidate rank OpenCV's answer reaches (150th corner, or    1,995      2,763   8,192
#: every candidate where a stream runs out)
#: rounds until every first-stage (1,024) candidate decided    13         13      24
#: second-stage survivors up to the last kept corner           158        283     768
#: rounds until every second-stage survivor decided            11         11      24
#: ==========================================================  =========  ======  ========
#:
#: (the maxima: flight and Middlebury at min_dist 30; rounds: a tight distribution, mode 8.) The
#: kernel count (~320 per call) depends on the rounds only; the bmm of a round reads
#: ``4 B x (first² + survivors²)`` per stream.
GFTT_BUDGET = GreedyBudget(block=8192, first=1024, rounds_first=24, survivors=768, rounds=24)

_I64_MIN = -(1 << 63)


@functools.lru_cache(maxsize=64)
def _upper(n: int, device: torch.device) -> torch.Tensor:
    """(n, n) bool, True on and above the diagonal: ``[j, i]`` with ``j <= i`` in rank (cached)."""
    return torch.ones(n, n, dtype=torch.bool, device=device).triu()


@functools.lru_cache(maxsize=64)
def _pixel_table(height: int, width: int, cell: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """Raster index -> ``(x, y)`` (``cell > 0``: ``(x, y, x // cell, y // cell)``): (H*W, 2 | 4)
    integers, a cached constant (one gather replaces the div / mod / stack per call)."""
    i = torch.arange(height * width, device=device)
    cols = [i % width, torch.div(i, width, rounding_mode="floor")]
    if cell > 0:
        cols += [torch.div(cols[0], cell, rounding_mode="floor"), torch.div(cols[1], cell, rounding_mode="floor")]
    return torch.stack(cols, -1).to(dtype)


@functools.lru_cache(maxsize=64)
def _iota(n: int, device: torch.device) -> torch.Tensor:
    """``arange(n)`` int64 (cached constant)."""
    return torch.arange(n, device=device)


def _resolve_fixed(conf: torch.Tensor, und: torch.Tensor, rounds: int) -> Tuple[torch.Tensor, torch.Tensor]:
    """:func:`_resolve_rounds` with a fixed number of rounds (no host check), 4 kernels a round.

    ``conf`` (B, C, C) bool, transposed conflicts *with the diagonal*: ``conf[b, j, i]`` iff
    ``j <= i`` in rank and j excludes i (every candidate excludes itself). ``und`` (B, C) bool.
    Returns ``accepted`` and ``undecided`` (B, C) bool after ``rounds`` rounds. Every decision
    taken is the sequential greedy one (by induction on rank); all is decided iff ``undecided``
    is empty, and above the first undecided candidate the result is exact.

    One state ``s`` per candidate: 0 rejected, 1 undecided, A accepted (A a power of two > C).
    ``c = s @ conf`` is ``s_i`` plus the higher conflicts' states: an undecided candidate has
    ``c = 1`` when every higher conflict is rejected (accept: s = A), ``2 <= c <= C`` while one is
    undecided (wait), ``c > A`` once one is accepted (reject: s = 0); an accepted one keeps ``c = A``
    (its higher conflicts are all rejected). So ``s *= h(c)`` with ``h = A, 1, 0`` on
    ``c <= 1.5 < c <= A + 0.5 < c``. Integers below 2**24: exact in float32 (TF32 too).
    """
    B, C = und.shape
    A = 1 << max(1, C.bit_length())  # > C
    dt = torch.float32 if (C + 1) * A < (1 << 24) else torch.float64
    dev = und.device
    bounds, table = _round_tables(A, dt, dev)
    s = und.to(dt).unsqueeze(1)  # (B, 1, C)
    conf = conf.to(dt)
    with _no_autocast(dev):  # a lower-precision matmul would not keep the counts exact
        for _ in range(rounds):
            s.mul_(table[torch.bucketize(torch.bmm(s, conf), bounds)])
    s = s.squeeze(1)
    return s == A, s == 1


@functools.lru_cache(maxsize=64)
def _round_tables(A: int, dtype: torch.dtype, device: torch.device) -> Tuple[torch.Tensor, torch.Tensor]:
    """:func:`_resolve_fixed`'s bucket bounds ``(1.5, A + 0.5)`` and factors ``(A, 1, 0)`` (cached)."""
    i = torch.arange(3, device=device, dtype=dtype)  # built on the device (no upload, traceable)
    return i[:2] * (A - 1) + 1.5, torch.where(i == 0, float(A), (i == 1).to(dtype))


def _no_autocast(device: torch.device):
    """A context without autocast for ``device`` when it is on (else a no-op)."""
    import contextlib

    if torch.is_autocast_enabled(device.type):
        return torch.autocast(device.type, enabled=False)
    return contextlib.nullcontext()


def _conflicts(a: torch.Tensor, b: torch.Tensor, r2i: int, cells: bool) -> torch.Tensor:
    """OpenCV's GFTT conflicts of ``a`` (B, Ca, 2 | 4) and ``b`` (B, Cb, 2 | 4) integer ``(x, y[, cell
    x, cell y])`` -> (B, Ca, Cb) bool: ``d² < r2i`` (and, with ``cells``, neighbouring grid cells)."""
    d = a[:, :, None, :2] - b[:, None, :, :2]
    c = d.mul_(d).sum(-1, dtype=d.dtype) < r2i
    if cells:
        c &= (a[:, :, None, 2:] - b[:, None, :, 2:]).abs_().le_(1).all(-1)
    return c


def _greedy_static(xy: torch.Tensor, cvalid: torch.Tensor, mc: torch.Tensor, min_distance: float, kcap: int,
                   budget: GreedyBudget) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`_greedy_accept` with a fixed schedule (:class:`GreedyBudget`'s two stages).

    ``xy`` (B, C, 2 | 4) integer positions (and grid cells) in rank order, ``cvalid`` (B, C),
    ``mc`` (B,) corner budgets <= ``kcap``. Returns ``accepted`` (B, C) bool, ``undecided``
    (B, C) bool (decisions the rounds left open) and ``n_surv`` (B,) (second-stage survivors,
    of which only ``budget.survivors`` are resolved). Every decision taken is the sequential
    greedy one; the result is OpenCV's above the first open decision.
    """
    B, C, nc = xy.shape
    dev = xy.device
    cells = nc == 4
    r2i = int(math.ceil(min_distance * min_distance))  # integer d²: d² < r²  <=>  d² < ceil(r²)
    far = _FAR[xy.dtype]
    F1 = min(budget.first, C)

    # stage 1: the best F1 candidates, dense
    cur = xy[:, :F1]
    und = cvalid[:, :F1] & (mc > 0)[:, None]
    conf = _conflicts(cur, cur, r2i, cells)  # d = 0 on the diagonal: a conflict, as _resolve_fixed wants
    conf &= _upper(F1, dev)
    acc1, left1 = _resolve_fixed(conf, und, budget.rounds_first)
    if F1 == C:
        return acc1, left1, torch.zeros(B, dtype=torch.long, device=dev)

    # the accepted corners in rank order in a (B, kcap + 1) buffer: free slots and the dump slot
    # (beyond kcap, and the rejected) hold a point farther than min_distance from every pixel
    slot = torch.cumsum(acc1, 1).sub_(1).clamp_max_(kcap)
    slot = torch.where(acc1, slot, kcap)
    buf = torch.full((B, kcap + 1, nc), far, dtype=xy.dtype, device=dev)
    buf.scatter_(1, slot[..., None].expand(B, F1, nc), cur)
    buf[:, kcap].fill_(far)
    count = acc1.sum(1)

    # stage 2: the rest, against stage 1's corners; the survivors compacted (rank order kept) into
    # S slots plus a dump slot, resolved among themselves
    rest = xy[:, F1:]
    R = C - F1
    S = min(budget.survivors, R)
    und = cvalid[:, F1:] & (count < mc)[:, None]  # streams still collecting
    und &= ~_conflicts(rest, buf, r2i, cells).any(-1)
    pos = torch.cumsum(und, 1)  # 1-based survivor index
    slot = torch.where(und, (pos - 1).clamp_max_(S), S)
    sur = torch.full((B, S + 1, nc), far, dtype=xy.dtype, device=dev)
    sur.scatter_(1, slot[..., None].expand(B, R, nc), rest)
    sv = torch.zeros(B, S + 1, dtype=torch.bool, device=dev)
    sv.scatter_(1, slot, und)
    sv[:, S].fill_(False)  # the dump slot is never a candidate
    conf = _conflicts(sur, sur, r2i, cells)
    conf &= _upper(S + 1, dev)
    acc2, left2 = _resolve_fixed(conf, sv, budget.rounds)
    accepted = torch.cat((acc1, torch.gather(acc2, 1, slot)), 1)
    undecided = torch.cat((left1, torch.gather(left2, 1, slot)), 1)
    return accepted, undecided, pos[:, -1]


def _select_corners_static(
    resp: torch.Tensor,
    mc: torch.Tensor,
    quality_level: float,
    min_distance: float,
    m: torch.Tensor | None,
    K: int,
    budget: GreedyBudget,
) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`_select_corners` with fixed work (the ``capturable`` path), no input checks.

    The candidates of each stream are ranked by one top-k of a unique integer key (response
    bits, then raster index: OpenCV's order and tie order) and the best ``budget.block`` enter
    :func:`_greedy_static`. Returns ``pts (B, K, 2)``, ``valid (B, K)`` as :func:`_select_corners`
    and ``overflow (B,)`` bool: True where OpenCV's answer needs a candidate beyond the block
    (fewer than ``mc`` corners accepted and more candidates than the block holds) or a decision
    the rounds left open above the ``mc``-th accepted corner. Where False, the result equals
    :func:`_select_corners`'s exactly.
    """
    B, H, W = resp.shape
    dev = resp.device
    HW = H * W
    if K <= 0 or B == 0 or HW == 0:
        return (torch.zeros(B, max(K, 0), 2, dtype=resp.dtype, device=dev),
                torch.zeros(B, max(K, 0), dtype=torch.bool, device=dev), torch.zeros(B, dtype=torch.bool, device=dev))
    mc = mc.clamp_max(K)
    Cb = min(budget.block, HW)

    if m is None:
        max_val = resp.flatten(1).amax(1)
    else:
        max_val = torch.where(m, resp, float("-inf")).flatten(1).amax(1)
    max_val = torch.nan_to_num(max_val, nan=0.0, posinf=0.0, neginf=0.0)  # == where(isfinite, ., 0)
    thr = (max_val.double() * float(quality_level)).to(resp.dtype)
    t = torch.where(resp > thr[:, None, None], resp, 0.0)
    cand = _nms_candidates(t)
    if m is not None:
        cand &= m
    cand = cand.view(B, HW)
    n_cand = cand.sum(1)

    ib = max(1, (HW - 1).bit_length())  # bits of a raster index
    if resp.dtype == torch.float32 and ib <= 31:
        # unique int64 key, larger = earlier in OpenCV's order: float32 bits made order-preserving
        # as signed ints (negative values: flip the magnitude bits), then the raster index (ties:
        # later raster position first)
        bits = resp.reshape(B, HW).view(torch.int32).to(torch.int64)
        bits ^= (bits >> 31) & 0x7FFFFFFF
        key = torch.where(cand, (bits << ib) + _iota(HW, dev), _I64_MIN)
        top = torch.topk(key, Cb, dim=1)
        idx, cvalid = top.indices, top.values != _I64_MIN
    else:
        # general dtype: a stable descending sort of the reversed raster order (ties: later first)
        vals = torch.where(cand, resp.reshape(B, HW), float("-inf")).flip(1)
        srt = torch.sort(vals, dim=1, descending=True, stable=True)
        idx = (HW - 1) - srt.indices[:, :Cb]
        cvalid = srt.values[:, :Cb] != float("-inf")

    if min_distance < 1:  # OpenCV: no distance test, the first max_corners candidates
        xy = _pixel_table(H, W, 0, torch.int32, dev).index_select(0, idx.reshape(-1)).view(B, Cb, 2)
        accepted, undecided = cvalid, None
    else:
        cell = int(round(min_distance))  # cvRound (half to even)
        cells = cell < min_distance  # OpenCV's 3x3 cell neighbourhood matters only then
        # int32 coordinates while d² (also to the far placeholder) stays below 2**31
        cdt = torch.int32 if max(H, W) <= _I32_SPAN and min_distance < -_FAR[torch.int32] else torch.int64
        xy = _pixel_table(H, W, cell if cells else 0, cdt, dev).index_select(0, idx.reshape(-1))
        xy = xy.view(B, Cb, -1)
        accepted, undecided, n_surv = _greedy_static(xy, cvalid, mc, min_distance, K, budget)

    cum = torch.cumsum(accepted, 1)  # (B, Cb) int64: accepted up to and including each rank
    n_acc = cum[:, -1]
    # candidates that were never looked at (beyond the block, or second-stage survivors beyond
    # their slots: all ranked below every resolved one) matter iff fewer than mc corners were found
    short = n_cand > Cb
    if undecided is not None:
        short |= n_surv > min(budget.survivors, max(Cb - budget.first, 0))
    overflow = short & (n_acc < mc)
    if undecided is not None:
        # the first open decision matters iff fewer than mc corners were accepted above it
        overflow |= (undecided & (cum - accepted.long() < mc[:, None])).any(1)
    keep = accepted & (cum <= mc[:, None])
    # compact into (B, K): kept corners at b * K + rank, the rest into one dump slot
    slot = torch.where(keep, cum + _stream_offsets(B, K, dev), B * K)
    out = torch.zeros(B * K + 1, 2, dtype=resp.dtype, device=dev)
    out.index_put_((slot.view(-1),), xy[..., :2].reshape(-1, 2).to(resp.dtype))
    n = torch.minimum(n_acc, mc)
    valid = _iota(K, dev) < n[:, None]
    return out[:B * K].view(B, K, 2), valid, overflow


@functools.lru_cache(maxsize=64)
def _stream_offsets(B: int, K: int, device: torch.device) -> torch.Tensor:
    """``b * K - 1`` per stream, (B, 1) int64 (cached constant): flat slot of rank ``cum - 1``."""
    return (torch.arange(B, device=device) * K - 1)[:, None]


# The far placeholder of the accepted-corner buffer, per coordinate dtype: farther than
# min_distance from every pixel (coordinates >= 0, min_distance < |far|). int32 coordinates up to
# _I32_SPAN keep every d² (to the placeholder too) below 2**31: 2 * (2**14 + 2**13)² < 2**31.
_FAR = {torch.int32: -(1 << 13), torch.int64: -(1 << 28)}
_I32_SPAN = 1 << 14
