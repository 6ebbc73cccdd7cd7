"""The capturable path of the OpenCV method (``_find_fundamental_impl(..., capturable=True)``):
shape-static, no host sync after a warm-up call, a kernel count (~300) independent of B and of the
data, for CUDA graphs and ``torch.compile``.

The sample tables of every point count 8..N are built once and kept on the device; every problem
evaluates one fixed block of ``max_iters`` samples (its OpenCV bookkeeping replayed with scans, so
the default path's result; a smaller block reports ``overflow`` where OpenCV would have drawn
more). Memory: ~18 MB per problem of 150 points (one float64 buffer of 3000 models x 5 terms x
150 points), problems scored in groups of at most ``_SCORE_PAIRS`` model-point pairs; on the CPU it
is ~15x slower than the default path, which stays the CPU's choice.

Convention: as ``_find_fundamental_impl``; ``block`` is the number of samples per problem (None:
``max_iters``, exact). The shared front (:func:`_front_capturable`) also serves the capturable
LO-RANSAC (``lo.py``).
"""

from __future__ import annotations

import math
from typing import NamedTuple, Sequence

import numpy as np
import torch

from .._cache import cached
from .bounds import _lmeds_iters, _niters_table
from .consts import _Consts, _consts
from .eager import _LMEDS_EXACT_FIT, _lmeds_sigma_scale
from .result import (
    _MIN_POINTS,
    _MIN_RANSAC_POINTS,
    _MODEL_POINTS,
    METHOD_LMEDS,
    METHOD_NONE,
    FundamentalFit,
    _canonical_sign_unit,
    _method_codes,
    _opencv_points,
    _unsolved,
)
from .samples import OPENCV_SEED, _state_of, _state_samples
from .scoring import _count_terms, _line_features, _line_rows, _outer_products, _score_rows, _score_terms
from .seven_point import _run_7point

#: The capturable path scores the block's RANSAC models on groups of problems of at most this many
#: model-point pairs (``scoring._score_terms``: 40 bytes each, ~3 more for the masks), i.e. ~0.35 GB
#: of scores at a time: one group (and a kernel count independent of B) up to B = 18 problems of 150
#: points and 1000 samples; above, 8 kernels more per group (graphs capture per B; at such B the
#: step is bandwidth-bound). Memory knob only: each problem's scores are the same in any group.
_SCORE_PAIRS = 1 << 23
_TABLES = 8  # cached table sets: a tracker needs one


class _Tables(NamedTuple):
    """Device tables of one capturable configuration (see :func:`_tables_capturable`)."""

    idx: torch.Tensor  # (S * (N - 7), K, 7) int64: the first K subsets of (state s, n) at row s * (N - 7) + n - 8
    state_row: torch.Tensor | None  # (B,) int64: s * (N - 7) for each problem's state; None when S == 1
    niters: torch.Tensor  # (N + 1, N + 2) int64: the iteration bound with best count b at n points, [n, b + 1]
    per_n: torch.Tensor  # (N + 1, 4) int64 per point count n: table row, n (N + 2) + 1, median rank, method
    sigma: torch.Tensor  # (N + 1,) float64: LMedS's inlier scale (eager._lmeds_sigma_scale)
    ar1: torch.Tensor  # (K,) int64: 1, 2, ..., K (samples drawn after each sample of the block)
    block: torch.Tensor  # () int64: K


@cached(_TABLES)
def _tables_capturable(states: tuple, N: int, K: int, max_iters: int, confidence: float,
                       device: torch.device) -> _Tables:
    """OpenCV's samples and iteration bounds for a capturable call, on ``device``: the first ``K``
    subsets of the sample stream of every point count ``n`` in ``[8, N]`` and every distinct state
    of ``states``, and ``RANSACUpdateNumIters`` for every ``(n, best count)``. Built once on the
    host and cached per ``(states, N, K, max_iters, confidence, device)``; a steady-state call is a
    look-up (no upload). The tracker passes one state for all problems (OpenCV re-seeds
    identically on every call), so the tables depend on n only."""
    uniq = list(dict.fromkeys(states)) or [_state_of(OPENCV_SEED)]  # (B = 0: any table)
    rows = N - _MODEL_POINTS  # n = 8 .. N
    idx = np.stack([_state_samples(st, N, K) for st in uniq])
    state_row = None
    if len(uniq) > 1:
        pos = {st: s * rows for s, st in enumerate(uniq)}
        state_row = torch.tensor([pos[st] for st in states], dtype=torch.int64, device=device)
    ns = torch.arange(N + 1, dtype=torch.int64)
    per_n = torch.stack([
        (ns - _MIN_POINTS).clamp(0, N - _MIN_POINTS),  # the table row (before the state offset)
        ns * (N + 2) + 1,  # + best count = the index into niters
        (ns // 2).clamp(max=min(N, _MIN_RANSAC_POINTS - 1) - 1),  # LMedS: OpenCV's upper median
        _method_codes(ns).to(torch.int64),
    ], -1)
    return _Tables(
        idx=torch.from_numpy(idx.reshape(-1, K, _MODEL_POINTS)).to(device),
        state_row=state_row,
        niters=_niters_table(N, max_iters, confidence).to(device),
        per_n=per_n.to(device),
        sigma=_lmeds_sigma_scale(ns).to(device),
        ar1=torch.arange(1, K + 1, dtype=torch.int64, device=device),
        block=torch.tensor(K, dtype=torch.int64, device=device),
    )


class _Front(NamedTuple):
    """What both capturable estimators share (:func:`_front_capturable`): the problems' points,
    their first ``Kt`` OpenCV samples solved, the models' scoring rows."""

    B: int
    N: int
    K: int  # RANSAC block (samples per problem)
    K_l: int  # LMedS samples scored
    L: int  # OpenCV's LMedS sample count
    has_r: bool  # N >= 15: some problem may run RANSAC
    k: _Consts
    tabs: _Tables
    x12: torch.Tensor  # (B, N, 4) float64 (x1, y1, x2, y2), float32-rounded, zero at masked-out slots
    eff: torch.Tensor  # (B, N) bool: valid and finite
    n: torch.Tensor  # (B,) int64 valid, finite points
    per_n: torch.Tensor  # (B, 4) int64: tabs.per_n of n
    ge8: torch.Tensor  # (B,) bool: n >= 8
    is_r: torch.Tensor  # (B,) bool: n >= 15 (RANSAC)
    order: torch.Tensor  # (B, N) int64: valid slots first (valid_first_order)
    Fm: torch.Tensor  # (B, 3 Kt, 9) float64 models, row-major (garbage where not fok)
    fok: torch.Tensor  # (B, 3 Kt) bool
    rows: torch.Tensor  # (B, 3 Kt, 5, 9): _score_rows of Fm
    outer: torch.Tensor  # (B, N, 9): h2 (x) h1, 0 at masked-out slots


def _front_capturable(p1, p2, valid, confidence, max_iters, states, block):
    """The first part of :func:`_find_fundamental_capturable` (shared with the capturable
    LO-RANSAC): a :class:`_Front`, or the final :class:`FundamentalFit` when ``N < 8``."""
    B, N = valid.shape
    dev = p1.device
    M = max(int(max_iters), 1)
    K = M if block is None else max(1, min(int(block), M))
    L = _lmeds_iters(confidence, max_iters)
    K_l = min(K, L)
    has_r = N >= _MIN_RANSAC_POINTS
    Kt = K if has_r else K_l  # samples solved per problem

    k = _consts(dev)
    pts = _opencv_points(p1, p2, valid, k.zero)
    x12, eff, n = pts
    if N < _MIN_POINTS:  # static: no problem can estimate
        fit = _unsolved(pts, p1.dtype)
        return fit._replace(overflow=torch.zeros_like(fit.ok))
    tabs = _tables_capturable(tuple(states), N, Kt, M, confidence, dev)
    per_n = tabs.per_n.index_select(0, n)  # (B, 4): row, niters offset, median rank, method
    ge8 = per_n[:, 3] > METHOD_NONE
    is_r = per_n[:, 3] > METHOD_LMEDS

    # the samples: positions among the valid points in slot order (OpenCV's arrays) -> slots
    row = per_n[:, 0] if tabs.state_row is None else per_n[:, 0] + tabs.state_row
    order = torch.sort(eff, dim=-1, descending=True, stable=True).indices  # valid_first_order
    slot = order.gather(1, tabs.idx.index_select(0, row).view(B, Kt * _MODEL_POINTS))
    smp = x12.gather(1, slot[..., None].expand(-1, -1, 4)).view(B * Kt, _MODEL_POINTS, 2, 2)
    Fm, fok = _run_7point(smp, k, full=True)
    Fm = Fm.view(B, Kt * 3, 9)
    fok = fok.view(B, Kt * 3)
    rows = _score_rows(Fm, k)  # (B, 3 Kt, 5, 9)
    return _Front(B, N, K, K_l, L, has_r, k, tabs, x12, eff, n, per_n, ge8, is_r, order, Fm, fok, rows,
                  _outer_products(x12, eff))


def _lmeds_capturable(sp: _Front):
    """LMedS (8..14 points) of the capturable path on every problem: ``F (B, 9)``, ``inl (B, N)``,
    ``ok``, ``iters`` and ``overflow`` (None when the block holds OpenCV's LMedS samples)."""
    N, K_l, L, k, tabs, per_n, n, eff, rows, outer = (sp.N, sp.K_l, sp.L, sp.k, sp.tabs, sp.per_n, sp.n, sp.eff,
                                                      sp.rows, sp.outer)
    # the median error of each model over the first 14 valid points
    Wd = min(N, _MIN_RANSAC_POINTS - 1)
    d2, smin = _score_terms(rows[:, : 3 * K_l], outer.gather(1, sp.order[:, :Wd, None].expand(-1, -1, 9)))
    # scoring._epipolar_errors: inf where a line is degenerate (d2 / 0; 0 / 0 at masked-out slots)
    err = torch.nan_to_num(d2 / smin, nan=math.inf, posinf=math.inf)  # (B, 3 K_l, Wd)
    kth = per_n[:, 2, None, None].expand(-1, 3 * K_l, 1)
    med = err.sort(dim=-1).values.gather(2, kth)[..., 0].clamp_min_(_LMEDS_EXACT_FIT)  # see eager._robust_group
    cand_l, k_l = torch.where(sp.fok[:, : 3 * K_l], med, k.inf).min(-1)  # first minimum: OpenCV's "<"
    have = cand_l < math.inf
    best = rows.gather(1, k_l[:, None, None, None].expand(-1, 1, 5, 9))  # (B, 1, 5, 9)
    d2, smin = _score_terms(best, outer)
    err = torch.nan_to_num(d2[:, 0] / smin[:, 0], nan=math.inf, posinf=math.inf)  # (B, N)
    sigma = (tabs.sigma.index_select(0, n) * torch.where(have, cand_l, k.zero).sqrt()).clamp_min_(0.001)
    inl = (err.to(torch.float32) <= (sigma * sigma).to(torch.float32)[:, None]) & eff
    ok = have & (inl.sum(-1) >= _MODEL_POINTS) & sp.ge8
    F = sp.Fm.gather(1, k_l[:, None, None].expand(-1, 1, 9))[:, 0]
    iters = sp.ge8 * K_l
    overflow = sp.ge8 & ~sp.is_r if K_l < L else None
    return F, inl, ok, iters, overflow


def _counts_capturable(sp: _Front, thr2: float):
    """RANSAC scoring of the block: the inlier masks ``(B, 3 K, N)`` of every model (OpenCV's test,
    ``scoring._inlier_mask``'s) and the counts ``(B, 3 K)`` int32, -1 where a sample gave no model.

    Problems are scored in groups of at most ``_SCORE_PAIRS`` model-point pairs (one group up to
    B = 18 at 150 points), each group's masks and counts written into the batch's (``out=``)."""
    Fm, outer, B, N = sp.Fm, sp.outer, sp.B, sp.N
    M = Fm.shape[1]  # 3 K models
    lines, feats = _line_rows(Fm), _line_features(outer)
    per = max(1, _SCORE_PAIRS // max(M * N, 1))  # problems per group

    def test(d2, smin, out=None):  # _inlier_mask's test, (b, M, N) bool
        bound = smin if thr2 == 1.0 else smin * thr2  # x * 1.0 == x: skip a pass (VINS: 1 px)
        return torch.bitwise_and(d2 <= bound, smin > 0, out=out)

    if B <= per:
        mask = test(*_count_terms(Fm, lines, outer, feats))
        # int32 counts: a bool sum into int64 converts the whole mask first (10x slower on the CPU)
        cnt = mask.sum(-1, dtype=torch.int32)
    else:
        mask = torch.empty((B, M, N), dtype=torch.bool, device=Fm.device)
        cnt = torch.empty((B, M), dtype=torch.int32, device=Fm.device)
        for b0 in range(0, B, per):
            g = slice(b0, b0 + per)
            terms = _count_terms(Fm[g], lines[g], outer[g], feats[g])
            torch.sum(test(*terms, out=mask[g]), -1, dtype=torch.int32, out=cnt[g])
    return mask, torch.where(sp.fok, cnt, sp.k.minus_one)  # -1: no model


def _fit_capturable(sp: _Front, F, inl, ok, iters, overflow, out_dtype) -> FundamentalFit:
    """The capturable path's :class:`FundamentalFit` from unit-norm ``F (B, 9)`` and the rest."""
    if overflow is None:
        overflow = torch.zeros_like(sp.ge8)
    F = torch.where(ok[:, None], _canonical_sign_unit(F), sp.k.nan).view(sp.B, 3, 3)
    return FundamentalFit(F.to(out_dtype), torch.where(ok[:, None], inl, sp.eff), ok, iters,
                          sp.per_n[:, 3].to(torch.int8), overflow)


def _find_fundamental_capturable(p1, p2, valid, threshold: float, confidence: float, max_iters: int,
                                 states: Sequence[int], block, fused: bool = False) -> FundamentalFit:
    """``_find_fundamental_impl(..., capturable=True)``: static shapes, no host syncs after a
    warm-up call with the same ``(states, N, max_iters, confidence, block)``, a kernel count
    independent of B and of the data.

    Every problem takes the first ``K`` samples of its OpenCV stream (``K = block``; default and at
    most ``max_iters``, which is exact) from one table look-up (:func:`_tables_capturable`, for
    both methods) and all are solved in one batched 7-point call. RANSAC scores the ``3 K`` models
    on all points (one batched matmul per group of problems, ``_SCORE_PAIRS``) and replays OpenCV's loop with scans over the
    block: the running best count (``cummax``), the iteration bound after every sample (a table
    look-up), the first sample that reaches its bound, the first strictly better model up to it.
    That is ``eager._robust_group`` in one round, hence its result. LMedS scores the first
    ``min(K, L)`` samples (``L = bounds._lmeds_iters``, 300 for VINS) on the first 14 valid points
    (all of an 8..14 point problem's). Both branches run on the whole batch; ``torch.where`` picks
    by point count.

    ``overflow``: a RANSAC problem that did not reach its bound within ``K`` samples, or an LMedS
    problem when ``K < L``; never with the default block.

    ``fused``: the scoring, the counts and the replay are one ``torch_frontend::ransac_score`` op
    (``fused/ransac_op.py``; one launch, no sync), which walks the block in OpenCV's order and stops
    at its last sample: no ``(B, 3 K, N)`` scores or masks.
    """
    sp = _front_capturable(p1, p2, valid, confidence, max_iters, states, block)
    if isinstance(sp, FundamentalFit):  # N < 8
        return sp
    F, inl, ok, iters, overflow = _lmeds_capturable(sp)
    if sp.has_r and fused:
        from ..fused.ransac_op import ransac_score_op

        best, nit, used, k_r, inl_r = ransac_score_op(sp.Fm, sp.fok, sp.x12, sp.eff, sp.n, sp.tabs.niters,
                                                      None, None, None, None, threshold * threshold)
        is_r = sp.is_r
        F = torch.where(is_r[:, None], sp.Fm.gather(1, k_r.clamp_min(0)[:, None, None].expand(-1, 1, 9))[:, 0], F)
        inl = torch.where(is_r[:, None], inl_r, inl)
        ok = torch.where(is_r, best > _MODEL_POINTS - 1, ok)
        iters = torch.where(is_r, used, iters)
        over_r = is_r & (used < nit)
        overflow = over_r if overflow is None else overflow | over_r
    elif sp.has_r:
        # RANSAC (>= 15 points): the inlier count of every model, then OpenCV's loop replayed
        B, N, K, k, tabs, per_n, is_r = sp.B, sp.N, sp.K, sp.k, sp.tabs, sp.per_n, sp.is_r
        mask, cnt = _counts_capturable(sp, threshold * threshold)
        cnt = cnt.view(B, K, 3)
        run_best = torch.cummax(cnt.amax(-1), 1).values  # the best count after each sample
        n_after = tabs.niters.take(run_best + per_n[:, 1, None])  # the bound after each sample
        reached, i_stop = (tabs.ar1 >= n_after).to(torch.int8).max(1)  # OpenCV: iter < niters
        used = torch.where(reached > 0, i_stop + 1, tabs.block)
        cm = torch.where((tabs.ar1 <= used[:, None])[..., None], cnt, k.minus_one).view(B, 3 * K)
        cand, k_r = cm.max(-1)  # first maximum: OpenCV's sequential strict ">"
        F = torch.where(is_r[:, None], sp.Fm.gather(1, k_r[:, None, None].expand(-1, 1, 9))[:, 0], F)
        inl = torch.where(is_r[:, None], mask.gather(1, k_r[:, None, None].expand(-1, 1, N))[:, 0], inl)
        ok = torch.where(is_r, cand > _MODEL_POINTS - 1, ok)
        iters = torch.where(is_r, used, iters)
        over_r = is_r & (reached == 0)
        overflow = over_r if overflow is None else overflow | over_r
    return _fit_capturable(sp, F, inl, ok, iters, overflow, p1.dtype)
