"""OpenCV's adaptive iteration bound (``RANSACUpdateNumIters``) and the tables of it the drivers
look up.

Convention: ``confidence`` in ``(0, 1)``; outlier ratios ``ep`` in ``[0, 1]``; bounds are numbers
of minimal samples (int64 tensors, or Python ints where noted).
"""

from __future__ import annotations

import math

import torch

from .._cache import cached
from .result import _MODEL_POINTS

__all__ = ["ransac_update_num_iters"]

_DBL_MIN = 2.2250738585072014e-308
_LMEDS_OUTLIER_RATIO = 0.45  # OpenCV LMeDSPointSetRegistrator: fixed prior for its iteration count


def ransac_update_num_iters(confidence: float, ep: torch.Tensor, model_points: int, max_iters: torch.Tensor) -> torch.Tensor:
    """OpenCV ``RANSACUpdateNumIters`` elementwise: ``ep`` outlier ratio, ``max_iters`` current bound."""
    p = min(max(float(confidence), 0.0), 1.0)
    ep = ep.to(torch.float64).clamp(0.0, 1.0)
    num = math.log(max(1.0 - p, _DBL_MIN))
    denom_raw = 1.0 - (1.0 - ep) ** model_points
    denom = torch.log(denom_raw.clamp_min(_DBL_MIN))
    mi = max_iters.to(torch.float64)
    capped = (denom >= 0) | (-num >= mi * (-denom))
    # cvRound = round half to even, as torch.round
    it = torch.where(capped, mi, torch.round(num / torch.where(denom < 0, denom, torch.full_like(denom, -1.0))))
    it = torch.where(denom_raw < _DBL_MIN, torch.zeros_like(it), it)
    return it.to(max_iters.dtype)


def _niters_table(N: int, max_iters: int, confidence: float) -> torch.Tensor:
    """OpenCV's iteration bound for every point count and best inlier count, ``(N + 1, N + 2)``
    int64 on the host: entry ``[n, b + 1]`` is the bound after a sample whose running best count is
    b (-1: no model yet): max_iters unless b > 6 (OpenCV: goodCount > max(maxGoodCount,
    modelPoints - 1)), else ``RANSACUpdateNumIters(conf, (n - b) / n, 7, bound)``. With one cap
    (max_iters) instead of the running bound: the same integers, as the bound only shrinks (see
    ``eager._robust_group``, whose ep expression this is, so the values are its own)."""
    cap = max(int(max_iters), 1)
    nf = torch.arange(N + 1, dtype=torch.float64)[:, None]
    b = torch.arange(-1, N + 1, dtype=torch.float64)[None, :]
    it = ransac_update_num_iters(confidence, (nf - b) / nf, _MODEL_POINTS,  # (n = 0: unused garbage)
                                 torch.full((N + 1, N + 2), cap, dtype=torch.int64))
    return torch.where(b > _MODEL_POINTS - 1, it, cap)


def _table_rows(N: int) -> int:
    """The ``N`` of the bound table a group of at most ``N`` points looks up (a power of two, at
    least 256: entries depend on ``(n, best)`` only, so one cached table serves every width)."""
    return max(256, 1 << max(int(N) - 1, 0).bit_length())


@cached(8)
def _niters_table_on(N: int, max_iters: int, confidence: float, device: torch.device) -> torch.Tensor:
    """:func:`_niters_table` on ``device`` (cached: the LO-RANSAC default path's bound look-up)."""
    return _niters_table(N, max_iters, confidence).to(device)


@cached(64)
def _lmeds_iters(confidence: float, max_iters: int) -> int:
    """OpenCV's LMedS sample count ``max(3, RANSACUpdateNumIters(confidence, 0.45, 7, max_iters))``
    (300 for 0.99), a Python int (cached: no host tensors per call)."""
    it0 = ransac_update_num_iters(
        confidence, torch.tensor(_LMEDS_OUTLIER_RATIO), _MODEL_POINTS, torch.tensor(max(int(max_iters), 1))
    )
    return max(int(it0), 3)
