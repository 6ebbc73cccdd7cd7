"""CLAHE -> pyramid -> LK of one frame on the CPU, group of streams by group (``fused/front_op.py``).

Convention:
    As the three kernels it calls (:func:`._numba_clahe.clahe_streams`,
    :func:`._numba_pyramid.pyramid_streams`, :func:`._numba_lk.lk_streams`; mono, no initial guess, no
    forward-backward check): ``img``, ``eq`` ``(B, H, W)`` uint8; ``prev``, ``nxt`` ``(B, total)`` uint8
    packed pyramids of one layout; ``pts`` ``(B, N, 2)`` float32, ``valid`` ``(B, N)`` bool; streams
    ``s0 <= b < s1`` in groups of ``group`` streams.

For each group the three kernels run back to back, so a stream's equalised image is still in cache
when its pyramid reads it, and its new pyramid when its LK reads it (the stage order, every stream's
CLAHE then every stream's pyramid then every stream's LK, reads both back from memory at B >= 16:
``benchmarks/results/cache_grouping.md``). Each stream's results depend on its own inputs only, so
every grouping gives the same bits.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ._numba_clahe import clahe_streams
from ._numba_lk import lk_streams
from ._numba_pyramid import pyramid_streams

__all__ = ["front_streams"]

_NO_INIT = np.zeros((1, 1, 2), dtype=np.float32)


@njit(cache=True, nogil=True)
def front_streams(img, eq, clip_limit, gx, gy, sizes, offs, org, pitch, pad, prev, nxt, pts, valid, no_init, top,
                  ww, wh, max_iters, eps, min_eig, out, status, capped, group, s0, s1):
    """CLAHE (into ``eq``), the packed pyramid of ``eq`` (into ``nxt``) and the LK from ``prev`` into
    ``nxt`` (into ``out``, ``status``, ``capped``) of streams ``s0 .. s1 - 1``, ``group`` streams at a
    time. ``sizes``, ``offs``, ``org``, ``pitch``: the layout's arrays (``ops.layout_arrays``)."""
    g = max(group, 1)
    for a in range(s0, s1, g):
        b = min(a + g, s1)
        clahe_streams(img, eq, clip_limit, gx, gy, a, b)
        pyramid_streams(eq, nxt, sizes, offs, pad, a, b)
        lk_streams(prev, nxt, org, pitch, org, pitch, sizes, pts, valid, no_init, False, top, ww, wh, max_iters,
                   eps, min_eig, -1, 0.0, False, out, status, capped, a, b)
