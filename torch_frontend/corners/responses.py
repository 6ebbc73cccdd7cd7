"""Corner responses, as OpenCV's ``cornerMinEigenVal`` / ``cornerHarris`` (spec §5.2), batched.

Scale of the responses (OpenCV ``cornerEigenValsVecs``): the Sobel derivatives are multiplied by
``scale = 1 / (2**(aperture - 1) * block_size * 255)`` for 8-bit input, i.e. ``1 / 3060`` for
aperture 3 and block 3 (confirmed against cv2 4.14: responses agree to ~2.4e-7 of the image
maximum); the response is therefore ``scale**2`` times the eigenvalue of the raw integer Sobel
sums. We apply the same scale (to float images too: grey levels are always taken as 8-bit
0..255), so values equal OpenCV's without rescaling. The derivatives and their box sums are
computed un-scaled (integers, exact in float32 for 8-bit images) and scaled once at the end,
which keeps OpenCV's exact ties exact.

Speed (CPU, 1 thread): the Sobel filters are in-place slice sums and the box sums one product at a
time, and the streams run in groups of about one 752x480 frame
(``_tuning.Strategy.corner_streams``), so temporaries stay cache-sized; see
``benchmarks/bench_image.py``. The capturable path computes the three products as one stacked
tensor in one pass over the batch (the same operations per element, so the same values).
"""

from __future__ import annotations

from typing import Tuple

import torch
import torch.nn.functional as F

from .. import _tuning
from ..errors import ConfigError

__all__ = ["check_block"]


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


#: largest box of the exact-integer path (:func:`_covariance_sums_integral`): a Sobel-3 derivative of
#: 8-bit grey levels is an integer of magnitude <= 4 * 255 = 1020, a product <= 1020² = 1,040,400,
#: and a box of ``b²`` products <= b² x 1,040,400, below 2**24 (every integer exact in float32) for
#: b <= 4 (16,646,400 < 16,777,216)
_INTEGRAL_BLOCK_MAX = 4


def _integral_ok(img: torch.Tensor, block_size: int) -> bool:
    """True when :func:`_covariance_sums_integral` applies: a uint8 image (no derivative), a box of
    at most :data:`_INTEGRAL_BLOCK_MAX`, eager (not under the compiler) and not in
    ``_tuning.reference_forms``."""
    return (img.dtype == torch.uint8 and 1 <= block_size <= _INTEGRAL_BLOCK_MAX
            and _tuning.inplace_ok() and not torch.compiler.is_compiling())


def _windows(x: torch.Tensor, dims: Tuple[int, ...], size: Tuple[int, ...], taps: Tuple[Tuple[int, int], ...],
             dtype: torch.dtype | None = None) -> torch.Tensor:
    """Sum over overlapping windows of contiguous ``x``, as one reduction (each element read once):
    the result's dim ``dims[i]`` has size ``size[i]``, and every window dim ``(n, step)`` of ``taps``
    adds ``n`` taps ``step`` elements apart (in ``x``'s flat storage). Two window dims with the same
    step give the taps ``0, step, step, 2 step``: the ``[1, 2, 1]`` smoothing of a Sobel-3."""
    shape = list(x.shape)
    for d, n in zip(dims, size):
        shape[d] = n
    stride = list(x.stride())
    view = x.as_strided(shape + [n for n, _ in taps], stride + [st for _, st in taps])
    return view.sum(tuple(range(len(shape), len(shape) + len(taps))), dtype=dtype)


def _reflect_borders(pp: torch.Tensor, lo: int, hi: int) -> None:
    """Fill the ``lo`` / ``hi`` border rows and columns of ``pp (..., lo + H + hi, lo + W + hi)`` in
    place from its interior as ``F.pad(..., mode="reflect")`` (reflect-101) does: rows first, then
    columns over every row (the corners: reflected twice, as ``F.pad``). A pair of border lines
    ``lo - i`` and ``lo + n - 1 + i`` with their sources ``lo + i`` and ``lo + n - 1 - i`` is one
    strided copy where both exist (one kernel instead of two)."""
    for dim in (-2, -1):
        n = pp.shape[dim] - lo - hi
        for i in range(1, max(lo, hi) + 1):
            top, bot = lo - i, lo + n - 1 + i
            if i <= lo and i <= hi and n - 1 - 2 * i > 0:
                dst = _every(pp, dim, top, bot - top)
                src = _every(pp, dim, lo + i, n - 1 - 2 * i)
                dst.copy_(src)
                continue
            if i <= lo:
                pp.narrow(dim, top, 1).copy_(pp.narrow(dim, lo + i, 1))
            if i <= hi:
                pp.narrow(dim, bot, 1).copy_(pp.narrow(dim, lo + n - 1 - i, 1))


def _every(x: torch.Tensor, dim: int, start: int, step: int) -> torch.Tensor:
    """Lines ``start`` and ``start + step`` of ``x`` along ``dim`` (a strided view of the two)."""
    idx = [slice(None)] * x.dim()
    idx[dim] = slice(start, start + step + 1, step)
    return x[tuple(idx)]


def _covariance_sums_integral(img: torch.Tensor, block_size: int) -> torch.Tensor:
    """:func:`_covariance_sums_stacked`'s products and box sums of a uint8 image
    (:func:`_integral_ok`), ``(B, 3, H, W)`` float32, in fewer passes over memory.

    Every value here is an integer of magnitude below 2**24 (:data:`_INTEGRAL_BLOCK_MAX`): the
    grey levels, their [1, 2, 1] smoothings (<= 1020), the Sobel derivatives (<= 1020 in
    magnitude), the products and every partial box sum. Float32 adds and products of such
    integers are exact, so any order of the same sums gives the same values as
    :func:`_covariance_sums_stacked`'s order, bit for bit (one exception, without effect: a sum
    of ``dx * dy`` products that is zero may be +0.0 here where the tap-by-tap order gives -0.0;
    the responses use ``Sxy`` only squared, ``Sxy * Sxy``, whose value is +0.0 for both). So:

    * the reflect-101 border is padded on the uint8 image (1 byte a pixel), and each Sobel
      derivative is a [1, 2, 1] smoothing (one reduction over overlapping windows of the padded
      uint8 image, summed in float32) then one difference: 4 passes instead of a float copy, a
      float pad and 6 slice sums;
    * the products are written into the interior of the padded stack, whose reflect-101 border
      (the box sum's) is then filled by strided copies of a few lines (no padded copy of the stack);
    * the box sum is one reduction over overlapping ``block x block`` windows instead of
      ``2 (block - 1)`` adds of image-sized planes.
    """
    B, _, H, W = img.shape
    lo = block_size // 2
    hi = block_size - 1 - lo
    xp = F.pad(img, (1, 1, 1, 1), mode="reflect")  # uint8 (B, 1, H + 2, W + 2)
    Wp = W + 2
    # vertical [1, 2, 1] (rows r, r+1, r+1, r+2) -> (B, 1, H, W + 2); horizontal -> (B, 1, H + 2, W)
    sv = _windows(xp, (2,), (H,), ((2, Wp), (2, Wp)), torch.float32)
    sh = _windows(xp, (3,), (W,), ((2, 1), (2, 1)), torch.float32)
    del xp
    dx = sv[..., 2:] - sv[..., :-2]  # (B, 1, H, W): [1, 2, 1]^T x [-1, 0, 1]
    del sv
    dy = sh[..., 2:, :] - sh[..., :-2, :]
    del sh
    Hq, Wq = H + lo + hi, W + lo + hi
    pp = dx.new_empty((B, 3, Hq, Wq))
    inner = pp[:, :, lo:lo + H, lo:lo + W]
    torch.mul(dx, dx, out=inner[:, 0:1])
    torch.mul(dx, dy, out=inner[:, 1:2])
    torch.mul(dy, dy, out=inner[:, 2:3])
    del dx, dy
    if block_size == 1:
        return pp
    _reflect_borders(pp, lo, hi)
    return _windows(pp, (2, 3), (H, W), ((block_size, Wq), (block_size, 1)))


def _covariance_sums_stacked(img: torch.Tensor, block_size: int) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor, float]:
    """:func:`_covariance_sums` with the three products in one tensor (see there).

    ``img`` float, or uint8: :func:`_covariance_sums_integral` where :func:`_integral_ok` (the same
    values), else converted by :func:`_as_float` first.

    Peak memory (the capturable step's largest moment, at detection): every image-sized buffer is
    dropped as soon as the next one exists, the products are written into the stacked tensor
    (no two concatenated copies of the derivatives; the concatenation is the form with a
    derivative or under the compiler, which takes no strided ``out=``), and the box sums start
    with an add of the first two taps instead of a copy of the first: the same additions in the
    same order, so the same values, in ~5 image-sized planes instead of ~12."""
    if not img.is_floating_point():
        if _integral_ok(img, block_size):
            prod = _covariance_sums_integral(img, block_size)
            return prod[:, 0], prod[:, 1], prod[:, 2], 1.0 / (4.0 * block_size * 255.0)
        img = _as_float(img)
    H, W = img.shape[-2:]
    lo = block_size // 2
    hi = block_size - 1 - lo
    xp = F.pad(img, (1, 1, 1, 1), mode="reflect")
    hx = xp[..., :, 2:] - xp[..., :, :-2]
    hs = torch.add(xp[..., :, :-2], xp[..., :, 1:-1], alpha=2.0)
    hs += xp[..., :, 2:]
    del xp
    dx = torch.add(hx[..., :-2, :], hx[..., 1:-1, :], alpha=2.0)
    dx += hx[..., 2:, :]
    del hx
    dy = hs[..., 2:, :] - hs[..., :-2, :]
    del hs
    if _tuning.inplace_ok(dx, dy) and not torch.compiler.is_compiling():
        prod = dx.new_empty((dx.shape[0], 3, H, W))  # (B, 3, H, W): xx, xy, yy
        torch.mul(dx, dx, out=prod[:, 0:1])
        torch.mul(dx, dy, out=prod[:, 1:2])
        torch.mul(dy, dy, out=prod[:, 2:3])
    else:
        prod = torch.cat((dx, dx, dy), 1) * torch.cat((dx, dy, dy), 1)
    del dx, dy
    if block_size > 1:
        pp = F.pad(prod, (lo, hi, lo, hi), mode="reflect")
        del prod
        rows = pp[:, :, 0:H, :] + pp[:, :, 1:1 + H, :]  # = clone of tap 0, += tap 1
        for i in range(2, block_size):
            rows += pp[:, :, i:i + H, :]
        del pp
        prod = rows[..., 0:W] + rows[..., 1:1 + W]
        for i in range(2, block_size):
            prod += rows[..., i:i + W]
        del rows
    scale = 1.0 / (4.0 * block_size * 255.0)
    return prod[:, 0], prod[:, 1], prod[:, 2], scale


def _safe_sqrt(x: torch.Tensor) -> torch.Tensor:
    # sqrt'(0) is infinite: flat regions ((a-c)² + b² == 0) would give inf/NaN gradients. The
    # inner where keeps the untaken branch finite, so the gradient there is exactly 0.
    pos = x > 0
    return torch.where(pos, torch.sqrt(torch.where(pos, x, torch.ones_like(x))), torch.zeros_like(x))


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


def _harris_impl(x: torch.Tensor, block_size: int, k: float, stacked: bool = False) -> torch.Tensor:
    sxx, sxy, syy, s = _covariance_sums(x, block_size, stacked)
    s2 = s * s
    a = sxx * s2
    b = sxy * s2
    c = syy * s2
    return (a * c - b * b - k * (a + c) * (a + c)).unsqueeze(1)

