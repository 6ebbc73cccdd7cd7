"""VINS's ``equalize`` step: CLAHE as OpenCV's ``cv2.createCLAHE(clip_limit, tile_grid_size).apply``
(8-bit), batched.

Reproduces OpenCV's algorithm step by step (spec §5.3), in float32 where OpenCV uses float32, so
that the output equals OpenCV's bit for bit on real images (measured: 100 % identical pixels on
EuRoC frames, see ``tests/test_clahe.py``):

* tile size ``(W // gx, H // gy)`` when both W and H are multiples of the grid; otherwise the
  histogram source is padded bottom/right with BORDER_REFLECT_101 by ``gx - W % gx`` and
  ``gy - H % gy`` (a dimension that was already divisible then gets a whole extra tile - an
  OpenCV quirk kept on purpose);
* per tile: 256-bin histogram, ``clip = max(1, int(clip_limit * area / 256))``, the clipped
  excess is spread as ``excess // 256`` on every bin plus one count on bins ``0, s, 2s, ...``
  (``residual`` of them, ``s = max(256 // residual, 1)``); ``LUT = saturate(cvRound(cumsum *
  (255 / area)))`` in float32;
* output: bilinear blend of the four nearest tile LUTs at tile-centre coordinates
  ``x / tileW - 0.5`` (clamped to the outer tiles), float32, rounded half-to-even like cvRound.

kornia's ``enhance.equalize_clahe`` is not used: it spreads the clipped residual over the first
``residual`` bins (not every ``s``-th bin), pads/tiles differently and works on 0..1 floats, which
on a EuRoC frame gives max |diff| 2 grey levels and only 77.6 % identical pixels against OpenCV
(measured with kornia 0.9.0), which misses the 99.9 % bar.

The module is named for the VINS step so that no public name of the package equals a module name
(``torch_frontend.clahe`` is the function, also after ``import torch_frontend.equalize``).
"""

from __future__ import annotations

import sys
from typing import NamedTuple, Optional, Tuple

import torch
import torch.nn.functional as F

from . import _tuning
from ._autodiff import derivative_wanted
from ._cache import cached
from ._checks import as_image_batch
from .errors import ConfigError

__all__ = ["clahe"]


def clahe(img: torch.Tensor, clip_limit: float = 3.0, tile_grid_size: Tuple[int, int] = (8, 8),
          backend: Optional[str] = None) -> torch.Tensor:
    """Contrast-limited adaptive histogram equalisation, as ``cv2.createCLAHE(...).apply``.

    Convention:
        Grey levels are 8-bit; float input is rounded (half-to-even) and clamped to 0..255 first.
        ``tile_grid_size`` is ``(tiles_x, tiles_y)`` like OpenCV. ``clip_limit <= 0`` disables
        clipping (plain tiled equalisation), as in OpenCV.

    Args:
        img: ``(B, 1, H, W)`` or ``(B, H, W)``, uint8 or float 0..255.
        clip_limit: OpenCV clip limit (3.0 in VINS).
        tile_grid_size: ``(tiles_x, tiles_y)``.
        backend: the kernel: None / ``"auto"`` (the device's ``_tuning`` strategy: the fused op
            ``torch_frontend::clahe`` on the CPU and CUDA, falling back with one warning where it
            cannot run), ``"fused"`` (a ``ConfigError`` where it cannot run) or ``"tensor"`` (the
            tensor CLAHE below). Both give OpenCV's bits (``docs/kernels.md``, "CLAHE").

    Returns:
        ``(B, 1, H, W)`` uint8 (same layout as the input: ``(B, H, W)`` in, ``(B, H, W)`` out).

    Raises:
        ValueError: wrong image shape. ConfigError: bad grid size, or an image too small for the
        reflect-101 padding.
    """
    squeeze = img.dim() == 3
    x = as_image_batch(img, "img")
    gx, gy = int(tile_grid_size[0]), int(tile_grid_size[1])
    if gx < 1 or gy < 1:
        raise ConfigError(f"tile_grid_size must be positive, got {tile_grid_size}")
    check_grid(x.shape[-2], x.shape[-1], gx, gy)
    if x.dtype != torch.uint8:
        x = x.round().clamp(0, 255).to(torch.uint8)
    from .fused import resolve_clahe_backend

    be = resolve_clahe_backend(backend, x.device)
    # _clahe_impl views the image as flat rows: a transposed / sliced image is copied first
    out = _clahe_impl(x[:, 0].contiguous(), float(clip_limit), gx, gy, backend=be).image
    return out if squeeze else out.unsqueeze(1)


def check_grid(height: int, width: int, gx: int, gy: int) -> None:
    """Raise ``ConfigError`` when an image of ``width x height`` is too small for the reflect-101
    padding of a ``gx x gy`` tile grid (the check :func:`clahe` makes; a pipeline that calls
    :func:`_clahe_impl` makes it once per image size)."""
    if width % gx == 0 and height % gy == 0:
        return
    if gx - width % gx >= width or gy - height % gy >= height:
        raise ConfigError(f"image {width}x{height} too small for CLAHE padding with grid {gx}x{gy}")


class ClaheResult(NamedTuple):
    """What :func:`_clahe_impl` returns, on both paths.

    Attributes:
        image: ``(B, H, W)`` uint8, the equalised image.
        overflow: always None: CLAHE has no budget (its work depends on sizes only), so both paths
            are exact.
    """

    image: torch.Tensor
    overflow: Optional[torch.Tensor] = None


def _clahe_impl(src: torch.Tensor, clip_limit: float, gx: int, gy: int, *, capturable: bool = False,
                backend: str = "tensor") -> ClaheResult:
    """CLAHE of ``src`` ``(B, H, W)`` uint8, contiguous, no input checks (the kernel's ``_impl``):
    a :class:`ClaheResult` holding the ``(B, H, W)`` uint8 image.

    ``clip_limit`` as OpenCV (``<= 0``: no clipping); ``gx, gy`` tiles along x / y (>= 1, the image
    large enough for the padding: :func:`check_grid`).

    On the CPU the per-pixel passes run on blocks of rows (``_tuning.Strategy.clahe_rows``): the
    float temporaries then stay in cache and below glibc's mmap threshold. Elsewhere: one block.
    ``capturable``: one block on every device, histograms by ``index_add_`` into a buffer of known
    size (no ``bincount``: its output size is read back on CUDA), a kernel count independent of B;
    the output is the same, bit for bit (:func:`_clahe_capturable`).

    ``backend``: a resolved backend (``fused.resolve_clahe_backend``): ``"fused"`` runs the one op
    ``torch_frontend::clahe`` (``fused/clahe_op.py``; capturable on CUDA: two launches, no sync)
    on both paths, ``"tensor"`` the tensor code below. The same bits.
    """
    if backend == "fused":
        from .fused.clahe_op import clahe_op

        return ClaheResult(clahe_op(src, float(clip_limit), gx, gy))
    if capturable:
        return ClaheResult(_clahe_capturable(src, clip_limit, gx, gy))
    B, H, W = src.shape
    dev = src.device
    rows = _tuning.for_device(dev).clahe_rows
    if W % gx == 0 and H % gy == 0:
        lut_src = src
    else:
        pad_x, pad_y = gx - W % gx, gy - H % gy
        # reflect-101 == torch 'reflect'; pad works on floats only (values stay exact integers).
        lut_src = F.pad(src[:, None].float(), (0, pad_x, 0, pad_y), mode="reflect")[:, 0].to(torch.uint8)
    Hs, Ws = lut_src.shape[-2:]
    th, tw = Hs // gy, Ws // gx
    area = th * tw
    T = gy * gx
    geo = _geometry(B, H, W, Hs, Ws, gx, gy, dev)

    # --- per-tile histograms: one int32 key (stream, tile, value) per pixel, bincount ----------
    # (int32 keys: no int64 image-sized temporaries; the uint8 -> int32 conversion and an in-place
    # add cost half of one mixed-dtype add)
    hist = torch.zeros(B * T * 256, dtype=torch.int64, device=dev)
    hs2 = lut_src.reshape(B * Hs, Ws)
    hk2 = geo.hist_key.view(B * Hs, Ws)
    for r0, r1 in rows(B * Hs, Ws):
        # keys of these rows lie in [lo, hi): count only that range (a histogram of the whole batch
        # per block made the work grow with B^2)
        lo, hi = (r0 // Hs) * T * 256, ((r1 - 1) // Hs + 1) * T * 256
        key = hs2[r0:r1].int().add_(hk2[r0:r1])
        if lo:
            key.sub_(lo)
        hist[lo:hi] += torch.bincount(key.view(-1), minlength=hi - lo)
    hist = hist.view(B, T, 256)

    # --- clip and redistribute exactly as OpenCV (tiny (B, T, 256) tensors) -----------------
    hist = _clip_histograms(hist, clip_limit, area, geo.i256)

    # float32 like OpenCV: sum * lutScale with lutScale = 255.f / area, then cvRound + saturate.
    lut = (hist.cumsum(-1).float() * geo.lut_scale).round_().clamp_(0, 255)  # (B, T, 256) float32

    # --- bilinear interpolation between tile LUTs -------------------------------------------
    # The four LUTs a pixel blends depend on its interpolation cell only: a small (stream, cell,
    # value) table holding l11 / l12 / l21 / l22 packed as the four bytes of one int32 (LUT values
    # are integers 0..255), read with one int32 index per pixel — one gather instead of four (the
    # gathers dominate: an index_select costs ~10x an elementwise pass) — and unpacked into planar
    # float32 rows (every following op contiguous and vectorised).
    l8 = lut.view(B, gy, gx, 256).to(torch.int32)
    packed = None
    for k, (cy, cx) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
        t = l8[:, geo.cell_ty[:, cy]][:, :, geo.cell_tx[:, cx]].reshape(-1)  # (B * ncy * ncx * 256,)
        packed = t if packed is None else packed.bitwise_or_(t.bitwise_left_shift_(8 * k))
    s2 = src.reshape(B * H, W)
    ck2 = geo.cell_key.view(B * H, W)
    out = torch.empty(B * H, W, dtype=torch.uint8, device=dev)
    little = sys.byteorder == "little"
    for r0, r1 in rows(B * H, W):
        idx = s2[r0:r1].int().add_(ck2[r0:r1]).view(-1)  # int32 (uint8 + int32 in one op is ~2x slower)
        n = r1 - r0
        q = packed.index_select(0, idx)
        if little:  # byte k of each int32 is LUT k: one contiguous uint8 -> float32 pass
            f = q.view(torch.uint8).view(n, W, 4).float()
        else:
            f = torch.stack([(q >> (8 * k)) & 255 for k in range(4)], -1).view(n, W, 4).float()
        ya1, ya = geo.ya1[r0:r1], geo.ya[r0:r1]
        # OpenCV's float32 expression and order: (l11*xa1 + l12*xa)*ya1 + (l21*xa1 + l22*xa)*ya,
        # every product and sum rounded separately, as OpenCV (no fused multiply-add).
        f *= geo.xw  # (W, 4): xa1, xa, xa1, xa
        top = torch.add(f[..., 0], f[..., 1])
        bot = torch.add(f[..., 2], f[..., 3])
        top *= ya1
        bot *= ya
        top += bot
        # values lie in [0, 255] up to float rounding, so the rounded value is a valid uint8;
        # going through int32 is ~2x faster on CPU than a direct float -> uint8 conversion.
        out[r0:r1] = top.round_().to(torch.int32)
    return ClaheResult(out.view(B, H, W))


def _clip_histograms(hist: torch.Tensor, clip_limit: float, area: int, i256: torch.Tensor) -> torch.Tensor:
    """OpenCV's clip and redistribution of ``hist (B, T, 256)`` integer tile histograms (``area``
    pixels per tile; ``clip_limit <= 0``: no clipping): bins above ``max(int(clip_limit area / 256),
    1)`` are cut, the excess spread evenly, its remainder one count every ``step`` bins. ``i256``:
    ``arange(256)`` on the device. Integer arithmetic in ``hist``'s dtype."""
    if clip_limit <= 0.0:
        return hist
    clip = max(int(clip_limit * area / 256), 1)
    excess = (hist - clip).clamp_min_(0).sum(-1, keepdim=True, dtype=hist.dtype)  # (B, T, 1)
    hist = hist.clamp_max(clip)
    batch = excess // 256
    residual = excess - batch * 256
    step = (256 // residual.clamp_min(1)).clamp_min_(1)
    extra = (i256 % step == 0) & (i256 // step < residual)
    hist += batch
    hist += extra
    return hist


def _histograms_capturable(src: torch.Tensor, clip_limit: float, gx: int, gy: int):
    """The clipped tile histograms of ``src (B, H, W)`` uint8 in a fixed op sequence: ``(hist (B, T,
    256) int32, geo, area)`` (histograms by ``index_add_`` of ones: int32 atomics on CUDA, no
    ``bincount``, whose output size is read back)."""
    B, H, W = src.shape
    dev = src.device
    if W % gx == 0 and H % gy == 0:
        lut_src = src
    else:
        lut_src = F.pad(src[:, None].float(), (0, gx - W % gx, 0, gy - H % gy), mode="reflect")[:, 0].to(torch.uint8)
    Hs, Ws = lut_src.shape[-2:]
    area = (Hs // gy) * (Ws // gx)
    geo = _geometry(B, H, W, Hs, Ws, gx, gy, dev)
    key = lut_src.reshape(-1).int().add_(geo.hist_key.view(-1))  # (B * Hs * Ws,) int32
    hist = torch.zeros(B * gy * gx * 256, dtype=torch.int32, device=dev)
    hist.index_add_(0, key, geo.ones.expand(key.numel()))
    hist = _clip_histograms(hist.view(B, gy * gx, 256), clip_limit, area, geo.i256)  # integers: exact
    return hist, geo, area


def _blend(q: torch.Tensor, geo, B: int, H: int, W: int) -> torch.Tensor:
    """OpenCV's float32 bilinear blend of the four tile values per pixel ``q (B * H, W, 4)`` float32
    (l11, l12, l21, l22): ``(l11 xa1 + l12 xa) ya1 + (l21 xa1 + l22 xa) ya``, every product and sum
    rounded separately, as OpenCV (no fused multiply-add). Returns ``(B * H, W)``; ``q`` is scaled in place."""
    q *= geo.xw
    top = torch.add(q[..., 0], q[..., 1])
    bot = torch.add(q[..., 2], q[..., 3])
    top *= geo.ya1
    bot *= geo.ya
    top += bot
    return top


def _clahe_capturable(src: torch.Tensor, clip_limit: float, gx: int, gy: int) -> torch.Tensor:
    """:func:`_clahe_impl` with a fixed op sequence (``capturable=True``): the same float32
    arithmetic in the same order as the default path, so the same bits.

    An image whose size is a multiple of the grid (no histogram padding) takes
    :func:`_clahe_blocks` (one int32 key per pixel serves the histograms and the LUT gather, ~20
    kernels); otherwise the histograms of the padded image are counted with their own key
    (:func:`_clahe_padded`).
    """
    B, H, W = src.shape
    if W % gx == 0 and H % gy == 0 and _tuning.for_device(src.device).clahe_block_keys:
        blk = _block_geometry(B, H, W, gx, gy, src.device)
        if blk is not None:
            return _clahe_blocks(src, clip_limit, gx, gy, blk)
    return _clahe_padded(src, clip_limit, gx, gy)


def _clahe_padded(src: torch.Tensor, clip_limit: float, gx: int, gy: int) -> torch.Tensor:
    """The capturable CLAHE of any size: histograms (of the reflect-101 padded image) by
    ``index_add_`` of ones (int32 atomics on CUDA), the four tile LUTs of every interpolation
    cell gathered as bytes with one cached index and read per pixel as one int32 (4 bytes: l11,
    l12, l21, l22)."""
    B, H, W = src.shape
    hist, geo, _ = _histograms_capturable(src, clip_limit, gx, gy)
    T = gx * gy
    lut = (hist.cumsum(-1).float() * geo.lut_scale).round_().clamp_(0, 255).to(torch.uint8)  # (B, T, 256)
    packed = lut.view(B, T * 256).index_select(1, geo.lut_bytes).view(torch.int32).view(-1)  # (B * cells * 256,)
    q = packed.index_select(0, src.reshape(-1).int().add_(geo.cell_key.view(-1)))
    top = _blend(q.view(torch.uint8).view(B * H, W, 4).float(), geo, B, H, W)
    # in [0, 255] up to float rounding: the rounded value converts exactly
    return top.round_().to(torch.uint8).view(B, H, W)


# 2^23: adding it to a float32 in [0, 2^22) rounds it to an integer, half to even (the spacing of
# float32 in [2^23, 2^24) is 1), as cvRound / torch.round; the integer is then the low mantissa
# bits, so an 8-bit result is byte 0 (little-endian) / 3 (big-endian) of the float32 word
_ROUND_MAGIC = float(1 << 23)
_LOW_BYTE = 0 if sys.byteorder == "little" else 3


def _clahe_blocks(src: torch.Tensor, clip_limit: float, gx: int, gy: int, blk) -> torch.Tensor:
    """Capturable CLAHE of ``src (B, H, W)`` uint8 whose size is a multiple of the grid.

    Every tile is cut by the interpolation cell boundaries (tile centres) into 2 x 2 *blocks*
    (``NB = 4 gx gy``): a block lies in one tile and one cell. One int32 key per pixel,
    ``(b * 256 + v) * NB + block``, made in one op from the uint8 image and a broadcast offset,
    serves twice: the block histograms ``(B, 256, NB)`` are counted with ``index_add_`` (int32
    atomics on CUDA; summed 2 x 2 into the tile histograms), and it indexes the ``(B, 256, NB)``
    int32 table whose 4 bytes are the cell's four tile LUT values (l11, l12, l21, l22). Tables are
    value-major (``(B, 256, ...)``), so no transpose is needed anywhere.

    The blend is OpenCV's float32 expression with each product and sum rounded separately, as on
    the default path, in 4 passes over 4-, 2-, 2- and 1-lane planes; its rounding adds 2^23
    (:data:`_ROUND_MAGIC`) and keeps the low byte (the LUT's ``cvRound`` likewise).
    """
    B, H, W = src.shape
    NB = 4 * gx * gy
    T = gx * gy
    # --- one key per pixel, (B, H, W) order: (b * 256 + v) * NB + block (exact int32 arithmetic)
    key = torch.add(blk.offset, src.view(blk.view_shape), alpha=NB).view(-1)  # offset broadcast where it can
    hist = torch.zeros(B * 256 * NB, dtype=torch.int32, device=src.device)
    hist.index_add_(0, key, blk.ones.expand(key.numel()))
    # tile histograms (B, 256, T): the 2 x 2 blocks of each tile (block = (2 ty + hy) * 2gx + 2 tx + hx)
    hist = hist.view(B, 256, gy, 2, gx, 2).sum((3, 5), dtype=torch.int32).view(B, 256, T)
    if clip_limit > 0.0:
        hist = _clip_value_major(hist, clip_limit, blk)
    # LUT = cvRound(cumsum * (255.f / area)) in float32 (in [0, 255] up to rounding: no saturation
    # needed); the product is rounded to float32 first, then to an integer by the 2^23 addition
    lut = torch.mul(hist.cumsum(1, dtype=torch.int32), blk.lut_scale).add_(_ROUND_MAGIC)  # (B, 256, T) float32
    # the four LUT bytes of every (value, block): byte _LOW_BYTE of the float words of its cell's tiles
    packed = lut.view(torch.uint8).view(B, 256, T * 4).index_select(2, blk.lut_bytes).view(torch.int32)
    q = packed.view(-1).index_select(0, key).view(torch.uint8).view(B, H, W, 4)  # (l11, l12, l21, l22) bytes
    del key, packed  # peak memory: dead before the float planes exist
    # OpenCV: (l11 xa1 + l12 xa) ya1 + (l21 xa1 + l22 xa) ya, every product and sum rounded in float32
    p = torch.mul(q, blk.xw)  # uint8 * float32 -> float32 (B, H, W, 4): exact conversion, one rounding
    del q
    # the sums and their products in place in lanes 0 and 2 (no second image-sized float plane:
    # the step's peak memory is CLAHE's at large B); the same ops on the same values
    tb = p[..., 0::2]
    tb += p[..., 1::2]  # (B, H, W, 2): top, bottom
    tb *= blk.yw  # (H, 1, 2): ya1, ya
    r = torch.add(tb[..., 0], tb[..., 1]).add_(_ROUND_MAGIC)  # (B, H, W); cvRound via 2^23
    return r.view(torch.uint8).view(B, H, W, 4)[..., _LOW_BYTE].contiguous()


def _clip_value_major(hist: torch.Tensor, clip_limit: float, blk) -> torch.Tensor:
    """:func:`_clip_histograms` of value-major ``hist (B, 256, T)`` int32 tile histograms, in place.

    The excess is ``area - sum(min(hist, clip))`` (a tile's bins sum to its area); the residual's
    one-count-every-``step``-bins pattern is a lookup in a cached ``(256 bins, 256 residuals)`` 0/1
    table (:attr:`_BlockGeo.extra`). Integer arithmetic: exact."""
    hist = hist.clamp_max_(max(int(clip_limit * blk.area / 256), 1))
    excess = torch.rsub(hist.sum(1, keepdim=True, dtype=torch.int32), blk.area)  # (B, 1, T), >= 0
    hist += blk.extra[blk.i256_col, excess & 255]  # (256, 1) x (B, 1, T) -> (B, 256, T)
    hist += excess >> 8  # excess // 256 on every bin
    return hist


class _BlockGeo:
    pass


@cached(16)
def _block_geometry(B, H, W, gx, gy, dev):
    """Keys, tables and weights of :func:`_clahe_blocks` (sizes and device only; cached), or None
    when a tile is not cut into exactly 2 x 2 blocks by the cell boundaries (a tile 1 pixel wide)."""
    th, tw = H // gy, W // gx
    i32, f32 = torch.int32, torch.float32
    inv_tw = torch.tensor(1.0, dtype=f32) / torch.tensor(float(tw), dtype=f32)
    inv_th = torch.tensor(1.0, dtype=f32) / torch.tensor(float(th), dtype=f32)
    # OpenCV's float32 tile coordinates, as _geometry
    txf = torch.arange(W, dtype=f32) * inv_tw - 0.5
    tyf = torch.arange(H, dtype=f32) * inv_th - 0.5
    tx1, ty1 = torch.floor(txf), torch.floor(tyf)
    xa, ya = txf - tx1, tyf - ty1

    def halves(t1, n, size):
        """Per pixel: which half of its tile (0: the cell left of / above the tile centre, 1: the
        other), or None unless every tile has both halves; the regular half length or None."""
        tile = torch.arange(n) // size
        half = t1.long() + 1 - tile  # cell index - tile index: 0 or 1
        blocks = tile * 2 + half
        if (bool(((half < 0) | (half > 1)).any()) or bool((blocks[1:] < blocks[:-1]).any())
                or blocks.unique().numel() != 2 * (n // size)):
            return None, None
        counts = torch.bincount(blocks)
        regular = size % 2 == 0 and bool((counts == size // 2).all())
        return blocks, (size // 2 if regular else None)

    by, ly = halves(ty1, H, th)
    bx, lx = halves(tx1, W, tw)
    if by is None or bx is None:
        return None
    geo = _BlockGeo()
    NB = 4 * gx * gy
    boff = torch.arange(B)[:, None, None] * (256 * NB)
    # the offset (b * 256 * NB + block) in one add with the uint8 image: broadcast along the rows
    # of a block where the blocks are a regular grid in y (or in x), else a (B, H, W) table. (The
    # float32 cell boundary need not sit at the exact tile centre: 752 / 8 gives blocks 48, 46, 47...)
    blocks = by[:, None] * (2 * gx) + bx[None, :]  # (H, W)
    if ly is not None:  # src as (B, 2gy, ly, W), offset (B, 2gy, 1, W)
        geo.view_shape = (B, 2 * gy, ly, W)
        off = boff.view(B, 1, 1, 1) + blocks[::ly].view(1, 2 * gy, 1, W)
    elif lx is not None:  # src as (B, H, 2gx, lx), offset (B, H, 2gx, 1)
        geo.view_shape = (B, H, 2 * gx, lx)
        off = boff.view(B, 1, 1, 1) + blocks[:, ::lx].reshape(1, H, 2 * gx, 1)
    else:
        geo.view_shape = (B, H, W)
        off = boff + blocks
    geo.offset = off.to(dev, i32).contiguous()
    geo.ones = torch.ones(1, dtype=i32, device=dev)
    area = th * tw
    geo.area = area
    geo.lut_scale = (torch.tensor(255.0, dtype=f32) / torch.tensor(float(area), dtype=f32)).to(dev)
    # residual -> one extra count on bins 0, s, 2s, ... (the first ``residual`` of them), s = 256 // residual
    r = torch.arange(256)
    i = torch.arange(256)[:, None]
    step = (256 // r.clamp_min(1)).clamp_min(1)[None, :]
    geo.extra = ((i % step == 0) & (i // step < r[None, :])).to(dev, i32)  # (256 bins, 256 residuals)
    geo.i256_col = torch.arange(256, device=dev)[:, None]
    # block -> the tiles of its cell: cell (cy, cx) = (tile + half) blends tiles rows clamp(cy - 1, 0)
    # and clamp(cy, gy - 1), columns likewise
    hb = torch.arange(2 * gy)
    wb = torch.arange(2 * gx)
    cy = hb // 2 + hb % 2  # cell row 0..gy
    cx = wb // 2 + wb % 2
    ry = torch.stack([(cy - 1).clamp_min(0), cy.clamp_max(gy - 1)], -1)  # (2gy, 2): top, bottom tile rows
    rx = torch.stack([(cx - 1).clamp_min(0), cx.clamp_max(gx - 1)], -1)  # (2gx, 2): left, right tile columns
    tiles = torch.stack([ry[:, None, a] * gx + rx[None, :, c] for a, c in ((0, 0), (0, 1), (1, 0), (1, 1))], -1)
    geo.lut_bytes = (tiles.reshape(-1) * 4 + _LOW_BYTE).to(dev, i32)  # (NB * 4,): bytes of (B, 256, T) float32
    geo.xw = torch.stack((1.0 - xa, xa, 1.0 - xa, xa), -1).to(dev)  # (W, 4)
    geo.yw = torch.stack((1.0 - ya, ya), -1)[:, None, :].contiguous().to(dev)  # (H, 1, 2)
    return geo


def _clahe_slope(src: torch.Tensor, clip_limit: float, gx: int, gy: int) -> torch.Tensor:
    """The local slope ``d out / d in`` of CLAHE's mapping at every pixel of ``src (B, H, W)`` uint8:
    ``(B, H, W)`` float32, grey levels out per grey level in.

    The mapping of a pixel with grey level ``v`` is the bilinear blend of four tile LUTs, and each
    LUT is the clipped histogram's cumulative sum times ``255 / area`` (rounded). The slope is the
    blend of the four *unrounded* LUTs' central differences, ``(c[v + 1] - c[v - 1]) / 2 =
    (h[v] + h[v + 1]) 255 / (2 area)`` (one-sided at 0 and 255): the rounded LUT's steps are 0 or
    1 grey level wide, and its difference quotient would be 0 or jump. Clipping bounds it by about
    ``clip_limit`` (the point of contrast limiting): the gradient cannot explode. The LUTs
    themselves (the histograms) are treated as constants: a discrete function of the image.
    """
    B, H, W = src.shape
    hist, geo, _ = _histograms_capturable(src, clip_limit, gx, gy)
    T = gx * gy
    c = hist.cumsum(-1).float() * geo.lut_scale  # (B, T, 256) unrounded LUTs
    slope = torch.empty_like(c)
    slope[..., 1:-1] = (c[..., 2:] - c[..., :-2]) * 0.5
    slope[..., 0] = c[..., 1] - c[..., 0]
    slope[..., -1] = c[..., -1] - c[..., -2]
    # the four tile slopes of every (cell, value), as the capturable path's packed LUT bytes
    cell = slope.view(B, T * 256).index_select(1, geo.lut_bytes).view(-1, 4)  # (B * cells * 256, 4)
    q = cell.index_select(0, src.reshape(-1).int().add_(geo.cell_key.view(-1))).view(B * H, W, 4)
    return _blend(q, geo, B, H, W).view(B, H, W)


def _clahe_straight_through(img: torch.Tensor, clip_limit: float, gx: int, gy: int, *,
                            capturable: bool = False, backend: str = "tensor") -> torch.Tensor:
    """CLAHE of ``img (B, H, W)`` float grey levels that are integers 0..255 (the differentiable
    tracker's door makes them so): ``(B, H, W)`` float holding :func:`_clahe_impl`'s output bit for bit,
    with the straight-through gradient ``d out / d in`` = the LUT's local slope
    (:func:`_clahe_slope`). Without a gradient to record: the 8-bit result as float. ``backend``
    computes the values (a resolved backend, :func:`_clahe_impl`); the slope is always the tensor
    CLAHE's (its histograms, unrounded LUTs)."""
    u8 = img.detach().to(torch.uint8).contiguous()
    hard = _clahe_impl(u8, clip_limit, gx, gy, capturable=capturable, backend=backend).image.to(img.dtype)
    if not derivative_wanted(img):
        return hard
    slope = _clahe_slope(u8, clip_limit, gx, gy).to(img.dtype)
    return hard + slope * (img - img.detach())  # img - img.detach() is exactly 0: the value is hard


class _Geo:
    pass


@cached(16)
def _geometry(B, H, W, Hs, Ws, gx, gy, dev) -> _Geo:
    """Per-pixel keys and interpolation weights: depend on sizes and device only (cached)."""
    th, tw = Hs // gy, Ws // gx
    T = gy * gx
    ncx, ncy = gx + 1, gy + 1  # cells: tx1 in -1..gx-1 (clamped) -> gx + 1 kinds, same for y
    geo = _Geo()
    i32 = torch.int32
    ys = torch.arange(Hs, device=dev, dtype=i32) // th
    xs = torch.arange(Ws, device=dev, dtype=i32) // tw
    tile256 = (ys[:, None] * gx + xs[None, :]) * 256
    boff = torch.arange(B, device=dev, dtype=i32)[:, None, None] * (T * 256)
    geo.hist_key = (tile256 + boff).contiguous()  # (B, Hs, Ws) int32
    geo.i256 = torch.arange(256, device=dev)
    geo.lut_scale = (torch.tensor(255.0, dtype=torch.float32) / torch.tensor(float(tw * th), dtype=torch.float32)).to(dev)

    inv_tw = torch.tensor(1.0, dtype=torch.float32) / torch.tensor(float(tw), dtype=torch.float32)
    inv_th = torch.tensor(1.0, dtype=torch.float32) / torch.tensor(float(th), dtype=torch.float32)
    txf = torch.arange(W, dtype=torch.float32) * inv_tw - 0.5
    tyf = torch.arange(H, dtype=torch.float32) * inv_th - 0.5
    tx1 = torch.floor(txf)
    ty1 = torch.floor(tyf)
    xa = txf - tx1
    ya = tyf - ty1
    geo.xw = torch.stack((1.0 - xa, xa, 1.0 - xa, xa), -1).to(dev)  # (W, 4) per-column weights
    # per-row weights, repeated per stream to match the (B * H, W) row blocks
    geo.ya1 = (1.0 - ya).repeat(B)[:, None].to(dev)  # (B * H, 1)
    geo.ya = ya.repeat(B)[:, None].to(dev)
    cy_ = torch.arange(-1, gy, device=dev)
    cx_ = torch.arange(-1, gx, device=dev)
    geo.cell_ty = torch.stack([cy_.clamp_min(0), (cy_ + 1).clamp_max(gy - 1)], -1)  # (ncy, 2)
    geo.cell_tx = torch.stack([cx_.clamp_min(0), (cx_ + 1).clamp_max(gx - 1)], -1)  # (ncx, 2)
    cell = ((ty1.long() + 1)[:, None] * ncx + (tx1.long() + 1)[None, :]).to(dev, i32)  # (H, W)
    boff_c = torch.arange(B, device=dev, dtype=i32)[:, None, None] * (ncy * ncx * 256)
    geo.cell_key = (cell * 256 + boff_c).contiguous()  # (B, H, W) int32
    # capturable path: byte k of entry (b, cell, v) of the packed LUT table = LUT k of that cell
    # (one index for all streams, along a stream's T * 256 LUT entries)
    tiles = torch.stack([geo.cell_ty[:, cy][:, None] * gx + geo.cell_tx[:, cx][None, :]
                         for cy, cx in ((0, 0), (0, 1), (1, 0), (1, 1))], -1)  # (ncy, ncx, 4)
    lut_idx = tiles[:, :, None, :] * 256 + torch.arange(256, device=dev)[None, None, :, None]
    geo.lut_bytes = lut_idx.reshape(-1).to(i32)  # (ncy * ncx * 256 * 4,)
    geo.ones = torch.ones(1, dtype=torch.int32, device=dev)
    return geo
