"""Keyframe features of the VINS pose graph (spec §5.6, §7.3): FAST corners, BRIEF descriptors and
Hamming distances, batched over B keyframes, on CPU and CUDA, without loops over pixels or points.

``fast`` reproduces ``cv2.FAST(img, threshold, nonmaxSuppression)`` (FAST-9/16) exactly:

* circle: the 16 pixels of the Bresenham circle of radius 3, in OpenCV's order, starting at
  ``(dx, dy) = (0, 3)``;
* corner: at least 9 contiguous circle pixels (circularly) all ``> I + t`` or all ``< I - t``
  (strict inequalities); pixels within 3 of the border are never tested;
* score (OpenCV ``cornerScore<16>``): ``max(t, max_s min_{k in arc s} (I - I_k),
  max_s min_{k in arc s} (I_k - I)) - 1`` over the 16 arcs ``s .. s+8``, i.e. the largest
  threshold at which the pixel is still a corner;
* non-maximum suppression: keep a corner iff its score is *strictly* greater than the scores of
  all 8 neighbours, where non-corners (and the untested 3-pixel border) count as score 0 — this
  is OpenCV's row-buffer rule (``score > prev[j±1]``, ``pprev[j-1..j+1]``, ``curr[j-1..j+1]``);
  plateaus of equal scores therefore lose every member, as in OpenCV;
* output in raster order (row-major), integer positions.

Implementation: a dense pre-test on the 4 compass pixels (0, 4, 8, 12; any 9-arc holds at least
2 of them) selects candidates (~8 % of EuRoC pixels at t = 20) with one ``nonzero`` (the one host
sync, unavoidable for a data-dependent count); their 16 circle values are gathered and the
contiguous-run test is done on bit sets: the 16 brighter/darker flags are packed into an int32,
doubled to 32 bits (``bits | bits << 16``) so that circular runs become linear ones, and
``x & x >> 1``, ``& >> 2``, ``& >> 4``, ``& x >> 8`` leaves bit ``s`` set iff the 9 flags
``s .. s+8`` are all set. The score uses min/max over the 16 arcs by doubling windows; NMS
gathers the 8 neighbour scores from a zero-padded score map.

``brief`` reproduces VINS's DVision ``BRIEF::compute`` (spec §7.3) bit for bit:

* the raw 8-bit image is smoothed with ``cv2.GaussianBlur(img, (9, 9), 2, 2,
  BORDER_REFLECT_101)``, reproduced exactly with OpenCV's 8-bit fixed-point path: separable
  integer kernel ``[7, 17, 32, 46, 52, 46, 32, 17, 7] / 256`` (OpenCV's error-diffused 8-bit
  quantisation of the Gaussian) in both directions, integer sums and one final
  ``(sum + 2**15) >> 16``;
* test point ``i`` of keypoint ``(kx, ky)``: ``x = trunc(kx + x_i)``, ``y = trunc(ky + y_i)``
  (C ``int`` cast, toward zero, computed in the points' dtype: pass float32 points for
  VINS's ``cv::Point2f`` rounding); bit ``i = I(p1) < I(p2)`` if both points are inside the
  image, else 0;
* packing: bit ``i`` is bit ``i mod 64`` of int64 word ``i div 64`` (DBoW2's bitset blocks); word
  3 holds bits 192..255, so a word may be negative (bit 63 is the sign bit).

Patterns: ``load_brief_pattern(path)`` reads VINS's ``brief_pattern.yml`` (OpenCV FileStorage
with integer sequences ``x1, y1, x2, y2``); VINS compatibility needs that file. Without it,
``default_brief_pattern()`` gives the package's own pattern (``data/brief_pattern_default.npy``,
made once by ``make_brief_pattern()``: BRIEF's isotropic Gaussian "G II" offsets with
``sigma = S / 5`` for a patch ``S = 48``, rounded and clipped to ``[-24, 24]``, the same
statistics as VINS's file). Descriptors from different patterns are not comparable.

``hamming`` unpacks the bits to ``+-1`` and uses one matmul: ``popcount(a ^ b) = (256 - <a, b>)
/ 2``; every product and partial sum is a small integer, exact in float32 on CPU and CUDA.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional, Tuple, Union

import numpy as np
import torch

from .._cache import cached
from .._checks import as_image_batch, check_points, check_shape, default_valid
from ..errors import ConfigError
from ..pyramid import _reflect101_index

__all__ = [
    "fast",
    "brief",
    "hamming",
    "gaussian_blur_u8",
    "load_brief_pattern",
    "default_brief_pattern",
    "make_brief_pattern",
    "DEFAULT_PATTERN_PATH",
]

DEFAULT_PATTERN_PATH = Path(__file__).resolve().parent / "data" / "brief_pattern_default.npy"

# OpenCV's FAST-9/16 circle, (dx, dy), in OpenCV's order (fast.cpp / makeOffsets).
_CIRCLE16 = (
    (0, 3), (1, 3), (2, 2), (3, 1), (3, 0), (3, -1), (2, -2), (1, -3),
    (0, -3), (-1, -3), (-2, -2), (-3, -1), (-3, 0), (-3, 1), (-2, 2), (-1, 3),
)
_NEIGH8 = ((-1, -1), (0, -1), (1, -1), (-1, 0), (1, 0), (-1, 1), (0, 1), (1, 1))


# ----------------------------------------------------------------------------------------- input
def _levels(img: torch.Tensor, name: str = "img") -> torch.Tensor:
    """``(B, H, W)`` int16 grey levels 0..255 (float images are rounded and clipped, as 8-bit)."""
    img = as_image_batch(img, name)[:, 0]
    if img.is_floating_point():
        # VINS works on 8-bit images; a float image is read as the 8-bit image it represents.
        img = img.round().clamp(0, 255)
    return img.to(torch.int16)


# ------------------------------------------------------------------------------------------ FAST
def _run9(bits: torch.Tensor) -> torch.Tensor:
    """``(...)`` bool: the 16-bit circular flag set ``bits`` (int32) has a run of >= 9 ones."""
    x = bits | (bits << 16)  # circular -> linear; bits >= 32 of the shifts never reach 0..15
    a = x & (x >> 1)  # bit s: flags s..s+1
    a = a & (a >> 2)  # s..s+3
    a = a & (a >> 4)  # s..s+7
    a = a & (x >> 8)  # s..s+8
    return (a & 0xFFFF) != 0


def _arc_extreme(d: torch.Tensor, op) -> torch.Tensor:
    """``(N, 16)``: ``op`` (min or max) of ``d`` over the 9-arcs ``s .. s+8`` (circular)."""
    ext = torch.cat([d, d[:, :8]], dim=1)  # (N, 24)
    m = op(ext[:, :-1], ext[:, 1:])  # 23 windows of 2
    m = op(m[:, :-2], m[:, 2:])  # 21 windows of 4
    m = op(m[:, :-4], m[:, 4:])  # 17 windows of 8
    return op(m[:, :16], ext[:, 8:24])  # 16 windows of 9


def _fast_impl(
    lv: torch.Tensor, threshold: int, nonmax: bool, max_points: Optional[int], dtype: torch.dtype
) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    B, H, W = lv.shape
    dev = lv.device
    h, w = H - 6, W - 6
    if h <= 0 or w <= 0:
        b_idx = torch.zeros(0, dtype=torch.long, device=dev)
        yy = xx = b_idx
        score = torch.zeros(0, dtype=torch.int16, device=dev)
    else:
        t = int(threshold)
        c = lv[:, 3:H - 3, 3:W - 3]
        hi, lo = c + t, c - t
        # Cheap dense pre-test (OpenCV's early-out idea): any 9-arc of the 16-circle contains at
        # least 2 of the 4 compass pixels 0, 4, 8, 12, so a corner has >= 2 of them brighter (or
        # >= 2 darker). Only these candidates (~10 % of EuRoC pixels at t = 20) get the full test.
        nb = torch.zeros((B, h, w), dtype=torch.uint8, device=dev)
        nd = torch.zeros_like(nb)
        for k in (0, 4, 8, 12):
            dx, dy = _CIRCLE16[k]
            v = lv[:, 3 + dy:3 + dy + h, 3 + dx:3 + dx + w]
            nb += v > hi
            nd += v < lo
        b_idx, yy, xx = ((nb >= 2) | (nd >= 2)).nonzero(as_tuple=True)  # raster order; host sync
        # full test at the candidates: gather the 16 circle values (OpenCV d[k] = v - I_k)
        flat = lv.reshape(-1)
        centre = b_idx * (H * W) + (yy + 3) * W + (xx + 3)
        offs = torch.tensor([dy * W + dx for dx, dy in _CIRCLE16], dtype=torch.long, device=dev)
        v = flat.take(centre).to(torch.int32)
        d = v[:, None] - flat.take(centre[:, None] + offs).to(torch.int32)  # (N, 16)
        pw = torch.ones(16, dtype=torch.int32, device=dev) << torch.arange(16, dtype=torch.int32, device=dev)
        dark = ((d > t).to(torch.int32) * pw).sum(dim=1, dtype=torch.int32)  # circle pixel darker
        bright = ((d < -t).to(torch.int32) * pw).sum(dim=1, dtype=torch.int32)
        corner = _run9(bright) | _run9(dark)
        b_idx, yy, xx, d = b_idx[corner], yy[corner], xx[corner], d[corner]
        # score (cornerScore<16>) at the corners only
        a0 = torch.clamp(_arc_extreme(d, torch.minimum).amax(dim=1), min=t)
        b0 = torch.minimum(_arc_extreme(d, torch.maximum).amin(dim=1), -a0)
        score = (-b0 - 1).to(torch.int16)
        if nonmax and score.numel():
            smap = torch.zeros((B, h + 2, w + 2), dtype=torch.int16, device=dev)
            smap[b_idx, yy + 1, xx + 1] = score
            sflat = smap.reshape(B, -1)
            pos = (yy + 1) * (w + 2) + (xx + 1)
            noffs = torch.tensor([dy * (w + 2) + dx for dx, dy in _NEIGH8], dtype=torch.long, device=dev)
            nb = sflat[b_idx[:, None], pos[:, None] + noffs]
            keep = (score[:, None] > nb).all(dim=1)
            b_idx, yy, xx, score = b_idx[keep], yy[keep], xx[keep], score[keep]
    return _pack(b_idx, xx + 3, yy + 3, score, B, H * W, max_points, dtype)


def _pack(b_idx, x, y, score, B, HW, max_points, dtype):
    """Scatter the flat raster-ordered corners into ``(B, K)`` slots (strongest K on overflow)."""
    dev = b_idx.device
    counts = torch.bincount(b_idx, minlength=B)
    if max_points is None:
        K = int(counts.max()) if counts.numel() and b_idx.numel() else 0
        keep = torch.ones_like(b_idx, dtype=torch.bool)
    else:
        K = int(max_points)
        # rank by (stream, score desc, raster order): ties keep the earlier raster position
        n = b_idx.numel()
        key = b_idx * (256 * n) + (255 - score.long()) * n + torch.arange(n, device=dev)
        order = torch.argsort(key)
        start = torch.cumsum(counts, 0) - counts
        rank = torch.arange(n, device=dev) - start[b_idx[order]]
        keep = torch.zeros(n, dtype=torch.bool, device=dev)
        keep[order] = rank < K
    b_k = b_idx[keep]
    kept_counts = torch.bincount(b_k, minlength=B)
    start = torch.cumsum(kept_counts, 0) - kept_counts
    slot = torch.arange(b_k.numel(), device=dev) - start[b_k]  # raster order is preserved
    pts = torch.zeros((B, K, 2), dtype=dtype, device=dev)
    sc = torch.zeros((B, K), dtype=dtype, device=dev)
    valid = torch.zeros((B, K), dtype=torch.bool, device=dev)
    pts[b_k, slot, 0] = x[keep].to(dtype)
    pts[b_k, slot, 1] = y[keep].to(dtype)
    sc[b_k, slot] = score[keep].to(dtype)
    valid[b_k, slot] = True
    return pts, sc, valid, counts


def fast(
    img: torch.Tensor,
    threshold: int = 20,
    nonmax: bool = True,
    max_points: Optional[int] = None,
    *,
    return_count: bool = False,
    dtype: torch.dtype = torch.float32,
):
    """FAST-9/16 corners as ``cv2.FAST(img, threshold, nonmax)`` (spec §5.6), batched.

    Convention:
        Pixel centres at integer coordinates; corners at integer positions ``(x, y)``, at least 3
        pixels from the border, listed per image in raster order (row by row, left to right).
        ``score`` is OpenCV's FAST score (``cornerScore<16>``: the largest threshold at which the
        pixel is still a corner); OpenCV reports it as ``KeyPoint.response`` only with NMS (0
        without), this function always reports it. Capacity ``K = max_points`` if given, else the
        largest count in the batch; images with fewer corners are padded (``valid`` False, zeros).
        When an image has more than ``max_points`` corners, the ``max_points`` highest scores are
        kept (ties: earlier raster position first), still listed in raster order; the count
        before truncation is returned with ``return_count=True`` (overflow iff ``num_found > K``).

    Args:
        img: ``(B, 1, H, W)`` or ``(B, H, W)``, uint8 or float grey levels 0..255 (float images
            are rounded and clipped to 8 bits, as the 8-bit image they stand for).
        threshold: int, intensity threshold ``t`` (clipped to 0..255 like OpenCV).
        nonmax: 3x3 non-maximum suppression on the score (OpenCV's strict rule).
        max_points: optional capacity ``K``.
        return_count: also return ``num_found``.
        dtype: floating dtype of ``pts`` and ``score``.

    Returns:
        ``pts``: ``(B, K, 2)`` float pixels ``(x, y)``; ``score``: ``(B, K)`` float;
        ``valid``: ``(B, K)`` bool; with ``return_count``: ``num_found``: ``(B,)`` int64.
    """
    lv = _levels(img)
    if max_points is not None and int(max_points) < 0:
        raise ValueError(f"max_points: expected >= 0 or None, got {max_points}")
    if not dtype.is_floating_point:
        raise TypeError(f"dtype: expected a floating dtype, got {dtype}")
    t = min(max(int(threshold), 0), 255)
    pts, score, valid, counts = _fast_impl(lv, t, bool(nonmax), max_points, dtype)
    if return_count:
        return pts, score, valid, counts
    return pts, score, valid


# ------------------------------------------------------------------------------- Gaussian blur
@cached(16)
def _fixed_gaussian_kernel(ksize: int, sigma: float, bits: int = 8) -> Tuple[int, ...]:
    """OpenCV's 8-bit fixed-point Gaussian kernel (``getGaussianKernelFixedPoint_ED``):
    the normalised Gaussian scaled by ``2**bits``, rounded left to right with error diffusion,
    symmetric, centre = remainder so that the kernel sums to ``2**bits``. Checked equal to
    OpenCV 4.x for ``(9, 2.0)``: ``[7, 17, 32, 46, 52, 46, 32, 17, 7]``."""
    half = ksize // 2
    g = [math.exp(-((i - half) ** 2) / (2.0 * sigma * sigma)) for i in range(ksize)]
    s = sum(g)
    g = [v / s for v in g]
    one = 1 << bits
    res = [0] * ksize
    err, acc = 0.0, 0
    for i in range(half):
        adj = g[i] * one + err
        v = int(np.rint(adj))
        err = adj - v
        res[i] = res[ksize - 1 - i] = v
        acc += v
    res[half] = one - 2 * acc
    return tuple(res)


def gaussian_blur_u8(img: torch.Tensor) -> torch.Tensor:
    """``cv2.GaussianBlur(img, (9, 9), 2, 2, borderType=BORDER_REFLECT_101)`` on 8-bit images,
    bit-exact (OpenCV's fixed-point path: integer kernel ``/256`` per direction, one rounding).

    Convention:
        ``img``: ``(B, 1, H, W)`` / ``(B, H, W)`` uint8 or float 0..255 (rounded to 8 bits).
        Returns ``(B, 1, H, W)`` uint8. Integer arithmetic (int32), exact on CPU and CUDA.
    """
    lv = _levels(img).to(torch.int32)
    return _blur_impl(lv).to(torch.uint8).unsqueeze(1)


def _blur_impl(lv: torch.Tensor) -> torch.Tensor:
    """``(B, H, W)`` int32 levels -> ``(B, H, W)`` int32 blurred levels (bit-exact, any device).

    Integer shifted-slice sums, using the kernel's symmetry (5 products per pass). Integers rather
    than a float conv: a CUDA float conv may run in TF32 and round the intermediates (and on CPU
    this is also faster than ``conv2d`` for a 1-channel 9-tap filter).
    """
    k = _fixed_gaussian_kernel(9, 2.0)
    r = len(k) // 2
    B, H, W = lv.shape
    px = lv.index_select(2, _reflect101_index(W, r, r, lv.device))
    hor = k[r] * px[:, :, r:r + W]
    for i in range(r):
        hor = hor + k[i] * (px[:, :, i:i + W] + px[:, :, 2 * r - i:2 * r - i + W])  # <= 255 * 256
    py = hor.index_select(1, _reflect101_index(H, r, r, lv.device))
    ver = k[r] * py[:, r:r + H]
    for i in range(r):
        ver = ver + k[i] * (py[:, i:i + H] + py[:, 2 * r - i:2 * r - i + H])  # <= 255 * 2**16 < 2**31
    return (ver + (1 << 15)) >> 16


# -------------------------------------------------------------------------------------- patterns
def make_brief_pattern(seed: int = 20260129, n_bits: int = 256, patch_size: int = 48) -> np.ndarray:
    """The package's BRIEF test pattern: ``(4, n_bits)`` int8 rows ``x1, y1, x2, y2``.

    BRIEF "G II": both points drawn i.i.d. from an isotropic Gaussian with ``sigma = S / 5``
    (``S = patch_size``), rounded to integers and clipped to ``[-S/2, S/2]``; pairs with
    ``p1 == p2`` (constant-0 bits) are redrawn. ``default_brief_pattern()`` is this with the
    default arguments, stored once under ``data/brief_pattern_default.npy``.
    """
    rng = np.random.default_rng(seed)
    half = patch_size // 2
    out = np.zeros((4, n_bits), dtype=np.int64)
    todo = np.ones(n_bits, dtype=bool)
    while todo.any():  # redraw degenerate pairs (terminates: almost every draw is fine)
        draw = np.clip(np.rint(rng.normal(0.0, patch_size / 5.0, (4, int(todo.sum())))), -half, half)
        out[:, todo] = draw
        todo = (out[0] == out[2]) & (out[1] == out[3])
    return out.astype(np.int8)


def _pattern_tensor(pattern, device) -> torch.Tensor:
    if pattern is None:
        pattern = _default_pattern_np()
    # built straight on the device (a numpy pattern is one upload; a tensor one moves if needed)
    p = torch.as_tensor(np.asarray(pattern) if not isinstance(pattern, torch.Tensor) else pattern, device=device)
    if p.dim() != 2 or p.shape[0] != 4 or p.shape[1] == 0:
        raise ValueError(f"pattern: expected shape (4, n_bits) rows x1, y1, x2, y2, got {tuple(p.shape)}")
    if p.shape[1] % 64:
        raise ValueError(f"pattern: n_bits must be a multiple of 64, got {p.shape[1]}")
    if p.is_floating_point():
        raise TypeError(f"pattern: expected integer offsets, got {p.dtype}")
    return p.to(device=device, dtype=torch.long)


@cached(1)
def _default_pattern_np() -> np.ndarray:
    return np.load(DEFAULT_PATTERN_PATH)


def default_brief_pattern() -> torch.Tensor:
    """The package's own pattern, ``(4, 256)`` int64 (not VINS's; see ``make_brief_pattern``)."""
    return torch.from_numpy(_default_pattern_np().astype(np.int64))


def load_brief_pattern(path: Union[str, Path]) -> torch.Tensor:
    """Read VINS's ``brief_pattern.yml`` (OpenCV FileStorage YAML, integer sequences ``x1, y1,
    x2, y2`` of equal length) into a ``(4, n_bits)`` int64 tensor (rows ``x1, y1, x2, y2``).

    Raises:
        ConfigError: unreadable file, missing key, unequal lengths, non-integers, or a length
            that is not a positive multiple of 64.
    """
    from ..opencv_yaml import read_opencv_yaml

    p = Path(path)
    try:
        raw = read_opencv_yaml(p)
    except ConfigError:
        raise
    except Exception as exc:  # noqa: BLE001 - any parse failure is a config problem here
        raise ConfigError(f"cannot read BRIEF pattern: {exc}", path=p) from exc
    rows = []
    for key in ("x1", "y1", "x2", "y2"):
        if key not in raw:
            raise ConfigError("missing BRIEF pattern sequence", path=p, key=key)
        seq = raw[key]
        try:
            arr = np.asarray(seq)
            if arr.ndim != 1 or not np.all(np.asarray(arr, dtype=np.float64) == np.round(arr.astype(np.float64))):
                raise ValueError
        except (TypeError, ValueError):
            raise ConfigError("expected a sequence of integers", path=p, key=key) from None
        rows.append(arr.astype(np.int64))
    n = {len(r) for r in rows}
    if len(n) != 1:
        raise ConfigError(f"x1, y1, x2, y2 have different lengths {[len(r) for r in rows]}", path=p)
    n_bits = n.pop()
    if n_bits == 0 or n_bits % 64:
        raise ConfigError(f"pattern length must be a positive multiple of 64, got {n_bits}", path=p)
    return torch.from_numpy(np.stack(rows))


# ----------------------------------------------------------------------------------------- BRIEF
def _brief_impl(blur: torch.Tensor, pts: torch.Tensor, valid: torch.Tensor, pat: torch.Tensor) -> torch.Tensor:
    B, H, W = blur.shape
    K = pts.shape[1]
    n_bits = pat.shape[1]
    # C: (int)(kp.pt.x + m_x1[i]) -> sum in the points' dtype, truncation toward zero
    off = pat.to(pts.dtype)
    x1 = torch.trunc(pts[..., 0:1] + off[0]).long()  # (B, K, n_bits)
    y1 = torch.trunc(pts[..., 1:2] + off[1]).long()
    x2 = torch.trunc(pts[..., 0:1] + off[2]).long()
    y2 = torch.trunc(pts[..., 1:2] + off[3]).long()
    inside = (x1 >= 0) & (x1 < W) & (y1 >= 0) & (y1 < H) & (x2 >= 0) & (x2 < W) & (y2 >= 0) & (y2 < H)
    # clamp only to keep the gather in range; outside bits are forced to 0 below
    i1 = y1.clamp(0, H - 1) * W + x1.clamp(0, W - 1)
    i2 = y2.clamp(0, H - 1) * W + x2.clamp(0, W - 1)
    flat = blur.reshape(B, H * W)
    v1 = flat.gather(1, i1.reshape(B, -1)).reshape(B, K, n_bits)
    v2 = flat.gather(1, i2.reshape(B, -1)).reshape(B, K, n_bits)
    bit = (v1 < v2) & inside & valid[..., None]
    shifts = torch.arange(64, device=blur.device, dtype=torch.long)
    # bits are disjoint, so the sum is an OR; bit 63 wraps to the sign bit as intended
    return (bit.reshape(B, K, n_bits // 64, 64).long() << shifts).sum(dim=-1)


def brief(
    img: torch.Tensor,
    pts: torch.Tensor,
    valid: Optional[torch.Tensor] = None,
    pattern: Optional[Union[torch.Tensor, np.ndarray]] = None,
) -> torch.Tensor:
    """BRIEF descriptors of keypoints as VINS's DVision ``BRIEF::compute`` (spec §7.3), batched.

    Convention:
        The raw 8-bit image is blurred (``gaussian_blur_u8``: Gaussian 9x9, sigma 2,
        BORDER_REFLECT_101, bit-exact with OpenCV). Test point ``i`` of ``(kx, ky)`` is
        ``(trunc(kx + dx_i), trunc(ky + dy_i))``; bit ``i = I(p1) < I(p2)`` when both points are
        inside the image, else 0. Bit ``i`` is bit ``i mod 64`` of word ``i div 64``. Invalid
        keypoints get all-zero descriptors.

    Args:
        img: ``(B, 1, H, W)`` / ``(B, H, W)`` uint8 or float 0..255 (rounded to 8 bits).
        pts: ``(B, K, 2)`` float pixels ``(x, y)`` (float32 reproduces VINS's float sums).
        valid: optional ``(B, K)`` bool.
        pattern: ``(4, n_bits)`` integer offsets ``x1, y1, x2, y2`` (``load_brief_pattern`` for
            VINS's file); default ``default_brief_pattern()``.

    Returns:
        ``(B, K, n_bits // 64)`` int64 packed descriptors (``(B, K, 4)`` for 256 bits).
    """
    lv = _levels(img).to(torch.int32)
    check_points(pts)
    if pts.shape[0] != lv.shape[0]:
        raise ValueError(f"pts: expected batch {lv.shape[0]} (from img), got shape {tuple(pts.shape)}")
    if pts.device != lv.device:
        raise ValueError(f"pts: on {pts.device}, img on {lv.device}")
    valid = default_valid(pts, valid)
    pat = _pattern_tensor(pattern, lv.device)
    return _brief_impl(_blur_impl(lv), pts, valid, pat)


# --------------------------------------------------------------------------------------- Hamming
def _unpack_bits(d: torch.Tensor) -> torch.Tensor:
    """``(..., W) int64 -> (..., 64 W) uint8`` bits (bit i = bit i%64 of word i//64)."""
    shifts = torch.arange(64, device=d.device, dtype=torch.int64)
    bits = (d.unsqueeze(-1) >> shifts) & 1  # sign-extension is masked off by & 1
    return bits.reshape(*d.shape[:-1], 64 * d.shape[-1]).to(torch.uint8)


def _unpack_pm1(d: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """``(..., K, W)`` int64 words -> ``(..., K, 64 W)`` of ``+1`` (bit 0) / ``-1`` (bit 1)."""
    return 1 - 2 * _unpack_bits(d).to(dtype)


def hamming(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """All-pairs Hamming distances ``popcount(a ^ b)`` between packed descriptors.

    Convention:
        ``a``: ``(..., Ka, W)`` int64, ``b``: ``(..., Kb, W)`` int64 (``W = 4`` for 256-bit BRIEF);
        leading dims broadcast like ``torch.matmul``. Returns ``(..., Ka, Kb)`` int64, exact:
        ``(64 W - <pm(a), pm(b)>) / 2`` with ``pm`` the ``+-1`` bit vectors (small integers,
        exact in float32 on CPU and CUDA, also under TF32 since ``+-1`` is representable).
    """
    check_shape(a, ("*", None, "W"), "a")
    check_shape(b, ("*", None, "W"), "b")
    if a.shape[-1] != b.shape[-1]:
        raise ValueError(f"a, b: expected the same word count, got shapes {tuple(a.shape)} and {tuple(b.shape)}")
    if a.dtype != torch.int64 or b.dtype != torch.int64:
        raise TypeError(f"a, b: expected int64 packed descriptors, got {a.dtype} and {b.dtype}")
    n_bits = 64 * a.shape[-1]
    pa = _unpack_pm1(a, torch.float32)
    pb = _unpack_pm1(b, torch.float32)
    dot = torch.matmul(pa, pb.transpose(-1, -2))
    return ((n_bits - dot) * 0.5).round().to(torch.int64)
