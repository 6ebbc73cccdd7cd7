"""Image pyramid (``cv2.pyrDown`` chain) and Scharr derivatives as used by ``calcOpticalFlowPyrLK``.

Convention:
    Images are ``(B, 1, H, W)`` (``(B, H, W)`` accepted), uint8 or float grey levels 0..255. Pixel
    centres sit at integer coordinates. Level ``l`` of a pyramid has size
    ``ceil(W_{l-1}/2) x ceil(H_{l-1}/2)``; a point ``p`` at level 0 is ``p / 2**l`` at level ``l``.

OpenCV facts reproduced here (spec §5.1):

* ``pyrDown``: 5x5 binomial ``[1 4 6 4 1]^T [1 4 6 4 1] / 256``, BORDER_REFLECT_101, output centred on
  even source pixels, size ``ceil(W/2) x ceil(H/2)``. For 8-bit images OpenCV computes the integer
  sum and rounds ``(sum + 128) >> 8`` (half up) at *every* level; ``build_pyramid`` does the same
  for uint8 input (``round_levels``) so that an LK on top of it sees the very same grey levels.
* Scharr derivatives (``calcSharrDeriv``): vertical ``[3 10 3]`` smoothing and horizontal
  ``[-1 0 1]`` difference for ``Ix`` (transposed for ``Iy``), BORDER_REFLECT_101, *not* normalised
  (a unit ramp gives 32) — the same values as ``cv2.Scharr(img, CV_16S, 1, 0)``.

The in-place fast forms (no autograd) perform the reference forms' operations in the same order
(``_tuning.inplace_ok``), so a float pyramid has the same values with and without gradients.
:func:`build_pyramid` checks its input and calls :func:`_build_pyramid_impl`, which a pipeline that
validated once calls directly.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Tuple

import torch
import torch.nn.functional as F

from . import _tuning
from ._autodiff import derivative_wanted, straight_through
from ._cache import cached, holds_plain_tensors
from ._checks import as_float_image, as_image_batch
from .errors import ConfigError
from .fused import resolve_backend
from .fused.layout import DEFAULT_PAD, PyramidLayout
from .fused.ops import MIN_PAD, pyramid_op

__all__ = ["Pyramid", "build_pyramid", "pyr_down", "scharr_gradients", "pad_reflect101"]


def _reflect101_index(n: int, before: int, after: int, device) -> torch.Tensor:
    """Source indices of OpenCV's ``borderInterpolate(p, n, BORDER_REFLECT_101)`` for
    ``p in [-before, n + after)`` (handles pads larger than the image by repeated reflection)."""
    p = torch.arange(-before, n + after, device=device)
    if n == 1:
        return torch.zeros_like(p)
    period = 2 * (n - 1)
    p = p.abs() % period
    return torch.where(p >= n, period - p, p)


def pad_reflect101(x: torch.Tensor, pad_h: int, pad_w: int) -> torch.Tensor:
    """Pad the last two dims by ``pad_h`` rows / ``pad_w`` columns on each side with
    BORDER_REFLECT_101 (``dcb|abcdefgh|gfe``).

    Implemented as an index gather (differentiable, any pad size, any image size >= 1) rather than
    ``F.pad(mode="reflect")``, which refuses pads >= the image size.
    """
    H, W = x.shape[-2:]
    if pad_h < H and pad_w < W and x.dim() == 4:
        # torch's "reflect" is reflect-101; faster than the gather, but limited to pads < size
        return F.pad(x, (pad_w, pad_w, pad_h, pad_h), mode="reflect")
    iy = _reflect101_index(H, pad_h, pad_h, x.device)
    ix = _reflect101_index(W, pad_w, pad_w, x.device)
    return x.index_select(-2, iy).index_select(-1, ix)


def _tap5(x: torch.Tensor, dim: int, n_out: int) -> torch.Tensor:
    """``[1 4 6 4 1]`` along ``dim`` evaluated at every second position: ``out[i] = x[2i] + 4 x[2i+1] +
    6 x[2i+2] + 4 x[2i+3] + x[2i+4]`` (``x`` already padded by 2), ``n_out`` outputs, summed as
    ``(((a + e) + 4 b) + 4 d) + 6 c`` (``add`` with ``alpha``: a fused multiply-add on CPU)."""
    a, b, c, d, e = (x.narrow(dim, k, 2 * n_out - 1)[(slice(None),) * (dim % x.dim()) + (slice(None, None, 2),)]
                     for k in range(5))
    if _tuning.inplace_ok(x):  # the same operations in place: 3 fewer full-size temporaries
        return torch.add(a, e).add_(b, alpha=4.0).add_(d, alpha=4.0).add_(c, alpha=6.0)
    return torch.add(torch.add(torch.add(a + e, b, alpha=4.0), d, alpha=4.0), c, alpha=6.0)


def _pyr_down_impl(img: torch.Tensor) -> torch.Tensor:
    # Separable 5-tap binomial evaluated only at the kept (even) rows, then the kept columns, on
    # strided slices of the padded image (3-4x faster than a 5x5 strided conv2d on CPU). Integer
    # taps, one division at the end: on integer grey levels every partial sum is an exact integer
    # (< 2^16) in float32, so the result is exactly ``sum / 256`` whatever the summation order.
    H, W = img.shape[-2:]
    padded = pad_reflect101(img, 2, 2)
    rows = _tap5(padded, -2, (H + 1) // 2)
    out = _tap5(rows, -1, (W + 1) // 2)
    return out * (1.0 / 256.0)  # a power of two: exact, same as ``/ 256``


def pyr_down(img: torch.Tensor) -> torch.Tensor:
    """Gaussian pyramid down-sampling, as ``cv2.pyrDown`` (default size and border).

    Args:
        img: ``(B, 1, H, W)`` or ``(B, H, W)``, uint8 or float grey levels.

    Returns:
        ``(B, 1, ceil(H/2), ceil(W/2))`` float (float32 for uint8 input), *not* rounded:
        ``floor(out + 0.5)`` equals ``cv2.pyrDown`` of a uint8 image exactly.

    Convention:
        ``out[y, x] = sum_{i,j} k[i] k[j] img[2y + i - 2, 2x + j - 2] / 256``, ``k = [1 4 6 4 1]``,
        out-of-image indices reflected with BORDER_REFLECT_101.
    """
    return _pyr_down_impl(as_float_image(img, "img"))


def _scharr_impl(img: torch.Tensor) -> torch.Tensor:
    """``(B, 1, H, W)`` float -> ``(B, 2, H, W)`` Scharr ``(Ix, Iy)`` (see :func:`scharr_gradients`)."""
    # separable, on shifted slices of the padded image (about 2x faster than a 1-channel conv2d):
    # Ix = [-1 0 1] along x of the [3 10 3] smoothing along y; Iy the transpose. Integer taps: exact
    # on integer grey levels whatever the order of the additions.
    H, W = img.shape[-2:]
    P = pad_reflect101(img, 1, 1)
    up, mid, down = P[..., 0:H, :], P[..., 1:H + 1, :], P[..., 2:H + 2, :]
    if not _tuning.inplace_ok(img):
        s = torch.add((up + down) * 3.0, mid, alpha=10.0)
        d = down - up
        ix = s[..., 2:] - s[..., :-2]
        iy = torch.add((d[..., :-2] + d[..., 2:]) * 3.0, d[..., 1:-1], alpha=10.0)
        return torch.cat([ix, iy], dim=1)
    # fast form: the same operations, both channels written straight into the output (no cat)
    out = img.new_empty(img.shape[:-3] + (2, H, W))
    ix, iy = out[..., 0:1, :, :], out[..., 1:2, :, :]
    s = torch.add(up, down).mul_(3.0).add_(mid, alpha=10.0)
    torch.sub(s[..., 2:], s[..., :-2], out=ix)
    d = torch.sub(down, up, out=s)  # reuse the buffer
    torch.add(d[..., :-2], d[..., 2:], out=iy)
    iy.mul_(3.0).add_(d[..., 1:-1], alpha=10.0)
    return out


def scharr_gradients(img: torch.Tensor) -> torch.Tensor:
    """3x3 Scharr derivatives ``(Ix, Iy)`` as OpenCV's LK (``calcSharrDeriv``) computes them.

    Args:
        img: ``(B, 1, H, W)`` or ``(B, H, W)``, uint8 or float grey levels.

    Returns:
        ``(B, 2, H, W)`` float: channel 0 ``Ix``, channel 1 ``Iy``; un-normalised (a ramp of slope 1
        grey level/px gives 32), equal to ``cv2.Scharr(img, cv2.CV_16S, 1, 0)`` / ``(…, 0, 1)``.

    Convention:
        BORDER_REFLECT_101 at the image edge (same as ``cv2.Scharr``'s default and ``calcSharrDeriv``).
    """
    return _scharr_impl(as_float_image(img, "img"))


@dataclass
class Pyramid:
    """An image pyramid kept between frames (the tracker keeps the last one).

    Attributes:
        levels: ``L + 1`` tensors ``(B, 1, H_l, W_l)`` grey levels, level 0 = the image: float, or, for
            a pyramid built by the fused kernel (``packed``), uint8 views into ``packed``.
        grads: ``None`` or ``L + 1`` tensors ``(B, 2, H_l, W_l)`` Scharr ``(Ix, Iy)`` of each level
            (optional: the LK computes the derivatives it needs from its own windows).
        rounded: levels hold OpenCV's 8-bit values (built from uint8 with per-level rounding); LK
            then defaults to its fixed-point emulation.
        packed: ``(B, total)`` uint8, the packed pyramid of ``fused/layout.py`` (every level padded by
            ``pad`` pixels of BORDER_REFLECT_101, as OpenCV's ``buildOpticalFlowPyramid`` stores them),
            or None (a pyramid of separate level tensors). The fused LK reads it as it is.
        pad: the border of ``packed`` (0 without it).

    The LK also caches padded copies of the levels here (:meth:`padded`), so that a pyramid that was
    the next image of one call is not padded again as the previous image of the next.
    """

    levels: List[torch.Tensor]
    grads: List[torch.Tensor] | None = None
    rounded: bool = False
    packed: torch.Tensor | None = None
    pad: int = 0
    # padded copies of the levels, keyed by (level, pad_h, pad_w, dtype): built once when the
    # pyramid is the *next* image of an LK call and reused when it is the *previous* one
    _padded: Dict[tuple, torch.Tensor] = field(default_factory=dict, init=False, repr=False, compare=False)

    @classmethod
    def from_packed(cls, packed: torch.Tensor, height: int, width: int, max_level: int, pad: int) -> Pyramid:
        """The pyramid of a packed ``(B, total)`` uint8 tensor (``fused/layout.py``), its levels as
        uint8 views (no copy)."""
        lay = PyramidLayout(height, width, max_level, pad)
        B = packed.shape[0]
        levels = []
        for (h, w), o in zip(lay.sizes, lay.offsets):
            hp, wp = h + 2 * pad, w + 2 * pad
            block = packed[:, o:o + hp * wp].view(B, 1, hp, wp)
            levels.append(block[..., pad:pad + h, pad:pad + w])
        return cls(levels, None, True, packed, pad)

    @property
    def layout(self) -> PyramidLayout | None:
        """The :class:`~torch_frontend.fused.layout.PyramidLayout` of ``packed`` (None without it)."""
        if self.packed is None:
            return None
        H, W = self.levels[0].shape[-2:]
        return PyramidLayout(int(H), int(W), self.max_level, self.pad)

    @property
    def max_level(self) -> int:
        return len(self.levels) - 1

    @property
    def batch(self) -> int:
        return self.levels[0].shape[0]

    def sizes(self) -> List[Tuple[int, int]]:
        """``(H_l, W_l)`` per level."""
        return [tuple(t.shape[-2:]) for t in self.levels]

    def with_gradients(self) -> Pyramid:
        """This pyramid with ``grads`` filled in: computed once if missing and cached on the object
        (a pyramid used as ``next`` of one LK call is the ``prev`` of the following one)."""
        if self.grads is None or len(self.grads) != len(self.levels):
            self.grads = [_scharr_impl(t if t.is_floating_point() else t.to(torch.float32)) for t in self.levels]
        return self

    def padded(self, level: int, pad_h: int, pad_w: int, dtype: torch.dtype | None = None) -> torch.Tensor:
        """Level ``level`` as ``dtype`` padded by ``pad_h`` rows / ``pad_w`` columns on each side with
        BORDER_REFLECT_101 (as ``buildOpticalFlowPyramid`` stores its levels), ``(B, 1, H + 2 pad_h,
        W + 2 pad_w)``. Cached on the pyramid unless the level needs a gradient (a copy padded under
        ``torch.no_grad`` would otherwise cut the gradient of a later call), or under a ``torch.func`` /
        forward-AD transform. A packed pyramid gives its stored border (a view for uint8, one
        conversion for another dtype) where it is wide enough."""
        t = self.levels[level]
        dtype = t.dtype if dtype is None else dtype
        key = (level, pad_h, pad_w, dtype)
        out = self._padded.get(key)
        if out is None:
            if self.packed is not None and pad_h <= self.pad and pad_w <= self.pad:
                p = self.pad
                h, w = t.shape[-2:]
                lay = self.layout
                hp, wp = lay.padded_shape(level)
                o = lay.offsets[level]
                block = self.packed[:, o:o + hp * wp].view(t.shape[0], 1, hp, wp)
                out = block[..., p - pad_h:p + h + pad_h, p - pad_w:p + w + pad_w]
                if dtype != torch.uint8:
                    out = out.to(dtype, memory_format=torch.contiguous_format)
            else:
                out = pad_reflect101(t.to(dtype), pad_h, pad_w)
            # a level that carries a derivative is padded per call (a copy padded under no_grad
            # would cut a later call's gradient); one padded under a torch.func transform is that
            # transform's wrapper, which must not outlive it
            if not derivative_wanted(t) and (torch.compiler.is_compiling() or holds_plain_tensors(out)):
                self._padded[key] = out
        return out

    def select(self, streams) -> Pyramid:
        """The pyramid of a subset of streams (``streams``: slice / index tensor along B); cached
        padded levels come along (as views for a slice)."""
        if self.packed is not None:
            lay = self.layout
            return Pyramid.from_packed(self.packed[streams], lay.height, lay.width, lay.max_level, lay.pad)
        g = None if self.grads is None else [t[streams] for t in self.grads]
        out = Pyramid([t[streams] for t in self.levels], g, self.rounded)
        out._padded = {k: v[streams] for k, v in self._padded.items()}
        return out

    def to(self, *args, **kwargs) -> Pyramid:
        if self.packed is not None:
            lay = self.layout
            packed = self.packed.to(*args, **kwargs)
            if packed.dtype == torch.uint8:
                return Pyramid.from_packed(packed, lay.height, lay.width, lay.max_level, lay.pad)
            return Pyramid([t.to(*args, **kwargs) for t in self.levels], None, self.rounded)
        g = None if self.grads is None else [t.to(*args, **kwargs) for t in self.grads]
        out = Pyramid([t.to(*args, **kwargs) for t in self.levels], g, self.rounded)
        for k, v in self._padded.items():
            v = v.to(*args, **kwargs)
            out._padded[k[:3] + (v.dtype,)] = v
        return out


def build_pyramid(
    img: torch.Tensor,
    max_level: int = 3,
    with_gradients: bool = True,
    round_levels: bool | None = None,
    *,
    pad: int = DEFAULT_PAD,
    backend: str | None = None,
) -> Pyramid:
    """Build levels ``0..max_level`` by repeated :func:`pyr_down` (``cv2.buildOpticalFlowPyramid``).

    Args:
        img: ``(B, 1, H, W)`` or ``(B, H, W)``, uint8 or float grey levels 0..255.
        max_level: last level index (3 => 4 levels), >= 0.
        with_gradients: also compute full-image Scharr ``(Ix, Iy)`` per level (as
            ``buildOpticalFlowPyramid(withDerivatives=True)``; the LK does not need them).
        round_levels: round every level to the nearest integer (half up) before down-sampling the
            next one, exactly as OpenCV does for 8-bit images. Default: True for uint8 input, False
            for float input (the pyramid of the float image). With a float image that requires a
            gradient the rounding is straight-through (value rounded, gradient of the unrounded
            level), as the differentiable tracker's 8-bit pyramid.
        pad: the border stored around every level of a fused (packed) pyramid, >= 3: an LK of window
            ``win`` reads ``max(win) + 1`` pixels out (default 22, VINS's 21 x 21 window; an LK with a
            wider window packs the levels again).
        backend: ``None`` / ``"auto"`` (the device's ``_tuning`` strategy), ``"fused"`` or
            ``"tensor"``, as ``track_lk``'s ``lk_backend``: with ``"fused"``, a uint8 image with
            ``round_levels`` is built by one custom op into a packed pyramid (``Pyramid.packed``).

    Returns:
        :class:`Pyramid`: uint8 levels (views into ``packed``) for a uint8 image on the fused backend;
        else float levels (float32 for uint8 input, the input dtype otherwise). The same values.

    Convention:
        Unlike OpenCV the levels are stored without the ``win_size`` border; the LK pads them itself
        once (BORDER_REFLECT_101, cached: :meth:`Pyramid.padded`) and treats derivatives outside the
        image as zeros, as ``calcOpticalFlowPyrLK``. OpenCV also stops building when a level would
        be <= ``win_size``; LK applies that cap for its own ``win_size``, so here all requested
        levels are built.
    """
    if not isinstance(max_level, int) or max_level < 0:
        raise ConfigError(f"max_level must be an int >= 0, got {max_level!r}")
    raw = as_image_batch(img, "img")
    if round_levels is None:
        round_levels = raw.dtype == torch.uint8
    if not isinstance(pad, int) or isinstance(pad, bool) or pad < _MIN_PACKED_PAD:
        raise ConfigError(f"pad must be an int >= {_MIN_PACKED_PAD}, got {pad!r}")
    return _build_pyramid_impl(raw, max_level, bool(with_gradients), bool(round_levels), pad=pad,
                               backend=resolve_backend(backend, raw.device))


# the packed pyramid's smallest border (the op's: pyrDown reads 2 pixels out, its 16-byte loads one more)
_MIN_PACKED_PAD = MIN_PAD


def _build_pyramid_impl(img: torch.Tensor, max_level: int, with_gradients: bool, round_levels: bool, *,
                        pad: int = DEFAULT_PAD, backend: str = "tensor") -> Pyramid:
    """:func:`build_pyramid` without input checks.

    Args:
        img: ``(B, 1, H, W)`` uint8 or float grey levels 0..255 (uint8 is converted to float32 on the
            tensor path).
        max_level: last level index, >= 0.
        with_gradients: also the Scharr ``(Ix, Iy)`` of every level.
        round_levels: round every level half up (OpenCV's 8-bit pyramid).
        pad: the fused pyramid's stored border (``fused.lk_pad(win)`` for an LK of window ``win``).
        backend: ``"fused"`` (resolved, :func:`~torch_frontend.fused.resolve_backend`): a uint8 image
            with ``round_levels`` is built by the fused op into a packed pyramid (one op; uint8
            levels, the same values); else the tensor kernels.

    On the CPU the tensor path builds a large batch without autograd in groups of streams
    (``_tuning.Strategy.pyramid_streams``), so that each group's temporaries stay in cache; the
    levels are the same as in one pass.
    """
    B, _, H, W = img.shape
    if backend == "fused" and round_levels and img.dtype == torch.uint8:
        packed = pyramid_op(img.view(B, H, W), max_level, pad)
        pyr = Pyramid.from_packed(packed, H, W, max_level, pad)
        return pyr.with_gradients() if with_gradients else pyr
    strategy = _tuning.for_device(img.device)
    if strategy.pyramid_conv and round_levels and img.dtype == torch.uint8:
        return _build_pyramid_conv(img, max_level, with_gradients)
    per = strategy.pyramid_streams(B, H, W)
    if per is not None and not img.requires_grad:
        parts = [_build_pyramid_impl(img[b0:b0 + per], max_level, with_gradients, round_levels, pad=pad)
                 for b0 in range(0, B, per)]
        levels = [torch.cat([p.levels[k] for p in parts]) for k in range(max_level + 1)]
        grads = [torch.cat([p.grads[k] for p in parts]) for k in range(max_level + 1)] if with_gradients else None
        return Pyramid(levels, grads, round_levels)
    level = img if img.is_floating_point() else img.to(torch.float32)
    levels = [level]
    for _ in range(max_level):
        level = _pyr_down_impl(level)
        if round_levels:
            # OpenCV: (sum + 128) >> 8, i.e. round half up; values are exact multiples of 1/256.
            if _tuning.inplace_ok(level):
                level = level.add_(0.5).floor_()
            else:  # straight through the rounding (floor's gradient is 0 everywhere), the same value
                level = straight_through(level, torch.floor(level + 0.5))
        levels.append(level)
    grads = [_scharr_impl(t) for t in levels] if with_gradients else None
    return Pyramid(levels, grads, round_levels)


# OpenCV's pyrDown taps [1 4 6 4 1]^T [1 4 6 4 1] / 256
_BINOMIAL5 = (1.0, 4.0, 6.0, 4.0, 1.0)


@cached(8)
def _pyr_down_weights(device) -> Tuple[torch.Tensor, torch.Tensor]:
    """``(weight (1, 1, 5, 5), bias (1,))`` float32 of :func:`_build_pyramid_conv`: the pyrDown
    taps / 256 (exact: k / 256 with k <= 36) and the rounding's + 0.5."""
    k = torch.tensor(_BINOMIAL5, dtype=torch.float32)
    w = (k[:, None] * k[None, :]) * (1.0 / 256.0)
    return w.view(1, 1, 5, 5).to(device), torch.full((1,), 0.5, dtype=torch.float32).to(device)


def _build_pyramid_conv(img: torch.Tensor, max_level: int, with_gradients: bool) -> Pyramid:
    """:func:`_build_pyramid_impl` of a uint8 image with rounded levels in 3 kernels per level
    (``_tuning.Strategy.pyramid_conv``): pad (BORDER_REFLECT_101 by 2), one strided 5x5 ``conv2d``
    with bias 0.5, ``floor_``: ``floor((sum + 128) / 256)`` = OpenCV's ``(sum + 128) >> 8``.

    Exact in float32 whatever the convolution algorithm's order of summation, fused multiply-adds
    or TF32 inputs: the grey levels are integers 0..255 and the taps k / 256 (k <= 36), both exact
    in TF32's 11 bits, and every partial sum (and the + 0.5) is a multiple of 1/256 below 2^8+1,
    exact in float32's 24 bits. Level 0 is a view into the padded float32 image (the uint8 image
    is padded first, then converted once: no separate level-0 copy).
    """
    weight, bias = _pyr_down_weights(img.device)
    padded = pad_reflect101(img, 2, 2).to(torch.float32)  # (B, 1, H + 4, W + 4)
    H, W = img.shape[-2:]
    levels = [padded[..., 2:H + 2, 2:W + 2]]
    for level in range(1, max_level + 1):
        nxt = F.conv2d(padded, weight, bias, stride=2).floor_()  # (B, 1, ceil(H / 2), ceil(W / 2))
        levels.append(nxt)
        if level < max_level:
            padded = pad_reflect101(nxt, 2, 2)
    grads = [_scharr_impl(t) for t in levels] if with_gradients else None
    return Pyramid(levels, grads, True)
