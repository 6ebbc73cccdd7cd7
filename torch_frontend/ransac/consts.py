"""The small device constants of the fundamental-matrix solvers, uploaded once per device
(:func:`_consts`): the per-frame path builds no tensor from host data and makes no upload.

Convention: float64 unless stated; ``k`` in the solvers is the :class:`_Consts` of their device.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from .._cache import cached
from .samples import _MWC_A, _U32

#: relative shift of a normal matrix in inverse iteration (keeps an exact null space invertible;
#: eigenvectors unchanged), see refit.py
_EIG_SHIFT = 1e-12
#: cv::solveCubic's trigonometric form: 2 pi k / 3, k = 0, 1, 2 (OpenCV's root order)
_CUBIC_PHASES = 2.0 * math.pi * torch.arange(3, dtype=torch.float64) / 3.0


def _opencv_null_seeds() -> torch.Tensor:
    """The two vectors OpenCV's ``SVDecomp(..., FULL_UV)`` of the 7x9 system completes ``V`` with:
    its Jacobi SVD draws, for each missing row, 9 entries ``+-1/9`` from a fresh ``cv::RNG(0x12345678)``
    (sign from bit 8 of ``next()``) and orthogonalises them against the rows before. So OpenCV's
    null-space basis of ``run7Point`` is ``f1 = P r7 / |P r7|``, ``f2`` = the unit vector of ``P r8``
    orthogonal to ``f1`` (P the projection onto the null space). Returned as ``(2, 9)`` rows
    ``r7, r8`` of +-1 (the scale does not matter)."""
    s, rows = 0x12345678, []
    for _ in range(2):
        row = []
        for _ in range(9):
            s = (s & _U32) * _MWC_A + (s >> 32)
            row.append(1.0 if s & 256 else -1.0)
        rows.append(row)
    return torch.tensor(rows, dtype=torch.float64)


def _score_select() -> torch.Tensor:
    """``(9, 45)`` 0/1 matrix: a row-major F -> its 5 scoring rows (``scoring._score_rows``). With
    ``o = h2 (x) h1`` (entry 3 i + j) the outer product of a point pair, ``x2^T F x1 = sum_q o_q
    F_q``; ``(F x1)_r = sum_j o_{6 + j} F_{3 r + j}`` (``h2_2 = 1`` at a valid point); ``(F^T x2)_c =
    sum_i o_{3 i + 2} F_{3 i + c}`` (``h1_2 = 1``)."""
    sel = torch.zeros(9, 5, 9, dtype=torch.float64)
    for q in range(9):
        sel[q, 0, q] = 1.0
    for r in range(2):
        for j in range(3):
            sel[3 * r + j, 1 + r, 6 + j] = 1.0
    for c in range(2):
        for i in range(3):
            sel[3 * i + c, 3 + c, 3 * i + 2] = 1.0
    return sel.view(9, 45)


class _Consts(NamedTuple):
    """Device constants of the solvers (see :func:`_consts`)."""

    null_rows: torch.Tensor  # (2, 9): OpenCV's SVD completion vectors r7, r8 (_opencv_null_seeds)
    basis: torch.Tensor  # (2, 2): [u; w] -> [u - w; w], i.e. [f1 - f2; f2]
    cubic_scale: torch.Tensor  # (4,): <cof F_p, F_q> -> cubic coefficients (det F = <cof F, F> / 3)
    phases: torch.Tensor  # (3,): _CUBIC_PHASES
    pair_j: torch.Tensor  # (15,) int64: j of the pairs j > k of a sample's six difference vectors
    pair_k: torch.Tensor  # (15,) int64: k
    select: torch.Tensor  # (9, 45): a row-major F -> its 5 scoring rows (_score_select)
    eye23: torch.Tensor  # (2, 3): the s-part of rows 0, 1 of a normalisation's T^T
    shift: torch.Tensor  # (9, 9): _EIG_SHIFT * I
    shift6: torch.Tensor  # (6, 6): _EIG_SHIFT * I
    eye9: torch.Tensor  # (9, 9): I
    eye3: torch.Tensor  # (3, 3): I
    one: torch.Tensor  # () 1 (0-dim operands of torch.where: no scalar_tensor launch)
    zero: torch.Tensor  # () 0
    inf: torch.Tensor  # () inf
    nan: torch.Tensor  # () nan
    minus_one: torch.Tensor  # () int32 -1


@cached(8)
def _consts(device: torch.device) -> _Consts:
    """The solvers' constants on ``device`` (cached per device)."""
    f64 = dict(dtype=torch.float64, device=device)
    eye9 = torch.eye(9, **f64)
    pair_j, pair_k = torch.tril_indices(6, 6, offset=-1, device=device)
    return _Consts(
        null_rows=_opencv_null_seeds().to(device),
        basis=torch.tensor([[1.0, -1.0], [0.0, 1.0]], **f64),
        cubic_scale=torch.tensor([1.0 / 3.0, 1.0, 1.0, 1.0 / 3.0], **f64),
        phases=_CUBIC_PHASES.to(device),
        pair_j=pair_j.contiguous(),
        pair_k=pair_k.contiguous(),
        select=_score_select().to(device),
        eye23=torch.eye(2, 3, **f64),
        shift=_EIG_SHIFT * eye9,
        shift6=_EIG_SHIFT * eye9[:6, :6].contiguous(),
        eye9=eye9,
        eye3=eye9[:3, :3].contiguous(),
        one=torch.tensor(1.0, **f64),
        zero=torch.tensor(0.0, **f64),
        inf=torch.tensor(math.inf, **f64),
        nan=torch.tensor(math.nan, **f64),
        minus_one=torch.tensor(-1, dtype=torch.int32, device=device),
    )
