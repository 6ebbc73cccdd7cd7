"""The packed pyramid: every level of a stream in one flat uint8 row, each level padded as the LK reads it.

Convention:
    A packed pyramid of B streams is a ``(B, total)`` uint8 tensor, C-contiguous. Stream ``b``'s row
    holds levels ``0..max_level`` one after the other. Level ``l`` has size ``H_l x W_l``
    (``H_0 = H``, ``H_l = ceil(H_{l-1} / 2)``, likewise ``W``: ``cv2.pyrDown``'s default size) and is
    stored with ``pad`` extra pixels on every side, row-major with row pitch ``Wp_l = W_l + 2 pad``
    and ``Hp_l = H_l + 2 pad`` rows, from offset ``off_l = sum_{k < l} Hp_k Wp_k``. Pixel ``(x, y)`` of
    level ``l``, ``x in [-pad, W_l + pad)``, ``y in [-pad, H_l + pad)``, is element
    ``off_l + (y + pad) Wp_l + (x + pad)``; outside the level it holds the level's BORDER_REFLECT_101
    value (``gfedcb|abcdefgh|gfedcba``, repeated reflection where ``pad`` exceeds the size, as
    ``cv2.borderInterpolate``). Grey levels are OpenCV's 8-bit pyramid: level 0 the image, level
    ``l`` ``cv2.pyrDown`` of level ``l - 1`` (``(sum + 128) >> 8``).

    The LK of a window ``win = (ww, wh)`` reads up to ``max(ww, wh) + 1`` pixels outside a level (its
    windows may start ``win`` pixels out, its template's Scharr derivatives read one more): a packed
    pyramid serves an LK whose ``pad >= max(ww, wh) + 1`` (:func:`lk_pad`).

This module is plain Python (no torch): the layout is shared by the CPU kernels, the CUDA kernels and
the views that :class:`~torch_frontend.pyramid.Pyramid` exposes as its levels.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Tuple

__all__ = ["PyramidLayout", "lk_pad", "DEFAULT_PAD", "reflect101"]

#: the pad of VINS's LK (winSize 21): 21 + 1
DEFAULT_PAD = 22


def lk_pad(win_size: Tuple[int, int]) -> int:
    """The smallest pad a packed pyramid needs for an LK with window ``(ww, wh)``."""
    return max(int(win_size[0]), int(win_size[1])) + 1


def reflect101(p: int, n: int) -> int:
    """``cv2.borderInterpolate(p, n, BORDER_REFLECT_101)`` for any ``p`` (repeated reflection)."""
    if n == 1:
        return 0
    period = 2 * (n - 1)
    p = abs(p) % period
    return period - p if p >= n else p


@dataclass(frozen=True)
class PyramidLayout:
    """Where each level of a packed pyramid of an ``H x W`` image lies (see the module docstring).

    Attributes:
        height, width: level 0's size in pixels.
        max_level: the top level (``max_level + 1`` levels).
        pad: pixels of BORDER_REFLECT_101 border stored on every side of every level.
    """

    height: int
    width: int
    max_level: int
    pad: int

    def __post_init__(self):
        if self.height < 1 or self.width < 1 or self.max_level < 0 or self.pad < 0:
            raise ValueError(f"PyramidLayout: bad sizes {self}")

    @property
    def sizes(self) -> List[Tuple[int, int]]:
        """``(H_l, W_l)`` of every level."""
        h, w = self.height, self.width
        out = [(h, w)]
        for _ in range(self.max_level):
            h, w = (h + 1) // 2, (w + 1) // 2
            out.append((h, w))
        return out

    @property
    def offsets(self) -> List[int]:
        """``off_l``: the first element of level ``l``'s padded block in a stream's row."""
        out, o = [], 0
        for h, w in self.sizes:
            out.append(o)
            o += (h + 2 * self.pad) * (w + 2 * self.pad)
        return out

    @property
    def total(self) -> int:
        """Elements per stream: the packed tensor is ``(B, total)``."""
        h, w = self.sizes[-1]
        return self.offsets[-1] + (h + 2 * self.pad) * (w + 2 * self.pad)

    def padded_shape(self, level: int) -> Tuple[int, int]:
        """``(Hp_l, Wp_l)``: level ``level``'s stored block."""
        h, w = self.sizes[level]
        return h + 2 * self.pad, w + 2 * self.pad
