"""Detection masks: VINS ``setMask`` (minimum spacing of tracked features) and the fisheye mask.

``distance_mask`` is VINS-Mono's ``setMask`` (spec §3.7) in tensor form: points are visited by
descending priority (the track count; ties by index, i.e. a stable sort - VINS' ``std::sort`` is
not stable, spec §3.7.2), a point is kept iff the mask at its rounded pixel is exactly 255, and
every kept point blanks a filled disc of ``radius`` around its rounded centre. The result is the
sequential result exactly, computed in parallel rounds (see ``corners.selection._resolve_rounds``)
on the N x N conflict matrix; the kept discs are then rasterised all at once as row spans (a +1/-1
difference buffer and one cumsum along x), so the cost is ~linear in B and independent of how
many discs overlap.

The disc is ``dx² + dy² <= radius²`` around the ``cvRound``-ed centre, which equals
``cv2.circle(mask, centre, radius, 0, -1)`` pixel for pixel for integer radii (checked for radii
1..60 in ``tests/test_masks.py``).

``fisheye_mask`` is an analytic, binarised replacement for VINS' ``fisheye_mask.jpg`` (spec §3.13).
"""

from __future__ import annotations

import math
from typing import NamedTuple, Optional, Tuple, Union

import torch

from ._cache import cached
from ._checks import check_points, check_shape, default_valid
from .corners.selection import _resolve_rounds
from .corners.selection_capturable import _iota, _lower, _pair_conflicts, _resolve_dense
from .errors import ConfigError
from .fused.mask_op import set_mask_op

__all__ = ["distance_mask", "fisheye_mask", "disc_offsets"]

# fitted to VINS-Mono config/fisheye_mask.jpg (512x512): the ==255 region is best matched by a
# disc of radius 271 centred at (255.5, 255.5) (99.1 % of pixels agree; the rest is the JPEG's
# ring of 1..254 values and clipping by the image border).
_FISHEYE_RADIUS_512 = 271.0


def disc_offsets(radius: float, device=None) -> torch.Tensor:
    """Integer offsets ``(dx, dy)`` with ``dx² + dy² <= radius²``: ``(P, 2)`` long.

    This is OpenCV's filled ``circle`` of an integer radius around an integer centre.
    """
    r = int(radius)
    if radius < 0:
        raise ConfigError(f"radius must be >= 0, got {radius}")
    ax = torch.arange(-r - 1, r + 2, device=device)
    dy, dx = torch.meshgrid(ax, ax, indexing="ij")
    inside = (dx * dx + dy * dy).double() <= float(radius) ** 2
    return torch.stack([dx[inside], dy[inside]], -1)


def _base_mask_batch(base_mask: torch.Tensor | None, B: int, height: int | None, width: int | None,
                     device) -> torch.Tensor:
    if base_mask is None:
        if height is None or width is None:
            raise ValueError("distance_mask: give base_mask or both height and width")
        return torch.full((B, int(height), int(width)), 255, dtype=torch.uint8, device=device)
    m = base_mask
    if m.dim() == 2:
        m = m.unsqueeze(0).expand(B, -1, -1)
    elif m.dim() == 4 and m.shape[1] == 1:
        m = m[:, 0]
    if m.dim() != 3 or m.shape[0] != B:
        raise ValueError(f"base_mask: expected shape (H, W), (B, H, W) or (B, 1, H, W) with B={B}, "
                         f"got {tuple(base_mask.shape)}")
    if height is not None and width is not None and tuple(m.shape[-2:]) != (int(height), int(width)):
        raise ValueError(f"base_mask: expected (H, W) = {(int(height), int(width))}, got {tuple(m.shape[-2:])}")
    if m.is_floating_point():
        m = m.round().clamp(0, 255)
    return m.to(device=device, dtype=torch.uint8).clone()


def distance_mask(
    pts: torch.Tensor,
    priority: torch.Tensor,
    valid: torch.Tensor | None,
    radius: Union[int, float],
    base_mask: torch.Tensor | None = None,
    height: int | None = None,
    width: int | None = None,
    backend: str | None = None,
) -> Tuple[torch.Tensor, torch.Tensor]:
    """VINS ``setMask``: keep well-spaced points (older tracks first) and build the detection mask.

    Convention:
        Points are visited by descending ``priority`` (ties: lower index first). A valid point is
        kept iff ``mask[cvRound(y), cvRound(x)] == 255`` (exactly 255; points rounding outside
        the image are dropped); each kept point sets the filled disc ``dx² + dy² <= radius²``
        around its rounded centre to 0. ``cvRound`` = ``torch.round`` (half to even).
        Pixel centres at integer coordinates.

    Args:
        pts: ``(B, N, 2)`` float, pixels ``(x, y)``.
        priority: ``(B, N)`` (track counts), larger first.
        valid: ``(B, N)`` bool or None (all valid).
        radius: disc radius in pixels (``MIN_DIST``).
        base_mask: optional ``(H, W)``, ``(B, H, W)`` or ``(B, 1, H, W)`` uint8 (e.g. the fisheye
            mask); default all 255 of size ``height`` x ``width``.
        backend: ``None`` / ``"auto"`` (the device's strategy, as the LK's: the fused op
            ``torch_frontend::set_mask`` on the CPU and CUDA), ``"fused"`` or ``"tensor"``
            (``fused.resolve_backend``); the same bits either way. The fused op needs an integer
            ``priority``: a float one runs the tensor kernel under ``"auto"``.

    Returns:
        keep: ``(B, N)`` bool, in the input order (VINS also reorders by priority; use
        ``torch.sort(priority, descending=True, stable=True)`` for that order).
        mask: ``(B, H, W)`` uint8, ``base_mask`` with the kept points' discs set to 0 - the mask
        to pass to ``good_features_to_track``.
    """
    check_points(pts, "pts")
    B, N, _ = pts.shape
    check_shape(priority, (B, N), "priority")
    valid = default_valid(pts, valid, "valid")
    if radius < 0:
        raise ConfigError(f"radius must be >= 0, got {radius}")
    mask = _base_mask_batch(base_mask, B, height, width, pts.device)
    backend = _mask_backend(backend, priority, pts.device)
    res = _distance_mask_impl(pts, priority, valid, float(radius), mask, backend=backend)
    return res.keep, res.mask


def _mask_backend(requested: str | None, priority: torch.Tensor, device) -> str:
    """The setMask kernel a :func:`distance_mask` call runs (see its ``backend``)."""
    from .fused import resolve_backend

    integer = priority.dtype in (torch.int32, torch.int64)
    if requested == "fused" and not integer:
        raise ConfigError(f"distance_mask: backend='fused' needs an int32 / int64 priority, got {priority.dtype}")
    if not integer and requested in (None, "auto"):
        return "tensor"
    return resolve_backend(requested, device)


class DistanceMaskResult(NamedTuple):
    """What :func:`_distance_mask_impl` returns, on both paths.

    Attributes:
        keep: ``(B, N)`` bool, the kept points in the input order.
        mask: ``(B, H, W)`` uint8, the base mask with the kept points' discs set to 0.
        overflow: ``(B,)`` bool on the capturable path (True where the fixed rounds left a decision
            open), None on the default path.
    """

    keep: torch.Tensor
    mask: torch.Tensor
    overflow: Optional[torch.Tensor]


def _distance_mask_impl(pts: torch.Tensor, priority: torch.Tensor, valid: torch.Tensor, radius: float,
                        mask: torch.Tensor, *, capturable: bool = False,
                        rounds: int | None = None, backend: str = "tensor") -> DistanceMaskResult:
    """:func:`distance_mask` without input checks (the kernel's ``_impl``).

    Args:
        pts: ``(B, N, 2)`` float, pixels ``(x, y)``.
        priority: ``(B, N)`` (track counts), larger first.
        valid: ``(B, N)`` bool.
        radius: disc radius in pixels, >= 0.
        mask: ``(B, H, W)`` uint8, the base mask (255 = free); the tensor kernel writes into it and
            returns it (pass a copy to keep it). ``backend="fused"``: ``(1 or B, H, W)``, only read
            (one mask for every stream needs no copy); the result is a new tensor.
        capturable: False: the conflicts are resolved in rounds until done (a host check each).
            True: shape-static, no host syncs, a kernel count independent of B and of the data:
            ``rounds`` rounds (default :data:`MASK_ROUNDS`), see :func:`_distance_mask_capturable`.
        backend: ``"tensor"`` (this module's kernels, the reference) or ``"fused"`` (the custom op
            ``torch_frontend::set_mask``, ``fused/mask_op.py``: the sequential VINS loop in one op on
            both paths; ``priority`` int32 / int64). The same bits; the fused op is exact on the
            capturable path too, so its ``overflow`` is all False.

    Returns:
        A :class:`DistanceMaskResult`: ``keep (B, N)`` bool and ``mask`` as :func:`distance_mask`;
        ``overflow (B,)`` bool with ``capturable`` (True where the rounds left a decision open;
        elsewhere the result equals the default path's), None on the default path (exact).
    """
    if backend == "fused":
        keep, out = set_mask_op(pts.detach(), priority, valid, mask, float(radius))
        overflow = torch.zeros(pts.shape[0], dtype=torch.bool, device=pts.device) if capturable else None
        return DistanceMaskResult(keep, out, overflow)
    if backend != "tensor":
        raise ConfigError(f"setMask backend must be 'tensor' or 'fused', got {backend!r}")
    if capturable:
        return DistanceMaskResult(*_distance_mask_capturable(pts, priority, valid, float(radius), mask,
                                                             MASK_ROUNDS if rounds is None else int(rounds)))
    B, N, _ = pts.shape
    H, W = mask.shape[-2:]
    dev = pts.device
    if N == 0:
        return DistanceMaskResult(torch.zeros(B, 0, dtype=torch.bool, device=dev), mask, None)

    # visiting order: priority descending, ties by index (stable); invalid points last
    key = torch.where(valid, priority.to(torch.float64), torch.full_like(priority, float("-inf"), dtype=torch.float64))
    order = torch.sort(key, dim=1, descending=True, stable=True).indices
    p = torch.gather(pts.detach(), 1, order[..., None].expand(B, N, 2))
    v = torch.gather(valid, 1, order)
    finite = torch.isfinite(p).all(-1)
    r = torch.where(finite[..., None], torch.round(p), torch.full_like(p, -1.0))
    rx = r[..., 0].clamp(-1, W).long()
    ry = r[..., 1].clamp(-1, H).long()
    inside = v & finite & (rx >= 0) & (rx < W) & (ry >= 0) & (ry < H)
    flat = ry.clamp(0, H - 1) * W + rx.clamp(0, W - 1)
    base_ok = torch.gather(mask.reshape(B, -1), 1, flat) == 255
    eligible = inside & base_ok

    # conflict: j ranked above i and j's disc covers i's rounded pixel, in the transposed
    # [j, i] layout of _resolve_rounds (cover is symmetric)
    dx = rx[:, :, None] - rx[:, None, :]
    dy = ry[:, :, None] - ry[:, None, :]
    cover = (dx * dx + dy * dy).double() <= radius ** 2
    higher = torch.ones(N, N, dtype=torch.bool, device=dev).triu(1)
    conf = cover & higher & eligible[:, :, None]
    keep_sorted = _resolve_rounds(conf.to(torch.float32), eligible)

    # back to input order
    keep = torch.zeros_like(keep_sorted).scatter_(1, order, keep_sorted)

    # rasterise the kept discs: each disc is 2r+1 row spans [x - hw(dy), x + hw(dy)]. A +1 / -1
    # at every span's ends in a per-row difference buffer and one cumsum along x give the cover
    # count of every pixel: O(B * N * r) scatter work plus a few image-sized passes, instead of
    # O(B * N * r²) disc-offset indices.
    mask = _clear_discs(mask, rx, ry, keep_sorted, radius)
    return DistanceMaskResult(keep, mask, None)


def _span_half_widths(radius: float, device) -> Tuple[torch.Tensor, torch.Tensor]:
    """Row offsets ``dy`` of the disc ``dx² + dy² <= radius²`` and each row's half width (long):
    device constants, computed once per radius and device (on the host: no sync per call)."""
    return _span_table(float(radius), torch.device(device))


@cached(32)
def _span_table(radius: float, device: torch.device) -> Tuple[torch.Tensor, torch.Tensor]:
    # built on the device without a boolean index (also traceable by torch.compile)
    r = int(radius)
    ax = torch.arange(-r - 1, r + 2, device=device)
    inside = (ax[:, None] * ax[:, None] + ax[None, :] * ax[None, :]).double() <= float(radius) ** 2
    n = inside.sum(1)  # dx count per row dy: 2 * hw + 1 (0 when the row is empty)
    # the non-empty rows are exactly |dy| <= r: dx = 0 is inside there (dy² <= r² <= radius²), and
    # (r + 1)² > radius²
    return ax[1:-1], (n[1:-1] - 1) // 2


def _clear_discs(mask: torch.Tensor, rx: torch.Tensor, ry: torch.Tensor, keep: torch.Tensor,
                 radius: float) -> torch.Tensor:
    """Set the filled discs ``dx² + dy² <= radius²`` around (rx, ry) (B, N) long of ``keep`` to 0."""
    B, H, W = mask.shape
    dev = mask.device
    dys, hws = _span_half_widths(radius, dev)  # (S,)
    py = ry[:, :, None] + dys  # (B, N, S) span rows
    x0 = (rx[:, :, None] - hws).clamp_min(0)
    x1 = (rx[:, :, None] + hws + 1).clamp_max(W)  # exclusive end, <= W
    ok = keep[:, :, None] & (py >= 0) & (py < H) & (x0 < x1)
    row = (torch.arange(B, device=dev)[:, None, None] * H + py.clamp(0, H - 1)) * W
    dump = B * H * W  # spans that are off the image or not kept add into a dump slot
    start = torch.where(ok, row + x0, dump)
    # a span ending at the right border needs no -1: the cumsum restarts on every row
    stop = torch.where(ok & (x1 < W), row + x1, dump)
    # Cover counts in uint8, modulo 256 (-1 is +255): kept points are pairwise more than
    # ``radius`` apart (each is outside the other's disc), so a pixel lies in at most 5 kept
    # discs (their centres, seen from the pixel, are > 60 degrees apart): the count is exact.
    diff = torch.zeros(dump + 1, dtype=torch.uint8, device=dev)
    n = start.numel()
    diff.index_put_((start.view(-1),), torch.ones(1, dtype=torch.uint8, device=dev).expand(n), accumulate=True)
    diff.index_put_((stop.view(-1),), torch.full((1,), 255, dtype=torch.uint8, device=dev).expand(n),
                    accumulate=True)
    cover = diff[:dump].view(B, H, W).cumsum(-1, dtype=torch.uint8)
    # logical_not + a uint8 multiply: ~10x faster on CPU than a comparison and masked_fill_
    return mask.mul_(torch.logical_not(cover).view(torch.uint8))


#: Conflict-resolution rounds of the capturable setMask (``capturable=True``). Measured through
#: this kernel on the tracker's setMask calls (max_cnt 150, min_dist 30 / 25 / 20, mono and fusion
#: trackers on EuRoC mini cam0 / cam1, V1_01 micro cam0 / cam1, the Middlebury pair and the
#: synthetic flight; 762 calls, up to 150 features): rounds until every feature is decided,
#: max 3 (574 calls need 1, 150 need 2, 5 need 3) -> 8 (4 kernels a round).
MASK_ROUNDS = 8


def _distance_mask_capturable(pts: torch.Tensor, priority: torch.Tensor, valid: torch.Tensor, radius: float,
                              mask: torch.Tensor, rounds: int) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`_distance_mask_impl` with ``capturable=True``: the same rules and results, a fixed
    op sequence.

    The conflicts resolve in ``rounds`` rounds
    (:func:`~torch_frontend.corners.selection_capturable._resolve_dense`); features the rounds leave
    undecided are not kept and set ``overflow``. The discs are rasterised as row spans into a
    difference buffer with ``r`` spare rows above and below each stream and one spare column, so
    that no span needs a bounds test (every index is in range). Points that are not kept add 0.
    """
    B, N, _ = pts.shape
    H, W = mask.shape[-2:]
    dev = pts.device
    if N == 0:
        return torch.zeros(B, 0, dtype=torch.bool, device=dev), mask, torch.zeros(B, dtype=torch.bool, device=dev)
    c = _mask_constants(B, H, W, float(radius), dev)

    # visiting order: priority descending, ties by index (stable); invalid points last
    key = torch.where(valid, priority.to(torch.float64), float("-inf"))
    order = torch.sort(key, dim=1, descending=True, stable=True).indices
    p = torch.gather(pts.detach(), 1, order[..., None].expand(B, N, 2))
    v = torch.gather(valid, 1, order)
    # cvRound; a non-finite coordinate -> -1 (outside; the other coordinate then does not matter)
    rxy = torch.nan_to_num(torch.round(p), nan=-1.0, posinf=-1.0, neginf=-1.0).clamp_(-1.0, c.size_f).long()
    cl = torch.minimum(rxy.clamp_min(0), c.size_m1)  # (B, N, 2) inside the image
    eligible = (cl == rxy).all(-1)
    eligible &= v
    flat = (cl * c.stride).sum(-1)
    eligible &= torch.gather(mask.reshape(B, H * W), 1, flat) == 255

    # conflict [i, j] (j visited first, j's disc covers i's pixel) among N slots and a dump slot
    # (far from every pixel: no conflicts; _resolve_dense sets its column)
    q = torch.cat((rxy, c.far.expand(B, 1, 2)), 1)
    conf = _pair_conflicts(q, c.r2)
    conf &= _lower(N + 1, dev)
    keep_sorted, left = _resolve_dense(conf, torch.cat((eligible, c.no.expand(B, 1)), 1), rounds)
    keep_sorted, left = keep_sorted[:, :N], left[:, :N]
    keep = torch.zeros_like(keep_sorted).scatter_(1, order, keep_sorted)

    # row spans of the kept discs: +1 at the start, -1 (255) after the end, one cumsum along x
    x0 = (cl[..., 0, None] - c.hws).clamp_min_(0)
    x1 = (cl[..., 0, None] + c.hws1).clamp_max_(W)
    row = (cl[..., 1] + c.row_base)[..., None] + c.dys
    row *= W + 1
    inc = keep_sorted.to(torch.uint8)[..., None]  # 0 for the points not kept
    diff = torch.zeros(B * (H + 2 * c.r) * (W + 1), dtype=torch.uint8, device=dev)
    diff.index_put_((row + x0,), inc, accumulate=True)
    diff.index_put_((row + x1,), inc * 255, accumulate=True)
    cover = diff.view(B, H + 2 * c.r, W + 1)[:, c.r:c.r + H].cumsum(-1, dtype=torch.uint8)
    mask.mul_(torch.logical_not(cover[..., :W]).view(torch.uint8))
    return keep, mask, left.any(1)


class _MaskConstants:
    pass


@cached(32)
def _mask_constants(B: int, H: int, W: int, radius: float, device: torch.device) -> _MaskConstants:
    """Device constants of :func:`_distance_mask_capturable` (built once per sizes, radius, device)."""
    c = _MaskConstants()
    c.r = int(radius)
    dys, hws = _span_table(radius, device)
    c.dys = dys + c.r  # span rows in the padded buffer, relative to the centre row
    c.hws = hws
    c.hws1 = hws + 1
    c.size_f = float(max(H, W))  # clamp before the long conversion (any value >= W, H is outside)
    i2 = torch.arange(2, device=device)  # built on the device (no upload, traceable)
    c.size_m1 = i2 * (H - W) + (W - 1)  # (W - 1, H - 1)
    c.stride = i2 * (W - 1) + 1  # (1, W): flat index x + W y
    # integer d²: d² <= r²  <=>  d² <= floor(r²); beyond every d² of the (clamped) points: no more
    c.r2 = int(min(math.floor(float(radius) ** 2), 4 * (max(H, W) + 2) ** 2))
    c.far = torch.full((1, 1, 2), -4 * (max(H, W) + 2), dtype=torch.long, device=device)  # the dump slot
    c.no = torch.zeros(1, 1, dtype=torch.bool, device=device)
    c.row_base = (_iota(B, device) * (H + 2 * c.r))[:, None]
    return c


def fisheye_mask(
    height: int,
    width: int,
    radius: float | None = None,
    center: Tuple[float, float] | None = None,
    device=None,
) -> torch.Tensor:
    """Binarised analytic fisheye mask: 255 inside the disc, 0 outside.

    Convention:
        Pixel ``(x, y)`` is 255 iff ``(x - cx)² + (y - cy)² <= radius²``. Defaults: centre
        ``((W - 1) / 2, (H - 1) / 2)``; radius ``271 * min(H, W) / 512``, i.e. VINS-Mono's
        ``config/fisheye_mask.jpg`` (512x512, used by the TUM config) scaled to the image:
        for 512x512 the ``== 255`` pixels agree with the JPEG on 99.1 % of pixels (the rest is the
        JPEG's soft edge ring). The unused ``fisheye_mask_752x480.jpg`` is reproduced with
        ``radius=279.5`` (99.4 %).

    Returns:
        ``(H, W)`` uint8.
    """
    H, W = int(height), int(width)
    if H < 1 or W < 1:
        raise ConfigError(f"fisheye_mask: size must be positive, got {(H, W)}")
    if radius is None:
        radius = _FISHEYE_RADIUS_512 * min(H, W) / 512.0
    if center is None:
        center = ((W - 1) / 2.0, (H - 1) / 2.0)
    ys = torch.arange(H, device=device, dtype=torch.float64)[:, None] - float(center[1])
    xs = torch.arange(W, device=device, dtype=torch.float64)[None, :] - float(center[0])
    inside = xs * xs + ys * ys <= float(radius) ** 2
    return inside.to(torch.uint8) * 255
